"""Wire format: topic names, message types, QoS, frame ids, encode/decode. The one place that
defines it (see msg_defs/README.md for the table).

Only standard common_interfaces messages are used, so any ROS tool (ros2 topic, RViz, evo,
rosbag) reads them, and a user's own IMU driver or detector can feed an estimator by remapping
one topic. Topic names are relative: each agent's node runs in the namespace ``/<agent>``.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped
from numpy.typing import NDArray
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
from sensor_msgs.msg import Imu, PointCloud2, PointField

from bearing_pose_estimation.core import so3

Array = NDArray[np.float64]

# ----------------------------------------------------------------------------- topics
IMU = 'imu'                        # sensor_msgs/Imu, in: own gyro
BEARINGS = 'bearings'              # sensor_msgs/PointCloud2, in: own unit bearings (body frame)
KNOWN_POSE = 'known_pose'          # geometry_msgs/PoseStamped, in: leaders' known pose
ESTIMATE = 'estimate'              # geometry_msgs/PoseStamped, out: (R̂_i, p̂_i) in world
WORLD_BEARINGS = 'world_bearings'  # sensor_msgs/PointCloud2, out: R̂_i b^i_il for listeners l
DIAGNOSTICS = '/diagnostics'       # diagnostic_msgs/DiagnosticArray, out: each node's health
GROUND_TRUTH = 'ground_truth'      # geometry_msgs/PoseStamped, simulator: true pose
CLOCK = '/clock'                   # rosgraph_msgs/Clock, simulator (use_sim_time)


def topic(agent: str, name: str) -> str:
    """Fully qualified name of an agent's topic, e.g. ``/agent_3/estimate``."""
    return f'/{agent}/{name}'


# ----------------------------------------------------------------------------- frames
WORLD_FRAME = 'world'


def body_frame(agent: str) -> str:
    """REP-105 style body frame with the agent prefix tf2 lacks: ``agent_3/base_link``."""
    return f'{agent}/base_link'


# ----------------------------------------------------------------------------- QoS
# Measurements: best effort (matches any publisher, like SensorDataQoS) but a deep queue, so a
# briefly busy estimator loses no gyro sample (each one is integrated).
SENSOR_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                        reliability=ReliabilityPolicy.BEST_EFFORT,
                        durability=DurabilityPolicy.VOLATILE)
# Estimates that other agents depend on: reliable.
ESTIMATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=20,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)
# Simulator outputs (sensors, truth, clock) are published reliably: on loopback nothing is lost
# to a best-effort subscriber unless its queue overflows.
SIM_PUB_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)


class WireError(ValueError):
    """A message that cannot be decoded (wrong layout, non-finite values, ...)."""


