"""The formation controller of De Carli et al. (2024), (30)-(31) with the corrections of
``../shared/estimators/de-carli-2024.md`` §9, and the formation error of their Fig. 2(d).

For every sensing edge ``k = (a, b)`` (a measures b), ``r*_k = p*_a - p*_b + R̂_a ᵃp_ab``, and
robot i commands the body-frame velocity

    (30)  v_i = sat_{ν_max}(k_c μ_i),   (31)  μ_i = R̂_iᵀ Σ_k E_ik r*_k,

``E_ik = +1`` if i is the tail a, -1 if the head b; ``sat_ν(x) = x · min(1, ν/|x|)`` (3-D norm).
The printed (31) expresses its in-neighbour sum in robot j's frame (the factor ``R̂_iᵀ R̂_j`` is
missing: with it the formation is never reached) and (30) saturates μ instead of ``k_c μ``.
``R̂`` holds the *estimated* yaws (``paper`` mode, Sec. IV) or the true ones (``exogenous``)."""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .motion import rot_z

Array = NDArray[np.float64]
Index = NDArray[np.intp]


def body_velocity(p: Array, psi_used: Array, psi_true: Array, p_star: Array, tail: Index,
                  head: Index, k_c: float, nu_max: float, moving: NDArray[np.bool_]) -> Array:
    """(30)-(31): every robot's body-frame velocity ``(N, 3)`` [m/s] from the true ``p`` and
    ``psi_true`` and the controller's yaws ``psi_used``; 0 for robots not ``moving`` (hover)."""
    measured = np.einsum('kba,kb->ka', rot_z(psi_true[tail]), p[head] - p[tail])
    r = p_star[tail] - p_star[head] + np.einsum('kab,kb->ka', rot_z(psi_used[tail]), measured)
    total = np.zeros_like(p)
    np.add.at(total, tail, r)
    np.add.at(total, head, -r)
    x = k_c * np.einsum('nba,nb->na', rot_z(psi_used), total)     # k_c μ
    v = x * np.minimum(1.0, nu_max / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-300))
    v[~moving] = 0.0
    return v


def formation_error(p: Array, p_star: Array) -> Array:
    """Fig. 2(d): each robot's distance ``(N,)`` [m] from the formation ``p*`` (defined up to yaw
    and translation) best fit to ``p`` (2-D Procrustes in xy, the mean in z)."""
    c, c_star = p.mean(axis=0), p_star.mean(axis=0)
    q, q_star = p - c, p_star - c_star
    w, w_star = q[:, 0] + 1j * q[:, 1], q_star[:, 0] + 1j * q_star[:, 1]
    rotation = np.vdot(w_star, w)   # Σ conj(w*) w: its angle is the best yaw
    turn = rotation / abs(rotation) if abs(rotation) > 1e-300 else 1.0
    fit = turn * w_star
    dz = q[:, 2] - q_star[:, 2]
    return np.sqrt(np.abs(w - fit) ** 2 + dz ** 2)
