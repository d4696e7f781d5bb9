"""Observe real node processes from the test process: their messages (an rclpy executor, no
launch), the errors of their estimates, and the processes themselves (:class:`ProcessWatch`)."""
from __future__ import annotations

import contextlib
import glob
import os
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from bearing_pose_estimation.cli import launch
from bearing_pose_estimation.core import so3
from bearing_pose_estimation import msg_defs as wire
from bearing_pose_estimation.msg_defs import cdr
from bearing_pose_estimation.plan import dds
from bearing_pose_estimation.scenario import load_scenario
from bearing_pose_estimation.sim.netsim import run_network
from bearing_pose_estimation.studies.summary import read_metrics_csv


class Observer:
    """A node in its own context that records every message on the topics it is given."""

    def __init__(self, node: Node, executor: SingleThreadedExecutor) -> None:
        self.node = node
        self.executor = executor
        self.messages: dict[str, list] = defaultdict(list)

    def subscribe(self, msg_type: type, topic: str, qos) -> None:
        self.node.create_subscription(msg_type, topic, self.messages[topic].append, qos)

    def take_the_monitor_s_place(self, timeout: float = 60.0) -> None:
        """Once every subscription of this observer has its publisher, announce it as the
        monitor does (latched ``/monitor/ready``): a simulator waiting for a monitor then
        starts the clock without losing this observer's first messages."""
        from std_msgs.msg import Empty

        pub = self.node.create_publisher(Empty, wire.MONITOR_READY, wire.LATCHED_QOS)
        self._keep = pub
        assert self.spin_until(lambda: all(s.get_publisher_count() > 0
                                           for s in self.node.subscriptions), timeout)
        pub.publish(Empty())

    def spin_until(self, condition: Callable[[], bool], timeout: float) -> bool:
        """Spin until ``condition()`` holds or ``timeout`` wall seconds pass."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if condition():
                return True
            self.executor.spin_once(timeout_sec=0.05)
        return condition()


def assert_no_shm_left(groups: launch.ProcessGroup | list[launch.ProcessGroup],
                       before: set[str], hung: bool = False) -> None:
    """Nothing the groups' processes created is left in /dev/shm (call it once the test's own
    participants are gone). A node that the teardown watchdog ended (the Fast DDS deadlock,
    eProsima/Fast-DDS#6502, about one process in 200) leaves its participant's files: its
    group removed those no process used, but a test's observer still used some (the ports it
    sent to, the segment it read), so they are orphans only now; remove them as ``bearing-pose
    run`` would, where every participant is a child that is gone by then. ``hung``: such a
    node was ended in a group the test does not hold (a launcher it ran said so)."""
    groups = groups if isinstance(groups, list) else [groups]
    if hung or any(group.hung_teardowns() for group in groups):
        dds.clean_shm(before)
    assert dds.leaked_shm(before) == [], 'Fast DDS files left in /dev/shm'


@contextmanager
def observer(name: str = 'test_observer') -> Iterator[Observer]:
    context = Context()
    rclpy.init(context=context)
    node = Node(name, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        yield Observer(node, executor)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)


def paired_errors(obs: Observer, agent: str, since: float = -1.0
                  ) -> list[tuple[float, float, float]]:
    """(t, attitude error [rad], position error [m]) of ``agent`` at the stamps where its
    recorded estimate and ground truth pair up; every estimate must be finite."""
    truth = {wire.stamp_ns(m.header.stamp): cdr.decode_pose_raw(m)
             for m in obs.messages[f'/{agent}/ground_truth']}
    out = []
    for m in obs.messages[f'/{agent}/estimate']:
        ns = wire.stamp_ns(m.header.stamp)
        t, R_hat, p_hat = cdr.decode_pose_raw(m)
        assert np.all(np.isfinite(R_hat)) and np.all(np.isfinite(p_hat))
        if ns in truth and t > since:
            _, R, p = truth[ns]
            out.append((t, float(so3.angle(R @ R_hat.T)), float(np.linalg.norm(p - p_hat))))
    return out


def error_at(errors: list[tuple[float, float, float]], t: float) -> tuple[float, float]:
    """The (attitude, position) error at stamp ``t`` (to 1 µs) from :func:`paired_errors`."""
    found = [(a, p) for s, a, p in errors if abs(s - t) < 1e-6]
    assert found, f'no estimate paired with the truth at t = {t} s'
    return found[0]


def _cmdline(pid: str) -> str:
    with contextlib.suppress(OSError):
        return Path(f'/proc/{pid}/cmdline').read_bytes().replace(b'\0', b' ').decode(
            errors='replace')
    return ''


class ProcessWatch:
    """Every process whose command line contains ``marker`` (e.g. a test's tmp_path, which
    each node's parameter file path holds), recorded by a thread polling /proc while the
    test runs, so that afterwards :meth:`left` can say whether any of them, or anything in
    their process groups, is still alive. Use as a context manager."""

    def __init__(self, marker: str, period: float = 0.1) -> None:
        self.marker = marker
        self.period = period
        self.seen: dict[int, str] = {}   # pid -> command line
        self.groups: list[launch.ProcessGroup] = []   # the test's own, if it starts them
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def __enter__(self) -> ProcessWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _poll(self) -> None:
        while not self._stop.is_set():
            self.scan()
            self._stop.wait(self.period)

    def scan(self) -> list[int]:
        """Record and return the live matching processes now."""
        live = []
        for path in glob.glob('/proc/[0-9]*/cmdline'):
            pid = path.split('/')[2]
            cmd = _cmdline(pid)
            if self.marker in cmd and int(pid) != os.getpid():
                self.seen[int(pid)] = cmd
                live.append(int(pid))
        return live

    def left(self) -> list[str]:
        """Recorded processes still alive (not zombies), and live members of their process
        groups (what a child's own children would be): command lines, or 'pid N'."""
        groups = launch.live_process_groups()
        live = {pid for members in groups.values() for pid in members}
        out = [self.seen[pid] for pid in self.seen
               if pid in live and self.marker in _cmdline(str(pid))]
        out += [f'pid {m} in the group of {pid}' for pid in self.seen
                for m in groups.get(pid, []) if m not in self.seen]
        return out


# A lockstep fleet whose steps must equal the batch run's: the wall-clock patience that breaks
# a deadlock of lost messages (neighbour_wait, 0.25 s) must not fire on a process that is only
# slow. On a loaded machine one stalled for 0.25 s once, at t = 0.3 s, and its neighbours went
# on without its z_hat: 5e-4 off the batch run. None of these fleets loses a message.
PATIENT = {'neighbour_wait': 10.0}


def with_parameters(params: dict[str, Path], agents: list[str], **values: object
                    ) -> dict[str, Path]:
    """``params`` (plan.write_params' files) with ``values`` added to each of ``agents``'."""
    import yaml

    for agent in agents:
        data = yaml.safe_load(params[agent].read_text())
        for node in data.values():
            node['ros__parameters'].update(values)
        params[agent].write_text(yaml.safe_dump(data, sort_keys=False))
    return params


_NETSIM: dict = {}   # scenario text -> netsim Recording


def _netsim(scenario_file: Path, duration: float):
    """netsim's followers, record times and errors of a scenario to ``duration``, cut from
    a longer run of the same scenario text when an earlier test made one."""
    text = scenario_file.read_text()
    net = _NETSIM.get(text)
    if net is None or net.t[-1] < duration - 1e-9:
        net = _NETSIM[text] = run_network(load_scenario(scenario_file), duration,
                                          record_every=0.1)
    k = int(np.searchsorted(net.t, duration + 1e-9))
    return net.followers, net.t[:k], net.att_err[:k], net.pos_err[:k]


def assert_equals_netsim(metrics: Path, scenario_file: Path, rtol: float = 2e-9) -> None:
    """Every follower's errors at every record of a DDS run equal netsim's (the same agent
    logic without DDS) to metrics.csv's rounding (10 digits): the nodes' fixed exchange under
    use_sim_time makes the run independent of the machine's load (issue 15). For errors near
    zero, the quaternions on the wire (exact to ~1e-16) set an absolute floor: 1e-12 here."""
    dds = read_metrics_csv(metrics)
    followers, t, att, pos = _netsim(scenario_file, float(dds.t[-1]))
    assert dds.followers == followers
    # Every record, t = 0 first (the monitor is ready only once it holds every follower's
    # t = 0 estimate; netsim's first record is one period in).
    assert dds.t[0] == 0.0, dds.t
    np.testing.assert_allclose(dds.t[1:], t, atol=1e-9)
    np.testing.assert_allclose(dds.att_err[1:], att, rtol=rtol, atol=1e-12)
    np.testing.assert_allclose(dds.pos_err[1:], pos, rtol=rtol, atol=1e-12)
