"""Transport floor: the CPU a fleet's DDS messages cost with no processing, against the nodes.

What moving exactly the messages of a ``bearing-pose run`` costs when nothing is computed,
and what the real nodes cost beyond it (issue 15, "Measure the floor").

The floor runs the process layout of ``bearing-pose run`` (one process per agent, the
monitor, the simulator) with the same nodes' names, topics, message types, QoS, sizes and
rates, but nothing else:

- each agent process creates the publishers and subscriptions that the estimator node of that
  agent creates (``ros/estimator_node.py``'s ``__init__``, from the one table of
  subscriptions, ``runtime.table.subscriptions``, the own sensor topics the method reads, a leader's
  ``known_pose`` remapped to ``ground_truth`` as the launcher does, and ``/clock`` as rclpy's
  time source subscribes to it under ``use_sim_time``, once per process with ``--per-process``:
  ``ros.estimator_group.share_clock``). Every subscription is raw
  (``raw=True``) with a callback that only counts. It publishes, on a wall-clock timer, the
  messages the node publishes at the instants the node publishes them: ``pose``, ``estimate``
  and the channels with a topic of their own on the publish grid ('exact' channels: when the
  method reads them, ``Estimator.due``; the pose also when a channel riding on it is), a
  two-round method's round-2 channels every step, ``/diagnostics`` every second;
- the simulator process publishes what the simulator node publishes (per agent ``imu``,
  ``bearings``, ``ground_truth`` and the sensors the scenario simulates, each at its rate,
  and ``/clock`` once per estimator step) and subscribes to every ``estimate`` and to
  ``/monitor/ready``, as the node does;
- the monitor process subscribes to what the monitor node reads (``ground_truth`` of the
  agents it watches, the followers' ``estimate``, ``/clock``) and creates ``/monitor/ready``,
  so that every writer has the readers it has in a real run.

Each message is built once as its serialised bytes, with msg_defs' codecs (``msg_defs.cdr``,
the nodes' own) from the scenario's own values (the simulator's ``sim.world.World`` at one
instant, each agent's ``outbox()``; ``/diagnostics`` with
``rclpy.serialization.serialize_message``), and the bytes are published (rclpy 7.1.6's
``Publisher.publish`` takes bytes: ``publish_raw``). Every process is spun like a node
(``ros.node_main.run_node``: the package's executor, ``DEFAULT_EXECUTOR``). Each process polls its own
publishers' and subscriptions' match counts until every one has the peers the fleet gives
it, then starts its timer with step 0 on a multiple of its cycle on the monotonic clock, so
that every process publishes at the same instants, as the nodes do (each estimator publishes
right after the simulator's sample that completes its step; ``--phases spread`` starts each
timer when its process is matched instead). The measured window starts ``--warmup`` seconds
after the last process reports, and lasts ``--duration`` seconds of wall time.

Not in the floor: decoding, the estimator's step, encoding, the simulator's world on its
internal grid and its wake-ups every 5 ms, the nodes' readiness, patience and step timers,
rclpy's time source (``/clock`` arrives as bytes nobody reads), the monitor's
``/diagnostics`` (Presenza et al.: once per simulated second) and ``/monitor/ready``
(created, never sent: the floor's simulator does not wait for it).

Then the real fleet (``bearing-pose run SCENARIO --real-time-factor 1 --no-plots``, through
``bench/fleet_scale.py``'s run configuration, for ``--warmup`` + ``--duration`` simulated
seconds). Its window starts ``--warmup`` wall seconds after the simulator started the clock
and ends when the simulator reaches the end, or ``--duration`` wall seconds later: the bench
then stops the monitor with SIGINT, the launcher stops the rest, and the simulated time at
the end is where the estimators' state was. The simulated time at the window's start takes
the clock's pace over the run as constant.

Columns. CPU time is user + system, all threads, from /proc/<pid>/stat, per process and
second, in % of one core; "per agent" is the median over the agent processes. The nodes'
is per *simulated* second (what they need to run at real time: lockstep slows the clock when
the estimators fall behind; "node speed" is its pace). The floor's is per wall second,
scaled to its planned traffic: its timers skip ticks when the machine cannot keep up, and
"floor rate" is the share of its planned messages (received and published) the median agent
moved, 100 % unless the machine is saturated. "floor µs per agent message": an agent
process's CPU per message it received or published. "others": what the rest of the machine
used during the window (every other process's CPU time, its reaped children's included), to
judge a run on a shared machine; before each run the bench waits until the rest of the
machine uses less than ``--quiet-below`` % of a core. ``--omit clock`` (any topics' last
names) leaves those topics out of the floor: what they cost is the difference. Each
configuration runs ``--repeat`` times, floor and nodes alternating; the table gives medians
and ranges.

    OMP_NUM_THREADS=1 .venv/bin/python bench/transport_floor.py
        [--scenario config/paper_8_agents.yaml[:METHOD] ...] [--method METHOD]
        [--duration 20] [--repeat 2] [--warmup 2] [--domain-id 60] [--floor-only]
        [--phases aligned|spread] [--omit TOPIC ...] [--quiet-below 30] [--logs DIR]
        [--per-process K]

``--per-process K`` runs K consecutive agents in one process, floor and nodes, as ``bearing-pose
run --agents-per-process K`` does (one ``estimators`` process, one executor, one participant):
an agent's figure is then its process's CPU divided by its agents.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import re
import signal
import statistics
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('OMP_NUM_THREADS', '1')
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue  # noqa: E402
from rclpy.clock import Clock, ClockType  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from rosgraph_msgs.msg import Clock as ClockMsg  # noqa: E402
from std_msgs.msg import Empty  # noqa: E402

from fleet_scale import run_config, simulator_stats  # noqa: E402

from bearing_pose_estimation import msg_defs as wire  # noqa: E402
from bearing_pose_estimation.cli import launch  # noqa: E402
from bearing_pose_estimation.estimators.base import Sensor  # noqa: E402
from bearing_pose_estimation.plan.dds import dds_env, leaked_shm, shm_files  # noqa: E402
from bearing_pose_estimation.plan.processes import ProcessSpec, estimator_groups  # noqa: E402
from bearing_pose_estimation.runtime.table import (ODOMETRY, optional_first,  # noqa: E402
                                                   subscriptions)
from bearing_pose_estimation.ros.estimator_group import parse_args as group_args  # noqa: E402
from bearing_pose_estimation.ros.monitor_node import watched  # noqa: E402
from bearing_pose_estimation.ros.node_main import run_node  # noqa: E402
from bearing_pose_estimation.scenario.runtimes import agent_specs, runtime_for  # noqa: E402
from bearing_pose_estimation.scenario import (Scenario, check_scenario,  # noqa: E402
                                              load_scenario, read_scenario_data)
from bearing_pose_estimation.sim.world import World  # noqa: E402
from bearing_pose_estimation.studies.compare import method_data  # noqa: E402

# What rclpy's TimeSource subscribes to /clock with, under use_sim_time (rclpy 7.1.6).
CLOCK_SUB_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
DIAGNOSTICS_QOS = 10            # the estimator node's /diagnostics publisher
DIAGNOSTICS_PERIOD_S = 1.0      # its diagnostics_period default [s, wall clock]
MATCH_TIMEOUT_S = 90.0
SAMPLE_S = 0.1                  # the real run's CPU sampling period [s]

_MATCHED = re.compile(r'FLOOR matched after (?P<s>\S+) s')
_COUNTS = re.compile(r'\[(?P<stamp>\d+\.\d+)\] \[(?P<node>[^]]*)\]: FLOOR count (?P<pub>\d+) '
                     r'(?P<sub>\d+)')
COUNT_PERIOD_S = 0.5            # how often a floor process logs its message counts
_CLOCK_STARTS = re.compile(r'\[(?P<stamp>\d+\.\d+)\] \[\S*simulator\]: all matched after .*'
                           r'clock starts')
_REACHED = re.compile(r'\[(?P<stamp>\d+\.\d+)\] \[\S*simulator\]: reached t = (?P<t>\S+) s')
_STATE_TIME = re.compile(r'\((?P<t>\S+) s of state time\)')   # an estimator's last words


# ----------------------------------------------------------------------------- the plan
@dataclass(frozen=True)
class Sub:
    """One subscription: absolute topic, type, QoS."""

    topic: str
    type: type
    qos: QoSProfile | int


@dataclass(frozen=True)
class Pub:
    """One publisher and what it sends: ``data`` (serialised) at the steps ``steps`` of the
    process's cycle, or every ``period_s`` of wall time."""

    topic: str
    type: type
    qos: QoSProfile | int
    data: bytes
    steps: frozenset[int] = frozenset()
    period_s: float | None = None


