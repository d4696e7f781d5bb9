"""Wire format: topic names, message types, QoS, frame ids, encode/decode. The one place that
defines it (see msg_defs/README.md for the table).

Only standard common_interfaces messages are used, so any ROS tool (ros2 topic, RViz, evo,
rosbag) reads them, and a user's own IMU driver or detector can feed an estimator by remapping
one topic. Topic names are relative: each agent's node runs in the namespace ``/<agent>``.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from numpy.typing import NDArray
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
from sensor_msgs.msg import Imu, PointCloud2, PointField

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.estimators.base import (POINTS, POSE_COVARIANCE, POSE_POSITION,
                                                     VECTOR, Channel)

Array = NDArray[np.float64]

# ----------------------------------------------------------------------------- topics
IMU = 'imu'                        # sensor_msgs/Imu, in: own gyro
ODOM = 'odom'                      # nav_msgs/Odometry, in: own odometry (body twist)
BEARINGS = 'bearings'              # sensor_msgs/PointCloud2, in: own unit bearings (body frame)
# sensor_msgs/PointCloud2, in: ⁱp_ij = R_iᵀ (p_j - p_i) [m] (body frame), one point per agent j
RELATIVE_POSITIONS = 'relative_positions'
BEARING_RATES = 'bearing_rates'    # sensor_msgs/PointCloud2, in: d/dt b^i_ij [1/s] (body frame)
RANGES = 'ranges'                  # sensor_msgs/PointCloud2, in: ‖p_j - p_i‖ [m] (field `range`)
KNOWN_POSE = 'known_pose'          # geometry_msgs/PoseStamped, in: leaders' known pose
ESTIMATE = 'estimate'              # geometry_msgs/PoseStamped, out: (R̂_i, p̂_i) in world
# geometry_msgs/PoseWithCovarianceStamped, out: the estimate with its covariance, for fusion
# (robot_localization) and the neighbours (their p̂_j and P_j, in one message)
POSE = 'pose'
# (or the estimation frame of methods without world poses, estimation_frame)
WORLD_BEARINGS = 'world_bearings'  # sensor_msgs/PointCloud2, out: R̂_i b^i_il for listeners l
YAW_ESTIMATE = 'yaw_estimate'      # geometry_msgs/Vector3Stamped, out: ẑ_i = (x + ιy), De Carli
RELATIVE_YAWS = 'relative_yaws'    # sensor_msgs/PointCloud2, out: unit(ẑ_ij) (x, y) per pair
# Presenza et al.'s second round, sensing robot j → each robot i it sees (PointCloud2, one
# point per i, in the anchor frame): g_{j→i} [1/m], its Gauss-Newton block (xx yy zz xy xz yz)
# [1/m²], 𝔟̂_ji = Q̂_j β_ji, n_ji [m/s].
ANGLE_GRADIENT = 'angle_gradient'
ANGLE_HESSIAN = 'angle_hessian'
ANCHOR_BEARING = 'anchor_bearing'
VELOCITY_TERM = 'velocity_term'
# ... and, for the listener's covariance (optional), what only the sensing robot knows of it:
# its angle terms' and velocity term's covariances (white, slow) and the bearing's rate.
TERM_COVARIANCE = 'term_covariance'
DIAGNOSTICS = '/diagnostics'       # diagnostic_msgs/DiagnosticArray, out: each node's health
GROUND_TRUTH = 'ground_truth'      # geometry_msgs/PoseStamped, simulator: true pose
CLOCK = '/clock'                   # rosgraph_msgs/Clock, simulator (use_sim_time)
MONITOR_READY = '/monitor/ready'   # std_msgs/Empty, latched: the monitor has matched everyone


def topic(agent: str, name: str, fleet: str = '') -> str:
    """Fully qualified name of an agent's topic, e.g. ``/agent_3/estimate``; in the fleet
    namespace ``team_a``, ``/team_a/agent_3/estimate``."""
    return f'{fleet_topic("", fleet)}/{agent}/{name}'


def fleet_topic(name: str, fleet: str = '') -> str:
    """A fleet-wide name (:data:`CLOCK`, :data:`MONITOR_READY`) in the fleet namespace
    ``fleet`` (empty: none): ``/clock`` becomes ``/team_a/clock``."""
    fleet = fleet.strip('/')
    return f'/{fleet}{name}' if fleet else name


def fleet_of(namespace: str) -> str:
    """The fleet namespace of an agent's node namespace (``/team_a/agent_3`` -> ``team_a``;
    ``/agent_3`` -> empty): its neighbours' topics live beside its own."""
    return namespace.strip('/').rpartition('/')[0]


