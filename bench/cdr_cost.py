"""What a message costs to build and read (msg_defs/cdr.py, issue 15): cdr's encode_*_raw and
decode_*_raw on the serialised bytes, against rclpy's serialize_message and
deserialize_message alone (what a typed publisher or subscription adds around any codec: the
cost of a message object), and cdr's decoder given a message object (what a node with typed
subscriptions pays: serialised first, msg_defs.raw) or its encoder's bytes made an object
(msg_defs.message), for a PoseStamped (the estimate) and a 4-point PointCloud2 (bearings).
Medians of repeated timings, one core, no DDS.

    OMP_NUM_THREADS=1 .venv/bin/python bench/cdr_cost.py
"""
from __future__ import annotations

import os
import sys
import tempfile
import timeit
from pathlib import Path

os.environ.setdefault('OMP_NUM_THREADS', '1')
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('ROS_LOG_DIR', tempfile.mkdtemp(prefix='bpe-bench-roslog-'))
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

from bearing_pose_estimation import msg_defs as wire  # noqa: E402
from bearing_pose_estimation.core import so3  # noqa: E402
from bearing_pose_estimation.msg_defs import cdr  # noqa: E402


def median_us(fn, number: int = 2000, repeat: int = 9) -> float:
    return float(np.median(timeit.repeat(fn, number=number, repeat=repeat)) / number * 1e6)


def main() -> None:
    t = 12.345678901
    R, p = so3.exp(np.array([0.3, -1.2, 0.7])), np.array([1.0, -2.0, 3.5])
    rng = np.random.default_rng(0)
    ids = np.arange(1, 5, dtype=np.uint32)
    b = rng.normal(size=(4, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    frame = 'agent_3/base_link'
    pose = cdr.encode_pose_raw(t, 'world', R, p)
    cloud = cdr.encode_vectors_raw(t, frame, ids, b)
    pose_msg, cloud_msg = wire.message(pose, PoseStamped), wire.message(cloud, PointCloud2)
    rows = [
        ('PoseStamped', 'decode',
         lambda: cdr.decode_pose_raw(pose),
         lambda: deserialize_message(pose, PoseStamped),
         lambda: cdr.decode_pose_raw(pose_msg)),
        ('PoseStamped', 'encode',
         lambda: cdr.encode_pose_raw(t, 'world', R, p),
         lambda: serialize_message(pose_msg),
         lambda: wire.message(cdr.encode_pose_raw(t, 'world', R, p), PoseStamped)),
        ('PointCloud2, 4 points', 'decode',
         lambda: cdr.decode_vectors_raw(cloud),
         lambda: deserialize_message(cloud, PointCloud2),
         lambda: cdr.decode_vectors_raw(cloud_msg)),
        ('PointCloud2, 4 points', 'encode',
         lambda: cdr.encode_vectors_raw(t, frame, ids, b),
         lambda: serialize_message(cloud_msg),
         lambda: wire.message(cdr.encode_vectors_raw(t, frame, ids, b), PointCloud2)),
    ]
    print(f'{len(pose)}-byte PoseStamped, {len(cloud)}-byte PointCloud2')
    print('| message | direction | cdr on bytes [µs] | rclpy (de)serialize_message alone [µs] '
          '| cdr with a message object [µs] | object / bytes |')
    print('|---|---|---|---|---|---|')
    for name, direction, on_bytes, rclpy_only, with_object in rows:
        us = [median_us(fn) for fn in (on_bytes, rclpy_only, with_object)]
        print(f'| {name} | {direction} | {us[0]:.1f} | {us[1]:.1f} | {us[2]:.1f} | '
              f'{us[2] / us[0]:.1f}x |')

if __name__ == '__main__':
    main()
