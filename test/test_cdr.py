"""Raw CDR (msg_defs/cdr.py) against rclpy's own serialisation, without DDS and without
rclpy.init: the encoders' bytes, the decoders' values and what both reject.

The oracle is a slow generic CDR writer (``reference``) that walks any message by its
introspection and records where it pads; it is itself checked against ``serialize_message``
(whose padding bytes are uninitialised memory, so only the other bytes compare)."""
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
from bearing_pose_estimation.msg_defs import cdr
from bearing_pose_estimation.msg_defs import WireError

RNG = np.random.default_rng(15)
T = 12.345678901                            # keeps its nanoseconds
FRAMES = ['abcdefghi'[:k] for k in range(10)]   # every residue of the padding after frame_id
COUNTS = [0, 1, 5]
R = so3.exp(np.array([0.3, -1.2, 0.7]))
P_ = RNG.normal(size=3) * 10
_A = RNG.normal(size=(6, 6))
COV = _A @ _A.T


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


# ----------------------------------------------------------------------------- the cases
def _clouds(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    ids = RNG.integers(1, 2 ** 32, size=n, dtype=np.uint32)
    return ids, RNG.normal(size=(n, 3)), RNG.normal(size=n), RNG.normal(size=(n, 6))


def _equal(a: Any, b: Any) -> bool:
    """Values equal, NaNs included; dicts and tuples element by element."""
    if isinstance(a, tuple):
        return len(a) == len(b) and all(map(_equal, a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, np.ndarray):
        return a.shape == b.shape and a.dtype == b.dtype and bool(
            np.array_equal(a, b, equal_nan=a.dtype.kind == 'f'))
    return a == b or (math.isnan(a) and math.isnan(b))


def _blocks(value: tuple) -> tuple[float, dict]:
    t, ids, packed = value
    return t, dict(zip(ids.tolist(), packed))


# name -> (message type, raw decoder, msg_defs' decoder of the message); each decoder's result
# is compared with _equal.
DECODERS: dict[str, tuple[type, Callable[[bytes], Any], Callable[[Any], Any]]] = {
    'pose': (PoseStamped, cdr.decode_pose_raw, wire.decode_pose),
    'pose_cov': (PoseWithCovarianceStamped, cdr.decode_covariance_raw, wire.decode_covariance),
    'complex': (Vector3Stamped, cdr.decode_complex_raw, wire.CHANNELS['z_hat'].decode),
    'imu': (Imu, cdr.decode_imu_raw, wire.decode_imu),
    'odometry': (Odometry, cdr.decode_odometry_raw, wire.decode_odometry),
    'vectors': (PointCloud2, cdr.decode_vectors_raw, wire.decode_vectors),
    'scalars': (PointCloud2, cdr.decode_scalars_raw, wire.decode_scalars),
    'blocks': (PointCloud2, lambda b: _blocks(cdr.decode_blocks_raw(b)),
               wire.CHANNELS['angle_hessian'].decode),
    'clock': (Clock, cdr.decode_clock_raw, lambda m: wire.from_stamp(m.clock)),
}


def case(kind: str, frame: str, n: int = 3) -> tuple[Any, bytes]:
    """msg_defs' message of ``kind`` and cdr's bytes of the same values."""
    ids, vectors, scalars, blocks = _clouds(n)
    omega, v = RNG.normal(size=3), RNG.normal(size=3)
    if kind == 'pose':
        return wire.encode_pose(T, frame, R, P_), cdr.encode_pose_raw(T, frame, R, P_)
    if kind == 'pose_cov':
        return (wire.encode_pose_covariance(T, frame, R, P_, COV),
                cdr.encode_pose_covariance_raw(T, frame, R, P_, COV))
    if kind == 'complex':
        z = RNG.normal(size=2)
        return (wire.CHANNELS['z_hat'].encode(T, z, frame),   # type: ignore[misc]
                cdr.encode_complex_raw(T, z, frame))
    if kind == 'imu':
        return wire.encode_imu(T, frame, omega), cdr.encode_imu_raw(T, frame, omega)
    if kind == 'odometry':
        return (wire.encode_odometry(T, frame, v, omega, R, P_, 0.05, 0.002),
                cdr.encode_odometry_raw(T, frame, v, omega, R, P_, 0.05, 0.002))
    if kind == 'vectors':
        return (wire.encode_vectors(T, frame, ids, vectors),
                cdr.encode_vectors_raw(T, frame, ids, vectors))
    if kind == 'scalars':
        return (wire.encode_scalars(T, frame, ids, scalars, 'range'),
                cdr.encode_scalars_raw(T, frame, ids, scalars, 'range'))
    if kind == 'blocks':
        return (wire.CHANNELS['angle_hessian'].encode(   # type: ignore[misc]
            T, dict(zip(ids.tolist(), blocks)), frame),
            cdr.encode_blocks_raw(T, frame, ids, blocks))
    assert kind == 'clock'
    t = T * (len(frame) - 4.5)   # negative ones too
    return Clock(clock=wire.to_stamp(t)), cdr.encode_clock_raw(t)


FIXED = ['pose', 'pose_cov', 'complex', 'imu', 'odometry', 'clock']
CLOUDS = ['vectors', 'scalars', 'blocks']
CASES = ([(k, f, 3) for k in FIXED for f in FRAMES]
         + [(k, f, n) for k in CLOUDS for f in FRAMES for n in COUNTS])


def test_rclpy_serialization_needs_no_init():
    assert not rclpy.ok()
    msg = wire.encode_pose(T, 'world', R, P_)
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


@pytest.mark.parametrize('kind, frame, n', CASES)
def test_decoders_return_msg_defs_values(kind, frame, n):
    msg, _ = case(kind, frame, n)
    _, raw, decode = DECODERS[kind]
    data = serialize_message(msg)   # with rclpy's garbage padding
    assert _equal(raw(data), decode(msg))
    assert _equal(raw(bytearray(data)), decode(msg))
    assert _equal(raw(memoryview(data)), decode(msg))


@pytest.mark.parametrize('frame', FRAMES)
def test_header_pose_covariance_vector3(frame):
    msg, data = case('pose_cov', frame)
    h = cdr.read_header(data)
    assert (h.frame_id, h.ns, h.t) == (frame, wire.stamp_ns(msg.header.stamp),
                                       wire.from_stamp(msg.header.stamp))
    t, R2, p2, P2 = cdr.decode_pose_covariance_raw(data)
    pose = PoseStamped(header=msg.header, pose=msg.pose.pose)
    assert _equal((t, R2, p2), wire.decode_pose(pose))
    assert _equal((t, P2), wire.decode_covariance(msg))
    vec = Vector3Stamped()
    vec.header = msg.header
    vec.vector.x, vec.vector.y, vec.vector.z = map(float, RNG.normal(size=3))
    t, v = cdr.decode_vector3_raw(serialize_message(vec))
    assert t == wire.from_stamp(vec.header.stamp)
    assert v.tolist() == [vec.vector.x, vec.vector.y, vec.vector.z]
    assert cdr.encode_vector3_raw(t, frame, v) == reference(vec)[0]


def test_odometry_defaults_and_child_frame():
    msg = wire.encode_odometry(0.5, 'agent_1', [1.0, 0, 0], [0, 0, 0.25])
    data = cdr.encode_odometry_raw(0.5, 'agent_1', [1.0, 0, 0], [0, 0, 0.25])
    assert data == reference(msg)[0]
    assert _equal(cdr.decode_odometry_raw(data, 'agent_1/base_link'),
                  wire.decode_odometry(msg, 'agent_1/base_link'))
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


# ----------------------------------------------------------------------------- clouds
def _cloud(fields: list[tuple[str, int, int]], point_step: int, points: np.ndarray,
           height: int = 1, frame: str = 'agent_2/base_link') -> PointCloud2:
    """A PointCloud2 with the given (name, offset, datatype) fields, as a detector might
    build it."""
    msg = PointCloud2()
    msg.header.stamp, msg.header.frame_id = wire.to_stamp(T), frame
    msg.height, msg.width = height, len(points) // height
    msg.fields = [PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in fields]
    msg.point_step, msg.row_step = point_step, point_step * msg.width
    msg.is_dense = True
    msg.data = points.tobytes()
    return msg


def _points(dtype: np.dtype, n: int) -> np.ndarray:
    points = np.zeros(n, dtype=dtype)
    for name in dtype.names or ():
        points[name] = (RNG.integers(1, 99, size=n) if name == 'agent_id'
                        else RNG.normal(size=n))
    return points


F32, F64, U32 = PointField.FLOAT32, PointField.FLOAT64, PointField.UINT32


@pytest.mark.parametrize('n', COUNTS + [4])
@pytest.mark.parametrize('layout', ['float32', 'pcl_padded', 'reordered', 'two_rows'])
def test_foreign_clouds_decode_as_msg_defs(layout, n):
    """FLOAT32 (widened), padding, any field order, height > 1: as msg_defs decodes them."""
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
    msg = _cloud(fields, dtype.itemsize, _points(dtype, rows * n), height=rows)
    data = serialize_message(msg)
    assert_same_but_padding(*reference(msg)[:1], data, reference(msg)[1])
    t, ids, vectors = cdr.decode_vectors_raw(data)
    assert _equal((t, ids, vectors), wire.decode_vectors(msg))
    assert vectors.dtype == np.float64
    # The same bytes as scalar and block clouds of FLOAT32 fields.
    scal = _cloud([('agent_id', 0, U32), ('range', 4, F32)], 8,
                  _points(np.dtype([('agent_id', '<u4'), ('range', '<f4')]), n))
    assert _equal(cdr.decode_scalars_raw(serialize_message(scal)), wire.decode_scalars(scal))


def test_float32_blocks():
    dtype = np.dtype([(f, '<f4') for f in ('xx', 'yy', 'zz', 'xy', 'xz', 'yz')]
                     + [('agent_id', '<u4')])
    points = _points(dtype, 5)
    msg = _cloud([(f, 4 * k, F32) for k, f in enumerate(dtype.names[:6])]
                 + [('agent_id', 24, U32)], 28, points)
    assert _equal(_blocks(cdr.decode_blocks_raw(serialize_message(msg))),
                  wire.CHANNELS['angle_hessian'].decode(msg))


def test_decode_cloud_raw_is_a_view():
    data = cdr.encode_vectors_raw(T, 'w', [7, 8], [[1.0, 2, 3], [4, 5, 6]])
    t, points = cdr.decode_cloud_raw(data, {'x': F64, 'agent_id': U32})
    assert points['x'].tolist() == [1.0, 4.0] and points['agent_id'].tolist() == [7, 8]
    assert not points.flags.writeable


# ----------------------------------------------------------------------------- rejected
def _first(kind: str) -> bytes:
    return case(kind, 'abc', 5)[1]


ALL = FIXED + CLOUDS


@pytest.mark.parametrize('kind', ALL)
def test_every_truncation_is_rejected(kind):
    data, raw = _first(kind), DECODERS[kind][1]
    for k in range(len(data)):
        with pytest.raises(WireError, match='truncated|past the end|cannot fit'):
            raw(data[:k])


@pytest.mark.parametrize('kind', ALL)
def test_trailing_bytes(kind):
    """Up to 3 bytes after the message pass (a writer's padding to 4), more do not."""
    data, raw = _first(kind), DECODERS[kind][1]
    assert _equal(raw(data + b'\xff' * 3), raw(data))
    with pytest.raises(WireError, match='4 after the end of the message'):
        raw(data + bytes(4))


@pytest.mark.parametrize('kind', ALL)
@pytest.mark.parametrize('encapsulation, name', [
    (b'\x00\x00\x00\x00', 'big-endian CDR'), (b'\x00\x07\x00\x00', 'XCDR2'),
    (b'\x00\x03\x00\x00', 'PL_CDR'), (b'\x01\x01\x00\x00', 'unknown')])
def test_wrong_encapsulation(kind, encapsulation, name):
    data, raw = _first(kind), DECODERS[kind][1]
    with pytest.raises(WireError, match=rf'encapsulation {encapsulation.hex(" ")} \({name}\)'):
        raw(encapsulation + data[4:])
    assert _equal(raw(data[:2] + b'\x00\x02' + data[4:]), raw(data))   # options: ignored


@pytest.mark.parametrize('kind', FIXED[:-1] + CLOUDS)
@pytest.mark.parametrize('extra', [1, 0x10000, 0xffffffff])
def test_frame_id_past_the_end(kind, extra):
    """A frame_id length ``extra`` bytes past the end (or the largest uint32)."""
    data, raw = _first(kind), DECODERS[kind][1]
    length = min(len(data) - 16 + extra, 0xffffffff)
    bad = data[:12] + struct.pack('<I', length) + data[16:]
    with pytest.raises(WireError, match='header.frame_id of length .* runs past the end'):
        raw(bad)


@pytest.mark.parametrize('kind', FIXED[:-1] + CLOUDS)
def test_frame_id_not_a_string(kind):
    data, raw = _first(kind), DECODERS[kind][1]
    end = 16 + struct.unpack_from('<I', data, 12)[0]   # after frame_id's NUL
    assert data[16:19] == b'abc' and data[end - 1] == 0
    for at, byte, match in [(end - 1, b'd', 'not one NUL-terminated string'),
                            (17, b'\0', 'not one NUL-terminated string'),
                            (17, b'\xff', 'not UTF-8')]:
        with pytest.raises(WireError, match=match):
            raw(data[:at] + byte + data[at + 1:])
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
    """0 points x any point_step is 0 bytes; numpy cannot make an item of 2^31 bytes, and
    msg_defs.decode_vectors raises a bare ValueError there (not a WireError)."""
    data = cdr.encode_vectors_raw(T, 'abc', [], np.zeros((0, 3)))
    at = _at(data, 0, 28)['point_step']
    assert struct.unpack_from('<I', data, at)[0] == 28
    bad = data[:at] + struct.pack('<I', 2 ** 31 + 5) + data[at + 4:]
    with pytest.raises(WireError, match='point_step 2147483653 .* too large'):
        cdr.decode_vectors_raw(bad)
    ok = data[:at] + struct.pack('<I', 2 ** 20) + data[at + 4:]
    assert cdr.decode_vectors_raw(ok)[2].shape == (0, 3)


def test_many_cloud_layouts():
    """More layouts than the decoder keeps parsed: each still decodes as msg_defs does."""
    for k in range(2 * cdr._SEEN_MAX):
        dtype = np.dtype([('agent_id', '<u4'), ('p' * (k + 1), '<u4'), ('x', '<f8'),
                          ('y', '<f8'), ('z', '<f4')])
        names = ['agent_id', 'p' * (k + 1), 'x', 'y', 'z']
        dt = [U32, U32, F64, F64, F32]
        fields = [(n, dtype.fields[n][1], d) for n, d in zip(names, dt)]
        msg = _cloud(fields, dtype.itemsize, _points(dtype, k % 4))
        assert _equal(cdr.decode_vectors_raw(serialize_message(msg)), wire.decode_vectors(msg))
    assert len(cdr._SEEN_FIELDS) <= cdr._SEEN_MAX >= len(cdr._SEEN_DTYPES)


def test_field_name_past_the_end():
    data = cdr.encode_vectors_raw(T, 'abc', np.arange(5), np.ones((5, 3)))
    at = data.index(b'\x09\x00\x00\x00agent_id')
    with pytest.raises(WireError, match='a field name of length .* runs past the end'):
        cdr.decode_vectors_raw(data[:at] + struct.pack('<I', 0xffff) + data[at + 4:])


def _vectors_cloud(**change: Any) -> PointCloud2:
    """msg_defs' 5-point vector cloud with some of its fields' or layout's values changed."""
    msg = wire.encode_vectors(T, 'abc', np.arange(5), RNG.normal(size=(5, 3)))
    # Copies: msg_defs' encoder shares its PointField objects between messages.
    msg.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                  for f in msg.fields]
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
    ({'agent_id.name': 'id'}, "needs field 'agent_id'"),
    ({'agent_id.datatype': PointField.INT32}, "needs field 'agent_id' of datatype 6"),
    ({'x.datatype': PointField.UINT32}, "needs field 'x' of datatype 8 or 7"),
    ({'x.count': 2}, "needs field 'x'"),
    ({'is_bigendian': True}, 'big-endian PointCloud2'),
])
def test_cloud_layouts_rejected_as_msg_defs(change, match):
    msg = _vectors_cloud(**change)
    with pytest.raises(WireError, match=match):
        cdr.decode_vectors_raw(serialize_message(msg))
    with pytest.raises(WireError):
        wire.decode_vectors(msg)


