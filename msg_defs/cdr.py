"""The codecs of the package's messages: values to a message's serialised bytes and back, with
numpy on the CDR layout (issue 15: no rclpy message object is built, BENCHMARKS.md "Raw CDR"); a
decoder also takes an rclpy message object. The bytes are ``serialize_message``'s (layout:
msg_defs/README.md). Each decoder raises :class:`WireError`, never another error, on values it
rejects and on malformed bytes (``test/test_cdr.py`` checks every codec against rclpy's)."""
from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from functools import lru_cache
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from sensor_msgs.msg import PointField

from bearing_pose_estimation.core import so3

from . import WireError, body_frame, checked_covariance, odom_frame, raw

Array = NDArray[np.float64]
# What a decoder takes: a message's serialised bytes, or its rclpy message object.
Data = bytes | bytearray | memoryview | Any

ENCAPSULATION = b'\x00\x01\x00\x00'   # CDR_LE (plain CDR, little endian), options 0
# What else the first two bytes may say (RTPS 2.3, 10.5): named in the error.
_REPRESENTATIONS = {b'\x00\x00': 'big-endian CDR', b'\x00\x02': 'big-endian PL_CDR',
                    b'\x00\x03': 'PL_CDR', b'\x00\x06': 'big-endian XCDR2', b'\x00\x07': 'XCDR2',
                    b'\x00\x08': 'big-endian delimited XCDR2', b'\x00\x09': 'delimited XCDR2',
                    b'\x00\x0a': 'big-endian PL_XCDR2', b'\x00\x0b': 'PL_XCDR2'}
_TRAILING = 3   # bytes a writer may pad after the message (RTPS: to a multiple of 4)

_HEAD = struct.Struct('<4siII')     # encapsulation, stamp.sec, stamp.nanosec, frame_id length
_U32 = struct.Struct('<I')
_ONE_ROW = struct.Struct('<II')             # height, width
_POINT_FIELD = struct.Struct('<IB3xI')      # PointField after its name: offset, datatype, count
_CLOUD_TAIL = struct.Struct('<B3xIII')      # is_bigendian, point_step, row_step, data length
_CLOCK = struct.Struct('<4siI')             # encapsulation, clock.sec, clock.nanosec
_POSE = struct.Struct('<7d')                # position x y z, orientation x y z w
_VECTOR3 = struct.Struct('<3d')
_F64 = np.dtype('<f8')

# PointField datatype <-> numpy (little endian).
_FORMATS: dict[int, np.dtype] = {
    PointField.INT8: np.dtype('i1'), PointField.UINT8: np.dtype('u1'),
    PointField.INT16: np.dtype('<i2'), PointField.UINT16: np.dtype('<u2'),
    PointField.INT32: np.dtype('<i4'), PointField.UINT32: np.dtype('<u4'),
    PointField.FLOAT32: np.dtype('<f4'), PointField.FLOAT64: np.dtype('<f8')}
_DATATYPES = {dtype: datatype for datatype, dtype in _FORMATS.items()}
# What a decoder accepts for a field it wants: FLOAT32 for FLOAT64, widened (most detectors
# and PCL publish FLOAT32 points; a unit bearing in float32 is unit to 1e-7).
_ACCEPTED = {PointField.FLOAT64: (PointField.FLOAT64, PointField.FLOAT32)}
_XYZ = ('x', 'y', 'z')


# ----------------------------------------------------------------------------- reading
class RawHeader(NamedTuple):
    """A message's ``std_msgs/Header``."""

    sec: int
    nanosec: int
    frame_id: str

    @property
    def t(self) -> float:
        """The stamp [s], as ``msg_defs.from_stamp``."""
        return self.sec + self.nanosec * 1e-9

    @property
    def ns(self) -> int:
        """The stamp in exact integer nanoseconds, as ``msg_defs.stamp_ns``."""
        return self.sec * 1_000_000_000 + self.nanosec


def _as_bytes(data: Data) -> bytes:
    return data if isinstance(data, bytes) else raw(data)


