"""The codecs (msg_defs/cdr.py) against rclpy's own serialisation, without DDS and without
rclpy.init: each encoder's bytes are those of the message rclpy builds of the same values,
each decoder reads from what rclpy serialises of a message the values it was built of, the
channel kinds round trip, and malformed bytes are rejected with WireError (never another
error).

Two oracles. The bytes: a slow generic CDR writer (``reference``) that walks any message by
its introspection and records where it pads; it is itself checked against
``serialize_message`` (whose padding bytes are uninitialised memory, so only the other bytes
compare). The values: the message object's fields, read one by one (``DECODERS``' readers),
on messages this file builds field by field (``pose_msg``, ...)."""
from __future__ import annotations

import math
import re
import struct
from typing import Any, Callable

import numpy as np
import pytest
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, PointCloud2, PointField

from bearing_pose_estimation import msg_defs as wire
from bearing_pose_estimation.core import so3
from bearing_pose_estimation.estimators import _BUILT_IN
from bearing_pose_estimation.estimators.base import (POINTS, POSE_COVARIANCE, POSE_POSITION,
                                                     VECTOR, Channel)
from bearing_pose_estimation.msg_defs import WireError, cdr

RNG = np.random.default_rng(15)
T = 12.345678901                            # keeps its nanoseconds
FRAMES = ['abcdefghi'[:k] for k in range(10)]   # every residue of the padding after frame_id
COUNTS = [0, 1, 5]
R = so3.exp(np.array([0.3, -1.2, 0.7]))
P_ = RNG.normal(size=3) * 10
_A = RNG.normal(size=(6, 6))
COV = _A @ _A.T
F32, F64, U32 = PointField.FLOAT32, PointField.FLOAT64, PointField.UINT32
BLOCK = ('xx', 'yy', 'zz', 'xy', 'xz', 'yz')   # a points cloud with fields of its own


# ----------------------------------------------------------------------------- the oracle
_PRIMITIVES = {'boolean': '?', 'octet': 'B', 'uint8': 'B', 'int8': 'b', 'char': 'B',
               'uint16': 'H', 'int16': 'h', 'uint32': 'I', 'int32': 'i', 'uint64': 'Q',
               'int64': 'q', 'float': 'f', 'double': 'd'}


class _Writer:
    """Plain little-endian CDR of any message, zero padding, padding positions recorded."""

    def __init__(self) -> None:
        self.buf = bytearray(b'\x00\x01\x00\x00')
        self.pad: set[int] = set()

    def align(self, size: int) -> None:
        while (len(self.buf) - 4) % size:
            self.pad.add(len(self.buf))
            self.buf.append(0)

    def write(self, typ: str, value: Any) -> None:
        if m := re.fullmatch(r'sequence<(.+)>', typ):
            self.write('uint32', len(value))
            for v in value:
                self.write(m[1], v)
        elif m := re.fullmatch(r'(.+)\[(\d+)\]', typ):
            assert len(value) == int(m[2])
            for v in value:
                self.write(m[1], v)
        elif typ == 'string':
            raw = value.encode()
            self.write('uint32', len(raw) + 1)
            self.buf += raw + b'\0'
        elif typ in _PRIMITIVES:
            fmt = '<' + _PRIMITIVES[typ]
            self.align(struct.calcsize(fmt))
            self.buf += struct.pack(fmt, value)
        else:
            for name, field_type in value.get_fields_and_field_types().items():
                self.write(field_type, getattr(value, name))


def reference(msg: Any) -> tuple[bytes, set[int]]:
    w = _Writer()
    for name, field_type in msg.get_fields_and_field_types().items():
        w.write(field_type, getattr(msg, name))
    return bytes(w.buf), w.pad


def assert_same_but_padding(ours: bytes, theirs: bytes, pad: set[int]) -> None:
    assert len(ours) == len(theirs)
    differ = [i for i, (a, b) in enumerate(zip(ours, theirs)) if a != b and i not in pad]
    assert not differ, f'bytes differ at {differ}'


# ----------------------------------------------------------------------------- rclpy's messages
# Each message as a user's driver would build it: rclpy's classes, field by field.
def _stamped(msg: Any, t: float, frame: str) -> Any:
    msg.header.stamp = wire.to_stamp(t)
    msg.header.frame_id = frame
    return msg


def _set(obj: Any, names: str, values: Any) -> None:
    for name, value in zip(names, values, strict=True):
        setattr(obj, name, float(value))


def pose_msg(t: float, frame: str, R: np.ndarray, p: np.ndarray) -> PoseStamped:
    msg = _stamped(PoseStamped(), t, frame)
    _set(msg.pose.position, 'xyz', p)
    _set(msg.pose.orientation, 'xyzw', so3.to_quat(R))   # x, y, z, w
    return msg


def pose_cov_msg(t: float, frame: str, R: np.ndarray, p: np.ndarray,
                 P: np.ndarray) -> PoseWithCovarianceStamped:
    msg = _stamped(PoseWithCovarianceStamped(), t, frame)
    msg.pose.pose = pose_msg(t, frame, R, p).pose
    msg.pose.covariance = np.asarray(P, dtype=float).reshape(36)   # row-major
    return msg


def vector3_msg(t: float, frame: str, v: np.ndarray) -> Vector3Stamped:
    msg = _stamped(Vector3Stamped(), t, frame)
    _set(msg.vector, 'xyz', v)
    return msg


