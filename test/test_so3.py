"""SO(3) helpers: group identities, and agreement with scipy's independent implementation."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bearing_pose_estimation.core import so3

RNG = np.random.default_rng(7)
VECS = RNG.normal(size=(50, 3))
ROTS = Rotation.random(50, random_state=3).as_matrix()


def test_hat_is_cross_product_and_vex_inverts_it():
    y = RNG.normal(size=(50, 3))
    np.testing.assert_allclose(so3.hat(VECS) @ y[..., None], np.cross(VECS, y)[..., None],
                               atol=1e-14)
    np.testing.assert_array_equal(so3.vex(so3.hat(VECS)), VECS)
    np.testing.assert_array_equal(so3.hat(VECS), -np.swapaxes(so3.hat(VECS), -1, -2))


def test_cross_product_is_twice_psi_of_outer_product():
    """x × y = 2 psi(y xᵀ), used throughout the paper's proofs."""
    y = RNG.normal(size=(50, 3))
    outer = y[:, :, None] * VECS[:, None, :]
    np.testing.assert_allclose(np.cross(VECS, y), 2.0 * so3.psi(outer), atol=1e-13)


def test_rotation_conjugates_hat():
    """[R x]x = R [x]x Rᵀ."""
    lhs = so3.hat(np.einsum('nab,nb->na', ROTS, VECS))
    rhs = ROTS @ so3.hat(VECS) @ np.swapaxes(ROTS, -1, -2)
    np.testing.assert_allclose(lhs, rhs, atol=1e-13)


@pytest.mark.parametrize('scale', [1e-9, 1e-5, 1e-3, 1.0, 1.5, 3.0, np.pi - 1e-6])
def test_exp_matches_scipy_and_stays_on_so3(scale):
    phi = scale * VECS / np.linalg.norm(VECS, axis=1, keepdims=True) * RNG.uniform(0.1, 1.0, (50, 1))
    R = so3.exp(phi)
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=1e-15)
    assert so3.orthonormality_error(R).max() < 4e-15  # a few ulps
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-15)


def test_exp_batch_mixing_every_branch_matches_the_one_vector_path():
    """Zero, series-range, half-angle (θ ≤ π/2) and cosine (θ > π/2) rows in one batch give the
    same matrices as the scalar path, row by row."""
    phi = np.vstack([np.zeros(3), 1e-6 * VECS[:5], 0.3 * VECS[:5], 2.5 * VECS[:5]])
    batch = so3.exp(phi)
    for row, R in zip(phi, batch):
        np.testing.assert_allclose(R, so3.exp(row), atol=2e-15)
    # Without the large rows the batch takes the half-angle branch: same answers.
    np.testing.assert_allclose(so3.exp(phi[:11]), batch[:11], atol=2e-15)


@pytest.mark.parametrize('n', [3, 64, 500])
def test_matmul_matches_numpy_for_small_and_large_stacks(n):
    """Stacks of 64 or more go through the components-last path; the product is the same."""
    A, B, C = (Rotation.random(n, random_state=s).as_matrix() for s in (1, 2, 4))
    np.testing.assert_allclose(so3.matmul(A, B, C), A @ B @ C, atol=1e-15)
    np.testing.assert_allclose(so3.matmul(A, B), A @ B, atol=1e-15)
    np.testing.assert_allclose(so3.dot(VECS, VECS[::-1]), np.sum(VECS * VECS[::-1], axis=1),
                               atol=1e-14)


def test_log_inverts_exp_and_angle_is_accurate_near_zero():
    phi = VECS / np.linalg.norm(VECS, axis=1, keepdims=True) * RNG.uniform(0, 3.1, (50, 1))
    np.testing.assert_allclose(so3.log(so3.exp(phi)), phi, atol=1e-12)
    np.testing.assert_allclose(so3.angle(so3.exp(phi)), np.linalg.norm(phi, axis=1), atol=1e-14)
    tiny = so3.exp([1e-12, 0.0, 0.0])
    assert so3.angle(tiny) == pytest.approx(1e-12, rel=1e-6)  # arccos would give 0 or 1e-8


def test_paper_distance_identities():
    """|R|_I² = tr(I - R)/4 ∈ [0, 1] and ‖I - R‖_F² = 8 |R|_I²."""
    d = so3.dist_I(ROTS)
    np.testing.assert_allclose(d**2, 0.25 * np.trace(np.eye(3) - ROTS, axis1=1, axis2=2),
                               atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(np.eye(3) - ROTS, axis=(1, 2))**2, 8 * d**2,
                               atol=1e-13)
    assert np.all((d >= 0) & (d <= 1))
    assert so3.dist_I(so3.axis_angle([0, 0, 1], np.pi)) == pytest.approx(1.0)


def test_projector_properties():
    P = so3.projector(VECS)
    np.testing.assert_allclose(P @ P, P, atol=1e-14)
    np.testing.assert_allclose(P, np.swapaxes(P, 1, 2), atol=0)
    np.testing.assert_allclose(np.einsum('nab,nb->na', P, VECS), 0, atol=1e-14)
    # R P_b Rᵀ = P_{R b}: why the node may use the body-frame bearing.
    np.testing.assert_allclose(ROTS @ P @ np.swapaxes(ROTS, 1, 2),
                               so3.projector(np.einsum('nab,nb->na', ROTS, VECS)), atol=1e-13)


def test_axis_angle_is_the_papers_rodrigues_form():
    v, theta = np.array([1.0, 2.0, 2.0]) / 3.0, 0.9 * np.pi
    K = so3.hat(v)
    expected = np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K
    np.testing.assert_allclose(so3.axis_angle(3 * v, theta), expected, atol=1e-15)


def test_reorthonormalize_removes_drift_and_keeps_rotations():
    drifted = ROTS + 1e-7 * RNG.normal(size=ROTS.shape)
    fixed = so3.reorthonormalize(drifted)
    before = so3.orthonormality_error(drifted)
    assert before.min() > 1e-8
    # The residual is squared (Newton-Schulz): ~1e-7 becomes ~1e-13, not ~1e-7.
    assert np.all(so3.orthonormality_error(fixed) < 10 * before**2 + 1e-15)
    np.testing.assert_allclose(so3.reorthonormalize(ROTS), ROTS, atol=1e-15)


def test_quaternion_conversions_match_scipy():
    """Including the branches of Shepperd's method: near-π rotations about each axis."""
    specials = np.stack([so3.axis_angle(a, np.pi - 1e-9) for a in np.eye(3)])
    for R in np.concatenate([ROTS, specials, np.eye(3)[None]]):
        q = so3.to_quat(R)
        ref = Rotation.from_matrix(R).as_quat()
        ref = -ref if ref[3] < 0 else ref
        np.testing.assert_allclose(q, ref, atol=1e-12)
        np.testing.assert_allclose(so3.from_quat(q), R, atol=1e-14)
        np.testing.assert_allclose(so3.from_quat(3.0 * q), R, atol=1e-14)  # normalises


def test_log_small_is_log_to_rounding_at_every_angle():
    rng = np.random.default_rng(0)
    for angle in (0.0, 1e-9, 1e-5, 1e-3, 0.1, 1.0, 2.9, 3.1, np.pi):
        phi = rng.normal(size=(50, 3))
        phi *= angle / np.linalg.norm(phi, axis=1, keepdims=True)
        R = so3.exp(phi)
        np.testing.assert_allclose(so3.log_small(R), so3.log(R), rtol=0,
                                   atol=1e-15 * max(angle, 1.0) + (1e-8 if angle > 3 else 0))