# A moving robot's sensor (scenario.Sensors name) -> its topic and message type.
SENSOR_TOPICS = {'odometry': ODOM, 'relative_positions': RELATIVE_POSITIONS,
                 'bearing_rates': BEARING_RATES, 'ranges': RANGES}
SENSOR_TYPES: dict[str, type] = {'odometry': Odometry, 'relative_positions': PointCloud2,
                                 'bearing_rates': PointCloud2, 'ranges': PointCloud2}


def type_name(msg_type: type) -> str:
    """The ROS 2 name of a message class, as rosbag2 stores it: ``geometry_msgs/msg/Pose``."""
    return f'{msg_type.__module__.split(".")[0]}/msg/{msg_type.__name__}'


# ----------------------------------------------------------------------------- frames
WORLD_FRAME = 'world'


def estimation_frame(fleet: str) -> str:
    """The common frame of a fleet whose estimates are not world poses (De Carli et al.: one
    yaw and one translation away from ``world``, neither known by design):
    ``<fleet>/estimation``."""
    return f'{fleet}/estimation'


def body_frame(agent: str) -> str:
    """REP-105 style body frame with the agent prefix tf2 lacks: ``agent_3/base_link``."""
    return f'{agent}/base_link'


def odom_frame(agent: str) -> str:
    """REP-105 odometry frame of an agent (where its dead reckoning starts): ``agent_3/odom``."""
    return f'{agent}/odom'


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
# The estimate writer keeps its last 20 samples for readers that match late (transient local):
# a recorder whose reader the writer discovers after t = 0 still receives the t = 0 estimate.
# Volatile readers (neighbours, RViz, ESTIMATE_QOS) match it unchanged.
ESTIMATE_PUB_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=20,
                              reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.TRANSIENT_LOCAL)
# The recorder's reader asks for that history.
ESTIMATE_RECORD_QOS = ESTIMATE_PUB_QOS
# Simulator outputs (sensors, truth, clock) are published reliably: on loopback nothing is lost
# to a best-effort subscriber unless its queue overflows.
SIM_PUB_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
# Announcements a late subscriber must still get (transient local, the last one).
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
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


# ----------------------------------------------------------------------------- Odometry
def encode_odometry(t: float, agent: str, v: Array, omega: Array, R_odom: Array | None = None,
                    p_odom: Array | None = None, v_std: float = 0.0,
                    omega_std: float = 0.0) -> Odometry:
    """Odometry sample: the body twist in ``child_frame_id`` = ``<agent>/base_link`` (REP-105),
    the dead-reckoned pose in ``header.frame_id`` = ``<agent>/odom``.

    The sample stamped ``t`` = ``t_k`` is an interval average, like the Imu gyro samples: the
    constant body twist ``(v_k, ω_k)`` that produces the true pose increment over
    ``(t_{k-1}, t_k]``, i.e. the SE(3) logarithm of the relative pose
    ``T_{k-1}⁻¹ T_k`` divided by ``h = t_k - t_{k-1}``. Its ``ω_k`` is the gyro sample of the
    same interval. Integrating the samples piecewise constant, ``R_k = R_{k-1} exp(ω_k h)`` and
    ``p_k = p_{k-1} + R_{k-1} J(ω_k h) v_k h`` (J: left Jacobian of SO(3)), is then exact from
    stamp to stamp; holding a sampled instantaneous velocity over a step leaves an O(h) bias.

    Args:
        v: body-frame linear velocity [m/s] (``twist.twist.linear``).
        omega: body rate [rad/s] (``twist.twist.angular``).
        R_odom, p_odom: the dead-reckoned attitude (body → odom) and position [m] for RViz;
            identity and zero when not given.
        v_std, omega_std: standard deviations [m/s], [rad/s]; ``twist.covariance`` (row-major
            6x6, x y z roll pitch yaw) is diagonal with ``v_std²`` and ``omega_std²``.
            ``pose.covariance`` stays zero: the estimator does not read the pose.
    """
    msg = Odometry()
    msg.header.stamp = to_stamp(t)
    msg.header.frame_id = odom_frame(agent)
    msg.child_frame_id = body_frame(agent)
    pose, twist = msg.pose.pose, msg.twist.twist
    if p_odom is not None:
        pose.position.x, pose.position.y, pose.position.z = map(float, p_odom)
    if R_odom is not None:
        o = pose.orientation
        o.x, o.y, o.z, o.w = map(float, so3.to_quat(R_odom))
    twist.linear.x, twist.linear.y, twist.linear.z = map(float, v)
    twist.angular.x, twist.angular.y, twist.angular.z = map(float, omega)
    cov = np.zeros(36)
    cov[[0, 7, 14]] = v_std ** 2
    cov[[21, 28, 35]] = omega_std ** 2
    msg.twist.covariance = cov
    return msg


