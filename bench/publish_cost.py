"""Cost of one rclpy publish (PoseStamped, as an estimator sends its estimate), by the number of
subscriber processes: wall time of ``publish()`` and CPU of the publishing process per publish.

    .venv/bin/python bench/publish_cost.py [--subscribers 1 3 6] [--qos reliable|best_effort]
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
from rclpy.executors import ExternalShutdownException  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402

from bearing_pose_estimation import msg_defs as wire  # noqa: E402

QOS = {'reliable': wire.ESTIMATE_QOS, 'best_effort': wire.SENSOR_QOS}


def subscriber(qos: str, seconds: float) -> None:
    rclpy.init()
    node = rclpy.create_node(f'sub_{os.getpid()}')
    node.create_subscription(PoseStamped, '/publish_cost', lambda _m: None, QOS[qos])
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.1)
    except ExternalShutdownException:  # terminated by the measuring process: done
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def measure(n_subs: int, qos: str, count: int) -> tuple[float, float, float]:
    subs = [subprocess.Popen([sys.executable, __file__, '--role', 'sub', '--qos', qos,
                              '--seconds', str(count * 0.006 + 20)]) for _ in range(n_subs)]
    rclpy.init()
    node = rclpy.create_node('publish_cost')
    pub = node.create_publisher(PoseStamped, '/publish_cost', QOS[qos])
    try:
        while pub.get_subscription_count() < n_subs:
            time.sleep(0.01)
        time.sleep(1.0)  # the readers' side finishes matching
        msg, walls = PoseStamped(), []
        cpu0 = time.process_time()
        for _ in range(count):
            t0 = time.perf_counter()
            pub.publish(msg)
            walls.append(time.perf_counter() - t0)
            time.sleep(0.005)  # 200 Hz: no queue build-up
        cpu = (time.process_time() - cpu0) / count
    finally:
        node.destroy_node()
        rclpy.shutdown()
        for s in subs:
            s.terminate()
            s.wait()
    return float(np.median(walls)), float(np.percentile(walls, 90)), cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--subscribers', type=int, nargs='+', default=[1, 3, 6])
    ap.add_argument('--qos', choices=sorted(QOS), default='reliable')
    ap.add_argument('--count', type=int, default=1000)
    ap.add_argument('--role', choices=['sub'], help=argparse.SUPPRESS)
    ap.add_argument('--seconds', type=float, default=30.0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role == 'sub':
        return subscriber(args.qos, args.seconds)
    print(f'PoseStamped, {args.qos}, {args.count} publishes at 200 Hz\n')
    print('| subscriber processes | publish() wall, median | p90 | publisher CPU per publish |')
    print('|---|---|---|---|')
    for n in args.subscribers:
        med, p90, cpu = measure(n, args.qos, args.count)
        print(f'| {n} | {med * 1e6:.0f} µs | {p90 * 1e6:.0f} µs | {cpu * 1e6:.0f} µs |',
              flush=True)


if __name__ == '__main__':
    main()