def _check_encapsulation(data: bytes, what: str) -> None:
    if len(data) < 4:
        raise _truncated(data, 4, what, 'the encapsulation header')
    head = data[:2]
    if head != ENCAPSULATION[:2]:
        name = _REPRESENTATIONS.get(head, 'unknown')
        raise WireError(f'{what}: encapsulation {data[:4].hex(" ")} ({name}) is not plain '
                        f'little-endian CDR (00 01 00 00)')


def _truncated(data: bytes, end: int, what: str, part: str) -> WireError:
    return WireError(f'{what}: {len(data)} bytes, truncated: {part} needs {end}')


def _finish(data: bytes, end: int, what: str) -> None:
    """The message ends at ``end``: the buffer must hold it, and at most the padding after."""
    extra = len(data) - end
    if extra < 0:
        raise _truncated(data, end, what, 'the message')
    if extra > _TRAILING:
        raise WireError(f'{what}: {len(data)} bytes, {extra} after the end of the message at '
                        f'{end} (another type?)')


def _string(data: bytes, pos: int, what: str, name: str) -> tuple[str, int]:
    """The string whose length is at ``pos`` (4-aligned) and the position after its NUL."""
    if pos + 4 > len(data):
        raise _truncated(data, pos + 4, what, f'the length of {name}')
    length = _U32.unpack_from(data, pos)[0]
    start, end = pos + 4, pos + 4 + length
    if end > len(data):
        raise WireError(f'{what}: {name} of length {length} at byte {start} runs past the end '
                        f'of the {len(data)}-byte buffer')
    if length == 0:   # no NUL at all: an empty string to rmw_fastrtps too
        return '', end
    if data[end - 1] != 0 or data.find(0, start, end - 1) >= 0:
        raise WireError(f'{what}: {name} of length {length} is not one NUL-terminated string')
    try:
        return data[start:end - 1].decode(), end
    except UnicodeDecodeError as exc:
        raise WireError(f'{what}: {name} is not UTF-8 ({exc})') from None


def _align(pos: int, size: int) -> int:
    """``pos`` (a buffer index) rounded up to a multiple of ``size`` after the encapsulation."""
    return pos + (-(pos - 4) % size)


def _header(data: bytes, what: str) -> tuple[int, int, str, int]:
    """``(sec, nanosec, frame_id, position after frame_id)`` of a message opening with a Header."""
    _check_encapsulation(data, what)
    if len(data) < 16:
        raise _truncated(data, 16, what, 'the header')
    _, sec, nanosec, _ = _HEAD.unpack_from(data)
    frame_id, pos = _string(data, 12, what, 'header.frame_id')
    return sec, nanosec, frame_id, pos


def read_header(data: Data) -> RawHeader:
    """The Header of any stamped message's bytes (e.g. to check the frame before decoding).
    WireError: a wrong encapsulation, or a header that does not fit the buffer."""
    sec, nanosec, frame_id, _ = _header(_as_bytes(data), 'message')
    return RawHeader(sec, nanosec, frame_id)


def _fixed(data: Data, what: str, count: int) -> tuple[bytes, float, int]:
    """The bytes, the stamp and the position of the ``count`` float64 that follow the Header
    (8-aligned) and end the message: every message here whose only string is ``frame_id``."""
    data = _as_bytes(data)
    sec, nanosec, _, pos = _header(data, what)
    pos = _align(pos, 8)
    _finish(data, pos + 8 * count, what)
    return data, sec + nanosec * 1e-9, pos


def _vector3(data: bytes, pos: int, what: str) -> Array:
    values = _VECTOR3.unpack_from(data, pos)
    if not all(map(math.isfinite, values)):
        raise WireError(f'non-finite {what}')
    return np.array(values)


# ----------------------------------------------------------------------------- writing
def _stamp(t: float) -> tuple[int, int]:
    """Seconds -> (sec, nanosec), rounded to the nanosecond as ``msg_defs.to_stamp``."""
    sec, nanosec = divmod(int(round(t * 1e9)), 1_000_000_000)
    if not -2 ** 31 <= sec < 2 ** 31:
        raise WireError(f'stamp {t} s does not fit builtin_interfaces/Time (int32 seconds)')
    return sec, nanosec