def _nan(*idx: int) -> np.ndarray:
    v = np.ones(3)
    v[list(idx)] = np.nan
    return v


def _pose_msg(q: list[float] | None = None, p: list[float] | None = None) -> PoseStamped:
    msg = wire.encode_pose(T, 'world', R, P_)
    if q is not None:
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = q
    if p is not None:
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = p
    return msg


def _cov_msg(P: np.ndarray) -> PoseWithCovarianceStamped:
    return wire.encode_pose_covariance(T, 'world', R, P_, P)


_ASYM = COV.copy()
_ASYM[0, 1] += 1.0
_NEG = np.diag([1.0, 1, 1, 1, 1, -1])
_NANCOV = COV.copy()
_NANCOV[2, 2] = np.inf
_TWIST = wire.encode_odometry(T, 'a', np.array([0, np.inf, 0]), np.zeros(3))


@pytest.mark.parametrize('kind, msg', [
    ('imu', wire.encode_imu(T, 'a', _nan(1))),
    ('imu', wire.encode_imu(T, 'a', np.array([0, 0, -np.inf]))),
    ('odometry', _TWIST),
    ('odometry', wire.encode_odometry(T, 'a', np.zeros(3), _nan(0))),
    ('pose', _pose_msg(p=[0, np.nan, 0])),
    ('pose', _pose_msg(q=[0, 0, np.inf, 1])),
    ('pose', _pose_msg(q=[0, 0, 0, 1.01])),
    ('pose', _pose_msg(q=[0, 0, 0, 0])),
    ('pose_cov', _cov_msg(_NANCOV)),
    ('pose_cov', _cov_msg(_ASYM)),
    ('pose_cov', _cov_msg(_NEG)),
    ('complex', wire.CHANNELS['z_hat'].encode(T, [np.nan, 0], 'f')),   # type: ignore[misc]
])
def test_values_rejected_as_msg_defs(kind, msg):
    """The same values rejected with the same message as msg_defs' decoder of the message."""
    _, raw, decode = DECODERS[kind]
    with pytest.raises(WireError) as theirs:
        decode(msg)
    with pytest.raises(WireError) as ours:
        raw(serialize_message(msg))
    assert str(ours.value) == str(theirs.value)


