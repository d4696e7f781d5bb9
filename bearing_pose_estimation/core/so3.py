"""SO(3) helpers in the notation of Boughellaba & Tayebi (Section II), in float64, on one
vector/matrix or a batch with leading axes (``(..., 3)``, ``(..., 3, 3)``)."""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

_I3 = np.eye(3)
# Below this angle the Taylor series is used: Rodrigues' coefficients lose precision.
_SMALL_ANGLE = 1e-4


def hat(x: ArrayLike) -> Array:
    """``[x]x``: the skew-symmetric matrix with ``hat(x) @ y == cross(x, y)``."""
    x = np.asarray(x, dtype=float)
    out = np.zeros(x.shape[:-1] + (3, 3))
    out[..., 0, 1] = -x[..., 2]
    out[..., 0, 2] = x[..., 1]
    out[..., 1, 0] = x[..., 2]
    out[..., 1, 2] = -x[..., 0]
    out[..., 2, 0] = -x[..., 1]
    out[..., 2, 1] = x[..., 0]
    return out


def vex(S: ArrayLike) -> Array:
    """Inverse of :func:`hat` (reads the lower triangle; ``S`` is assumed skew)."""
    S = np.asarray(S, dtype=float)
    return np.stack([S[..., 2, 1], S[..., 0, 2], S[..., 1, 0]], axis=-1)


def psi(A: ArrayLike) -> Array:
    """``vex`` of the anti-symmetric part ``(A - Aᵀ)/2``; note ``x × y = 2 psi(y xᵀ)``."""
    A = np.asarray(A, dtype=float)
    return vex(0.5 * (A - np.swapaxes(A, -1, -2)))


def projector(x: ArrayLike) -> Array:
    """``P_x = I - x xᵀ/‖x‖²``, the orthogonal projector onto the plane normal to ``x``."""
    x = np.asarray(x, dtype=float)
    outer = x[..., :, None] * x[..., None, :]
    return _I3 - outer / np.sum(x * x, axis=-1)[..., None, None]


def exp(phi: ArrayLike) -> Array:
    """Rotation vector ``phi`` (axis × angle) to a rotation matrix, by Rodrigues' formula in
    half-angle form (orthonormal to machine precision at any angle)."""
    phi = np.asarray(phi, dtype=float)
    if phi.shape == (3,):
        return _exp_one(phi)
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    theta2 = x * x + y * y + z * z
    theta = np.sqrt(theta2)
    # Half-angle form, exact down to θ = 0 without a series: with s = sin(θ/2), c = cos(θ/2)
    # and sh = s/(θ/2) (1 at θ = 0), a = sin θ/θ = sh c and b = (1 - cos θ)/θ² = sh²/2.
    # c = √(1 - s²) saves the cosine while θ ≤ π/2, where c ≥ 0.7 keeps it exact.
    half = 0.5 * theta
    s = np.sin(half)
    sh = np.divide(s, half, out=np.ones_like(s), where=half > 0.0)
    c = np.sqrt(1.0 - s * s) if theta.size and theta.max() <= 0.5 * np.pi else np.cos(half)
    a, b = sh * c, 0.5 * sh * sh
    # I + a K + b K² entry by entry (K² = φφᵀ - θ² I): no 3x3 products, ~4x faster in batch.
    out = np.empty(phi.shape[:-1] + (3, 3))
    bx, by, bz = b * x, b * y, b * z
    ax, ay, az = a * x, a * y, a * z
    diag = 1.0 - b * theta2
    out[..., 0, 0] = diag + bx * x
    out[..., 1, 1] = diag + by * y
    out[..., 2, 2] = diag + bz * z
    out[..., 0, 1] = bx * y - az
    out[..., 1, 0] = bx * y + az
    out[..., 0, 2] = bx * z + ay
    out[..., 2, 0] = bx * z - ay
    out[..., 1, 2] = by * z - ax
    out[..., 2, 1] = by * z + ax
    return out


# Below this angle the Jacobians' coefficients use their Taylor series (no cancellation).
_SERIES_ANGLE = 1e-2