def _string_bytes(text: str, name: str) -> bytes:
    """A CDR string: uint32 length with the NUL, UTF-8 bytes, NUL (unpadded)."""
    raw = text.encode()
    if b'\0' in raw:
        raise WireError(f'{name} {text!r} contains a NUL')
    return _U32.pack(len(raw) + 1) + raw + b'\0'


def _padded(head: bytes, align: int) -> bytes:
    """``head`` (encapsulation included) and zeros up to the next multiple of ``align``."""
    return head + bytes(-(len(head) - 4) % align)


def _header_bytes(t: float, frame_id: str, align: int) -> bytes:
    """Encapsulation, Header, then zeros up to the next multiple of ``align``."""
    return _padded(_CLOCK.pack(ENCAPSULATION, *_stamp(t)) + _string_bytes(frame_id, 'frame_id'),
                   align)


def _with_doubles(t: float, frame_id: str, values: NDArray[np.float64]) -> bytes:
    return _header_bytes(t, frame_id, 8) + values.astype(_F64, copy=False).tobytes()


# ----------------------------------------------------------------------------- PoseStamped
def _pose_values(R: Array, p: Array) -> Array:
    """Pose: position x, y, z, then orientation x, y, z, w (float64)."""
    out = np.empty(7)
    out[:3] = np.asarray(p, dtype=float).reshape(3)
    out[3:] = so3.to_quat(np.asarray(R, dtype=float))
    return out


def _pose(data: bytes, pos: int) -> tuple[Array, Array]:
    """``(R, p)`` of the Pose at ``pos``: finite, the quaternion of norm 1 to 1e-3 (normalised)."""
    values = _POSE.unpack_from(data, pos)
    if not all(map(math.isfinite, values)):
        raise WireError('non-finite pose')
    q = values[3:]
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not math.isclose(norm, 1.0, abs_tol=1e-3):
        raise WireError(f'quaternion norm {norm:.6g} is not 1')
    return so3.from_quat(np.array(q)), np.array(values[:3])


def encode_pose_raw(t: float, frame_id: str, R: Array, p: Array) -> bytes:
    """geometry_msgs/PoseStamped of the attitude ``R`` (body → ``frame_id``) and position
    ``p``: Header, 8-aligned, then 7 float64 (position, quaternion x, y, z, w)."""
    return _with_doubles(t, frame_id, _pose_values(R, p))


def decode_pose_raw(data: Data) -> tuple[float, Array, Array]:
    """``(t, R, p)`` of a PoseStamped. WireError: malformed, non-finite, not a unit quaternion."""
    data, t, pos = _fixed(data, 'PoseStamped', 7)
    return (t, *_pose(data, pos))


# ----------------------------------------------------------------------------- covariance
def encode_pose_covariance_raw(t: float, frame_id: str, R: Array, p: Array,
                               P: Array) -> bytes:
    """geometry_msgs/PoseWithCovarianceStamped: the pose as :func:`encode_pose_raw`, then its
    6x6 covariance ``P`` (position [m], then rotation about the frame's axes [rad]), 36 float64."""
    values = np.concatenate([_pose_values(R, p), np.asarray(P, dtype=float).reshape(36)])
    return _with_doubles(t, frame_id, values)


def _covariance(data: bytes, pos: int) -> Array:
    return checked_covariance(np.frombuffer(data, dtype=_F64, count=36, offset=pos + 56).copy())


def decode_covariance_raw(data: Data) -> tuple[float, Array]:
    """``(t, P)`` of a PoseWithCovarianceStamped (the pose not read). WireError: malformed
    bytes, or not a finite, symmetric, positive semi-definite covariance."""
    data, t, pos = _fixed(data, 'PoseWithCovarianceStamped', 43)
    return t, _covariance(data, pos)


def decode_pose_covariance_raw(data: Data) -> tuple[float, Array, Array, Array]:
    """``(t, R, p, P)`` of a PoseWithCovarianceStamped, checked as the two decoders above."""
    data, t, pos = _fixed(data, 'PoseWithCovarianceStamped', 43)
    R, p = _pose(data, pos)
    return t, R, p, _covariance(data, pos)