@dataclass(frozen=True)
class ProcessPlan:
    """One process of the floor: its node, entities and schedule. Publications repeat every
    ``cycle`` steps of ``step`` seconds; the timer ticks every ``stride`` steps."""

    name: str
    node: str
    namespace: str
    step: float
    cycle: int
    pubs: tuple[Pub, ...]
    subs: tuple[Sub, ...]

    @property
    def stride(self) -> int:
        return math.gcd(self.cycle, *(k for p in self.pubs for k in p.steps))

    def rate(self, pub: Pub) -> float:
        """Messages per second of one publisher."""
        if pub.period_s is not None:
            return 1.0 / pub.period_s
        return len(pub.steps) / (self.cycle * self.step)


def _ser(msg: Any) -> bytes:
    return serialize_message(msg)


def _steps(cycle: int, every: int) -> frozenset[int]:
    return frozenset(range(0, cycle, every))


def _diagnostics(agent: str, fleet: str) -> bytes:
    """A /diagnostics message of the size an estimator's usually has (the keys its
    ``publish_diagnostics`` fills for a follower)."""
    values = {'state_time_s': '12.340', 'steps_per_wall_second': '100.0',
              'stale_neighbours': '', 'edges_used': '3',
              'conditioning_eigenvalues': '0.5312,1.207,2.262', 'non_finite_steps': '0',
              'gyro_gaps_bridged': '0'}
    status = DiagnosticStatus(name=f'{fleet}{agent}/estimator', hardware_id=agent,
                              level=DiagnosticStatus.OK, message='ok',
                              values=[KeyValue(key=k, value=v) for k, v in values.items()])
    return _ser(DiagnosticArray(status=[status]))


