"""Wire format of the moving robots' sensors (msg_defs): odometry, relative positions, bearing
rates and ranges. Pure encode/decode (msg_defs.cdr, on bytes or on the rclpy message objects a
driver builds), no DDS."""
import numpy as np
import pytest
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2, PointField

from bearing_pose_estimation import msg_defs as wire
from bearing_pose_estimation.core import so3
from bearing_pose_estimation.msg_defs import cdr

RNG = np.random.default_rng(11)
T = 12.345678901  # not a multiple of anything: the stamp keeps its nanoseconds


def test_topics_and_frames():
    assert [wire.topic('agent_3', name) for name in (wire.ODOM, wire.RELATIVE_POSITIONS,
                                                      wire.BEARING_RATES, wire.RANGES)] == [
        '/agent_3/odom', '/agent_3/relative_positions', '/agent_3/bearing_rates',
        '/agent_3/ranges']
    assert wire.odom_frame('agent_3') == 'agent_3/odom'
    assert wire.body_frame('agent_3') == 'agent_3/base_link'


# ----------------------------------------------------------------------------- Odometry
def test_odometry_round_trip():
    v, omega, p = RNG.normal(size=3), RNG.normal(size=3), RNG.normal(size=3) * 10
    R = so3.exp(np.array([0.3, -1.2, 0.7]))
    data = cdr.encode_odometry_raw(T, 'agent_3', v, omega, R_odom=R, p_odom=p, v_std=0.05,
                                   omega_std=0.002)
    msg = wire.message(data, Odometry)
    assert msg.header.frame_id == 'agent_3/odom'
    assert msg.child_frame_id == 'agent_3/base_link'
    assert wire.stamp_ns(msg.header.stamp) == 12_345_678_901

    t, v2, omega2 = cdr.decode_odometry_raw(data, child_frame='agent_3/base_link')
    assert t == pytest.approx(T, abs=1e-9)
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(omega2, omega)

    cov = np.asarray(msg.twist.covariance).reshape(6, 6)
    np.testing.assert_array_equal(cov, np.diag([0.05 ** 2] * 3 + [0.002 ** 2] * 3))
    assert cov[0, 0] == msg.twist.covariance[0] and cov[5, 5] == msg.twist.covariance[35]
    np.testing.assert_array_equal(msg.pose.covariance, np.zeros(36))

    pos, o = msg.pose.pose.position, msg.pose.pose.orientation
    np.testing.assert_array_equal([pos.x, pos.y, pos.z], p)
    np.testing.assert_allclose(so3.from_quat(np.array([o.x, o.y, o.z, o.w])), R, atol=1e-12)


def test_odometry_without_pose_or_noise():
    data = cdr.encode_odometry_raw(0.5, 'agent_1', [1.0, 0, 0], [0, 0, 0.25])
    msg = wire.message(data, Odometry)
    pos, o = msg.pose.pose.position, msg.pose.pose.orientation
    assert [pos.x, pos.y, pos.z] == [0.0, 0.0, 0.0]
    assert [o.x, o.y, o.z, o.w] == [0.0, 0.0, 0.0, 1.0]
    np.testing.assert_array_equal(msg.twist.covariance, np.zeros(36))
    t, v, omega = cdr.decode_odometry_raw(data)  # no child_frame: the frame is not checked
    assert t == 0.5
    np.testing.assert_array_equal(v, [1.0, 0, 0])
    np.testing.assert_array_equal(omega, [0, 0, 0.25])


@pytest.mark.parametrize('v, omega', [([np.nan, 0, 0], [0, 0, 0]),
                                      ([0, 0, 0], [0, -np.inf, 0])])
def test_odometry_with_non_finite_twist_is_rejected(v, omega):
    data = cdr.encode_odometry_raw(T, 'agent_3', v, omega)
    with pytest.raises(wire.WireError, match='non-finite twist'):
        cdr.decode_odometry_raw(data, child_frame='agent_3/base_link')


def test_odometry_in_another_frame_is_rejected():
    msg = wire.message(cdr.encode_odometry_raw(T, 'agent_3', [1.0, 0, 0], [0, 0, 0]), Odometry)
    msg.child_frame_id = 'camera_link'   # a driver's message: decoded as its bytes
    with pytest.raises(wire.WireError) as err:
        cdr.decode_odometry_raw(msg, child_frame='agent_3/base_link')
    assert "'agent_3/base_link'" in str(err.value) and "'camera_link'" in str(err.value)