# ----------------------------------------------------------------------------- Vector3Stamped
def encode_vector3_raw(t: float, frame_id: str, v: Array) -> bytes:
    """geometry_msgs/Vector3Stamped: Header, 8-aligned, then x, y, z float64."""
    return _with_doubles(t, frame_id, np.asarray(v, dtype=float).reshape(3))


def decode_vector3_raw(data: Data) -> tuple[float, Array]:
    """``(t, v)`` of a Vector3Stamped. WireError: malformed bytes or a non-finite vector."""
    data, t, pos = _fixed(data, 'Vector3Stamped', 3)
    return t, _vector3(data, pos, 'vector')


# ----------------------------------------------------------------------------- Imu
# sensor_msgs/Imu after its Header (8-aligned), 37 float64: orientation x y z w [0:4],
# orientation_covariance [4:13], angular_velocity [13:16], its covariance [16:25],
# linear_acceleration [25:28], its covariance [28:37].
_IMU = np.zeros(37)
_IMU[[3, 4, 28]] = 1.0, -1.0, -1.0   # w = 1 (the default); no orientation, no acceleration


def encode_imu_raw(t: float, agent: str, omega: Array) -> bytes:
    """sensor_msgs/Imu gyro sample, frame ``<agent>/base_link``: ``angular_velocity`` the body
    rate averaged over the interval ending at ``t`` (``sim.world``); no orientation, no
    acceleration (their covariances' first elements -1, as sensor_msgs/Imu specifies)."""
    values = _IMU.copy()
    values[13:16] = np.asarray(omega, dtype=float).reshape(3)
    return _with_doubles(t, body_frame(agent), values)


def decode_imu_raw(data: Data) -> tuple[float, Array]:
    """``(t, omega)`` of an Imu (its ``angular_velocity``). WireError: malformed or non-finite."""
    data, t, pos = _fixed(data, 'Imu', 37)
    return t, _vector3(data, pos + 8 * 13, 'angular velocity')


# ----------------------------------------------------------------------------- Odometry
# nav_msgs/Odometry after its Header: child_frame_id (4-aligned), then (8-aligned) 85 float64:
# pose.pose [0:7], pose.covariance [7:43], twist.twist linear [43:46], angular [46:49],
# twist.covariance [49:85].
_ODOMETRY = np.zeros(85)
_ODOMETRY[6] = 1.0   # orientation w


def encode_odometry_raw(t: float, agent: str, v: Array, omega: Array,
                        R_odom: Array | None = None, p_odom: Array | None = None,
                        v_std: float = 0.0, omega_std: float = 0.0) -> bytes:
    """nav_msgs/Odometry sample: the body twist ``v`` [m/s], ``omega`` [rad/s] in
    ``<agent>/base_link`` (REP-105), an interval average like the gyro's (:mod:`core.odometry`),
    with the diagonal ``twist.covariance`` of ``v_std``, ``omega_std``; the dead-reckoned pose
    (for RViz; default identity, zero) in ``<agent>/odom``, its covariance zero."""
    values = _ODOMETRY.copy()
    if p_odom is not None:
        values[0:3] = np.asarray(p_odom, dtype=float).reshape(3)
    if R_odom is not None:
        values[3:7] = so3.to_quat(np.asarray(R_odom, dtype=float))
    values[43:46] = np.asarray(v, dtype=float).reshape(3)
    values[46:49] = np.asarray(omega, dtype=float).reshape(3)
    values[[49, 56, 63]] = v_std ** 2
    values[[70, 77, 84]] = omega_std ** 2
    return _padded(_header_bytes(t, odom_frame(agent), 4)
                   + _string_bytes(body_frame(agent), 'child_frame_id'), 8) + values.tobytes()