def agent_plan(s: Scenario, name: str, world: World) -> ProcessPlan:
    """What the estimator node of ``name`` subscribes to and publishes (its ``__init__``,
    ``_publish``, ``_send_reply``), with one message of each."""
    method = type(s.estimator())
    spec = agent_specs(s)[s.index[name]]
    rt = runtime_for(s, spec)
    own = lambda topic: wire.topic(name, topic)  # noqa: E731
    chans = {c.name: c for c in method.sends}
    qos_in = wire.SENSOR_QOS
    qos_est = wire.ESTIMATE_RECORD_QOS if method.rounds() == 2 else wire.ESTIMATE_QOS
    frame = wire.estimate_frame(method.frame.value, s.name, s.anchor, s.world_frame)
    sent = [c for c in optional_first(method.sends) if c.sensor is None]
    topics = {t: cs for t, cs in wire.by_topic(sent).items() if t != wire.POSE}
    # Subscriptions, in the node's order.
    subs = [Sub(own(wire.IMU), wire.Imu, qos_in)]
    for sensor in method.measures:
        if not (sensor is Sensor.BEARING_RATES and spec.rate_tau is not None):
            subs.append(Sub(own(sensor.value), wire.PointCloud2, qos_in))
    if method.uses(Sensor.ODOMETRY):
        subs.append(Sub(own(wire.ODOM), wire.Odometry, qos_in))
    if spec.leader:   # known_pose, remapped to ground_truth by the launcher
        subs.append(Sub(own(wire.GROUND_TRUTH), wire.PoseStamped, qos_in))
    for sub in subscriptions(method, spec):
        msg_type = (wire.Odometry if sub.kind == ODOMETRY else wire.PointCloud2
                    if sub.kind == 'points' else wire.channel_type(chans[sub.channels[0]]))
        subs.append(Sub(wire.topic(sub.source, sub.topic), msg_type,
                        qos_est if sub.kind == 'channels' else qos_in))
    subs.append(Sub(wire.CLOCK, ClockMsg, CLOCK_SUB_QOS))   # use_sim_time: the time source
    # One message of each, from the agent's own values at t = 0.
    for sensor in method.measures:   # per-edge values for the agents it measures
        if sensor is Sensor.BEARINGS:
            j, b = world.bearings(s.index[name])
        elif sensor.value in world.sensor_every:
            j, b = world.sensed(sensor.value, s.index[name])
        else:
            continue
        rt.add_points(sensor, 0.0, j + 1, b)
    values: dict[str, Any] = dict(rt.outbox())
    for c in method.sends:   # a second round: one value per robot it goes to
        if c.round == 2:
            values[c.name] = rt._addressed(c, np.tile(np.ones(c.shape) / np.sqrt(
                np.prod(c.shape)), (len(rt.peers),) + (1,) * len(c.shape)))
    t = 0.0
    data = {}
    for topic, cs in topics.items():
        content = {c.name: values[c.name] for c in cs
                   if c.name in values and not (isinstance(values[c.name], dict)
                                                and not values[c.name])}
        if content:
            data[topic] = wire.encode_channels(t, wire.channel_frame(
                cs[0], name, frame, s.world_frame), cs, content)
    estimate = wire.cdr.encode_pose_raw(t, frame, rt.R0, rt.p0)
    pose = wire.cdr.encode_pose_covariance_raw(t, frame, rt.R0, rt.p0, rt.covariance())
    # When the node publishes each, over a cycle of steps.
    h, every = s.step, max(1, int(round(1.0 / (s.step * s.publish_rate))))
    cycle = every * max(1, int(round(s.frequency)))
    when: dict[str, set[int]] = {n: set() for n in ['estimate', *topics]}
    estimator = s.estimator()

    def sends(c: Any, k: int) -> bool:
        return (estimator.due(c.name, k * h, h) if c.pairing == 'exact' else k % every == 0)
    for k in range(cycle):
        if k % every == 0 or any(sends(c, k) for c in sent if c.topic == wire.POSE):
            when['estimate'].add(k)
        for topic, cs in topics.items():
            if any(c.round == 2 or sends(c, k) for c in cs):
                when[topic].add(k)
    cycle = _period(cycle, when.values())
    when = {n: {k for k in steps if k < cycle} for n, steps in when.items()}
    pubs = [Pub(own(wire.ESTIMATE), wire.PoseStamped, wire.ESTIMATE_PUB_QOS, estimate,
                frozenset(when['estimate']))]
    pubs += [Pub(own(topic), wire.channel_type(cs[0]), qos_est, data.get(topic, b''),
                 frozenset(when[topic]) if topic in data else frozenset())
             for topic, cs in topics.items()]
    if any(c.topic == wire.POSE for c in sent):
        pubs.append(Pub(own(wire.POSE), wire.PoseWithCovarianceStamped,
                        wire.ESTIMATE_PUB_QOS, pose, frozenset(when['estimate'])))
    pubs.append(Pub(wire.DIAGNOSTICS, DiagnosticArray, DIAGNOSTICS_QOS,
                    _diagnostics(name, ''), period_s=DIAGNOSTICS_PERIOD_S))
    return ProcessPlan(name, 'estimator', f'/{name}', h, cycle, tuple(pubs), tuple(subs))


def _period(cycle: int, patterns: Iterable[set[int]]) -> int:
    """The shortest period (a divisor of ``cycle``) of steps ``patterns`` over ``cycle``."""
    patterns = list(patterns)
    return next(d for d in range(1, cycle + 1) if cycle % d == 0
                and all(steps == {k for k in range(cycle) if k % d in steps}
                        for steps in patterns))


def simulator_plan(s: Scenario) -> ProcessPlan:
    """What the simulator node publishes (``_publish``, ``_publish_sensor``) and subscribes
    to, with one message of each from the world at one instant."""
    w = World(s)
    names = [a.name for a in s.agents]
    clock_every = max(1, int(round(s.step / w.dt)))
    everys = [w.imu_every, w.bearing_every, w.truth_every, clock_every,
              *w.sensor_every.values()]
    cycle = math.lcm(*everys)
    for _ in range(cycle):   # an instant at which everything is due
        w.step()
    t = w.t
    imu = w.imu()
    odometry = w.odometry() if 'odometry' in w.sensor_every else None
    qos = wire.SIM_PUB_QOS
    pubs = []
    for i, name in enumerate(names):   # the node creates imu, bearings, ground truth per agent
        j, b = w.bearings(i)
        pubs += [Pub(wire.topic(name, wire.IMU), wire.Imu, qos,
                     wire.cdr.encode_imu_raw(t, name, imu[i]), _steps(cycle, w.imu_every)),
                 Pub(wire.topic(name, wire.BEARINGS), wire.PointCloud2, qos,
                     wire.cdr.encode_vectors_raw(t, wire.body_frame(name), j + 1, b),
                     _steps(cycle, w.bearing_every)),
                 Pub(wire.topic(name, wire.GROUND_TRUTH), wire.PoseStamped, qos,
                     wire.cdr.encode_pose_raw(t, s.world_frame, w.R[i], w.p[i]),
                     _steps(cycle, w.truth_every))]
    for sensor, every in w.sensor_every.items():
        spec = s.sensors.spec(sensor)
        for i, name in enumerate(names):
            if sensor == 'odometry':
                assert odometry is not None
                msg = wire.cdr.encode_odometry_raw(t, name, odometry[0][i], odometry[1][i],
                                                   w.odom_R[i], w.odom_p[i], spec.std,
                                                   spec.angular_std)
            else:
                j, values = w.sensed(sensor, i)
                encode = (wire.cdr.encode_scalars_raw if sensor == 'ranges'
                          else wire.cdr.encode_vectors_raw)
                msg = encode(t, wire.body_frame(name), j + 1, values)
            pubs.append(Pub(wire.topic(name, wire.SENSOR_TOPICS[sensor]),
                            wire.SENSOR_TYPES[sensor], qos, msg, _steps(cycle, every)))
    pubs.append(Pub(wire.CLOCK, ClockMsg, wire.CLOCK_QOS,
                    wire.cdr.encode_clock_raw(t), _steps(cycle, clock_every)))
    subs = [Sub(wire.topic(n, wire.ESTIMATE), wire.PoseStamped, wire.ESTIMATE_QOS)
            for n in names]
    subs.append(Sub(wire.MONITOR_READY, Empty, wire.LATCHED_QOS))
    # Publication order within an instant as in _publish: gyro, bearings, sensors, truth,
    # clock (the order of the list above groups by agent; each instant's set is the same).
    order = {wire.IMU: 0, wire.BEARINGS: 1, **{v: 2 for v in wire.SENSOR_TOPICS.values()},
             wire.GROUND_TRUTH: 3}
    pubs.sort(key=lambda p: order.get(p.topic.rsplit('/', 1)[-1], 4))
    return ProcessPlan('simulator', 'simulator', '/', w.dt, cycle, tuple(pubs), tuple(subs))