def decode_odometry(msg: Odometry, child_frame: str | None = None) -> tuple[float, Array, Array]:
    """``(stamp, v, omega)`` of an odometry sample (:func:`encode_odometry`); the pose and the
    covariances are not read.

    Args:
        child_frame: when given, the frame the twist must be expressed in (the agent's
            :func:`body_frame`): a twist in another frame would be misread.

    Raises:
        WireError: a ``child_frame_id`` other than ``child_frame``, or a non-finite twist.
    """
    if child_frame is not None and msg.child_frame_id != child_frame:
        raise WireError(f'Odometry twist is in child_frame_id {msg.child_frame_id!r}, '
                        f'expected {child_frame!r}')
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    v = np.array([lin.x, lin.y, lin.z])
    omega = np.array([ang.x, ang.y, ang.z])
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(omega))):
        raise WireError('non-finite twist')
    return from_stamp(msg.header.stamp), v, omega


# ----------------------------------------------------------------------------- PointCloud2
# One point per observed agent: float64 values and the observed agent's id (its 1-based
# position in the scenario's `agents` list, the paper's agent number). One message per agent
# and instant, so the topic count grows with agents, not edges. Vectors (bearings, relative
# positions, bearing rates) are fields x, y, z; a scalar (range) is one field.
_FORMATS: dict[int, np.dtype] = {PointField.FLOAT64: np.dtype('<f8'),  # datatype -> numpy
                                 PointField.FLOAT32: np.dtype('<f4'),
                                 PointField.UINT32: np.dtype('<u4')}
# What a decoder accepts for each datatype it wants: most detectors and PCL publish FLOAT32
# points (the values are widened to float64; a unit bearing in float32 is unit to 1e-7).
_ACCEPTED = {PointField.FLOAT64: (PointField.FLOAT64, PointField.FLOAT32),
             PointField.UINT32: (PointField.UINT32,)}
_VECTOR_FIELDS = {'x': PointField.FLOAT64, 'y': PointField.FLOAT64, 'z': PointField.FLOAT64,
                  'agent_id': PointField.UINT32}


def _scalar_fields(field: str) -> dict[str, int]:
    return {field: PointField.FLOAT64, 'agent_id': PointField.UINT32}


def _cloud_dtype(want: dict[str, int], offsets: list[int], point_step: int) -> np.dtype:
    """The numpy view of points of ``point_step`` bytes with the fields ``want``
    (``{name: datatype}``) at ``offsets``."""
    return np.dtype({'names': list(want), 'formats': [_FORMATS[d] for d in want.values()],
                     'offsets': offsets, 'itemsize': point_step})


def _cloud_layout(want: dict[str, int]) -> tuple[np.dtype, list[PointField]]:
    """The packed layout of the fields ``want``, in this order: its dtype and PointFields."""
    sizes = [_FORMATS[datatype].itemsize for datatype in want.values()]
    offsets = [sum(sizes[:k]) for k in range(len(sizes))]
    fields = [PointField(name=name, offset=offset, datatype=datatype, count=1)
              for (name, datatype), offset in zip(want.items(), offsets)]
    return _cloud_dtype(want, offsets, sum(sizes)), fields


