"""How many processes of one domain discover each other on localhost.

Starts N idle processes (one rclpy context, so one DDS participant, each) on a private
domain with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, as every run here uses, then two more:
one subscribes to a probe topic, the other publishes it and waits (at most ``--wait`` s) until
its writer has the reader. Prints, per N, whether and when they matched. Every process is
stopped with SIGINT and shuts rclpy down; what Fast DDS still leaves in /dev/shm is removed
and reported.

    .venv/bin/python bench/discovery_limit.py [--idle 5 30 31 32] [--wait 30]

Measured 2026-12-06 (BENCHMARKS.md, "Discovery"): the pair matches within a second after 5,
30 or 31 idle processes and never after 32: the 33rd and 34th participants of a domain never
discover each other, which is why ``bearing-pose run`` uses at most 32 processes
(``plan.processes.MAX_PROCESSES``).
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time

from bearing_pose_estimation.plan import dds

CHILD = r'''
import sys, time
import rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import Empty

role, wait = sys.argv[1], float(sys.argv[2])
rclpy.init()
node = rclpy.create_node(f'probe_{role}')
try:
    if role == 'pub':
        pub = node.create_publisher(Empty, '/discovery_probe', 10)
        t0 = time.monotonic()
        while time.monotonic() - t0 < wait and pub.get_subscription_count() < 1:
            rclpy.spin_once(node, timeout_sec=0.05)
        print(f'{pub.get_subscription_count()} {time.monotonic() - t0:.2f}', flush=True)
    else:
        if role == 'sub':
            node.create_subscription(Empty, '/discovery_probe', lambda _: None, 10)
        print('up', flush=True)
        while rclpy.ok():
            rclpy.spin_once(node, timeout_sec=0.2)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
'''


def _stop(procs: list[subprocess.Popen[str]]) -> list[int]:
    """SIGINT, then SIGTERM, then SIGKILL (a Fast DDS teardown can hang: the nodes have a
    watchdog for it, these probes do not); the pids that needed SIGKILL."""
    killed = []
    for sig, grace in ((signal.SIGINT, 15.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        alive = [p for p in procs if p.poll() is None]
        for proc in alive:
            proc.send_signal(sig)
        deadline = time.monotonic() + grace
        for proc in alive:
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        if sig == signal.SIGKILL:
            killed = [p.pid for p in alive]
    return killed


def probe(n_idle: int, wait: float, domain_id: int) -> tuple[bool, float]:
    """(matched, seconds) for the probe pair started after ``n_idle`` idle processes."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_DOMAIN_ID=str(domain_id), ROS_LOG_DIR=tempfile.mkdtemp())
    start = lambda role: subprocess.Popen(  # noqa: E731
        [sys.executable, '-c', CHILD, role, str(wait)], env=env, stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL, text=True)
    idle: list[subprocess.Popen[str]] = []
    before = dds.shm_files()
    try:
        for _ in range(n_idle):   # one at a time: each takes the next participant id
            idle.append(start('idle'))
            assert idle[-1].stdout is not None
            idle[-1].stdout.readline()
        idle.append(start('sub'))
        assert idle[-1].stdout is not None
        idle[-1].stdout.readline()
        pub = start('pub')
        out, _ = pub.communicate(timeout=wait + 60)
        count, seconds = out.split()
        return int(count) > 0, float(seconds)
    finally:
        killed = _stop(idle)
        left = dds.leaked_shm(before, lockless=True)
        for path in left:
            os.remove(path)
        if killed or left:   # Fast DDS keeps a port file after clean exits now and then
            print(f'  (after {n_idle} idle: {len(killed)} process(es) needed SIGKILL; removed '
                  f'{len(left)} file(s) left in /dev/shm: {", ".join(left)})', flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--idle', type=int, nargs='+', default=[5, 30, 31, 32])
    ap.add_argument('--wait', type=float, default=30.0, help='seconds the pair may take')
    ap.add_argument('--domain-id', type=int, default=90)
    args = ap.parse_args()
    print('| idle processes | the pair are participants | matched | after |')
    print('|---|---|---|---|')
    for n in args.idle:
        matched, seconds = probe(n, args.wait, args.domain_id)
        print(f'| {n} | {n + 1} and {n + 2} | {"yes" if matched else "no"} | '
              f'{seconds:.1f} s |', flush=True)


if __name__ == '__main__':
    main()
