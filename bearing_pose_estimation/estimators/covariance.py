"""Covariance of the Boughellaba & Tayebi estimate: its linearised error dynamics, one step.

Error of agent i, in the order of ``geometry_msgs/PoseWithCovariance`` (position, then
rotation): ``x_i = (e_i, φ_i)`` with ``e_i = p̂_i − p_i`` [m] (world) and ``R̂_i = exp([φ_i]x)
R_i`` (a rotation error about the world axes [rad]).

Linearising :func:`.boughellaba_tayebi.cascade_step` about the truth (``y_ij = R̂_i b^i_ij ≈
b_ij + φ_i × b_ij + ν_ij``, the neighbour's ``R̂_j b^j_ij ≈ b_ij + φ_j × b_ij + ν'_ij``, each
bearing noise ``ν ~ N(0, σ_b² P_b)``, ``d_ij = ‖p_j − p_i‖``; (23) sums its projectors
unweighted, ``M_i = Σ_j P_{b_ij}``, while ``σ_i`` weighs with ``k_ij``, ``Q_i = Σ_j k_ij P_{b_ij}``)::

    σ_i  ≈ Σ_j k_ij (P_b (φ_i − φ_j) + [b]x (ν_ij − ν'_ij))
    φ_i⁺ = φ_i − h k_R σ_i + w_i,                        w_i ~ N(0, h N_g² I)
    e_i⁺ = e_i − h k_p Σ_j (P_b (e_i − e_j) + d_ij (ν_ij − [b]x φ_i)) + h k_R [p_i]x σ_i

(the last term: ``Q = exp(−h k_R [σ]x)`` turns ``p̂_i`` about the world origin with ``R̂_i``).
So ``x_i⁺ = F_i x_i + Σ_j G_ij x_j + noise``, and each agent propagates

    P_i⁺ = F_i P_i F_iᵀ + W_i + c_i Σ_j G_ij P_j G_ijᵀ

from its own geometry and noise model (``W_i``: the bearing and gyro noise, ``N_g`` the gyro's
angle random walk [rad/√s]) and the covariances ``P_j`` its neighbours send. Solved over the
whole fleet at once, the recursion without ``c_i`` but with the cross-covariances ``E[x_i x_jᵀ]``
is exact to first order (on paper_noisy its NEES is 3.0-3.6 for 3 dof, bench/nees.py). An agent
has neither those cross-covariances nor the neighbours' dynamics, so ``c_i`` stands for them:

- a neighbour's error is slow (correlated over ~1/a), not white: over its own window agent i
  sees it as white noise of density ``2 P_j / (a_i + a_j)``; with ``a_j`` unknown, ``a_j`` is
  taken as agent i's slowest rate and ``a_i`` as its median rate (the eigenvalues of ``k_p M_i``
  and ``k_R Q_i``), so ``2 / (h (a_slow + a_median))``;
- the neighbours' errors are correlated with each other (shared ancestors) in an unknown way:
  covariance intersection with equal weights multiplies by the number of neighbours whose
  covariance is not zero (leaders send zeros), which bounds any correlation.
"""
from __future__ import annotations

import numpy as np

from ..core import so3
from .base import Array, Edges

DOF = 6


def initial_covariance(n: int, position_std: float, attitude_std: float) -> Array:
    """``(n, 6, 6)`` diagonal prior: ``position_std`` [m] and ``attitude_std`` [rad] per axis."""
    diag = np.array([position_std ** 2] * 3 + [attitude_std ** 2] * 3)
    return np.tile(np.diag(diag), (n, 1, 1))


