"""Errors measured as each estimate frame requires (metrics/results.py): world estimates
directly; anchor-free estimates after the exact common-yaw-and-translation alignment; estimates
in the anchor's body frame through the anchor's true pose."""
import numpy as np

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.estimators.base import EstimateFrame
from bearing_pose_estimation.metrics.results import Recording, pose_errors

RNG = np.random.default_rng(4)
N = 6


def _rot_z(a):
    return so3.axis_angle([0, 0, 1], a)


def _fleet(yaw_only=False):
    if yaw_only:
        R = np.stack([_rot_z(a) for a in RNG.uniform(-np.pi, np.pi, N)])
    else:
        R = so3.exp(RNG.normal(size=(N, 3)))
    return R, RNG.normal(size=(N, 3)) * 5.0


def test_world_estimates_are_measured_directly():
    R, p = _fleet()
    R_hat = R @ so3.axis_angle([1, 0, 0], 0.1)
    p_hat = p + [0.0, 0.3, 0.0]
    e = pose_errors(EstimateFrame.WORLD, R, p, R_hat, p_hat, [1, 2])
    np.testing.assert_allclose(e.att_err, 0.1, atol=1e-12)
    np.testing.assert_allclose(e.pos_err, 0.3, atol=1e-12)


def test_common_yaw_and_translation_are_aligned_away_exactly():
    """Estimates in a frame turned by an unknown yaw and shifted: zero error; one agent off by
    a further yaw and a displacement: its error shows, the others stay near zero."""
    R, p = _fleet(yaw_only=True)
    a, t = 1.1, np.array([3.0, -2.0, 0.5])
    R_hat, p_hat = _rot_z(a) @ R, p @ _rot_z(a).T + t
    e = pose_errors(EstimateFrame.COMMON_YAW_TRANSLATION, R, p, R_hat, p_hat)
    assert e.att_err.max() < 1e-12 and e.pos_err.max() < 1e-12
    assert pose_errors(EstimateFrame.WORLD, R, p, R_hat, p_hat).pos_err.min() > 0.1
    R_hat[2] = _rot_z(0.01) @ R_hat[2]
    p_hat[2] += [0.0, 0.0, 0.06]
    e = pose_errors(EstimateFrame.COMMON_YAW_TRANSLATION, R, p, R_hat, p_hat)
    # The circular mean of the yaw offsets moves by 0.01/N (to first order).
    assert abs(e.att_err[2] - 0.01 * (N - 1) / N) < 1e-6
    assert abs(e.pos_err[2] - 0.05) < 0.01 and np.delete(e.pos_err, 2).max() < 0.02


def test_anchor_body_estimates_go_through_the_anchor_pose():
    R, p = _fleet()
    anchor = 0
    Q = R[anchor].T @ R                               # Q_i = R_aᵀ R_i
    q = (p - p[anchor]) @ R[anchor]                   # q_i = R_aᵀ (p_i - p_a)
    e = pose_errors(EstimateFrame.ANCHOR_BODY, R, p, Q, q, anchor=anchor)
    assert e.att_err.max() < 1e-12 and e.pos_err.max() < 1e-12
    q[3] += R[anchor].T @ [0.2, 0.0, 0.0]             # 0.2 m off, in the world
    e = pose_errors(EstimateFrame.ANCHOR_BODY, R, p, Q, q, anchor=anchor)
    np.testing.assert_allclose(e.pos_err[3], 0.2, atol=1e-12)


def test_a_recording_is_assembled_in_one_place():
    R, p = _fleet()
    rows = [pose_errors(EstimateFrame.WORLD, R, p, R, p + k, [0, 1]) for k in (0.0, 1.0)]
    rec = Recording.of([0.0, 0.5], ['a', 'b'], rows)
    assert rec.att_err.shape == rec.pos_err.shape == (2, 2)
    np.testing.assert_allclose(rec.mean_errors()[1], [0.0, np.sqrt(3.0)])