def imu_msg(t: float, agent: str, omega: np.ndarray) -> Imu:
    """A gyro sample: no orientation, no acceleration (their covariances' first elements -1,
    as sensor_msgs/Imu specifies)."""
    msg = _stamped(Imu(), t, f'{agent}/base_link')
    _set(msg.angular_velocity, 'xyz', omega)
    msg.orientation_covariance[0] = -1.0
    msg.linear_acceleration_covariance[0] = -1.0
    return msg


def odometry_msg(t: float, agent: str, v: Any, omega: Any, R_odom: Any = None,
                 p_odom: Any = None, v_std: float = 0.0, omega_std: float = 0.0) -> Odometry:
    """REP-105: pose in ``<agent>/odom``, twist in ``<agent>/base_link``, a diagonal twist
    covariance."""
    msg = _stamped(Odometry(), t, f'{agent}/odom')
    msg.child_frame_id = f'{agent}/base_link'
    if p_odom is not None:
        _set(msg.pose.pose.position, 'xyz', p_odom)
    if R_odom is not None:
        _set(msg.pose.pose.orientation, 'xyzw', so3.to_quat(R_odom))
    _set(msg.twist.twist.linear, 'xyz', v)
    _set(msg.twist.twist.angular, 'xyz', omega)
    cov = np.zeros(36)
    cov[[0, 7, 14]] = v_std ** 2
    cov[[21, 28, 35]] = omega_std ** 2
    msg.twist.covariance = cov
    return msg


_STRUCT = {F64: 'd', F32: 'f', U32: 'I'}


def cloud_msg(t: float, frame: str, fields: list[tuple[str, int]], rows: list[tuple]
              ) -> PointCloud2:
    """A packed, little-endian, dense, one-row cloud of ``rows`` with ``fields`` (name,
    datatype) in this order."""
    msg = _stamped(PointCloud2(), t, frame)
    formats = [_STRUCT[datatype] for _, datatype in fields]
    msg.fields = [PointField(name=name, offset=struct.calcsize('<' + ''.join(formats[:k])),
                             datatype=datatype, count=1)
                  for k, (name, datatype) in enumerate(fields)]
    fmt = '<' + ''.join(formats)
    msg.height, msg.width = 1, len(rows)
    msg.point_step = struct.calcsize(fmt)
    msg.row_step = msg.point_step * len(rows)
    msg.is_bigendian, msg.is_dense = False, True
    msg.data = b''.join(struct.pack(fmt, *row) for row in rows)
    return msg


def _tagged(fields: tuple[str, ...]) -> list[tuple[str, int]]:
    return [(f, F64) for f in fields] + [('agent_id', U32)]


def _rows(ids: np.ndarray, values: np.ndarray) -> list[tuple]:
    values = np.asarray(values)
    return [(*v, i) for v, i in zip(values.reshape(len(ids), values.size // max(len(ids), 1)),
                                     ids)]


# ----------------------------------------------------------------------------- reading objects
def _t(msg: Any) -> float:
    return wire.from_stamp(msg.header.stamp)


def _xyz(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z])


def _column(msg: PointCloud2, name: str) -> list:
    """The field ``name`` of every point (the last field of that name), widened."""
    f = {f.name: f for f in msg.fields}[name]
    fmt, data = '<' + _STRUCT[f.datatype], bytes(msg.data)
    return [struct.unpack_from(fmt, data, k * msg.point_step + f.offset)[0]
            for k in range(msg.width * msg.height)]


def _points(msg: PointCloud2, names: tuple[str, ...]) -> tuple:
    out = np.empty((msg.width * msg.height, len(names)))
    for k, name in enumerate(names):
        out[:, k] = _column(msg, name)
    return _t(msg), np.array(_column(msg, 'agent_id'), dtype=np.uint32), out


def _pose_of(pose: Any) -> tuple[np.ndarray, np.ndarray]:
    o = pose.orientation
    return so3.from_quat(np.array([o.x, o.y, o.z, o.w])), _xyz(pose.position)


def _cov_of(msg: PoseWithCovarianceStamped) -> np.ndarray:
    return np.array(msg.pose.covariance, dtype=float).reshape(6, 6)


# kind -> its message type
KINDS: dict[str, type] = {'pose': PoseStamped, 'pose_cov': PoseWithCovarianceStamped,
                          'vector3': Vector3Stamped, 'imu': Imu, 'odometry': Odometry,
                          'clock': Clock, 'vectors': PointCloud2, 'scalars': PointCloud2,
                          'points': PointCloud2}