def jacobian_apply(phi: ArrayLike, v: ArrayLike) -> Array:
    """``J(φ) v``, ``J = I + (1 - cos θ)/θ² [φ]x + (θ - sin θ)/θ³ [φ]x²`` the left Jacobian of
    SO(3): the translation of the SE(3) exponential of the twist ``(v, φ)``."""
    phi, v = np.asarray(phi, dtype=float), np.asarray(v, dtype=float)
    if phi.shape == (3,) and v.shape == (3,):
        return _jacobian_apply_one(phi, v)
    theta2 = np.sum(phi * phi, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < _SERIES_ANGLE
    safe = np.where(small, 1.0, theta)
    b = np.where(small, 0.5 - theta2 / 24.0 + theta2 ** 2 / 720.0,
                 (1.0 - np.cos(safe)) / safe ** 2)
    c = np.where(small, 1.0 / 6.0 - theta2 / 120.0 + theta2 ** 2 / 5040.0,
                 (safe - np.sin(safe)) / safe ** 3)
    pv = cross(phi, v)
    return v + b[..., None] * pv + c[..., None] * cross(phi, pv)


def _jacobian_apply_one(phi: Array, v: Array) -> Array:
    """:func:`jacobian_apply` of one pair with scalar math: several times faster (an agent
    integrates its neighbours' odometry sample by sample)."""
    x, y, z = float(phi[0]), float(phi[1]), float(phi[2])
    v0, v1, v2 = float(v[0]), float(v[1]), float(v[2])
    theta2 = x * x + y * y + z * z
    theta = math.sqrt(theta2)
    if theta < _SERIES_ANGLE:
        b = 0.5 - theta2 / 24.0 + theta2 ** 2 / 720.0
        c = 1.0 / 6.0 - theta2 / 120.0 + theta2 ** 2 / 5040.0
    else:
        b = (1.0 - math.cos(theta)) / theta ** 2
        c = (theta - math.sin(theta)) / theta ** 3
    p0, p1, p2 = y * v2 - z * v1, z * v0 - x * v2, x * v1 - y * v0          # φ × v
    q0, q1, q2 = y * p2 - z * p1, z * p0 - x * p2, x * p1 - y * p0          # φ × (φ × v)
    return np.array([v0 + b * p0 + c * q0, v1 + b * p1 + c * q1, v2 + b * p2 + c * q2])


def jacobian_inv_apply(phi: ArrayLike, v: ArrayLike) -> Array:
    """``J(φ)⁻¹ v`` (:func:`jacobian_apply`):
    ``J⁻¹ = I - ½ [φ]x + (1/θ² - (1 + cos θ)/(2 θ sin θ)) [φ]x²``, for ``θ < π``."""
    phi, v = np.asarray(phi, dtype=float), np.asarray(v, dtype=float)
    theta2 = np.sum(phi * phi, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < _SERIES_ANGLE
    safe = np.where(small, 1.0, theta)
    e = np.where(small, 1.0 / 12.0 + theta2 / 720.0 + theta2 ** 2 / 30240.0,
                 1.0 / safe ** 2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)))
    pv = cross(phi, v)
    return v - 0.5 * pv + e[..., None] * cross(phi, pv)


def _exp_one(phi: Array) -> Array:
    """:func:`exp` of one vector with scalar math: ~10x faster (the node's many small rotations)."""
    x, y, z = float(phi[0]), float(phi[1]), float(phi[2])
    theta2 = x * x + y * y + z * z
    if theta2 < _SMALL_ANGLE**2:
        a = 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0
        b = 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0
    else:
        theta = math.sqrt(theta2)
        a = math.sin(theta) / theta
        b = (1.0 - math.cos(theta)) / theta2
    # I + a K + b K², with K² = φφᵀ - θ² I.
    return np.array([
        [1.0 + b * (x * x - theta2), -a * z + b * x * y, a * y + b * x * z],
        [a * z + b * x * y, 1.0 + b * (y * y - theta2), -a * x + b * y * z],
        [-a * y + b * x * z, a * x + b * y * z, 1.0 + b * (z * z - theta2)]])


