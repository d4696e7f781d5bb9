"""SO(3) helpers in the notation of Boughellaba & Tayebi (Section II).

Every function accepts a single vector/matrix or a batch with leading axes
(``(..., 3)`` vectors, ``(..., 3, 3)`` matrices) and works in float64.

- ``hat(x)`` is ``[x]x``, the skew matrix with ``[x]x y = x × y``; ``vex`` is its inverse.
- ``Pa(A) = (A - Aᵀ)/2`` and ``psi(A) = vex(Pa(A))``.
- ``projector(x) = P_x = I - x xᵀ/‖x‖²``.
- ``exp``/``log`` are the exponential and logarithm maps between R³ (rotation vectors) and SO(3).
"""
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


def Pa(A: ArrayLike) -> Array:
    """Anti-symmetric projection ``(A - Aᵀ)/2`` onto so(3)."""
    A = np.asarray(A, dtype=float)
    return 0.5 * (A - np.swapaxes(A, -1, -2))


def psi(A: ArrayLike) -> Array:
    """``psi(A) = vex(Pa(A))``; note ``x × y = 2 psi(y xᵀ)``."""
    return vex(Pa(A))


def projector(x: ArrayLike) -> Array:
    """``P_x = I - x xᵀ/‖x‖²``, the orthogonal projector onto the plane normal to ``x``."""
    x = np.asarray(x, dtype=float)
    outer = x[..., :, None] * x[..., None, :]
    return _I3 - outer / np.sum(x * x, axis=-1)[..., None, None]


def exp(phi: ArrayLike) -> Array:
    """Exponential map: rotation vector ``phi`` (axis × angle) to a rotation matrix.

    Rodrigues' formula, with a Taylor expansion near zero so the result is
    orthonormal to machine precision for any angle.
    """
    phi = np.asarray(phi, dtype=float)
    if phi.shape == (3,):
        return _exp_one(phi)
    theta2 = np.sum(phi * phi, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    # a = sin θ/θ, b = (1 - cos θ)/θ², with their series near 0.
    a = np.where(small, 1.0 - theta2 / 6.0 + theta2**2 / 120.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0 + theta2**2 / 720.0, (1.0 - np.cos(safe)) / safe**2)
    K = hat(phi)
    return _I3 + a[..., None, None] * K + b[..., None, None] * (K @ K)


def _exp_one(phi: Array) -> Array:
    """:func:`exp` of one vector with scalar math: ~10x faster than the batched path, which
    matters in the per-agent node (many small rotations per step)."""
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
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def log(R: ArrayLike) -> Array:
    """Logarithm map: rotation matrix to rotation vector with angle in ``[0, π]``.

    Uses the quaternion route of scipy (well conditioned near 0 and π).
    """
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    out = Rotation.from_matrix(flat).as_rotvec()
    return out.reshape(R.shape[:-2] + (3,))


def to_quat(R: Array) -> Array:
    """One rotation matrix → unit quaternion ``(x, y, z, w)`` with ``w >= 0`` (REP-103 order).

    Shepperd's method (branch on the largest diagonal term, so no precision is lost); scalar
    code, ~20x faster than scipy for a single matrix, which the nodes convert every message.
    """
    m = R
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s
    out = np.array(q, dtype=float)
    out /= math.sqrt(float(out @ out))
    return -out if out[3] < 0.0 else out


def from_quat(q: Array) -> Array:
    """Unit quaternion ``(x, y, z, w)`` → rotation matrix (``q`` is normalised first)."""
    x, y, z, w = (float(c) for c in q)
    n = x * x + y * y + z * z + w * w
    s = 2.0 / n
    return np.array([
        [1.0 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
        [s * (x * y + z * w), 1.0 - s * (x * x + z * z), s * (y * z - x * w)],
        [s * (x * z - y * w), s * (y * z + x * w), 1.0 - s * (x * x + y * y)]])


def angle(R: ArrayLike) -> Array:
    """Geodesic angle of ``R`` from the identity, in ``[0, π]`` radians.

    ``atan2(‖psi(R)‖, (tr R - 1)/2)``: accurate near 0, unlike ``arccos``.
    """
    R = np.asarray(R, dtype=float)
    s = np.linalg.norm(psi(R), axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(s, c)


def dist_I(R: ArrayLike) -> Array:
    """The paper's normalised distance ``|R|_I = sqrt(tr(I - R)/4) ∈ [0, 1]``.

    Computed as ``sin(θ/2)`` from the geodesic angle (``tr(I - R) = 4 sin²(θ/2)``): the trace
    form cancels catastrophically and bottoms out at 1e-8.
    """
    return np.sin(0.5 * angle(R))


def axis_angle(axis: ArrayLike, theta: float) -> Array:
    """``R_alpha(theta, v)`` of the paper: rotation by ``theta`` about the unit vector ``v``."""
    v = np.asarray(axis, dtype=float)
    return exp(v / np.linalg.norm(v) * theta)


def reorthonormalize(R: ArrayLike) -> Array:
    """Pull a nearly orthonormal ``R`` back onto SO(3): one Newton-Schulz step of the polar
    factor, ``R (3I - RᵀR)/2``. The residual ``RᵀR - I`` is squared, so rounding errors of
    long products never accumulate (two matrix products, far cheaper than an SVD)."""
    R = np.asarray(R, dtype=float)
    return 0.5 * R @ (3.0 * _I3 - np.swapaxes(R, -1, -2) @ R)


def orthonormality_error(R: ArrayLike) -> Array:
    """``‖RᵀR - I‖_F``: how far a matrix has drifted off SO(3)."""
    R = np.asarray(R, dtype=float)
    return np.linalg.norm(np.swapaxes(R, -1, -2) @ R - _I3, axis=(-2, -1))