# decoder -> (the kind it reads, the decoder, what it must return read from rclpy's object)
DECODERS: dict[str, tuple[str, Callable[[Any], Any], Callable[[Any], Any]]] = {
    'decode_pose_raw': ('pose', cdr.decode_pose_raw, lambda m: (_t(m), *_pose_of(m.pose))),
    'decode_covariance_raw': ('pose_cov', cdr.decode_covariance_raw,
                              lambda m: (_t(m), _cov_of(m))),
    'decode_pose_covariance_raw': ('pose_cov', cdr.decode_pose_covariance_raw,
                                   lambda m: (_t(m), *_pose_of(m.pose.pose), _cov_of(m))),
    'decode_position_raw': ('pose_cov', cdr.decode_position_raw,
                            lambda m: (_t(m), _xyz(m.pose.pose.position))),
    'decode_vector3_raw': ('vector3', cdr.decode_vector3_raw, lambda m: (_t(m), _xyz(m.vector))),
    'decode_imu_raw': ('imu', cdr.decode_imu_raw, lambda m: (_t(m), _xyz(m.angular_velocity))),
    'decode_odometry_raw': ('odometry', cdr.decode_odometry_raw,
                            lambda m: (_t(m), _xyz(m.twist.twist.linear),
                                       _xyz(m.twist.twist.angular))),
    'decode_clock_raw': ('clock', cdr.decode_clock_raw, lambda m: wire.from_stamp(m.clock)),
    'decode_vectors_raw': ('vectors', cdr.decode_vectors_raw,
                           lambda m: _points(m, ('x', 'y', 'z'))),
    'decode_scalars_raw': ('scalars', cdr.decode_scalars_raw,
                           lambda m: (lambda t, ids, v: (t, ids, v[:, 0]))(
                               *_points(m, ('range',)))),
    'decode_points_raw': ('points', lambda b: cdr.decode_points_raw(b, BLOCK),
                          lambda m: _points(m, BLOCK)),
}


def _equal(a: Any, b: Any) -> bool:
    """Values equal, NaNs included; tuples element by element; arrays of one dtype."""
    if isinstance(a, tuple):
        return isinstance(b, tuple) and len(a) == len(b) and all(map(_equal, a, b))
    if isinstance(a, np.ndarray):
        return (isinstance(b, np.ndarray) and a.shape == b.shape and a.dtype == b.dtype
                and bool(np.array_equal(a, b, equal_nan=a.dtype.kind == 'f')))
    return a == b or (math.isnan(a) and math.isnan(b))


# ----------------------------------------------------------------------------- the cases
def case(kind: str, frame: str, n: int = 3) -> tuple[Any, bytes]:
    """rclpy's message of ``kind`` and cdr's bytes of the same values (``frame``: the frame
    id, or the agent's name where the frames are an agent's)."""
    ids = RNG.integers(1, 2 ** 32, size=n, dtype=np.uint32)
    vectors, scalars, blocks = RNG.normal(size=(n, 3)), RNG.normal(size=n), RNG.normal(size=(n, 6))
    omega, v = RNG.normal(size=3), RNG.normal(size=3)
    if kind == 'pose':
        return pose_msg(T, frame, R, P_), cdr.encode_pose_raw(T, frame, R, P_)
    if kind == 'pose_cov':
        return (pose_cov_msg(T, frame, R, P_, COV),
                cdr.encode_pose_covariance_raw(T, frame, R, P_, COV))
    if kind == 'vector3':
        return vector3_msg(T, frame, v), cdr.encode_vector3_raw(T, frame, v)
    if kind == 'imu':
        return imu_msg(T, frame, omega), cdr.encode_imu_raw(T, frame, omega)
    if kind == 'odometry':
        return (odometry_msg(T, frame, v, omega, R, P_, 0.05, 0.002),
                cdr.encode_odometry_raw(T, frame, v, omega, R, P_, 0.05, 0.002))
    if kind == 'vectors':
        return (cloud_msg(T, frame, _tagged(('x', 'y', 'z')), _rows(ids, vectors)),
                cdr.encode_vectors_raw(T, frame, ids, vectors))
    if kind == 'scalars':
        return (cloud_msg(T, frame, _tagged(('range',)), _rows(ids, scalars)),
                cdr.encode_scalars_raw(T, frame, ids, scalars, 'range'))
    if kind == 'points':
        return (cloud_msg(T, frame, _tagged(BLOCK), _rows(ids, blocks)),
                cdr.encode_points_raw(T, frame, ids, blocks, BLOCK))
    assert kind == 'clock'
    t = T * (len(frame) - 4.5)   # negative ones too
    return Clock(clock=wire.to_stamp(t)), cdr.encode_clock_raw(t)


FIXED = ['pose', 'pose_cov', 'vector3', 'imu', 'odometry', 'clock']
CLOUDS = ['vectors', 'scalars', 'points']
STAMPED = [k for k in FIXED + CLOUDS if k != 'clock']
CASES = ([(k, f, 3) for k in FIXED for f in FRAMES]
         + [(k, f, n) for k in CLOUDS for f in FRAMES for n in COUNTS])
DECODER_CASES = [(name, f, n) for name, (kind, _, _) in DECODERS.items()
                 for k, f, n in CASES if k == kind]


def test_rclpy_serialization_needs_no_init():
    assert not rclpy.ok()
    msg = pose_msg(T, 'world', R, P_)
    assert deserialize_message(serialize_message(msg), PoseStamped) == msg


@pytest.mark.parametrize('kind, frame, n', CASES)
def test_encoders_are_rclpys_bytes(kind, frame, n):
    msg, ours = case(kind, frame, n)
    ref, pad = reference(msg)
    theirs = serialize_message(msg)
    assert_same_but_padding(ref, theirs, pad)   # the oracle is rclpy's layout
    assert ours == ref                          # ours: that layout, zero padding
    assert_same_but_padding(ours, theirs, pad)
    assert deserialize_message(ours, type(msg)) == msg
    assert wire.message(ours, KINDS[kind]) == msg