# ----------------------------------------------------------------------------- PointCloud2
def test_relative_positions_round_trip_through_vectors():
    """Relative positions and bearing rates share the bearings' layout but are not unit
    vectors: the codec returns them unchanged, zero and large ones included."""
    ids = np.array([1, 4, 7, 4_000_000_000], dtype=np.uint32)
    p_rel = np.array([[3.0, -4.0, 12.0], [0.0, 0.0, 0.0], [1e-9, 2e5, -7.5],
                      RNG.normal(size=3)])
    data = cdr.encode_vectors_raw(T, wire.body_frame('agent_2'), ids, p_rel)
    assert cdr.read_header(data).frame_id == 'agent_2/base_link'
    t, ids2, p2 = cdr.decode_vectors_raw(data)
    assert t == pytest.approx(T, abs=1e-9)
    assert ids2.dtype == np.uint32 and ids2.tolist() == ids.tolist()
    np.testing.assert_array_equal(p2, p_rel)
    assert np.linalg.norm(p2[0]) == 13.0


def test_ranges_round_trip():
    ids = np.array([2, 5, 3], dtype=np.uint32)
    ranges = np.array([1.5, 1e-3, 123.456789])
    data = cdr.encode_scalars_raw(T, 'agent_1/base_link', ids, ranges)
    msg = wire.message(data, PointCloud2)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ('range', 0, PointField.FLOAT64, 1), ('agent_id', 8, PointField.UINT32, 1)]
    assert (msg.point_step, msg.width, msg.height, msg.row_step) == (12, 3, 1, 36)
    assert not msg.is_bigendian and msg.is_dense
    assert msg.header.frame_id == 'agent_1/base_link'
    t, ids2, ranges2 = cdr.decode_scalars_raw(data)
    assert t == pytest.approx(T, abs=1e-9)
    assert ids2.dtype == np.uint32 and ids2.tolist() == [2, 5, 3]
    assert ranges2.dtype == np.float64
    np.testing.assert_array_equal(ranges2, ranges)


def test_scalars_with_another_field_name():
    data = cdr.encode_scalars_raw(T, 'agent_1/base_link', [9], [0.25], field='snr')
    assert cdr.decode_scalars_raw(data, field='snr')[2].tolist() == [0.25]
    with pytest.raises(wire.WireError, match="field 'range'"):
        cdr.decode_scalars_raw(data)


def test_ranges_in_any_field_order_with_padding():
    """A driver's layout: agent_id first, padding, range, then a field we do not read."""
    n = 2
    data = np.zeros(n, dtype=np.dtype({'names': ['agent_id', 'range', 'intensity'],
                                       'formats': ['<u4', '<f8', '<f4'],
                                       'offsets': [0, 8, 16], 'itemsize': 24}))
    data['agent_id'], data['range'], data['intensity'] = [6, 1], [2.5, 0.75], [9.0, 9.0]
    msg = PointCloud2()
    msg.header.stamp = wire.to_stamp(T)
    msg.fields = [PointField(name='agent_id', offset=0, datatype=PointField.UINT32, count=1),
                  PointField(name='range', offset=8, datatype=PointField.FLOAT64, count=1),
                  PointField(name='intensity', offset=16, datatype=PointField.FLOAT32, count=1)]
    msg.height, msg.width, msg.point_step, msg.row_step = 1, n, 24, 24 * n
    msg.data = data.tobytes()
    _, ids, ranges = cdr.decode_scalars_raw(msg)
    assert ids.tolist() == [6, 1]
    assert ranges.tolist() == [2.5, 0.75]


def _ranges() -> PointCloud2:
    return wire.message(cdr.encode_scalars_raw(T, 'agent_1/base_link', [2, 3], [1.0, 2.0]),
                        PointCloud2)


def _renamed(msg: PointCloud2) -> PointCloud2:
    msg.fields = [PointField(name='distance', offset=0, datatype=PointField.FLOAT64, count=1),
                  msg.fields[1]]
    return msg


def _integer_range(msg: PointCloud2) -> PointCloud2:
    msg.fields = [PointField(name='range', offset=0, datatype=PointField.INT32, count=1),
                  msg.fields[1]]
    return msg


def _truncated(msg: PointCloud2) -> PointCloud2:
    msg.data = bytes(msg.data)[:-1]
    return msg