def monitor_plan(s: Scenario) -> ProcessPlan:
    """What the monitor node reads (and its /monitor/ready writer, which publishes nothing
    here: the floor's simulator does not wait for it)."""
    subs = [Sub(wire.topic(n, wire.GROUND_TRUTH), wire.PoseStamped, wire.SIM_PUB_QOS)
            for n in watched(s)]
    subs += [Sub(wire.topic(a.name, wire.ESTIMATE), wire.PoseStamped,
                 wire.ESTIMATE_RECORD_QOS) for a in s.followers]
    subs.append(Sub(wire.CLOCK, ClockMsg, CLOCK_SUB_QOS))
    pubs = (Pub(wire.DIAGNOSTICS, DiagnosticArray, DIAGNOSTICS_QOS, b''),
            Pub(wire.MONITOR_READY, Empty, wire.LATCHED_QOS, b''))
    return ProcessPlan('monitor', 'monitor', '/', 1.0, 1, pubs, tuple(subs))


def fleet_plan(s: Scenario, omit: Collection[str] = (),
               per_process: int = 1) -> dict[str, ProcessPlan]:
    """Every process of the floor, in the launcher's start order (agents, monitor,
    simulator); without the topics whose last name is in ``omit`` (``clock``, ``pose``:
    what one kind of message costs is the difference). With ``per_process`` agents in a
    process, only the first of them reads ``/clock`` (``estimator_group.share_clock``)."""
    world = World(s)
    plans = {a.name: agent_plan(s, a.name, world) for a in s.agents}
    for k, name in enumerate([a.name for a in s.agents]):
        if k % max(1, per_process):
            p = plans[name]
            plans[name] = replace(p, subs=tuple(x for x in p.subs if x.topic != wire.CLOCK))
    plans['monitor'] = monitor_plan(s)
    plans['simulator'] = simulator_plan(s)
    kept = lambda topic: topic.rsplit('/', 1)[-1] not in omit  # noqa: E731
    return {name: replace(p, pubs=tuple(x for x in p.pubs if kept(x.topic)),
                          subs=tuple(x for x in p.subs if kept(x.topic)))
            for name, p in plans.items()}


def peers(plans: dict[str, ProcessPlan]) -> tuple[Counter[str], Counter[str]]:
    """Per topic: how many subscriptions (readers) and publishers (writers) the fleet has."""
    readers = Counter(sub.topic for p in plans.values() for sub in p.subs)
    writers = Counter(pub.topic for p in plans.values() for pub in p.pubs)
    return readers, writers


def traffic(plans: dict[str, ProcessPlan]) -> dict[str, dict[str, float]]:
    """Per process: subscriptions, messages received and published per second, bytes
    published per second (one copy per message, whatever the readers)."""
    rate = {pub.topic: 0.0 for p in plans.values() for pub in p.pubs}
    for p in plans.values():
        for pub in p.pubs:
            rate[pub.topic] += p.rate(pub)
    return {name: {'subs': len(p.subs),
                   'received': sum(rate.get(sub.topic, 0.0) for sub in p.subs),
                   'published': sum(p.rate(pub) for pub in p.pubs),
                   'bytes': sum(p.rate(pub) * len(pub.data) for pub in p.pubs)}
            for name, p in plans.items()}


# ----------------------------------------------------------------------------- a process
class FloorNode(Node):
    """One process of the floor: its plan's entities; raw subscriptions that count; once
    everything is matched, the plan's publications on wall-clock timers."""

    def __init__(self, plan: ProcessPlan, readers: Counter[str], writers: Counter[str],
                 aligned: bool = True) -> None:
        super().__init__(plan.node, namespace=plan.namespace)
        self.plan, self.readers, self.writers, self.aligned = plan, readers, writers, aligned
        self.pubs = [(self.create_publisher(p.type, p.topic, p.qos), p) for p in plan.pubs]
        self.subs = [(self.create_subscription(s.type, s.topic, self._count, s.qos, raw=True),
                      s) for s in plan.subs]
        self.received = self.published = 0
        self.tick, self.stride, self.cycle = 0, plan.stride, plan.cycle
        self.due: dict[int, list[tuple[Any, bytes]]] = {}
        for pub, p in self.pubs:
            for k in sorted(p.steps):
                self.due.setdefault(k, []).append((pub, p.data))
        self.started = time.monotonic()
        self.matched_at: float | None = None
        self._said = 0.0
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.ready_timer = self.create_timer(0.05, self._check, clock=self.steady)

    def _count(self, _msg: bytes) -> None:
        self.received += 1

    def _unmatched(self) -> list[str]:
        out = [f'{p.topic} (readers)' for pub, p in self.pubs
               if pub.get_subscription_count() < self.readers[p.topic]]
        return out + [f'{s.topic} (writers)' for sub, s in self.subs
                      if sub.get_publisher_count() < self.writers[s.topic]]

    def _check(self) -> None:
        missing = self._unmatched()
        now = time.monotonic()
        if missing:
            if now - self._said > 5.0:
                self._said = now
                self.get_logger().info(f'waiting for {len(missing)}: {", ".join(missing[:6])}')
            return
        self.ready_timer.cancel()
        self.matched_at = now
        self.get_logger().info(f'FLOOR matched after {now - self.started:.2f} s')
        if self.due:
            self._start_grid(now)
        self._log_counts()
        self.create_timer(COUNT_PERIOD_S, self._log_counts, clock=self.steady)
        for pub, p in self.pubs:
            if p.period_s is not None:
                self.create_timer(p.period_s, lambda pub=pub, data=p.data: self._send(pub, data),
                                  clock=self.steady)

    def _start_grid(self, now: float) -> None:
        """The step timer. ``aligned``: its step 0 on a multiple of the cycle's duration on
        the monotonic clock (rclpy's steady time), shared by every process: their instants
        then coincide, as the nodes' do (an estimator publishes right after the simulator's
        sample that completes its step), and each wake-up takes what is due at once. Else
        its phase is wherever matching ended."""
        period = self.plan.step * self.stride
        if not self.aligned:
            self.tick = 0
            self.create_timer(period, self._on_tick, clock=self.steady)
            return
        cycle = self.plan.step * self.cycle
        first = (math.floor(now / cycle) + 2) * cycle   # step 0

        def start() -> None:
            waiting.cancel()
            time.sleep(max(0.0, first - period - time.monotonic()))
            self.tick = -1   # the timer's first call is one period after its creation
            self.create_timer(period, self._on_tick, clock=self.steady)

        waiting = self.create_timer(max(first - period - now - 0.002, 1e-4), start,
                                    clock=self.steady)

    def _log_counts(self) -> None:
        self.get_logger().info(f'FLOOR count {self.published} {self.received}')

    def _send(self, pub: Any, data: bytes) -> None:
        pub.publish(data)
        self.published += 1

    def _on_tick(self) -> None:
        self.tick += 1
        for pub, data in self.due.get(self.tick * self.stride % self.cycle, ()):
            pub.publish(data)
            self.published += 1