@pytest.mark.parametrize('name, frame, n', DECODER_CASES)
def test_decoders_read_rclpys_bytes(name, frame, n):
    kind, decode, read = DECODERS[name]
    msg, _ = case(kind, frame, n)
    want = read(msg)
    data = serialize_message(msg)   # with rclpy's garbage padding
    assert _equal(decode(data), want)
    assert _equal(decode(bytearray(data)), want)
    assert _equal(decode(memoryview(data)), want)
    assert _equal(decode(msg), want)   # a message object: its bytes


@pytest.mark.parametrize('kind', STAMPED)
@pytest.mark.parametrize('frame', FRAMES[::3])
def test_read_header(kind, frame):
    msg, data = case(kind, frame)
    h = cdr.read_header(data)
    assert (h.frame_id, h.ns, h.t) == (msg.header.frame_id, wire.stamp_ns(msg.header.stamp),
                                       wire.from_stamp(msg.header.stamp))
    assert cdr.read_header(msg) == h


def test_odometry_defaults_and_child_frame():
    msg = odometry_msg(0.5, 'agent_1', [1.0, 0, 0], [0, 0, 0.25])
    data = cdr.encode_odometry_raw(0.5, 'agent_1', [1.0, 0, 0], [0, 0, 0.25])
    assert data == reference(msg)[0]
    assert wire.message(data, Odometry).pose.pose.orientation.w == 1.0   # identity, zero
    t, v, omega = cdr.decode_odometry_raw(data, 'agent_1/base_link')
    assert t == 0.5 and v.tolist() == [1.0, 0, 0] and omega.tolist() == [0, 0, 0.25]
    with pytest.raises(WireError, match="child_frame_id 'agent_1/base_link', expected 'x'"):
        cdr.decode_odometry_raw(data, 'x')


def test_outputs_are_writable_and_do_not_alias_the_buffer():
    data = bytearray(cdr.encode_pose_covariance_raw(T, 'world', R, P_, COV))
    _, R2, p2, P2 = cdr.decode_pose_covariance_raw(data)
    cloud = bytearray(cdr.encode_vectors_raw(T, 'w', [1], [[1.0, 2, 3]]))
    _, ids, b = cdr.decode_vectors_raw(cloud)
    data[-300:] = bytes(300)
    cloud[-29:-1] = bytes(28)
    assert P2[5, 5] == COV[5, 5] and p2.tolist() == P_.tolist()
    assert ids.tolist() == [1] and b.tolist() == [[1.0, 2, 3]]
    for a in (R2, p2, P2, ids, b):
        a[...] = 0   # writable


def test_message_objects_and_bytes():
    """msg_defs.raw and msg_defs.message: rclpy's (de)serialisation, bytes that are none of
    the type rejected with a WireError."""
    msg, data = case('pose', 'world')
    # rclpy's padding bytes are uninitialised memory: two serialisations may differ there.
    assert_same_but_padding(wire.raw(msg), serialize_message(msg), reference(msg)[1])
    assert wire.raw(bytearray(data)) == wire.raw(memoryview(data)) == data
    assert wire.message(bytearray(data), PoseStamped) == msg
    for bad in (b'', b'\x00\x01\x00\x00garbage', data[:-8]):
        with pytest.raises(WireError, match='not a geometry_msgs/msg/PoseStamped'):
            wire.message(bad, PoseStamped)


# ----------------------------------------------------------------------------- clouds
def _cloud(fields: list[tuple[str, int, int]], point_step: int, points: np.ndarray,
           height: int = 1, frame: str = 'agent_2/base_link') -> PointCloud2:
    """A PointCloud2 with the given (name, offset, datatype) fields, as a detector might
    build it."""
    msg = _stamped(PointCloud2(), T, frame)
    msg.height, msg.width = height, len(points) // height
    msg.fields = [PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in fields]
    msg.point_step, msg.row_step = point_step, point_step * msg.width
    msg.is_dense = True
    msg.data = points.tobytes()
    return msg


def _random_points(dtype: np.dtype, n: int) -> np.ndarray:
    points = np.zeros(n, dtype=dtype)
    for name in dtype.names or ():
        points[name] = (RNG.integers(1, 99, size=n) if name == 'agent_id'
                        else RNG.normal(size=n))
    return points