_CLOUD_DTYPE, _CLOUD_FIELDS = _cloud_layout(_VECTOR_FIELDS)


def _encode_cloud(t: float, frame_id: str, data: np.ndarray,
                  fields: list[PointField]) -> PointCloud2:
    """A little-endian, dense, one-row PointCloud2 of the structured array ``data``."""
    msg = PointCloud2()
    msg.header.stamp = to_stamp(t)
    msg.header.frame_id = frame_id
    msg.height, msg.width = 1, len(data)
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = data.dtype.itemsize
    msg.row_step = msg.point_step * msg.width
    msg.is_dense = True
    msg.data = data.tobytes()
    return msg


# A point of more than this many bytes is no point of ours (a fuzzed point_step of 2^31 made
# numpy raise a bare ValueError).
MAX_POINT_STEP = 1 << 16


def _decode_cloud(msg: PointCloud2, want: dict[str, int]) -> tuple[float, np.ndarray]:
    """The stamp and the points of ``msg`` as a structured array of the fields ``want``
    (``{name: datatype}``), in any order and with any padding.

    Raises:
        WireError: missing or mistyped fields, fields that overlap each other or the end of
            the point, inconsistent sizes, or big-endian data.
    """
    fields = {f.name: f for f in msg.fields}
    for name, datatype in want.items():
        if (name not in fields or fields[name].datatype not in _ACCEPTED[datatype]
                or fields[name].count != 1):
            raise WireError(f'PointCloud2 needs field {name!r} of datatype '
                            f'{" or ".join(map(str, _ACCEPTED[datatype]))} '
                            f'(fields: {sorted(fields)})')
    if msg.is_bigendian:
        raise WireError('big-endian PointCloud2 is not supported')
    want = {name: fields[name].datatype for name in want}   # as they come
    sizes = [_FORMATS[datatype].itemsize for datatype in want.values()]
    if msg.point_step > MAX_POINT_STEP:   # numpy's dtypes take no larger item
        raise WireError(f'PointCloud2 point_step {msg.point_step} is absurd (at most '
                        f'{MAX_POINT_STEP} bytes)')
    n = msg.width * msg.height
    if msg.point_step < sum(sizes) or len(msg.data) != n * msg.point_step:
        raise WireError(f'PointCloud2 data is {len(msg.data)} bytes, expected '
                        f'{n} points x {msg.point_step} bytes')
    offsets = [fields[name].offset for name in want]
    spans = sorted(zip(offsets, sizes, want))
    ends = [offset for offset, _, _ in spans[1:]] + [msg.point_step]
    for (offset, size, name), end in zip(spans, ends):
        if offset + size > end:
            raise WireError(f'PointCloud2 field {name!r} (offset {offset}, {size} bytes) '
                            f'overlaps the next field or the end of the {msg.point_step}-byte '
                            f'point')
    dtype = _cloud_dtype(want, offsets, msg.point_step)
    return from_stamp(msg.header.stamp), np.frombuffer(bytes(msg.data), dtype=dtype, count=n)


def encode_vectors(t: float, frame_id: str, ids: NDArray[np.integer],
                   vectors: Array) -> PointCloud2:
    """Vectors tagged with agent ids as a PointCloud2 (fields x, y, z: FLOAT64; agent_id:
    UINT32; little endian, dense): unit bearings, relative positions [m], bearing rates
    [1/s]."""
    vectors = np.asarray(vectors, dtype=float).reshape(-1, 3)
    data = np.empty(len(vectors), dtype=_CLOUD_DTYPE)
    data['x'], data['y'], data['z'] = vectors.T
    data['agent_id'] = np.asarray(ids, dtype=np.uint32)
    return _encode_cloud(t, frame_id, data, _CLOUD_FIELDS)


def decode_vectors(msg: PointCloud2) -> tuple[float, NDArray[np.uint32], Array]:
    """Inverse of :func:`encode_vectors`. Accepts any field order or padding (e.g. a user's
    detector, PCL) as long as x, y, z are FLOAT64 or FLOAT32 and agent_id is UINT32. The
    values are not checked (finite, unit norm): each receiver validates its points.

    Raises:
        WireError: missing, mistyped or overlapping fields, inconsistent sizes, or big-endian
            data.
    """
    t, data = _decode_cloud(msg, _VECTOR_FIELDS)
    vectors = np.stack([data['x'], data['y'], data['z']], axis=1).astype(float)
    return t, data['agent_id'].astype(np.uint32), vectors