def decode_odometry_raw(data: Data,
                        child_frame: str | None = None) -> tuple[float, Array, Array]:
    """``(t, v, omega)`` of an Odometry (the pose not read). WireError: malformed bytes, a
    non-finite twist, or one in another ``child_frame_id`` than ``child_frame`` (if given)."""
    data = _as_bytes(data)
    sec, nanosec, _, pos = _header(data, 'Odometry')
    child, pos = _string(data, _align(pos, 4), 'Odometry', 'child_frame_id')
    pos = _align(pos, 8)
    _finish(data, pos + 8 * 85, 'Odometry')
    if child_frame is not None and child != child_frame:
        raise WireError(f'Odometry twist is in child_frame_id {child!r}, expected {child_frame!r}')
    return (sec + nanosec * 1e-9, _vector3(data, pos + 8 * 43, 'twist'),
            _vector3(data, pos + 8 * 46, 'twist'))


# ----------------------------------------------------------------------------- Clock
def encode_clock_raw(t: float) -> bytes:
    """rosgraph_msgs/Clock: ``clock.sec`` int32, ``clock.nanosec`` uint32."""
    return _CLOCK.pack(ENCAPSULATION, *_stamp(t))


def decode_clock_raw(data: Data) -> float:
    """The time [s] of a Clock. WireError: malformed bytes."""
    data = _as_bytes(data)
    _check_encapsulation(data, 'Clock')
    _finish(data, _CLOCK.size, 'Clock')
    _, sec, nanosec = _CLOCK.unpack_from(data)
    return sec + nanosec * 1e-9


# ----------------------------------------------------------------------------- PointCloud2
# sensor_msgs/PointCloud2 after its Header (4-aligned): height, width uint32; fields: uint32
# count, then per PointField its name (string), 4-aligned offset uint32, datatype uint8, 3
# bytes, count uint32; is_bigendian uint8, 3 bytes, point_step, row_step uint32; data: uint32
# length, the bytes; is_dense uint8. Everything after frame_id is 4-aligned (the data and
# is_dense are bytes), so the fields' bytes do not depend on the frame_id.
_SEEN_MAX = 32   # entries per cache of layouts; beyond, each new one is built anew


@lru_cache(maxsize=_SEEN_MAX)
def _fields_bytes(dtype: np.dtype) -> bytes:
    """The count and PointFields of points of the structured ``dtype`` (count 1 each)."""
    assert dtype.names is not None and dtype.fields is not None
    out = [_U32.pack(len(dtype.names))]
    for name in dtype.names:
        field, offset = dtype.fields[name][:2]
        datatype = _DATATYPES.get(field)
        if datatype is None:
            raise WireError(f'point field {name!r} of dtype {field} has no little-endian '
                            f'PointField datatype')
        text = _string_bytes(name, 'point field name')
        out.append(text + bytes(-len(text) % 4) + _POINT_FIELD.pack(offset, datatype, 1))
    return b''.join(out)


def encode_cloud_raw(t: float, frame_id: str, points: np.ndarray) -> bytes:
    """A little-endian, dense, one-row PointCloud2 of the structured array ``points``, one
    PointField per field of its dtype."""
    if points.dtype.names is None:
        raise WireError(f'points must be a structured array, not {points.dtype}')
    n, step = len(points), points.dtype.itemsize
    return b''.join([_header_bytes(t, frame_id, 4), _ONE_ROW.pack(1, n),
                     _fields_bytes(points.dtype), _CLOUD_TAIL.pack(0, step, step * n, step * n),
                     np.ascontiguousarray(points).tobytes(), b'\x01'])


@lru_cache(maxsize=_SEEN_MAX)
def _tagged(fields: tuple[str, ...]) -> dict[str, int]:
    """The PointFields of values tagged with agent ids: ``fields`` FLOAT64, agent_id UINT32."""
    return {**dict.fromkeys(fields, PointField.FLOAT64), 'agent_id': PointField.UINT32}


@lru_cache(maxsize=_SEEN_MAX)
def _tagged_dtype(fields: tuple[str, ...]) -> np.dtype:
    return np.dtype([(name, _FORMATS[datatype]) for name, datatype in _tagged(fields).items()])


# The PointFields and points' dtypes of the clouds seen, keyed by their bytes: a publisher sends
# the same fields every time, so they are parsed once. A tuple, replaced whole (thread-safe).
_SEEN_FIELDS: tuple[tuple[bytes, dict[str, tuple[int, int, int]]], ...] = ()
_SEEN_DTYPES: dict[tuple[bytes, int, tuple[tuple[str, int], ...]], np.dtype] = {}