@pytest.mark.parametrize('n', COUNTS + [4])
@pytest.mark.parametrize('layout', ['float32', 'pcl_padded', 'reordered', 'two_rows'])
def test_foreign_clouds(layout, n):
    """FLOAT32 (widened), padding, any field order, height > 1: each read as its fields say."""
    if layout == 'float32':
        dtype = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('agent_id', '<u4')])
        fields = [('x', 0, F32), ('y', 4, F32), ('z', 8, F32), ('agent_id', 12, U32)]
    elif layout == 'pcl_padded':   # PCL's PointXYZ: 16-byte point, id after it
        dtype = np.dtype({'names': ['x', 'y', 'z', 'agent_id'], 'formats': ['<f4'] * 3
                          + ['<u4'], 'offsets': [0, 4, 8, 16], 'itemsize': 32})
        fields = [('x', 0, F32), ('y', 4, F32), ('z', 8, F32), ('agent_id', 16, U32)]
    elif layout == 'reordered':
        dtype = np.dtype([('agent_id', '<u4'), ('pad', '<u4'), ('z', '<f8'), ('x', '<f8'),
                          ('y', '<f8')])
        fields = [('agent_id', 0, U32), ('z', 8, F64), ('x', 16, F64), ('y', 24, F64),
                  ('intensity', 4, F32)]
    else:   # 2 rows of n points
        dtype = np.dtype([('x', '<f8'), ('y', '<f8'), ('z', '<f8'), ('agent_id', '<u4')])
        fields = [('x', 0, F64), ('y', 8, F64), ('z', 16, F64), ('agent_id', 24, U32)]
    rows = 2 if layout == 'two_rows' else 1
    msg = _cloud(fields, dtype.itemsize, _random_points(dtype, rows * n), height=rows)
    data = serialize_message(msg)
    assert_same_but_padding(*reference(msg)[:1], data, reference(msg)[1])
    t, ids, vectors = cdr.decode_vectors_raw(data)
    assert _equal((t, ids, vectors), _points(msg, ('x', 'y', 'z')))
    assert vectors.dtype == np.float64 and vectors.shape == (rows * n, 3)
    # Scalar and named-field clouds of FLOAT32 fields.
    scal = _cloud([('agent_id', 0, U32), ('range', 4, F32)], 8,
                  _random_points(np.dtype([('agent_id', '<u4'), ('range', '<f4')]), n))
    t, ids, values = cdr.decode_scalars_raw(serialize_message(scal))
    assert _equal((t, ids, values[:, None]), _points(scal, ('range',)))
    block = np.dtype([(f, '<f4') for f in BLOCK] + [('agent_id', '<u4')])
    named = _cloud([(f, 4 * k, F32) for k, f in enumerate(BLOCK)] + [('agent_id', 24, U32)],
                   28, _random_points(block, n))
    assert _equal(cdr.decode_points_raw(serialize_message(named), BLOCK), _points(named, BLOCK))


def test_decode_cloud_raw_is_a_view():
    data = cdr.encode_vectors_raw(T, 'w', [7, 8], [[1.0, 2, 3], [4, 5, 6]])
    t, points = cdr.decode_cloud_raw(data, {'x': F64, 'agent_id': U32})
    assert points['x'].tolist() == [1.0, 4.0] and points['agent_id'].tolist() == [7, 8]
    assert not points.flags.writeable


def test_many_cloud_layouts():
    """More layouts than the decoder keeps parsed: each still read as its fields say."""
    for k in range(2 * cdr._SEEN_MAX):
        dtype = np.dtype([('agent_id', '<u4'), ('p' * (k + 1), '<u4'), ('x', '<f8'),
                          ('y', '<f8'), ('z', '<f4')])
        names = ['agent_id', 'p' * (k + 1), 'x', 'y', 'z']
        dt = [U32, U32, F64, F64, F32]
        fields = [(n, dtype.fields[n][1], d) for n, d in zip(names, dt)]
        msg = _cloud(fields, dtype.itemsize, _random_points(dtype, k % 4))
        assert _equal(cdr.decode_vectors_raw(serialize_message(msg)),
                      _points(msg, ('x', 'y', 'z')))
    assert len(cdr._SEEN_FIELDS) <= cdr._SEEN_MAX >= len(cdr._SEEN_DTYPES)


# ----------------------------------------------------------------------------- rejected
def _first(kind: str) -> bytes:
    return case(kind, 'abc', 5)[1]


def _decoder(name: str) -> tuple[bytes, Callable[[Any], Any]]:
    kind, decode, _ = DECODERS[name]
    return _first(kind), decode


@pytest.mark.parametrize('name', DECODERS)
def test_every_truncation_is_rejected(name):
    data, decode = _decoder(name)
    for k in range(len(data)):
        with pytest.raises(WireError, match='truncated|past the end|cannot fit'):
            decode(data[:k])


@pytest.mark.parametrize('name', DECODERS)
def test_trailing_bytes(name):
    """Up to 3 bytes after the message pass (a writer's padding to 4), more do not."""
    data, decode = _decoder(name)
    assert _equal(decode(data + b'\xff' * 3), decode(data))
    with pytest.raises(WireError, match='4 after the end of the message'):
        decode(data + bytes(4))


@pytest.mark.parametrize('name', DECODERS)
@pytest.mark.parametrize('encapsulation, what', [
    (b'\x00\x00\x00\x00', 'big-endian CDR'), (b'\x00\x07\x00\x00', 'XCDR2'),
    (b'\x00\x03\x00\x00', 'PL_CDR'), (b'\x01\x01\x00\x00', 'unknown')])
def test_wrong_encapsulation(name, encapsulation, what):
    data, decode = _decoder(name)
    with pytest.raises(WireError, match=rf'encapsulation {encapsulation.hex(" ")} \({what}\)'):
        decode(encapsulation + data[4:])
    assert _equal(decode(data[:2] + b'\x00\x02' + data[4:]), decode(data))   # options: ignored


STAMPED_DECODERS = [name for name, (kind, _, _) in DECODERS.items() if kind != 'clock']


@pytest.mark.parametrize('name', STAMPED_DECODERS)
@pytest.mark.parametrize('extra', [1, 0x10000, 0xffffffff])
def test_frame_id_past_the_end(name, extra):
    """A frame_id length ``extra`` bytes past the end (or the largest uint32)."""
    data, decode = _decoder(name)
    length = min(len(data) - 16 + extra, 0xffffffff)
    bad = data[:12] + struct.pack('<I', length) + data[16:]
    with pytest.raises(WireError, match='header.frame_id of length .* runs past the end'):
        decode(bad)