def process_main(role: str, scenario_file: str, aligned: bool, omit: Collection[str],
                 per_process: int) -> None:
    """One process of the floor (``--role``: a plan's name, or agents' names joined by commas
    for agents that share a process, as an ``estimators`` process runs them)."""
    scenario = load_scenario(scenario_file)
    plans = fleet_plan(scenario, omit, per_process)
    readers, writers = peers(plans)
    names = role.split(',')
    raise SystemExit(run_node(
        lambda: [FloorNode(plans[n], readers, writers, aligned) for n in names], names[0]))


def process_groups(agents: Sequence[str], others: Iterable[str],
                   per_process: int) -> dict[str, list[str]]:
    """A run's processes: name -> what it runs. Consecutive agents share a process as
    ``plan_processes`` groups them (:func:`estimator_groups`); the ``others``
    (monitor, simulator) and, with ``per_process`` 1, each agent run alone."""
    out = ({name: [name] for name in agents} if per_process <= 1
           else estimator_groups(agents, per_process))
    out.update({name: [name] for name in others})
    return out


# ----------------------------------------------------------------------------- measuring
@dataclass
class Measured:
    """One run: CPU per second [% of a core] of each process, its kind's figures."""

    agent_pct: list[float]          # per agent process (shared: its CPU / its agents)
    simulator_pct: float
    monitor_pct: float
    speed: float                    # the nodes: simulated / wall seconds in the window
    rate: float = 1.0               # the floor: share of its planned traffic an agent moved
    window_s: float = 0.0
    notes: list[str] = field(default_factory=list)
    us_per_message: list[float] = field(default_factory=list)  # the floor: CPU per message
    others_pct: float = math.nan    # what other processes used meanwhile [% of a core]

    @property
    def agent_median(self) -> float:
        return statistics.median(self.agent_pct) if self.agent_pct else float('nan')


def _log(path: Path) -> str:
    try:
        return path.read_text(errors='replace')
    except OSError:
        return ''


def run_floor(scenario_file: Path, scenario: Scenario, plans: dict[str, ProcessPlan],
              duration: float, warmup: float, domain_id: int, work: Path,
              phases: str = 'aligned', omit: Sequence[str] = (),
              match_timeout: float = MATCH_TIMEOUT_S, per_process: int = 1) -> Measured:
    """Start the floor's processes (``per_process`` agents in each agent process), wait until
    every node is matched (at most ``match_timeout`` s), measure the window."""
    logs = work / 'logs'
    env = dds_env(domain_id, logs / 'ros')
    me = [sys.executable, str(Path(__file__).resolve()), '--scenario', str(scenario_file),
          '--phases', phases, *(['--omit', *omit] if omit else []),
          '--per-process', str(per_process)]
    agents = [a.name for a in scenario.agents]
    groups = process_groups(agents, [n for n in plans if n not in agents], per_process)
    specs = [ProcessSpec(name, 'floor', tuple(me + ['--role', ','.join(members)]),
                         logs / f'{name}.log') for name, members in groups.items()]
    before = shm_files()
    notes = []
    with launch.ProcessGroup(env) as group:
        for spec in specs:
            group.start(spec)
        deadline = time.monotonic() + match_timeout
        while not all(len(_MATCHED.findall(_log(spec.log))) >= len(groups[spec.name])
                      for spec in specs):
            dead = [n for n in groups if group.returncode(n) is not None]
            if dead or time.monotonic() > deadline:
                group.shutdown()
                why = f'{dead[0]} exited' if dead else f'not matched in {match_timeout:g} s'
                raise RuntimeError(f'floor: {why}; logs in {logs}')
            time.sleep(0.05)
        time.sleep(warmup)   # everything is matched: the first messages settle
        cpu0, t0, others0 = group.cpu_seconds(), time.time(), _others_cpu()
        time.sleep(duration)
        cpu1, t1, others1 = group.cpu_seconds(), time.time(), _others_cpu()
        time.sleep(COUNT_PERIOD_S * 1.5)   # the counts just after the window
        killed = group.shutdown()
        unclean = group.unclean()
    if killed or unclean:
        notes.append(f'unclean stop: {killed or unclean}')
    if leaked_shm(before):
        notes.append('files left in /dev/shm')
    # How much of its planned traffic (received and published) each process moved in the
    # window; its CPU is scaled to the plan (1.0 unless the machine could not keep up).
    flow = traffic(plans)
    done, moved = {}, {}
    for spec in specs:
        counts: dict[str, list[tuple[float, float]]] = {}   # per node of the process
        for m in _COUNTS.finditer(_log(spec.log)):
            counts.setdefault(m['node'], []).append(
                (float(m['stamp']), int(m['pub']) + int(m['sub'])))
        moved[spec.name] = sum(_at(c, t1) - _at(c, t0) for c in counts.values())
        planned = sum(flow[n]['received'] + flow[n]['published'] for n in groups[spec.name])
        if planned > 0:
            done[spec.name] = moved[spec.name] / (planned * (t1 - t0))
    # An agent process's CPU is shared by its agents.
    pct = {n: 100.0 * (cpu1[n] - cpu0[n]) / (t1 - t0) / done.get(n, 1.0) / len(groups[n])
           for n in groups if n in cpu0 and n in cpu1}
    procs = [n for n in groups if n not in ('simulator', 'monitor') and n in pct]
    notes.append(f'simulator sent {100 * done.get("simulator", math.nan):.0f} % of the plan')
    return Measured(
        [pct[n] for n in procs], pct.get('simulator', math.nan), pct.get('monitor', math.nan),
        speed=1.0, rate=statistics.median(done.get(n, math.nan) for n in procs),
        window_s=t1 - t0, notes=notes,
        us_per_message=[1e6 * (cpu1[n] - cpu0[n]) / moved[n] for n in procs if moved[n] > 0],
        others_pct=100.0 * (others1 - others0) / (t1 - t0))


