"""Wire format: topic names (relative to ``/<agent>``), message types, QoS, frame ids and the
codecs, defined here only (msg_defs/README.md has the table and why). One codec per message
type (:mod:`msg_defs.cdr`); channels travel by their kind (:func:`encode_channels`).
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, TypeVar

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from numpy.typing import NDArray
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
from sensor_msgs.msg import Imu, PointCloud2

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
# (robot_localization) and the neighbours; the estimators' channels declare their own topics
POSE = 'pose'
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
    """``<fleet>/estimation``: the common frame of a fleet whose estimates are not world poses
    (De Carli et al.: one yaw and one translation away from ``world``, neither known)."""
    return f'{fleet}/estimation'


def body_frame(agent: str) -> str:
    """REP-105 style body frame with the agent prefix tf2 lacks: ``agent_3/base_link``."""
    return f'{agent}/base_link'


def odom_frame(agent: str) -> str:
    """REP-105 odometry frame of an agent (where its dead reckoning starts): ``agent_3/odom``."""
    return f'{agent}/odom'


# ----------------------------------------------------------------------------- QoS
def _qos(depth: int, reliability: ReliabilityPolicy = ReliabilityPolicy.RELIABLE,
         durability: DurabilityPolicy = DurabilityPolicy.VOLATILE) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=reliability,
                      durability=durability)


# Measurements: best effort (matches any publisher, like SensorDataQoS) but a deep queue, so a
# briefly busy estimator loses no gyro sample (each one is integrated).
SENSOR_QOS = _qos(200, ReliabilityPolicy.BEST_EFFORT)
# Estimates that other agents depend on: reliable.
ESTIMATE_QOS = _qos(20)
# The estimate writer keeps its last 20 samples (transient local) for readers that match late: a
# recorder discovered after t = 0 still gets the t = 0 estimate. Volatile readers match it too.
ESTIMATE_PUB_QOS = ESTIMATE_RECORD_QOS = _qos(20, durability=DurabilityPolicy.TRANSIENT_LOCAL)
# A recorder's other readers: reliable and volatile match every writer; deep for bursts.
RECORD_QOS = _qos(1000)
# Simulator outputs (sensors, truth, clock) are published reliably: on loopback nothing is lost
# to a best-effort subscriber unless its queue overflows.
SIM_PUB_QOS = _qos(200)
# Announcements a late subscriber must still get (transient local, the last one).
LATCHED_QOS = _qos(1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
CLOCK_QOS = _qos(10)


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


def diagnostics(name: str, hardware_id: str, message: str, values: Mapping[str, str],
                stamp: Time, level: int = 0) -> DiagnosticArray:
    """A diagnostic_msgs/DiagnosticArray of one status (``level``: 0 OK, 1 WARN, 2 ERROR)."""
    status = DiagnosticStatus(name=name, hardware_id=hardware_id, level=bytes([level]),
                              message=message,
                              values=[KeyValue(key=k, value=v) for k, v in values.items()])
    msg = DiagnosticArray(status=[status])
    msg.header.stamp = stamp
    return msg


# ----------------------------------------------------------------------------- covariance
def checked_covariance(values: Array) -> Array:
    """The 6x6 covariance of 36 row-major ``values`` (``cdr.py``'s decoders check theirs).
    WireError: not 36 finite values, not symmetric or not positive semi-definite."""
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


# ----------------------------------------------------------------------------- bytes, objects
_Msg = TypeVar('_Msg')


def raw(msg: Any) -> bytes:
    """A message's serialised bytes (rclpy's ``serialize_message`` of an object)."""
    if isinstance(msg, (bytes, bytearray, memoryview)):
        return bytes(msg)
    from rclpy.serialization import serialize_message
    return serialize_message(msg)


def message(data: bytes | bytearray | memoryview, msg_type: type[_Msg]) -> _Msg:
    """The ``msg_type`` object of a message's serialised bytes (rclpy's
    ``deserialize_message``); WireError: bytes rclpy cannot read as a ``msg_type``."""
    from rclpy.serialization import deserialize_message
    try:
        return deserialize_message(bytes(data), msg_type)
    except RuntimeError as exc:   # rclpy's RMWError
        raise WireError(f'not a {type_name(msg_type)}: {exc}') from None


# ----------------------------------------------------------------------------- channels
# A channel travels by its wire kind, not by its name (a Vector3Stamped zero-padded; a
# PointCloud2's points: the channel's fields, FLOAT64, then agent_id UINT32).
KIND_TYPES: dict[str, type] = {POSE_POSITION: PoseWithCovarianceStamped,
                               POSE_COVARIANCE: PoseWithCovarianceStamped,
                               VECTOR: Vector3Stamped, POINTS: PointCloud2}


def channel_type(c: Channel) -> type:
    """The message type that carries channel ``c`` (a sensor's readings: the sensor's)."""
    return PointCloud2 if c.sensor is not None else KIND_TYPES[c.kind]


def channel_frame(c: Channel, sender: str, estimate: str, world: str = WORLD_FRAME) -> str:
    """The frame id a message of ``sender`` carrying ``c`` must have."""
    return {'world': world, 'body': body_frame(sender)}.get(c.frame, estimate)


def by_topic(channels: Iterable[Channel]) -> dict[str, list[Channel]]:
    """The channels that travel on each topic, in their order."""
    out: dict[str, list[Channel]] = {}
    for c in channels:
        out.setdefault(c.topic, []).append(c)
    return out


def decode_channels(msg: Any, channels: Sequence[Channel]
                    ) -> tuple[float, dict[str, object], dict[str, str]]:
    """``(stamp, values, problems)`` of a message carrying one topic's ``channels`` (per-edge
    ones as ``{listener id: value}``); one that cannot be decoded is left out, its reason in
    ``problems`` (a bad covariance does not cost the position)."""
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
    """The frame id of a method's estimates (``frame``: an ``EstimateFrame`` value): ``world``,
    the ``anchor``'s :func:`body_frame`, or :func:`estimation_frame`."""
    if frame == 'world':
        return world
    if frame == 'anchor_body':
        if anchor is None:
            raise WireError('anchor-frame estimates need the anchor\'s name')
        return body_frame(anchor)
    return estimation_frame(fleet)


from . import cdr  # noqa: E402  (cdr reads WireError and the frames from here)