@pytest.mark.parametrize('name', STAMPED_DECODERS)
def test_frame_id_not_a_string(name):
    data, decode = _decoder(name)
    end = 16 + struct.unpack_from('<I', data, 12)[0]   # after frame_id's NUL
    assert data[16:19] == b'abc' and data[end - 1] == 0
    for at, byte, match in [(end - 1, b'd', 'not one NUL-terminated string'),
                            (17, b'\0', 'not one NUL-terminated string'),
                            (17, b'\xff', 'not UTF-8')]:
        with pytest.raises(WireError, match=match):
            decode(data[:at] + byte + data[at + 1:])
    assert cdr.read_header(data[:12] + bytes(4) + data[16:]).frame_id == ''   # as rmw reads it


def test_odometry_child_frame_past_the_end():
    data = cdr.encode_odometry_raw(T, 'abc', [0, 0, 0], [0, 0, 0])
    at = data.index(b'abc/base_link') - 4
    for length in (len(data), 0xffffffff):
        with pytest.raises(WireError, match='child_frame_id of length .* runs past the end'):
            cdr.decode_odometry_raw(data[:at] + struct.pack('<I', length) + data[at + 4:])


def _at(data: bytes, n: int, step: int) -> dict[str, int]:
    """Byte positions in a one-row cloud of n points of ``step`` bytes."""
    size = len(data) - 1 - n * step - 4
    return {'is_dense': len(data) - 1, 'size': size, 'row_step': size - 4,
            'point_step': size - 8, 'is_bigendian': size - 12,
            'count': data.index(b'\x02\x00\x00\x00x\0') - 4}


@pytest.mark.parametrize('where, value, match', [
    ('size', 5 * 28 + 1, 'data of 141 bytes .* runs past the end'),
    ('size', 0xffffffff, 'runs past the end'),
    ('size', 4 * 28, '28 after the end of the message'),   # the data says 4 points
    ('count', 0x7fffffff, '2147483647 fields cannot fit'),
    ('count', 5, '.'),   # the tail read as a fifth field: whatever it breaks
    ('is_bigendian', 2, 'a bool is 0 or 1'),
    ('is_dense', 2, 'a bool is 0 or 1'),
])
def test_cloud_bytes_rejected(where, value, match):
    data = cdr.encode_vectors_raw(T, 'abc', np.arange(5), np.ones((5, 3)))
    at = _at(data, 5, 28)[where]
    fmt = '<B' if where.startswith('is_') else '<I'
    bad = data[:at] + struct.pack(fmt, value) + data[at + struct.calcsize(fmt):]
    with pytest.raises(WireError, match=match):
        cdr.decode_vectors_raw(bad)


def test_empty_cloud_with_a_huge_point_step():
    """0 points x any point_step is 0 bytes, but numpy cannot make an item of 2^31 bytes:
    a WireError, not numpy's ValueError."""
    data = cdr.encode_vectors_raw(T, 'abc', [], np.zeros((0, 3)))
    at = _at(data, 0, 28)['point_step']
    assert struct.unpack_from('<I', data, at)[0] == 28
    bad = data[:at] + struct.pack('<I', 2 ** 31 + 5) + data[at + 4:]
    with pytest.raises(WireError, match='point_step 2147483653 .* too large'):
        cdr.decode_vectors_raw(bad)
    ok = data[:at] + struct.pack('<I', 2 ** 20) + data[at + 4:]
    assert cdr.decode_vectors_raw(ok)[2].shape == (0, 3)


def test_field_name_past_the_end():
    data = cdr.encode_vectors_raw(T, 'abc', np.arange(5), np.ones((5, 3)))
    at = data.index(b'\x09\x00\x00\x00agent_id')
    with pytest.raises(WireError, match='a field name of length .* runs past the end'):
        cdr.decode_vectors_raw(data[:at] + struct.pack('<I', 0xffff) + data[at + 4:])


def _vectors_cloud(**change: Any) -> PointCloud2:
    """A 5-point vector cloud with some of its fields' or layout's values changed."""
    msg = case('vectors', 'abc', 5)[0]
    fields = {f.name: f for f in msg.fields}
    for key, value in change.items():
        if '.' in key:
            name, attr = key.split('.')
            setattr(fields[name], attr, value)
        else:
            setattr(msg, key, value)
    return msg


@pytest.mark.parametrize('change, match', [
    ({'width': 4}, 'data is 140 bytes, expected 4 points x 28 bytes'),
    ({'height': 2}, 'data is 140 bytes, expected 10 points x 28 bytes'),
    ({'point_step': 32}, 'data is 140 bytes, expected 5 points x 32 bytes'),
    ({'point_step': 20, 'width': 7}, 'data is 140 bytes|does not hold its fields'),
    ({'agent_id.offset': 26}, "field 'agent_id' .* overlaps .* the end of the 28-byte point"),
    ({'y.offset': 4}, "field 'x' .* overlaps the next field"),
    ({'z.offset': 100}, "field 'z' .* overlaps"),
    ({'agent_id.name': 'id'}, r"needs field 'agent_id' of datatype 6 \(fields: "
                              r"\['id', 'x', 'y', 'z'\]\)"),
    ({'agent_id.datatype': PointField.INT32}, "needs field 'agent_id' of datatype 6"),
    ({'x.datatype': PointField.UINT32}, "needs field 'x' of datatype 8 or 7"),
    ({'x.count': 2}, "needs field 'x'"),
    ({'is_bigendian': True}, 'big-endian PointCloud2 is not supported'),
])
def test_cloud_layouts_rejected(change, match):
    msg = _vectors_cloud(**change)
    with pytest.raises(WireError, match=match):
        cdr.decode_vectors_raw(serialize_message(msg))