# ----------------------------------------------------------------------------- time
def to_stamp(t: float) -> Time:
    """Seconds → builtin_interfaces/Time (rounded to the nanosecond)."""
    ns = int(round(t * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def from_stamp(stamp: Time) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def stamp_ns(stamp: Time) -> int:
    """Exact integer nanoseconds: a dictionary key that survives the float round trip."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


# ----------------------------------------------------------------------------- Imu
def encode_imu(t: float, agent: str, omega: Array) -> Imu:
    """Gyro sample: ``angular_velocity`` is the body rate averaged over the interval ending at
    ``t`` (see ``bearing_pose_estimation.gyro``). No orientation, no acceleration: their
    covariances' first elements are -1, as sensor_msgs/Imu specifies."""
    msg = Imu()
    msg.header.stamp = to_stamp(t)
    msg.header.frame_id = body_frame(agent)
    msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = map(float, omega)
    msg.orientation_covariance[0] = -1.0
    msg.linear_acceleration_covariance[0] = -1.0
    return msg


def decode_imu(msg: Imu) -> tuple[float, Array]:
    w = msg.angular_velocity
    omega = np.array([w.x, w.y, w.z])
    if not np.all(np.isfinite(omega)):
        raise WireError('non-finite angular velocity')
    return from_stamp(msg.header.stamp), omega


# ----------------------------------------------------------------------------- PointCloud2
# One point per observed agent: a float64 unit vector and the observed agent's id (its 1-based
# position in the scenario's `agents` list, the paper's agent number). One message per agent
# and instant, so the topic count grows with agents, not edges.
_CLOUD_DTYPE = np.dtype([('x', '<f8'), ('y', '<f8'), ('z', '<f8'), ('agent_id', '<u4')])
_CLOUD_FIELDS = [PointField(name='x', offset=0, datatype=PointField.FLOAT64, count=1),
                 PointField(name='y', offset=8, datatype=PointField.FLOAT64, count=1),
                 PointField(name='z', offset=16, datatype=PointField.FLOAT64, count=1),
                 PointField(name='agent_id', offset=24, datatype=PointField.UINT32, count=1)]


def encode_vectors(t: float, frame_id: str, ids: NDArray[np.integer], vectors: Array) -> PointCloud2:
    """Unit vectors tagged with agent ids as a PointCloud2 (fields x, y, z: FLOAT64;
    agent_id: UINT32; little endian, dense)."""
    vectors = np.asarray(vectors, dtype=float).reshape(-1, 3)
    data = np.empty(len(vectors), dtype=_CLOUD_DTYPE)
    data['x'], data['y'], data['z'] = vectors.T
    data['agent_id'] = np.asarray(ids, dtype=np.uint32)
    msg = PointCloud2()
    msg.header.stamp = to_stamp(t)
    msg.header.frame_id = frame_id
    msg.height, msg.width = 1, len(vectors)
    msg.fields = _CLOUD_FIELDS
    msg.is_bigendian = False
    msg.point_step = _CLOUD_DTYPE.itemsize
    msg.row_step = msg.point_step * msg.width
    msg.is_dense = True
    msg.data = data.tobytes()
    return msg


def decode_vectors(msg: PointCloud2) -> tuple[float, NDArray[np.uint32], Array]:
    """Inverse of :func:`encode_vectors`. Accepts any field order or padding (e.g. a user's
    detector) as long as x, y, z are FLOAT64 and agent_id is UINT32.

    Raises:
        WireError: missing or mistyped fields, inconsistent sizes, or big-endian data.
    """
    fields = {f.name: f for f in msg.fields}
    want = {'x': PointField.FLOAT64, 'y': PointField.FLOAT64, 'z': PointField.FLOAT64,
            'agent_id': PointField.UINT32}
    for name, datatype in want.items():
        if name not in fields or fields[name].datatype != datatype or fields[name].count != 1:
            raise WireError(f'PointCloud2 needs field {name!r} of datatype {datatype} '
                            f'(fields: {sorted(fields)})')
    if msg.is_bigendian:
        raise WireError('big-endian PointCloud2 is not supported')
    n = msg.width * msg.height
    if msg.point_step < 28 or len(msg.data) != n * msg.point_step:
        raise WireError(f'PointCloud2 data is {len(msg.data)} bytes, expected '
                        f'{n} points x {msg.point_step} bytes')
    dtype = np.dtype({'names': list(want), 'formats': ['<f8', '<f8', '<f8', '<u4'],
                      'offsets': [fields[k].offset for k in want], 'itemsize': msg.point_step})
    data = np.frombuffer(bytes(msg.data), dtype=dtype, count=n)
    vectors = np.stack([data['x'], data['y'], data['z']], axis=1).astype(float)
    return from_stamp(msg.header.stamp), data['agent_id'].astype(np.uint32), vectors


# ----------------------------------------------------------------------------- PoseStamped
def encode_pose(t: float, frame_id: str, R: Array, p: Array) -> PoseStamped:
    """Attitude (body → frame) and position as PoseStamped, quaternion (x, y, z, w)."""
    msg = PoseStamped()
    msg.header.stamp = to_stamp(t)
    msg.header.frame_id = frame_id
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, p)
    q = so3.to_quat(R)
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    return msg


def decode_pose(msg: PoseStamped) -> tuple[float, Array, Array]:
    """Inverse of :func:`encode_pose`; the quaternion is normalised.

    Raises:
        WireError: non-finite values or a quaternion far from unit norm.
    """
    o, pos = msg.pose.orientation, msg.pose.position
    q = np.array([o.x, o.y, o.z, o.w])
    p = np.array([pos.x, pos.y, pos.z])
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(p))):
        raise WireError('non-finite pose')
    norm = float(np.linalg.norm(q))
    if not math.isclose(norm, 1.0, abs_tol=1e-3):
        raise WireError(f'quaternion norm {norm:.6g} is not 1')
    return from_stamp(msg.header.stamp), so3.from_quat(q), p


# ----------------------------------------------------------------------------- channels
@dataclass(frozen=True)
class ChannelWire:
    """How one estimator channel (``estimators.base.Channel``, by name) travels: the topic of
    the sender's namespace, its type and frame, and the decoder to ``(stamp, value)``; a
    per-edge value is ``{listener id: vector}``. ``encode(t, value)`` builds the message; None:
    the channel rides on the ``estimate`` every estimator publishes anyway."""

    topic: str
    type: type
    frame: str
    decode: Callable[[Any], tuple[float, Any]]
    encode: Callable[[float, Any], Any] | None


def _decode_position(msg: PoseStamped) -> tuple[float, Array]:
    t, _, p = decode_pose(msg)
    return t, p


def _decode_id_vectors(msg: PointCloud2) -> tuple[float, dict[int, Array]]:
    t, ids, vectors = decode_vectors(msg)
    return t, dict(zip(ids.tolist(), vectors))


def _encode_id_vectors(t: float, value: dict[int, Array]) -> PointCloud2:
    ids = np.fromiter(value.keys(), dtype=np.uint32, count=len(value))
    return encode_vectors(t, WORLD_FRAME, ids, np.array(list(value.values())).reshape(-1, 3))


# Channel name -> wire. p_hat: the position of the sender's `estimate`; world_bearing: its
# `world_bearings`, one point per listener.
CHANNELS = {
    'p_hat': ChannelWire(ESTIMATE, PoseStamped, WORLD_FRAME, _decode_position, None),
    'world_bearing': ChannelWire(WORLD_BEARINGS, PointCloud2, WORLD_FRAME, _decode_id_vectors,
                                 _encode_id_vectors),
}


def channel(name: str) -> ChannelWire:
    """The wire of channel ``name``.

    Raises:
        WireError: no wire format is defined for it (a new method's channel needs an entry in
            :data:`CHANNELS`).
    """
    try:
        return CHANNELS[name]
    except KeyError:
        raise WireError(f'channel {name!r} has no wire format; add it to msg_defs.CHANNELS '
                        f'(known: {", ".join(CHANNELS)})') from None
