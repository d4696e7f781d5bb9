"""A pose from the bearings to neighbours whose poses are estimated: the package's warm start (none
of the papers has one; derivation: docs/warm_start.md).

Agent i measures ``b_j`` (unit, its body frame) to each neighbour j, and hears ``d_j``, the same
bearing in the world frame as j sees it (``-R̂_j b^j_ji``), and ``p̂_j``. Then

- the attitude solves Wahba's problem ``min_R Σ w_j ‖d_j − R b_j‖²``: with ``B = Σ w_j d_j b_jᵀ
  = U S Vᵀ``, ``R = U diag(1, 1, det U det V) Vᵀ`` (Markley 1988);
- the position is the point closest to the lines through each ``p̂_j`` along ``d_j``:
  ``(Σ w_j P_j) p = Σ w_j P_j p̂_j`` with ``P_j = I − d_j d_jᵀ``.

Both need two bearings at least :data:`MIN_SPREAD_RAD` apart. Each returns its residual angles
[rad], for the caller to judge against the noise. :func:`planar` fits a yaw and a translation to
relative positions (De Carli et al.).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

# Two bearings closer than this to collinear leave a rotation about them (and the position
# along them) unobserved: no warm start (5 deg, as the methods' own collinearity warning).
MIN_SPREAD_RAD = np.radians(5.0)
# A fit is accepted when every residual is within this many per-component std of the noise it
# explains (at least the floors: noise-free neighbours are exact only to rounding). A true 2-D
# residual exceeds 4 sigma with probability exp(-8) = 3e-4 (Rayleigh), a 3-D one 1e-3.
WARM_SIGMAS = 4.0
WARM_FLOOR_RAD = 1e-3
WARM_FLOOR_M = 1e-3


def _angles(a: Array, b: Array) -> Array:
    """The angles between the unit rows of ``a`` and ``b`` (atan2: exact near 0 and π)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum('ea,ea->e', a, b))


def spread(b: Array) -> float:
    """The widest angle between two of the unit rows of ``b``, up to π/2 (0: fewer than two)."""
    if len(b) < 2:
        return 0.0
    c = np.abs(b @ b.T)
    return float(np.arccos(np.clip(c.min(), 0.0, 1.0)))


def wahba(body: Array, world: Array, w: Array) -> tuple[Array, Array] | None:
    """``R`` ``(3, 3)`` minimising ``Σ w_j ‖world_j − R body_j‖²`` and the residual angles
    ``(E,)``; None if the bearings do not determine it (fewer than two, or collinear)."""
    if spread(body) < MIN_SPREAD_RAD:
        return None
    U, _, Vt = np.linalg.svd(np.einsum('e,ea,eb->ab', w, world, body))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U) * np.linalg.det(Vt)]) @ Vt
    return R, _angles(body @ R.T, world)


def triangulate(points: Array, d: Array, w: Array) -> tuple[Array, Array] | None:
    """``p`` ``(3,)`` closest (weighted least squares) to the lines through ``points`` ``(E, 3)``
    along the unit directions ``d`` (from ``p`` to each point), and the angles ``(E,)`` between
    ``d`` and ``p`` → point (π: behind); None if undetermined."""
    if spread(d) < MIN_SPREAD_RAD:
        return None
    P = np.eye(3) - np.einsum('ea,eb->eab', d, d)
    A = np.einsum('e,eab->ab', w, P)
    p = np.linalg.solve(A, np.einsum('e,eab,eb->a', w, P, points))
    to = points - p
    dist = np.linalg.norm(to, axis=1)
    return p, _angles(to / np.maximum(dist, 1e-300)[:, None], d)


def information(d: Array, sigma: Array, dist: Array | None = None) -> Array:
    """``Σ_j (I − d_j d_jᵀ) / (σ_j² r_j²)`` ``(3, 3)``: the information the bearings ``d`` with
    angular noise ``sigma`` ``(E,)`` give on an attitude (``dist`` None) or, at ranges ``dist``,
    on a position; its inverse is the fit's covariance to first order."""
    scale = sigma ** 2 if dist is None else (sigma * dist) ** 2
    return np.einsum('e,eab->ab', 1.0 / scale, np.eye(3) - np.einsum('ea,eb->eab', d, d))


class Planar(NamedTuple):
    """:func:`planar`'s fit: ``world_k ≈ c + R_z(ψ) body_k``."""

    psi: float
    c: Array            # (3,)
    residuals: Array    # (E, 3)
    information: Array  # (4, 4) on (c, ψ): Σ w_k J_kᵀ J_k
    lever: float        # the weighted RMS horizontal distance of body_k to their centroid [m]


def planar(body: Array, world: Array, w: Array) -> Planar | None:
    """The yaw and translation that carry ``body`` ``(E, 3)`` onto ``world`` (weighted least
    squares, weights ``w``); None if the horizontal ``body_k`` coincide (no yaw).

    In complex numbers ``x + ιy`` (2-D Procrustes): with the weighted means ``ā, b̄``,
    ``e^{ιψ} = unit(Σ w_k conj(b_k − b̄)(a_k − ā))`` and ``c = ā − e^{ιψ} b̄``."""
    a, b = world[:, 0] + 1j * world[:, 1], body[:, 0] + 1j * body[:, 1]
    a_bar, b_bar = np.average(a, weights=w), np.average(b, weights=w)
    lever = float(np.sqrt(np.average(np.abs(b - b_bar) ** 2, weights=w)))
    s = np.sum(w * np.conj(b - b_bar) * (a - a_bar))
    if lever <= 1e-9 * max(1.0, float(np.abs(b).max())) or s == 0:
        return None
    u = s / abs(s)
    c_xy = a_bar - u * b_bar
    c = np.array([c_xy.real, c_xy.imag, np.average(world[:, 2] - body[:, 2], weights=w)])
    r_xy = a - c_xy - u * b
    res = np.column_stack([r_xy.real, r_xy.imag, world[:, 2] - body[:, 2] - c[2]])
    turn = np.column_stack([-(u * b).imag, (u * b).real, np.zeros(len(b)), np.abs(b) ** 2])
    info = np.zeros((4, 4))
    info[[0, 1, 2], [0, 1, 2]] = w.sum()
    info[:, 3] = info[3, :] = np.sum(w[:, None] * turn, axis=0)   # ∂(residual)/∂ψ = ι e^{ιψ} b_k
    return Planar(float(np.angle(u)), c, res, info, lever)