def _spoilt_pose(q: list[float] | None = None, p: list[float] | None = None) -> PoseStamped:
    msg = pose_msg(T, 'world', R, P_)
    if q is not None:
        _set(msg.pose.orientation, 'xyzw', q)
    if p is not None:
        _set(msg.pose.position, 'xyz', p)
    return msg


_ASYM = COV.copy()
_ASYM[0, 1] += 1.0
_NEG = np.diag([1.0, 1, 1, 1, 1, -1])
_NANCOV = COV.copy()
_NANCOV[2, 2] = np.inf


@pytest.mark.parametrize('name, msg, match', [
    ('decode_imu_raw', imu_msg(T, 'a', [1.0, np.nan, 1.0]), 'non-finite angular velocity'),
    ('decode_imu_raw', imu_msg(T, 'a', [0, 0, -np.inf]), 'non-finite angular velocity'),
    ('decode_odometry_raw', odometry_msg(T, 'a', [0, np.inf, 0], np.zeros(3)),
     'non-finite twist'),
    ('decode_odometry_raw', odometry_msg(T, 'a', np.zeros(3), [np.nan, 1, 1]),
     'non-finite twist'),
    ('decode_pose_raw', _spoilt_pose(p=[0, np.nan, 0]), 'non-finite pose'),
    ('decode_pose_raw', _spoilt_pose(q=[0, 0, np.inf, 1]), 'non-finite pose'),
    ('decode_pose_raw', _spoilt_pose(q=[0, 0, 0, 1.01]), 'quaternion norm 1.01 is not 1'),
    ('decode_pose_raw', _spoilt_pose(q=[0, 0, 0, 0]), 'quaternion norm 0 is not 1'),
    ('decode_covariance_raw', pose_cov_msg(T, 'world', R, P_, _NANCOV),
     'non-finite or malformed covariance'),
    ('decode_covariance_raw', pose_cov_msg(T, 'world', R, P_, _ASYM),
     'covariance is not symmetric'),
    ('decode_pose_covariance_raw', pose_cov_msg(T, 'world', R, P_, _NEG),
     'covariance is not positive semi-definite'),
    ('decode_vector3_raw', vector3_msg(T, 'f', [0.0, 0.0, np.nan]), 'non-finite vector'),
])
def test_values_rejected(name, msg, match):
    """Values no receiver can use, in rclpy's message: rejected by name."""
    with pytest.raises(WireError, match=match):
        DECODERS[name][1](serialize_message(msg))


def test_what_a_decoder_does_not_read_is_not_checked():
    msg = pose_cov_msg(T, 'world', R, P_, COV)
    msg.pose.pose.orientation.w = 2.0
    with pytest.raises(WireError, match='quaternion norm'):
        cdr.decode_pose_covariance_raw(serialize_message(msg))
    cdr.decode_covariance_raw(serialize_message(msg))   # the pose is not read
    cdr.decode_position_raw(pose_cov_msg(T, 'world', R, P_, _ASYM))   # nor the covariance
    cloud = cloud_msg(T, 'f', _tagged(('x', 'y', 'z')), [(np.nan, 0, 1, 4)])
    assert np.isnan(cdr.decode_vectors_raw(cloud)[2][0, 0])   # receivers check their points
    named = cloud_msg(T, 'f', _tagged(BLOCK), [(1, 2, 3, np.inf, 5, 6, 9)])
    assert np.isinf(cdr.decode_points_raw(named, BLOCK)[2][0, 3])


@pytest.mark.filterwarnings('ignore:overflow encountered:RuntimeWarning')  # huge quaternions
@pytest.mark.parametrize('name', DECODERS)
def test_mutated_bytes_are_rejected_or_read_as_rclpy_reads_them(name):
    """Random byte changes: a WireError, or the values of the message rclpy deserialises of
    the same bytes (finite, where the decoder checks it); never another exception."""
    kind, decode, read = DECODERS[name]
    data = _first(kind)
    rng = np.random.default_rng(len(name))
    accepted = 0
    for _ in range(1000):
        bad = bytearray(data)
        for at in rng.integers(0, len(data), size=rng.integers(1, 4)):
            bad[at] = rng.integers(0, 256) if rng.random() < 0.7 else bad[at] ^ 1
        try:
            ours = decode(bytes(bad))
        except WireError:
            continue
        accepted += 1
        theirs = deserialize_message(bytes(bad), KINDS[kind])
        assert _equal(ours, read(theirs)), bytes(bad).hex(' ')
        if kind in FIXED:
            values = ours if isinstance(ours, tuple) else (ours,)
            assert all(np.isfinite(v).all() for v in values), bytes(bad).hex(' ')
    assert accepted > 0