def _point_fields(data: bytes, pos: int) -> tuple[bytes, dict[str, tuple[int, int, int]], int]:
    """The PointField sequence at ``pos`` (4-aligned): its bytes, ``{name: (offset,
    datatype, count)}`` (a repeated name: the last) and the position after it."""
    global _SEEN_FIELDS
    for block, fields in _SEEN_FIELDS:
        if data.startswith(block, pos):   # the same bytes parse the same
            return block, fields, pos + len(block)
    what, start = 'PointCloud2', pos
    if pos + 4 > len(data):
        raise _truncated(data, pos + 4, what, 'the number of fields')
    count = _U32.unpack_from(data, pos)[0]
    pos += 4
    if 16 * count > len(data) - pos:   # a PointField takes at least 16 bytes
        raise WireError(f'{what}: {count} fields cannot fit in the {len(data)}-byte buffer')
    fields = {}
    for _ in range(count):
        name, pos = _string(data, pos, what, 'a field name')
        pos = _align(pos, 4)
        if pos + _POINT_FIELD.size > len(data):
            raise _truncated(data, pos + _POINT_FIELD.size, what, f'field {name!r}')
        fields[name] = _POINT_FIELD.unpack_from(data, pos)
        pos += _POINT_FIELD.size
    block = data[start:pos]
    if len(_SEEN_FIELDS) < _SEEN_MAX:
        _SEEN_FIELDS += ((block, fields),)
    return block, fields, pos


def _point_dtype(fields: Mapping[str, tuple[int, int, int]], want: Mapping[str, int],
                 point_step: int) -> np.dtype:
    """The numpy view of the wanted fields, each present, of an accepted datatype, count 1,
    within the ``point_step`` bytes and overlapping no other."""
    for name, datatype in want.items():
        accepted = _ACCEPTED.get(datatype, (datatype,))
        if name not in fields or fields[name][1] not in accepted or fields[name][2] != 1:
            raise WireError(f'PointCloud2 needs field {name!r} of datatype '
                            f'{" or ".join(map(str, accepted))} (fields: {sorted(fields)})')
    offsets = [fields[name][0] for name in want]
    formats = [_FORMATS[fields[name][1]] for name in want]
    sizes = [f.itemsize for f in formats]
    if not sum(sizes) <= point_step < 2 ** 31:   # numpy's itemsize is a C int
        raise WireError(f'PointCloud2 point_step {point_step} does not hold its fields '
                        f'({sum(sizes)} bytes) or is too large')
    spans = sorted(zip(offsets, sizes, want))
    ends = [offset for offset, _, _ in spans[1:]] + [point_step]
    for (offset, size, name), end in zip(spans, ends):
        if offset + size > end:
            raise WireError(f'PointCloud2 field {name!r} (offset {offset}, {size} bytes) '
                            f'overlaps the next field or the end of the {point_step}-byte '
                            f'point')
    return np.dtype({'names': list(want), 'formats': formats, 'offsets': offsets,
                     'itemsize': point_step})