def test_pose_covariance_raw_checks_the_pose_too():
    msg = _cov_msg(COV)
    msg.pose.pose.orientation.w = 2.0
    with pytest.raises(WireError, match='quaternion norm'):
        cdr.decode_pose_covariance_raw(serialize_message(msg))
    cdr.decode_covariance_raw(serialize_message(msg))   # as decode_covariance: pose unread
    vec = Vector3Stamped()
    vec.vector.z = np.nan
    with pytest.raises(WireError, match='non-finite vector'):
        cdr.decode_vector3_raw(serialize_message(vec))
    assert cdr.decode_complex_raw(serialize_message(vec))[1].tolist() == [0.0, 0.0]  # z unread


@pytest.mark.filterwarnings('ignore:overflow encountered:RuntimeWarning')  # huge quaternions
@pytest.mark.parametrize('kind', ALL)
def test_mutated_bytes_are_rejected_or_read_as_rclpy_reads_them(kind):
    """Random byte changes: a WireError, or the values msg_defs decodes from what rclpy
    deserialises of the same bytes; never another exception."""
    msg_type, raw, decode = DECODERS[kind]
    data = _first(kind)
    rng = np.random.default_rng(len(kind))
    accepted = 0
    for _ in range(1000):
        bad = bytearray(data)
        for at in rng.integers(0, len(data), size=rng.integers(1, 4)):
            bad[at] = rng.integers(0, 256) if rng.random() < 0.7 else bad[at] ^ 1
        try:
            ours = raw(bytes(bad))
        except WireError:
            continue
        accepted += 1
        theirs = deserialize_message(bytes(bad), msg_type)
        assert _equal(ours, decode(theirs)), bytes(bad).hex(' ')
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
def _channel_value(name: str) -> Any:
    """A value of each channel that has an encoder, as the estimator node gives it."""
    ids = [2, 5, 7]
    if name == 'z_hat':
        return np.array([0.6, -0.8])
    if name == 'relyaw':
        return {i: RNG.normal(size=2) for i in ids}
    if name == 'angle_hessian':
        return {i: RNG.normal(size=6) for i in ids}
    if name == 'term_cov':
        blocks = [_A[:3, :3] @ _A[:3, :3].T * k for k in range(1, 5)]
        packed = np.concatenate([[b[0, 0], b[1, 1], b[2, 2], b[0, 1], b[0, 2], b[1, 2]]
                                 for b in blocks])
        return {i: np.concatenate([packed, RNG.normal(size=3)]) for i in ids}
    return {i: RNG.normal(size=3) for i in ids}


