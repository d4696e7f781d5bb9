"""One-way DDS latency between two processes on this machine, with the package's estimate QoS.

A child process publishes geometry_msgs/PoseStamped at RATE Hz, stamped with the system clock
just before publishing; this process receives them and records `receipt - stamp`. Prints the
median and percentiles in microseconds. Loopback only, private domain.

    .venv/bin/python bench/dds_latency.py [--count 2000] [--rate 100] [--load N]

--load N also runs N busy-loop processes meanwhile (to see latency on a loaded machine).
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
from rclpy.node import Node  # noqa: E402

from bearing_pose_estimation import msg_defs as wire  # noqa: E402

PUBLISHER = r'''
import sys, time, rclpy
from rclpy.node import Node
from bearing_pose_estimation import msg_defs as wire
from bearing_pose_estimation.msg_defs import cdr
import numpy as np
rate, count = float(sys.argv[1]), int(sys.argv[2])
rclpy.init(); node = Node('latency_pub')
pub = node.create_publisher(wire.PoseStamped, '/latency', wire.ESTIMATE_QOS)
while pub.get_subscription_count() < 1:
    rclpy.spin_once(node, timeout_sec=0.05)
R, p = np.eye(3), np.zeros(3)
for k in range(count):
    pub.publish(cdr.encode_pose_raw(time.time(), 'world', R, p))
    time.sleep(1.0 / rate)
time.sleep(0.5); node.destroy_node(); rclpy.shutdown()
'''


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--count', type=int, default=2000)
    ap.add_argument('--rate', type=float, default=100.0)
    ap.add_argument('--load', type=int, default=0, help='busy-loop processes meanwhile')
    args = ap.parse_args()
    rclpy.init()
    node = Node('latency_sub')
    lat: list[float] = []
    node.create_subscription(wire.PoseStamped, '/latency',
                             lambda m: lat.append(time.time() - wire.from_stamp(m.header.stamp)),
                             wire.ESTIMATE_QOS)
    load = [subprocess.Popen([sys.executable, '-c', 'while True: pass'])
            for _ in range(args.load)]
    pub = subprocess.Popen([sys.executable, '-c', PUBLISHER, str(args.rate), str(args.count)])
    try:
        end = time.monotonic() + args.count / args.rate + 30
        while len(lat) < args.count and time.monotonic() < end and pub.poll() is None:
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        pub.wait(timeout=30)
        for p in load:
            p.terminate()
            p.wait()
        node.destroy_node()
        rclpy.shutdown()
    us = np.array(lat) * 1e6
    print(f'{len(us)} messages at {args.rate:g} Hz, load {args.load}: one-way latency '
          f'median {np.median(us):.0f} us, p90 {np.percentile(us, 90):.0f} us, '
          f'p99 {np.percentile(us, 99):.0f} us, max {us.max():.0f} us')


if __name__ == '__main__':
    main()
