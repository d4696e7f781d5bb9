"""Per-message ceiling: CPU per received message, rclpy's executor against ours.

A publisher process sends one message type (``--type``: Imu, PointCloud2 with three bearings,
PoseStamped; as the nodes encode them) at ``--rate`` for ``--seconds``. The receiver process
holds one active subscription plus ``--idle`` subscriptions on silent topics and a 100 Hz timer,
like an estimator process (8 subscriptions and a timer per agent), and is spun either by
rclpy's SingleThreadedExecutor or by the package's ``ros.executor.DrainingExecutor`` (what the
nodes use: one wait, then every queued message of each ready subscription). Prints CPU time of
the receiver process (all its threads, DDS included) per received message.

    .venv/bin/python bench/executor_ceiling.py [--type Imu] [--rate 4000] [--seconds 5]
        [--idle 0 7 39]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 101))

import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from sensor_msgs.msg import Imu, PointCloud2  # noqa: E402

from bearing_pose_estimation import msg_defs as wire  # noqa: E402
from bearing_pose_estimation.msg_defs import cdr  # noqa: E402
from bearing_pose_estimation.ros.executor import DrainingExecutor  # noqa: E402

QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
# What the nodes exchange: gyro samples, bearing sets (3 bearings), estimates. Message objects:
# the publisher changes each one's stamp.
SAMPLES = {'Imu': lambda: wire.message(cdr.encode_imu_raw(0.0, 'agent_1', [0.1, 0.2, 0.3]),
                                       Imu),
           'PointCloud2': lambda: wire.message(cdr.encode_vectors_raw(
               0.0, 'agent_1/base_link', np.array([2, 3, 4]),
               [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]), PointCloud2),
           'PoseStamped': PoseStamped}


def publish(kind: str, rate: float, seconds: float) -> None:
    rclpy.init()
    node = rclpy.create_node('ceiling_pub')
    msg = SAMPLES[kind]()
    pub = node.create_publisher(type(msg), '/ceiling', QOS)
    while pub.get_subscription_count() < 1:
        time.sleep(0.01)
    time.sleep(0.5)  # let the reader finish matching its other entities
    period, t0 = 1.0 / rate, time.monotonic()
    for k in range(int(rate * seconds)):
        msg.header.stamp.sec = k
        pub.publish(msg)
        delay = t0 + (k + 1) * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    time.sleep(1.0)  # reliable delivery of the tail
    node.destroy_node()
    rclpy.shutdown()


def receive(kind: str, mode: str, idle: int, expected: int, seconds: float) -> None:
    rclpy.init()
    node = rclpy.create_node('ceiling_sub')
    count = [0]
    node.create_subscription(type(SAMPLES[kind]()), '/ceiling',
                             lambda _m: count.__setitem__(0, count[0] + 1), QOS)
    for k in range(idle):
        node.create_subscription(Imu, f'/silent_{k}', lambda _m: None, QOS)
    node.create_timer(0.01, lambda: None)
    deadline = time.monotonic() + seconds + 30.0
    done = lambda: count[0] >= expected  # noqa: E731
    executor = SingleThreadedExecutor() if mode == 'executor' else DrainingExecutor()
    executor.add_node(node)
    # Wait for the first message before timing: discovery is not the subject here.
    while count[0] == 0 and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.1)
    first, cpu0, wall0 = count[0], time.process_time(), time.monotonic()
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.1)
    cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
    got = count[0] - first
    print(f'{mode} {idle} {got} {cpu:.4f} {wall:.4f}', flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--rate', type=float, default=4000.0)
    ap.add_argument('--seconds', type=float, default=5.0)
    ap.add_argument('--idle', type=int, nargs='+', default=[0, 7, 39])
    ap.add_argument('--type', choices=sorted(SAMPLES), default='Imu')
    ap.add_argument('--role', choices=['pub', 'sub'], help=argparse.SUPPRESS)
    ap.add_argument('--mode', default='executor', help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role == 'pub':
        return publish(args.type, args.rate, args.seconds)
    if args.role == 'sub':
        return receive(args.type, args.mode, args.idle[0], int(args.rate * args.seconds),
                       args.seconds)
    print(f'{args.type} at {args.rate:g}/s for {args.seconds:g} s; receiver CPU (all threads) per '
          'message\n')
    print('| subscriptions in the process | rclpy SingleThreadedExecutor [µs/msg] | '
          'DrainingExecutor [µs/msg] | ratio | received (executor, drain) |')
    print('|---|---|---|---|---|')
    me = [sys.executable, __file__, '--rate', str(args.rate), '--seconds', str(args.seconds),
          '--type', args.type]
    for idle in args.idle:
        row = {}
        for mode in ('executor', 'drain'):
            pub = subprocess.Popen(me + ['--role', 'pub'])
            out = subprocess.run(me + ['--role', 'sub', '--mode', mode, '--idle', str(idle)],
                                 capture_output=True, text=True, check=True).stdout.split()
            pub.wait(timeout=60)
            got, cpu = int(out[2]), float(out[3])
            row[mode] = (cpu / max(got, 1) * 1e6, got / (args.rate * args.seconds))
        (ex, ex_frac), (dr, dr_frac) = row['executor'], row['drain']
        print(f'| {idle + 1} | {ex:.0f} | {dr:.0f} | {ex / dr:.1f} | '
              f'{ex_frac:.0%}, {dr_frac:.0%} |', flush=True)


if __name__ == '__main__':
    main()