def decode_cloud_raw(data: Data, want: Mapping[str, int]) -> tuple[float, np.ndarray]:
    """The stamp and the points of a PointCloud2, a read-only structured view of the fields
    ``want`` (``{name: PointField datatype}``) in any order and padding (a detector, PCL;
    FLOAT64 may come as FLOAT32). WireError: malformed bytes, bad fields, a data length other
    than width x height x point_step, or big-endian data."""
    what = 'PointCloud2'
    data = _as_bytes(data)
    sec, nanosec, _, pos = _header(data, what)
    pos = _align(pos, 4)
    if pos + 8 > len(data):
        raise _truncated(data, pos + 8, what, 'height and width')
    height, width = _ONE_ROW.unpack_from(data, pos)
    block, fields, pos = _point_fields(data, pos + 8)
    if pos + _CLOUD_TAIL.size > len(data):
        raise _truncated(data, pos + _CLOUD_TAIL.size, what, 'point_step and the data length')
    bigendian, point_step, _, size = _CLOUD_TAIL.unpack_from(data, pos)
    start = pos + _CLOUD_TAIL.size
    if start + size + 1 > len(data):
        raise WireError(f'{what}: data of {size} bytes at byte {start} runs past the end of '
                        f'the {len(data)}-byte buffer')
    dense = data[start + size]
    _finish(data, start + size + 1, what)
    if bigendian > 1 or dense > 1:
        raise WireError(f'{what}: is_bigendian {bigendian}, is_dense {dense}: a bool is 0 or 1')
    key = (block, point_step, tuple(want.items()))
    dtype = _SEEN_DTYPES.get(key)
    if dtype is None:
        dtype = _point_dtype(fields, want, point_step)
        if len(_SEEN_DTYPES) < _SEEN_MAX:
            _SEEN_DTYPES[key] = dtype
    if bigendian:
        raise WireError('big-endian PointCloud2 is not supported')
    n = width * height
    if size != n * point_step:
        raise WireError(f'PointCloud2 data is {size} bytes, expected {n} points x '
                        f'{point_step} bytes')
    return sec + nanosec * 1e-9, np.frombuffer(data, dtype=dtype, count=n, offset=start)


def encode_points_raw(t: float, frame_id: str, ids: NDArray[np.integer], values: Array,
                      fields: tuple[str, ...]) -> bytes:
    """One point per agent id: ``values`` ``(n, len(fields))`` as FLOAT64 ``fields``, then
    agent_id UINT32, packed (a channel's per-listener values, msg_defs.encode_channels)."""
    values = np.asarray(values, dtype=float).reshape(-1, len(fields))
    points = np.empty(len(values), dtype=_tagged_dtype(fields))
    for k, f in enumerate(fields):
        points[f] = values[:, k]
    points['agent_id'] = np.asarray(ids, dtype=np.uint32)
    return encode_cloud_raw(t, frame_id, points)


def decode_points_raw(data: Data, fields: tuple[str, ...]
                      ) -> tuple[float, NDArray[np.uint32], Array]:
    """``(t, ids, values)`` of :func:`encode_points_raw`'s cloud, ``values`` ``(n, len(fields))``,
    unchecked: each listener checks its own point (one's bad point costs the others nothing).
    WireError: as :func:`decode_cloud_raw`."""
    t, points = decode_cloud_raw(data, _tagged(fields))
    values = np.empty((len(points), len(fields)))
    for k, name in enumerate(fields):
        values[:, k] = points[name]
    return t, points['agent_id'].astype(np.uint32), values


def encode_vectors_raw(t: float, frame_id: str, ids: NDArray[np.integer],
                       vectors: Array) -> bytes:
    """Vectors tagged with agent ids (unit bearings, relative positions [m], bearing rates
    [1/s]) as a PointCloud2: x, y, z FLOAT64, agent_id UINT32, point_step 28."""
    return encode_points_raw(t, frame_id, ids, vectors, _XYZ)


def decode_vectors_raw(data: Data) -> tuple[float, NDArray[np.uint32], Array]:
    """``(t, ids, vectors)`` of :func:`encode_vectors_raw`'s cloud."""
    return decode_points_raw(data, _XYZ)


def encode_scalars_raw(t: float, frame_id: str, ids: NDArray[np.integer], values: Array,
                       field: str = 'range') -> bytes:
    """Scalars tagged with agent ids (e.g. ranges [m]) as a PointCloud2: ``field`` FLOAT64 at
    0, agent_id UINT32 at 8, point_step 12."""
    return encode_points_raw(t, frame_id, ids, values, (field,))


def decode_scalars_raw(data: Data,
                       field: str = 'range') -> tuple[float, NDArray[np.uint32], Array]:
    """``(t, ids, values)`` of :func:`encode_scalars_raw`'s cloud."""
    t, ids, values = decode_points_raw(data, (field,))
    return t, ids, values[:, 0]


def decode_position_raw(data: Data) -> tuple[float, Array]:
    """``(t, p)`` of a PoseWithCovarianceStamped (the covariance not read)."""
    data, t, pos = _fixed(data, 'PoseWithCovarianceStamped', 43)
    return t, _pose(data, pos)[1]