def cross(a: ArrayLike, b: ArrayLike) -> Array:
    """``a × b`` over the last axis; much cheaper than ``np.cross`` for small batches."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def dot(a: Array, b: Array) -> Array:
    """``a · b`` over the last axis, written out (numpy's length-3 reductions cost ~4x more)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def log(R: ArrayLike) -> Array:
    """Rotation matrix to rotation vector, angle in ``[0, π]`` (scipy's quaternion route: well
    conditioned near 0 and π)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float)
    out = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec()
    return out.reshape(R.shape[:-2] + (3,))


def log_small(R: ArrayLike) -> Array:
    """:func:`log` for a step's small rotation: ``θ/(2 sin θ) vee(R - Rᵀ)``, ten times cheaper;
    beyond 3 rad (where that form loses digits) through :func:`log`."""
    R = np.asarray(R, dtype=float)
    v = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    s = np.sqrt(np.sum(v * v, axis=-1))
    c = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)
    theta = np.arctan2(s, c)
    # θ / sin θ, with its limit 1 (series below 1e-4 rad: exact to rounding).
    small = s < 1e-4
    scale = np.where(small, 1.0 + theta * theta / 6.0, theta / np.where(small, 1.0, s))
    out = v * scale[..., None]
    far = theta > 3.0
    if np.any(far):
        out[far] = log(R[far])
    return out


def to_quat(R: Array) -> Array:
    """One rotation matrix → unit quaternion ``(x, y, z, w)``, ``w >= 0`` (REP-103 order), by
    Shepperd's method (no precision lost); scalar code ~20x faster than scipy for one matrix."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s
    out = np.array(q, dtype=float)
    out /= math.sqrt(float(out @ out))
    return -out if out[3] < 0.0 else out


def from_quat(q: Array) -> Array:
    """Unit quaternion ``(x, y, z, w)`` → rotation matrix (``q`` is normalised first)."""
    x, y, z, w = (float(c) for c in q)
    s = 2.0 / (x * x + y * y + z * z + w * w)
    return np.array([
        [1.0 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
        [s * (x * y + z * w), 1.0 - s * (x * x + z * z), s * (y * z - x * w)],
        [s * (x * z - y * w), s * (y * z + x * w), 1.0 - s * (x * x + y * y)]])


def angle(R: ArrayLike) -> Array:
    """Geodesic angle of ``R`` from the identity, in ``[0, π]`` radians:
    ``atan2(‖psi(R)‖, (tr R - 1)/2)``, accurate near 0, unlike ``arccos``."""
    R = np.asarray(R, dtype=float)
    s = np.linalg.norm(psi(R), axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(s, c)


def dist_I(R: ArrayLike) -> Array:
    """The paper's normalised distance ``|R|_I = sqrt(tr(I - R)/4) ∈ [0, 1]``, as ``sin(θ/2)``
    (``tr(I - R) = 4 sin²(θ/2)``): the trace form cancels catastrophically below 1e-8."""
    return np.sin(0.5 * angle(R))


def axis_angle(axis: ArrayLike, theta: float) -> Array:
    """``R_alpha(theta, v)`` of the paper: rotation by ``theta`` about the unit vector ``v``."""
    v = np.asarray(axis, dtype=float)
    return exp(v / np.linalg.norm(v) * theta)


# Above this many matrices, :func:`matmul` multiplies in a components-last layout: numpy's
# stacked ``@`` loops over 3x3 products one by one: 2.4x slower at 1 000 (61 vs 149 µs here).
_COMPONENTS_LAST_FROM = 64


def matmul(*mats: Array) -> Array:
    """``mats[0] @ mats[1] @ ...`` for stacks ``(N, 3, 3)`` (a single ``(3, 3)`` is broadcast
    in the small path only); large stacks as nine length-N vectors per matrix."""
    if len(mats) == 1:
        return mats[0]
    first = mats[0]
    if first.ndim != 3 or first.shape[0] < _COMPONENTS_LAST_FROM or any(
            m.shape != first.shape for m in mats):
        out = first
        for m in mats[1:]:
            out = out @ m
        return out
    acc = np.ascontiguousarray(first.transpose(1, 2, 0))
    for m in mats[1:]:
        b = np.ascontiguousarray(m.transpose(1, 2, 0))
        nxt = acc[:, 0, None, :] * b[None, 0]
        nxt += acc[:, 1, None, :] * b[None, 1]
        nxt += acc[:, 2, None, :] * b[None, 2]
        acc = nxt
    return np.ascontiguousarray(acc.transpose(2, 0, 1))


def reorthonormalize(R: ArrayLike) -> Array:
    """Pull a nearly orthonormal ``R`` back onto SO(3): one Newton-Schulz step of the polar
    factor, ``R (3I - RᵀR)/2``. The residual ``RᵀR - I`` is squared, so rounding errors of
    long products never accumulate (two matrix products, far cheaper than an SVD)."""
    R = np.asarray(R, dtype=float)
    return 0.5 * matmul(R, 3.0 * _I3 - matmul(np.swapaxes(R, -1, -2), R))


def orthonormality_error(R: ArrayLike) -> Array:
    """``‖RᵀR - I‖_F``: how far a matrix has drifted off SO(3)."""
    R = np.asarray(R, dtype=float)
    return np.linalg.norm(np.swapaxes(R, -1, -2) @ R - _I3, axis=(-2, -1))


# The upper triangle of a symmetric 3x3, in the order the wire carries it (msg_defs).
SYM_INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def sym_pack(m: Array) -> Array:
    """Symmetric ``(..., 3, 3)`` → ``(..., 6)`` xx, yy, zz, xy, xz, yz."""
    return np.stack([m[..., r, s] for r, s in SYM_INDEX], axis=-1)


def sym_unpack(v: Array) -> Array:
    """``(..., 6)`` xx, yy, zz, xy, xz, yz → symmetric ``(..., 3, 3)``."""
    out = np.empty(v.shape[:-1] + (3, 3))
    for c, (r, s) in enumerate(SYM_INDEX):
        out[..., r, s] = out[..., s, r] = v[..., c]
    return out