def test_encoders_reject_what_cannot_be_sent():
    with pytest.raises(WireError, match='contains a NUL'):
        cdr.encode_pose_raw(T, 'wor\0ld', R, P_)
    with pytest.raises(WireError, match='does not fit builtin_interfaces/Time'):
        cdr.encode_clock_raw(2.0 ** 31)
    with pytest.raises(WireError, match='structured'):
        cdr.encode_cloud_raw(T, 'w', np.zeros(3))
    with pytest.raises(WireError, match='no little-endian PointField datatype'):
        cdr.encode_cloud_raw(T, 'w', np.zeros(3, dtype=[('x', '>f8')]))
    clock = deserialize_message(cdr.encode_clock_raw(-1.5), Clock).clock
    assert clock == Time(sec=-2, nanosec=500_000_000)


# ----------------------------------------------------------------------------- channels
# Every channel of the built-in methods, once per way it travels.
CHANNELS = list({(c.kind, c.shape, c.fields, c.sensor is None): c
                 for cls in _BUILT_IN for c in cls.sends}.values())
SENT = [c for c in CHANNELS if c.kind in (VECTOR, POINTS) and c.sensor is None]


def test_every_kind_is_covered():
    assert {c.kind for c in CHANNELS} == {POSE_POSITION, POSE_COVARIANCE, VECTOR, POINTS}
    assert set(wire.KIND_TYPES) == {POSE_POSITION, POSE_COVARIANCE, VECTOR, POINTS}
    assert any(c.sensor is not None for c in CHANNELS)


def _value(c: Channel) -> Any:
    """A value of channel ``c`` as the estimator gives it: an array, or per listener."""
    if c.per == 'agent':
        return RNG.normal(size=c.shape)
    return {i: RNG.normal(size=c.shape) for i in (7, 2, 5)}


def _same(a: Any, b: Any) -> None:
    if isinstance(a, dict):
        assert list(a) == list(b)
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    else:
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize('c', SENT, ids=lambda c: c.name)
def test_channel_kinds_round_trip(c):
    """encode_channels → rclpy's message of the channel's type (zero-padded to the
    message's three components, or a point per listener with the channel's FLOAT64 fields and
    agent_id) → decode_channels gives the value back."""
    value = _value(c)
    data = wire.encode_channels(T, 'agent_1/base_link', [c], {c.name: value})
    msg = wire.message(data, wire.channel_type(c))
    assert wire.channel_type(c) is wire.KIND_TYPES[c.kind]
    assert msg.header.frame_id == 'agent_1/base_link' and _t(msg) == T
    if c.kind == VECTOR:
        want = np.zeros(3)
        want[:c.shape[0]] = value
        np.testing.assert_array_equal(_xyz(msg.vector), want)
    else:
        assert [(f.name, f.datatype, f.count) for f in msg.fields] == [
            (n, d, 1) for n, d in _tagged(c.fields)]
        t, ids, points = _points(msg, c.fields)
        assert ids.tolist() == list(value)
        np.testing.assert_array_equal(points[:, :c.shape[0]], np.array(list(value.values())))
        assert not points[:, c.shape[0]:].any()   # zero-padded
    for given in (data, msg):
        t, values, problems = wire.decode_channels(given, [c])
        assert t == T and not problems
        _same(values[c.name], value)


def test_pose_channels_ride_on_the_pose():
    """p_hat / q_hat (the position) and pose_cov (the covariance) from one
    PoseWithCovarianceStamped, each decoded on its own: a broken covariance costs only
    itself."""
    position = next(c for c in CHANNELS if c.kind == POSE_POSITION)
    covariance = next(c for c in CHANNELS if c.kind == POSE_COVARIANCE)
    both = [position, covariance]
    assert {wire.channel_type(c) for c in both} == {PoseWithCovarianceStamped}
    t, values, problems = wire.decode_channels(
        cdr.encode_pose_covariance_raw(T, 'world', R, P_, COV), both)
    assert t == T and not problems
    np.testing.assert_array_equal(values[position.name], P_)
    np.testing.assert_array_equal(values[covariance.name], COV)
    t, values, problems = wire.decode_channels(pose_cov_msg(T, 'world', R, P_, _ASYM), both)
    assert list(values) == [position.name] and list(problems) == [covariance.name]
    assert 'not symmetric' in problems[covariance.name]


def test_sensor_channels_are_the_sensor_s_points():
    """A channel of a sensor's readings (``meas``) is read from the sensor's cloud."""
    c = next(c for c in CHANNELS if c.sensor is not None)
    assert wire.channel_type(c) is PointCloud2
    vectors = RNG.normal(size=(2, 3))
    t, values, problems = wire.decode_channels(
        cdr.encode_vectors_raw(T, 'agent_2/base_link', [4, 1], vectors), [c])
    assert t == T and not problems
    _same(values[c.name], {4: vectors[0], 1: vectors[1]})


@pytest.mark.parametrize('c', SENT, ids=lambda c: c.name)
def test_malformed_channel_bytes_are_problems_not_exceptions(c):
    data = wire.encode_channels(T, 'f', [c], {c.name: _value(c)})
    for bad in (data[:-9], b'\x00\x01\x00\x00garbage', b'\x00\x00\x00\x00' + data[4:]):
        _, values, problems = wire.decode_channels(bad, [c])
        assert not values and list(problems) == [c.name]
    if c.kind == POINTS:   # a non-finite value: the listener's runtime says so, by cause
        bad_value = {3: np.full(c.shape, np.nan), 4: np.ones(c.shape)}
        _, values, problems = wire.decode_channels(
            wire.encode_channels(T, 'f', [c], {c.name: bad_value}), [c])
        assert not problems and np.isnan(values[c.name][3]).all()