def encode_scalars(t: float, frame_id: str, ids: NDArray[np.integer], values: Array,
                   field: str = 'range') -> PointCloud2:
    """Scalars tagged with agent ids as a PointCloud2 (fields ``field``: FLOAT64; agent_id:
    UINT32; little endian, dense), e.g. ranges [m]."""
    values = np.asarray(values, dtype=float).reshape(-1)
    dtype, fields = _cloud_layout(_scalar_fields(field))
    data = np.empty(len(values), dtype=dtype)
    data[field] = values
    data['agent_id'] = np.asarray(ids, dtype=np.uint32)
    return _encode_cloud(t, frame_id, data, fields)


def decode_scalars(msg: PointCloud2,
                   field: str = 'range') -> tuple[float, NDArray[np.uint32], Array]:
    """Inverse of :func:`encode_scalars`: ``(stamp, ids, values)``. Accepts any field order or
    padding as long as ``field`` is FLOAT64 (or FLOAT32) and agent_id is UINT32. The values are
    not checked.

    Raises:
        WireError: missing, mistyped or overlapping fields, inconsistent sizes, or big-endian
            data.
    """
    t, data = _decode_cloud(msg, _scalar_fields(field))
    return t, data['agent_id'].astype(np.uint32), data[field].astype(float)


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


def encode_pose_covariance(t: float, frame_id: str, R: Array, p: Array,
                           P: Array) -> PoseWithCovarianceStamped:
    """The pose as :func:`encode_pose` with its 6x6 covariance ``P`` (position [m], then
    rotation about the frame's axes [rad], row-major: ROS's x, y, z, rot x, rot y, rot z)."""
    msg = PoseWithCovarianceStamped()
    pose = encode_pose(t, frame_id, R, p)
    msg.header, msg.pose.pose = pose.header, pose.pose
    msg.pose.covariance = np.asarray(P, dtype=float).reshape(36).tolist()
    return msg


def decode_covariance(msg: PoseWithCovarianceStamped) -> tuple[float, Array]:
    """The stamp and the 6x6 covariance of a PoseWithCovarianceStamped.

    Raises:
        WireError: a covariance that is not finite, symmetric and positive semi-definite.
    """
    return from_stamp(msg.header.stamp), checked_covariance(
        np.asarray(msg.pose.covariance, dtype=float))


def checked_covariance(values: Array) -> Array:
    """The 6x6 covariance of 36 row-major ``values`` (also raw CDR's, ``cdr.py``).

    Raises:
        WireError: not 36 finite values, not symmetric or not positive semi-definite.
    """
    if values.size != 36 or not np.isfinite(values).all():
        raise WireError('non-finite or malformed covariance')
    P = values.reshape(6, 6)
    magnitude = np.abs(P)
    scale = max(float(magnitude.max()), 1e-300)
    # np.allclose(P, P.T, rtol=1e-6, atol=1e-12 scale) written out: a neighbour's pose
    # arrives 50 times a second, and allclose alone cost 18 µs of its 35.
    if (np.abs(P - P.T) > 1e-12 * scale + 1e-6 * magnitude.T).any():
        raise WireError('covariance is not symmetric')
    if np.linalg.eigvalsh(0.5 * (P + P.T))[0] < -1e-9 * scale:
        raise WireError('covariance is not positive semi-definite')
    return P


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
# How an estimator's channels (``estimators.base.Channel``) travel, by their wire kind, not by
# their name: a value on the sender's ``pose`` (its position; its covariance), a per-agent
# vector of its own Vector3Stamped (zero-padded), or one point per listener of a PointCloud2
# (the channel's fields, FLOAT64, then agent_id UINT32). Each decodes from the message's bytes
# (msg_defs/cdr.py); a message object is serialised first (one implementation, :func:`raw`).
KIND_TYPES: dict[str, type] = {POSE_POSITION: PoseWithCovarianceStamped,
                               POSE_COVARIANCE: PoseWithCovarianceStamped,
                               VECTOR: Vector3Stamped, POINTS: PointCloud2}