def _at(series: Sequence[tuple[float, float]], x: float) -> float:
    """``series`` (time, value), increasing in time, linearly interpolated at ``x`` (NaN
    outside it)."""
    for (ta, a), (tb, b) in zip(series, series[1:]):
        if ta <= x <= tb:
            return a + (b - a) * ((x - ta) / (tb - ta) if tb > ta else 1.0)
    return math.nan


def _stat(proc: Path) -> list[str]:
    """The fields of /proc/<pid>/stat after the command name (state, ppid, ...; utime is
    [11]); empty if the process is gone."""
    try:
        return (proc / 'stat').read_text().rsplit(')', 1)[1].split()
    except (OSError, IndexError):
        return []


def _children() -> dict[str, int]:
    """This process's children (a run's nodes) by name (an estimator's: its namespace; an
    ``estimators`` process's: ``estimators:`` and its agents joined by commas)."""
    out = {}
    me = os.getpid()
    for proc in Path('/proc').glob('[0-9]*'):
        fields = _stat(proc)
        if not fields or int(fields[1]) != me:
            continue
        try:
            raw = (proc / 'cmdline').read_bytes().decode(errors='replace')
            args = raw.rstrip('\0').split('\0')
        except OSError:
            continue
        name = Path(args[1]).name if len(args) > 1 else '?'
        ns = next((a.split(':=', 1)[1].strip('/') for a in args if a.startswith('__ns:=')), '')
        if name == 'estimators':
            ns = 'estimators:' + ','.join(group_args(args[1:]).agents)
        out[ns or name] = int(proc.name)
    return out