def cascade_jacobians(h: float, edges: Edges, y: Array, dist: Array, p_hat: Array,
                      k_R: float, k_p: float) -> tuple[Array, Array, Array, Array]:
    """The linearised step of the module docstring at the current estimate.

    Args:
        y: ``(E, 3)`` estimated world bearings ``R̂_i b^i_ij`` (unit).
        dist: ``(E,)`` estimated distances ``‖p̂_i − p̂_j‖`` [m].
        p_hat: ``(N, 3)`` the agents' positions (the lever arm of the attitude correction).

    Returns:
        ``F`` ``(N, 6, 6)``, ``G`` ``(E, 6, 6)`` (neighbour j's error into the edge's agent),
        and the maps of the two bearing noises of each edge ``(E, 6, 3)``, own then the
        neighbour's.
    """
    k = edges.k[:, None, None]
    eye = np.eye(3)
    P_b = eye - np.einsum('ea,eb->eab', y, y)
    B = so3.hat(y)                                           # [b]x, (E, 3, 3)
    # (23) sums the projectors unweighted; σ_i weighs its terms with k_ij.
    M = edges.sum_by_agent(P_b.reshape(-1, 9)).reshape(-1, 3, 3)
    Q = edges.sum_by_agent((k * P_b).reshape(-1, 9)).reshape(-1, 3, 3)
    A = edges.sum_by_agent((dist[:, None, None] * B).reshape(-1, 9)).reshape(-1, 3, 3)
    Hp = so3.hat(p_hat)                                      # [p_i]x, (N, 3, 3)
    Hp_e = np.take(Hp, edges.agent, axis=0)
    n = p_hat.shape[0]
    F = np.zeros((n, DOF, DOF))
    F[:, :3, :3] = eye - h * k_p * M
    F[:, :3, 3:] = h * k_p * A + h * k_R * Hp @ Q
    F[:, 3:, 3:] = eye - h * k_R * Q
    G = np.zeros((len(y), DOF, DOF))
    G[:, :3, :3] = h * k_p * P_b
    G[:, :3, 3:] = -h * k_R * Hp_e @ (k * P_b)
    G[:, 3:, 3:] = h * k_R * k * P_b
    own = np.zeros((len(y), DOF, 3))          # ν_ij, agent i's own bearing
    own[:, :3] = -h * k_p * dist[:, None, None] * eye + h * k_R * Hp_e @ (k * B)
    own[:, 3:] = -h * k_R * k * B
    theirs = np.zeros((len(y), DOF, 3))       # ν'_ij, in what neighbour j sent
    theirs[:, :3] = -h * k_R * Hp_e @ (k * B)
    theirs[:, 3:] = h * k_R * k * B
    return F, G, own, theirs


def cascade_covariance(P: Array, h: float, edges: Edges, y: Array, dist: Array, p_hat: Array,
                       P_nbr: Array, k_R: float, k_p: float, bearing_std: float,
                       gyro_noise_density: float) -> Array:
    """``P_i⁺`` of every agent (module docstring) from its ``P`` ``(N, 6, 6)`` and the
    covariances its neighbours sent, ``P_nbr`` ``(E, 6, 6)``."""
    F, G, own, theirs = cascade_jacobians(h, edges, y, dist, p_hat, k_R, k_p)
    n = P.shape[0]
    P_b = np.eye(3) - np.einsum('ea,eb->eab', y, y)
    noise = bearing_std ** 2 * (own @ P_b @ own.transpose(0, 2, 1)
                                + theirs @ P_b @ theirs.transpose(0, 2, 1))
    W = edges.sum_by_agent(noise.reshape(-1, DOF * DOF)).reshape(n, DOF, DOF)
    W[:, 3:, 3:] += h * gyro_noise_density ** 2 * np.eye(3)
    # c_i: the neighbours' errors are slow and correlated with each other (module docstring).
    rates = np.sort(np.concatenate([np.linalg.eigvalsh(np.eye(3) - F[:, :3, :3]),
                                    np.linalg.eigvalsh(np.eye(3) - F[:, 3:, 3:])], axis=1),
                    axis=1) / h      # of k_p M_i and k_R Q_i
    slow = np.maximum(rates[:, 0], 1e-9)
    c = 2.0 / (h * (slow + np.median(rates, axis=1)))
    informative = (np.einsum('eii->e', P_nbr) > 0.0).astype(float)
    c = c * np.maximum(np.bincount(edges.agent, weights=informative, minlength=n), 1.0)
    nbr = np.einsum('e,eab->eab', np.take(c, edges.agent), G @ P_nbr @ G.transpose(0, 2, 1))
    out = F @ P @ F.transpose(0, 2, 1) + W
    out += edges.sum_by_agent(nbr.reshape(-1, DOF * DOF)).reshape(n, DOF, DOF)
    return 0.5 * (out + out.transpose(0, 2, 1))