def _same(a: Any, b: Any) -> None:
    if isinstance(a, dict):
        assert list(a) == list(b)
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    else:
        np.testing.assert_array_equal(a, b)


def test_every_channel_has_raw_codecs():
    assert list(cdr.RAW_CHANNELS) == list(wire.CHANNELS)
    for name, w in wire.CHANNELS.items():
        assert (cdr.RAW_CHANNELS[name][1] is None) == (w.encode is None), name


@pytest.mark.parametrize('name', [n for n, w in wire.CHANNELS.items() if w.encode is not None])
def test_raw_channels_are_the_typed_ones(name):
    """Typed encode → bytes → raw decode, and raw encode → rclpy's message → typed decode,
    give the typed path's values."""
    w = wire.CHANNELS[name]
    decode_raw, encode_raw = cdr.RAW_CHANNELS[name]
    assert encode_raw is not None
    value = _channel_value(name)
    msg = w.encode(T, value, 'agent_1/base_link')
    want = w.decode(msg)
    got = decode_raw(serialize_message(msg))
    assert got[0] == want[0]
    _same(got[1], want[1])
    again = w.decode(deserialize_message(encode_raw(T, value, 'agent_1/base_link'), w.type))
    assert again[0] == want[0]
    _same(again[1], want[1])


@pytest.mark.parametrize('name', [n for n, w in wire.CHANNELS.items() if w.encode is None])
def test_raw_channels_riding_on_other_messages(name):
    w = wire.CHANNELS[name]
    msg = (wire.encode_pose(T, 'world', R, P_) if w.type is PoseStamped
           else wire.encode_pose_covariance(T, 'world', R, P_, COV)
           if w.type is PoseWithCovarianceStamped
           else wire.encode_vectors(T, 'agent_1/base_link', [3, 4], RNG.normal(size=(2, 3))))
    want, got = w.decode(msg), cdr.RAW_CHANNELS[name][0](serialize_message(msg))
    assert got[0] == want[0]
    _same(got[1], want[1])


def test_a_raw_term_covariance_that_is_no_covariance_is_rejected():
    value = _channel_value('term_cov')
    value[2][0] = -1.0    # a negative variance
    with pytest.raises(WireError, match='not positive semi-definite'):
        cdr.RAW_CHANNELS['term_cov'][0](cdr.RAW_CHANNELS['term_cov'][1](T, value, 'f'))