def _machine_busy() -> float:
    """CPU seconds the whole machine has spent busy (all cores; not idle, not iowait)."""
    fields = [int(v) for v in Path('/proc/stat').read_text().split('\n', 1)[0].split()[1:]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = fields[:8]
    return (user + nice + system + irq + softirq + steal) / os.sysconf('SC_CLK_TCK')


def _others_cpu() -> float:
    """CPU seconds used so far by every process but this one and its children, with what
    their own exited children used (``cutime``, ``cstime``): the difference between two
    calls is what the rest of the machine used in between, short-lived processes (tests)
    included once their parent has reaped them."""
    me, total = os.getpid(), 0
    for proc in Path('/proc').glob('[0-9]*'):
        fields = _stat(proc)
        if fields and int(proc.name) != me and int(fields[1]) != me:
            total += sum(int(v) for v in fields[11:15])   # utime stime cutime cstime
    return total / os.sysconf('SC_CLK_TCK')


def wait_quiet(below: float, timeout: float = 600.0) -> float:
    """Wait until the machine (without us: call it between runs) stays under ``below`` % of
    a core for 2 s, at most ``timeout`` s; return what it used last [% of a core]."""
    deadline, said = time.monotonic() + timeout, False
    while True:
        busy0 = _machine_busy()
        time.sleep(2.0)
        used = 100.0 * (_machine_busy() - busy0) / 2.0
        if used < below or time.monotonic() > deadline:
            return used
        if not said:
            print(f'  (waiting: other processes use {used:.0f} % of a core)', flush=True)
            said = True


def _cpu_seconds(pid: int) -> float | None:
    """CPU time (user + system, every thread) of a live process so far, from /proc."""
    fields = _stat(Path(f'/proc/{pid}'))
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK') if fields else None


class _RunSampler(threading.Thread):
    """Samples the CPU of a ``bearing-pose run``'s processes while it runs, and finds the
    window in the simulator's log: from ``warmup`` wall seconds after it started the clock to
    the end of the run, or to ``window`` wall seconds later: it then stops the monitor with
    SIGINT (the monitor writes what it has and exits; the launcher stops the rest, as when a
    run is done)."""

    def __init__(self, logs: Path, processes: int, warmup: float, window: float) -> None:
        super().__init__(daemon=True)
        self.logs, self.processes, self.warmup, self.window = logs, processes, warmup, window
        self.pids: dict[str, int] = {}
        self.samples: list[tuple[float, dict[str, float]]] = []   # (wall, CPU by process)
        self.clock_at: float | None = None       # wall time the clock started (t = 0)
        self.end_at: tuple[float, float | None] | None = None   # (wall, simulated or None)
        self.others: list[tuple[float, float]] = []   # (wall, _others_cpu()) at both ends
        self.finished = False                    # the run is over: stop sampling

    def run(self) -> None:
        while True:
            if len(self.pids) < self.processes:   # until every node has started
                self.pids = _children()
            now = time.time()
            cpu = {name: _cpu_seconds(pid) for name, pid in self.pids.items()}
            self.samples.append((now, {k: c for k, c in cpu.items() if c is not None}))
            if self.end_at is not None:
                self.others.append((time.time(), _others_cpu()))
                return   # one sample after the end
            log = _log(self.logs / 'simulator.log')
            if self.clock_at is None and (m := _CLOCK_STARTS.search(log)):
                self.clock_at = float(m['stamp'])
            start = math.inf if self.clock_at is None else self.clock_at + self.warmup
            if not self.others and now >= start:
                self.others.append((now, _others_cpu()))
            if (m := _REACHED.search(log)):
                self.end_at = (float(m['stamp']), float(m['t']))
                continue
            if self.finished:
                return
            if now >= start + self.window:
                self.end_at = (now, None)
                self.others.append((time.time(), _others_cpu()))
                with contextlib.suppress(ProcessLookupError, KeyError):
                    os.kill(self.pids['monitor'], signal.SIGINT)
                return
            time.sleep(SAMPLE_S)

    def cpu_at(self, wall: float) -> dict[str, float]:
        """Each process's CPU seconds at ``wall``, interpolated between samples (a process
        that has exited: its last value)."""
        out = {}
        for n in {n for _, cpu in self.samples for n in cpu}:
            series = [(t, cpu[n]) for t, cpu in self.samples if n in cpu]
            out[n] = series[-1][1] if wall > series[-1][0] else _at(series, wall)
        return out


def run_nodes(scenario_file: Path, scenario: Scenario, duration: float, warmup: float,
              domain_id: int, work: Path, per_process: int = 1) -> Measured:
    """``bearing-pose run`` of the scenario (fleet_scale's configuration, ``per_process``
    agents in each estimator process), measured over the window."""
    cfg = run_config(scenario_file, work, warmup + duration, domain_id, per_process)
    work.mkdir(parents=True, exist_ok=True)
    processes = process_groups([a.name for a in scenario.agents], ['simulator', 'monitor'],
                               per_process)
    sampler = _RunSampler(cfg.logs_dir, len(processes), warmup, duration)
    before = shm_files()
    sampler.start()
    try:
        with (work / 'run.out').open('w') as out, contextlib.redirect_stdout(out), \
                contextlib.redirect_stderr(out):
            result = launch.launch_run(scenario, cfg)
    finally:
        sampler.finished = True
        sampler.join()
    notes = []
    if not result.ok:
        notes.append(f'run failed: {result.failure.format() if result.failure else "?"}')
    if leaked_shm(before):
        notes.append('files left in /dev/shm')
    if sampler.clock_at is None or sampler.end_at is None:
        raise RuntimeError(f'nodes: no window found; logs in {cfg.logs_dir}')
    w1, s1 = sampler.end_at
    log = _log(cfg.logs_dir / 'simulator.log')
    if s1 is None and (m := _REACHED.search(log)) and float(m['stamp']) <= w1:
        w1, s1 = float(m['stamp']), float(m['t'])   # it ended just before we stopped it
    if s1 is None:   # stopped by us: where the estimators' state was
        times = [float(m['t']) for name in processes if name not in ('simulator', 'monitor')
                 for m in _STATE_TIME.finditer(_log(cfg.logs_dir / f'{name}.log'))]
        s1 = statistics.median(times) if times else math.nan
        notes.append(f'stopped at t = {s1:.2f} s (simulated)')
    # The clock's pace over the run, taken as constant to place the window's start.
    w0 = sampler.clock_at + warmup
    speed = s1 / (w1 - sampler.clock_at)
    sim_s = s1 - speed * warmup
    cpu0, cpu1 = sampler.cpu_at(w0), sampler.cpu_at(w1)
    pct = {n: 100.0 * (cpu1[n] - cpu0[n]) / sim_s for n in cpu0.keys() & cpu1.keys()}
    shared = {n: n.split(':', 1)[1].split(',') for n in pct if n.startswith('estimators:')}
    for n, members in shared.items():   # an estimators process: its CPU per agent
        pct.update(dict.fromkeys(members, pct.pop(n) / len(members)))
    stats = simulator_stats(log)
    if 'missed' in stats:
        notes.append(f'missed {stats["missed"]:.1f} %')
    (o0, c0), (o1, c1) = (sampler.others + [(math.nan, math.nan)] * 2)[:2]
    return Measured([pct[a.name] for a in scenario.agents if a.name in pct],
                    pct.get('simulator', math.nan), pct.get('monitor', math.nan),
                    speed=speed, window_s=w1 - w0, notes=notes,
                    others_pct=100.0 * (c1 - c0) / (o1 - o0))


# ----------------------------------------------------------------------------- the bench
def prepare(spec: str, method: str | None, work: Path) -> tuple[str, Path, Scenario]:
    """``FILE[:METHOD]`` as a scenario file the nodes can run: the method changed (as
    ``bearing-pose compare`` derives it), a paper-mode formation controller made exogenous
    (as ``bearing-pose run --formation-mode exogenous``)."""
    path, _, own = spec.partition(':')
    method = own or method
    data = read_scenario_data(path)
    scenario = load_scenario(path)
    if method and method != scenario.method:
        data = method_data(data, scenario, method)
    if isinstance(data.get('formation_control'), dict) \
            and data['formation_control'].get('mode') == 'paper':
        data['formation_control']['mode'] = 'exogenous'
    derived = work / f'{Path(path).stem}_{method or scenario.method}.yaml'
    derived.write_text(yaml.safe_dump(data, sort_keys=False, width=100))
    scenario = load_scenario(derived)
    report = check_scenario(scenario)
    if report.errors:
        raise SystemExit(f'{spec}: {scenario.method} cannot run it: {report.errors[0]}')
    return f'{Path(path).stem} / {scenario.method}', derived, scenario


def describe(label: str, plans: dict[str, ProcessPlan]) -> None:
    """What the floor moves, per process."""
    flow = traffic(plans)
    print(f'\n{label}: what each floor process does (per second; bytes: one copy per message)\n')
    print('| process | subscriptions | received [msg/s] | published [msg/s] | published [kB/s] '
          '| publications: topic (writers x rate, size) |')
    print('|---|---|---|---|---|---|')
    for name, p in plans.items():
        f = flow[name]
        groups: dict[tuple[str, float], list[int]] = {}
        for pub in p.pubs:
            if p.rate(pub) > 0:
                groups.setdefault((pub.topic.rsplit('/', 1)[-1], p.rate(pub)),
                                  []).append(len(pub.data))
        pubs = ', '.join(
            f'{leaf} ({len(sizes)} x {rate:g}/s, '
            f'{min(sizes) if min(sizes) == max(sizes) else f"{min(sizes)}-{max(sizes)}"} B)'
            for (leaf, rate), sizes in groups.items())
        print(f'| {name} | {f["subs"]} | {f["received"]:.0f} | {f["published"]:.0f} | '
              f'{f["bytes"] / 1e3:.1f} | {pubs or "-"} |')


def _spread(values: Sequence[float], fmt: Callable[[float], str]) -> str:
    values = [v for v in values if not math.isnan(v)]
    if not values:
        return 'n/a'
    mid = fmt(statistics.median(values))
    if len(values) == 1:
        return mid
    return f'{mid} ({fmt(min(values))}-{fmt(max(values))})'


def _pct(v: float) -> str:
    return f'{v:.1f} %'


@contextlib.contextmanager
def _workdir(keep: str | None) -> Iterator[Path]:
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        yield Path(keep)
    else:
        with tempfile.TemporaryDirectory(prefix='transport_floor_') as tmp:
            yield Path(tmp)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--scenario', nargs='+', default=['config/paper_8_agents.yaml'],
                    help='scenario files, each optionally FILE:METHOD')
    ap.add_argument('--method', help='run every scenario without its own :METHOD with this one')
    ap.add_argument('--duration', type=float, default=20.0,
                    help='measured window [s]: wall for the floor, simulated for the nodes '
                         '(at most as many wall seconds)')
    ap.add_argument('--warmup', type=float, default=2.0,
                    help='wall seconds after matching (floor) or the clock\'s start (nodes) '
                         'left out of the window')
    ap.add_argument('--repeat', type=int, default=2,
                    help='runs of each configuration, floor and nodes alternating')
    ap.add_argument('--domain-id', type=int, default=60,
                    help='ROS_DOMAIN_ID of the first run; runs take the next ones (mod 10)')
    ap.add_argument('--floor-only', action='store_true', help='no run of the real nodes')
    ap.add_argument('--phases', choices=['aligned', 'spread'], default='aligned',
                    help="the floor processes' publication instants: on one grid (default) or "
                         'wherever each one finished matching')
    ap.add_argument('--omit', nargs='+', default=[], metavar='TOPIC',
                    help='leave these topics (last name: clock, pose, ...) out of the floor')
    ap.add_argument('--logs', help='keep every run\'s files in this directory')
    ap.add_argument('--match-timeout', type=float, default=MATCH_TIMEOUT_S, metavar='S',
                    help='wall seconds the floor\'s processes may take to match (large fleets)')
    ap.add_argument('--quiet-below', type=float, default=30.0, metavar='PCT',
                    help='before each run, wait (at most 10 min) until the rest of the machine '
                         'uses less than this [%% of a core]')
    ap.add_argument('--per-process', type=int, default=1, metavar='K',
                    help='agents per estimator process, floor and nodes (bearing-pose run '
                         '--agents-per-process)')
    ap.add_argument('--role', help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role:
        return process_main(args.role, args.scenario[0], args.phases == 'aligned', args.omit,
                            args.per_process)
    start = time.strftime('%Y-%m-%d %H:%M')
    load = os.getloadavg()
    rows = []
    runs = 0

    def domain() -> int:
        nonlocal runs
        runs += 1
        return args.domain_id - args.domain_id % 10 + (args.domain_id + runs - 1) % 10

    with _workdir(args.logs) as work:
        for spec in args.scenario:
            label, path, scenario = prepare(spec, args.method, work)
            plans = fleet_plan(scenario, args.omit, args.per_process)
            describe(label, plans)
            floors, nodes = [], []
            for r in range(args.repeat):
                wait_quiet(args.quiet_below)
                floors.append(run_floor(path, scenario, plans, args.duration, args.warmup,
                                        domain(), work / f'{path.stem}_floor_{r}',
                                        args.phases, args.omit, args.match_timeout,
                                        args.per_process))
                print(f'  floor run {r + 1}: agents {floors[-1].agent_median:.1f} % (median), '
                      f'simulator {floors[-1].simulator_pct:.1f} %, monitor '
                      f'{floors[-1].monitor_pct:.1f} %; agents moved {100 * floors[-1].rate:.0f} %'
                      f' of their planned traffic; others {floors[-1].others_pct:.0f} %; '
                      f'{"; ".join(floors[-1].notes)}', flush=True)
                if args.floor_only:
                    continue
                wait_quiet(args.quiet_below)
                nodes.append(run_nodes(path, scenario, args.duration, args.warmup, domain(),
                                       work / f'{path.stem}_nodes_{r}', args.per_process))
                print(f'  nodes run {r + 1}: agents {nodes[-1].agent_median:.1f} % (median), '
                      f'simulator {nodes[-1].simulator_pct:.1f} %, monitor '
                      f'{nodes[-1].monitor_pct:.1f} %, speed {nodes[-1].speed:.2f}x over '
                      f'{nodes[-1].window_s:.1f} s; others {nodes[-1].others_pct:.0f} %; '
                      f'{"; ".join(nodes[-1].notes)}', flush=True)
            shared = f', {args.per_process} per process' if args.per_process > 1 else ''
            rows.append((label + shared, len(scenario.agents), floors, nodes))
    print(f'\nStarted {start}, load average before {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, '
          f'after {" ".join(f"{v:.2f}" for v in os.getloadavg())}; {args.repeat} run(s) each, '
          f'window {args.duration:g} s after {args.warmup:g} s; medians (ranges). CPU in % of '
          'one core: the floor per wall second, the nodes per simulated second; others: what '
          'the rest of the machine used meanwhile.\n')
    print('| scenario / method | agents | floor CPU per agent | node CPU per agent | ratio | '
          'floor simulator | node simulator | floor monitor | node monitor | floor rate | '
          'node speed | floor µs per agent message | others (floor, nodes) |')
    print('|---|---|---|---|---|---|---|---|---|---|---|---|---|')
    pct, x = _pct, (lambda v: f'{v:.2f}x')
    for label, n, floors, nodes in rows:
        f_agent = statistics.median(m.agent_median for m in floors)
        n_agent = statistics.median(m.agent_median for m in nodes) if nodes else math.nan
        us = [statistics.median(m.us_per_message) for m in floors if m.us_per_message]
        cells = [label, str(n), _spread([m.agent_median for m in floors], pct),
                 _spread([m.agent_median for m in nodes], pct), f'{n_agent / f_agent:.1f}',
                 _spread([m.simulator_pct for m in floors], pct),
                 _spread([m.simulator_pct for m in nodes], pct),
                 _spread([m.monitor_pct for m in floors], pct),
                 _spread([m.monitor_pct for m in nodes], pct),
                 _spread([100 * m.rate for m in floors], lambda v: f'{v:.0f} %'),
                 _spread([m.speed for m in nodes], x), _spread(us, lambda v: f'{v:.0f}'),
                 f'{_spread([m.others_pct for m in floors], pct)}, '
                 f'{_spread([m.others_pct for m in nodes], pct)}']
        print('| ' + ' | '.join(cells) + ' |')

if __name__ == '__main__':
    main()