def _big_endian(msg: PointCloud2) -> PointCloud2:
    msg.is_bigendian = True
    return msg


def _id_past_the_point(msg: PointCloud2) -> PointCloud2:
    msg.fields = [msg.fields[0],
                  PointField(name='agent_id', offset=10, datatype=PointField.UINT32, count=1)]
    return msg


def _absurd_point_step(msg: PointCloud2) -> PointCloud2:
    msg.width, msg.data, msg.point_step = 0, b'', 1 << 31   # numpy's itemsize is a C int
    return msg


@pytest.mark.parametrize('spoil, match', [
    (_absurd_point_step, 'point_step 2147483648 does not hold its fields .* or is too large'),
    (_renamed,
     r"needs field 'range' of datatype 8 or 7 \(fields: \['agent_id', 'distance'\]\)"),
    (_integer_range, "needs field 'range' of datatype 8 or 7"),
    (_truncated, 'data is 23 bytes, expected 2 points x 12 bytes'),
    (_big_endian, 'big-endian'),
    (_id_past_the_point, "field 'agent_id' .*end of the 12-byte point"),
])
def test_malformed_ranges_are_rejected(spoil, match):
    cdr.decode_scalars_raw(_ranges())  # the unspoilt message decodes
    with pytest.raises(wire.WireError, match=match):
        cdr.decode_scalars_raw(spoil(_ranges()))


def _vectors(ids: list[int], vectors) -> PointCloud2:
    return wire.message(cdr.encode_vectors_raw(T, 'agent_3/base_link', ids, vectors),
                        PointCloud2)


def test_decode_vectors_errors_name_what_is_wrong():
    msg = _vectors([1], [[0, 0, 1.0]])
    msg.fields = msg.fields[:2]
    with pytest.raises(wire.WireError) as err:
        cdr.decode_vectors_raw(msg)
    assert str(err.value) == ("PointCloud2 needs field 'z' of datatype 8 or 7 (fields: "
                              "['x', 'y'])")   # FLOAT64 or FLOAT32

    msg = _vectors([1, 2], np.eye(3)[:2])
    msg.data = bytes(msg.data)[:28]
    with pytest.raises(wire.WireError) as err:
        cdr.decode_vectors_raw(msg)
    assert str(err.value) == 'PointCloud2 data is 28 bytes, expected 2 points x 28 bytes'


def test_overlapping_vector_fields_are_rejected():
    msg = _vectors([1], [[0, 0, 1.0]])
    msg.fields = [msg.fields[0],
                  PointField(name='y', offset=4, datatype=PointField.FLOAT64, count=1),
                  *msg.fields[2:]]
    with pytest.raises(wire.WireError, match="field 'x' .*overlaps"):
        cdr.decode_vectors_raw(msg)


def test_float32_points_are_accepted_as_detectors_and_pcl_publish_them():
    """x, y, z as FLOAT32 (16-byte points): decoded to float64, and a unit bearing in float32
    is still a unit bearing for the estimator (1e-7 against its 1e-3 tolerance)."""
    from bearing_pose_estimation.runtime.buffers import unit_problem

    b = RNG.normal(size=(3, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    data = np.zeros(3, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('agent_id', '<u4')])
    data['x'], data['y'], data['z'] = b.T
    data['agent_id'] = [2, 5, 7]
    msg = PointCloud2(height=1, width=3, is_bigendian=False, point_step=16, row_step=48,
                      is_dense=True, data=data.tobytes(), fields=[
                          PointField(name=n, offset=4 * k, datatype=PointField.FLOAT32, count=1)
                          for k, n in enumerate('xyz')] + [
                          PointField(name='agent_id', offset=12, datatype=PointField.UINT32,
                                     count=1)])
    msg.header.stamp = wire.to_stamp(T)
    t, ids, vectors = cdr.decode_vectors_raw(msg)
    assert t == pytest.approx(T) and ids.tolist() == [2, 5, 7] and vectors.dtype == np.float64
    np.testing.assert_allclose(vectors, b, atol=1e-7)
    assert all(unit_problem(v, 1e-3) is None for v in vectors)
    msg.fields[1].datatype = PointField.INT16   # a type no bearing comes in
    with pytest.raises(wire.WireError, match="field 'y' of datatype 8 or 7"):
        cdr.decode_vectors_raw(msg)