def raw(msg: Any) -> bytes:
    """A message's serialised bytes (bytes are returned as they are)."""
    if isinstance(msg, (bytes, bytearray, memoryview)):
        return bytes(msg)
    from rclpy.serialization import serialize_message
    return serialize_message(msg)


def channel_type(c: Channel) -> type:
    """The message type that carries channel ``c`` (a sensor's readings: the sensor's)."""
    return PointCloud2 if c.sensor is not None else KIND_TYPES[c.kind]


def channel_frame(c: Channel, sender: str, estimate: str, world: str = WORLD_FRAME) -> str:
    """The frame id a message of ``sender`` carrying ``c`` must have (``estimate``: the frame
    of the method's estimates; ``world``: the world frame's id)."""
    return {'world': world, 'body': body_frame(sender)}.get(c.frame, estimate)


def by_topic(channels: Iterable[Channel]) -> dict[str, list[Channel]]:
    """The channels that travel on each topic, in their order (``p_hat`` and ``pose_cov``
    share the ``pose``)."""
    out: dict[str, list[Channel]] = {}
    for c in channels:
        out.setdefault(c.topic, []).append(c)
    return out


def decode_channels(msg: Any, channels: Sequence[Channel]
                    ) -> tuple[float, dict[str, object], dict[str, str]]:
    """``(stamp, values, problems)`` of a message carrying ``channels`` (one topic's):
    per-agent values as arrays, per-edge ones as ``{listener id: value}``; a channel that
    cannot be decoded is left out, with the reason in ``problems`` (a bad covariance does not
    cost the position)."""
    data = raw(msg)
    values: dict[str, object] = {}
    problems: dict[str, str] = {}
    t = math.nan
    for c in channels:
        try:
            if c.sensor is not None or c.kind == POINTS:
                t, ids, points = cdr.decode_points_raw(data, c.fields)
                values[c.name] = dict(zip(ids.tolist(), points[:, :c.shape[0]]))
            elif c.kind == POSE_POSITION:
                t, values[c.name] = cdr.decode_position_raw(data)
            elif c.kind == POSE_COVARIANCE:
                t, values[c.name] = cdr.decode_covariance_raw(data)
            else:
                t, v = cdr.decode_vector3_raw(data)
                values[c.name] = v[:c.shape[0]]
        except WireError as exc:
            problems[c.name] = str(exc)
    return t, values, problems


def encode_channels(t: float, frame: str, channels: Sequence[Channel],
                    values: Mapping[str, object]) -> bytes:
    """The message of one topic's ``channels`` (a Vector3Stamped's or a PointCloud2's: the
    pose's are the estimate's, :func:`cdr.encode_pose_covariance_raw`)."""
    c = channels[0]
    value = values[c.name]
    if c.kind == VECTOR:
        v = np.zeros(3)
        v[:c.shape[0]] = np.asarray(value, dtype=float)
        return cdr.encode_vector3_raw(t, frame, v)
    assert isinstance(value, Mapping)
    ids = np.fromiter(value.keys(), dtype=np.uint32, count=len(value))
    points = np.zeros((len(value), len(c.fields)))
    points[:, :c.shape[0]] = np.array(list(value.values()), dtype=float).reshape(len(value), -1)
    return cdr.encode_points_raw(t, frame, ids, points, c.fields)


def estimate_frame(frame: str, fleet: str, anchor: str | None = None,
                   world: str = WORLD_FRAME) -> str:
    """The frame id of a method's estimates (``frame``: ``estimators.base.EstimateFrame``
    value): ``world`` (the scenario's ``world_frame``) for world poses, the ``anchor``'s
    :func:`body_frame` for anchor-frame estimates (Presenza et al.), else
    :func:`estimation_frame`."""
    if frame == 'world':
        return world
    if frame == 'anchor_body':
        if anchor is None:
            raise WireError('anchor-frame estimates need the anchor\'s name')
        return body_frame(anchor)
    return estimation_frame(fleet)


from . import cdr  # noqa: E402  (cdr reads WireError and the frames from here)
