"""Covariance of the leader-follower estimates: their linearised error dynamics, one step,
written out for Boughellaba & Tayebi (Tran et al.: :func:`tran_jacobians`). Error of agent i,
in the order of ``geometry_msgs/PoseWithCovariance``: ``x_i = (e_i, φ_i)``, ``e_i = p̂_i − p_i``
[m] (world) and ``R̂_i = exp([φ_i]x) R_i`` (about the world axes [rad]).

Linearising :func:`.boughellaba_tayebi.cascade_step` about the truth (``R̂_i b^i_ij ≈ b_ij +
φ_i × b_ij + ν_ij``, ``R̂_j b^j_ij ≈ b_ij + φ_j × b_ij + ν'_ij``, ``ν ~ N(0, σ_b² P_b)``, ``d_ij =
‖p_j − p_i‖``; (23) sums ``M_i = Σ_j P_{b_ij}``, ``σ_i`` weighs ``Q_i = Σ_j k_ij P_{b_ij}``)::

    σ_i  ≈ Σ_j k_ij (P_b (φ_i − φ_j) + [b]x (ν_ij − ν'_ij))
    φ_i⁺ = φ_i − h k_R σ_i + w_i,                        w_i ~ N(0, h N_g² I)
    e_i⁺ = e_i − h k_p Σ_j (P_b (e_i − e_j) + d_ij (ν_ij − [b]x φ_i)) + h k_R [p_i]x σ_i

(the last term: ``Q = exp(−h k_R [σ]x)`` turns ``p̂_i`` about the world origin with ``R̂_i``).
So ``x_i⁺ = F_i x_i + Σ_j G_ij x_j + noise``, and each agent propagates

    P_i⁺ = F_i P_i F_iᵀ + W_i + c_i Σ_j G_ij P_j G_ijᵀ

from its own geometry and noise model (``W_i``; ``N_g`` the gyro's angle random walk [rad/√s])
and the ``P_j`` its neighbours send. With the fleet's cross-covariances and no ``c_i`` this is
exact to first order; an agent has neither those nor its neighbours' dynamics, so ``c_i``:

- a neighbour's error is slow (correlated over ~1/a): over agent i's window, white noise of
  density ``2 P_j / (a_i + a_j)``, with ``a_j`` taken as i's slowest rate and ``a_i`` as its
  median (of ``k_p M_i``'s and ``k_R Q_i``'s eigenvalues): ``2 / (h (a_slow + a_median))``;
- the neighbours' errors are correlated with each other (shared ancestors): covariance
  intersection with equal weights multiplies by the number of neighbours whose covariance is not
  zero (leaders send zeros), which bounds any correlation.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core import so3
from .base import POSE_COVARIANCE, Array, Channel, Edges, gain

EYE3 = np.eye(3)
DOF = 6     # what the pose covariance covers, what neighbours send: (e_i, φ_i)
# Optional: a neighbour whose covariance is lost still corrects the estimate; the covariance
# then takes the prior for it (Estimator.missing).
POSE_COV = Channel('pose_cov', per='agent', frame='estimate', shape=(DOF, DOF), optional=True,
                   topic='pose', kind=POSE_COVARIANCE,
                   doc="P_j, the covariance of the sender's pose estimate (position, then "
                       'rotation; covariance.py, de_carli_covariance.py)')
# F, G, own, theirs, rates: a method's linearised step (cascade_jacobians)
Jacobians = tuple[Array, Array, Array, Array, Array]


@dataclass(frozen=True, kw_only=True)
class PoseCovarianceModel:
    """The gains every method's covariance reads (a keyword-only base of the methods' gains): the
    motion sensors' noise, by default a simulation's ``noise:`` and ``sensors:`` (else 0), and
    the prior. De Carli et al.'s excitation monitor reads the odometry's too."""

    gyro_noise_density: float = gain(0.0, 'gyro angle random walk [rad/sqrt(s)] (gyro std / '
                                     'sqrt(IMU rate)), for the covariance', zero_allowed=True,
                                     model=True)
    odometry_noise_density: float = gain(0.0, 'odometry velocity random walk [m/sqrt(s)] '
                                         '(velocity std / sqrt(odometry rate)), for the '
                                         'covariance', zero_allowed=True, model=True)
    initial_position_std: float = gain(2.0, 'std of the initial position estimate [m], the '
                                       "covariance's prior", model=True)
    initial_attitude_std: float = gain(1.0, 'std of the initial attitude estimate [rad], the '
                                       "covariance's prior", model=True)


@dataclass(frozen=True, kw_only=True)
class CovarianceModel(PoseCovarianceModel):
    """The leader-follower methods' model: the motion sensors' and the bearings' noise."""

    bearing_std: float = gain(0.0, 'bearing noise std [rad] per component, for the covariance',
                              zero_allowed=True, model=True)


def initial_covariance(n: int, position_std: float, attitude_std: float, dof: int = DOF) -> Array:
    """``(n, dof, dof)`` diagonal prior; 0 beyond the pose (true at the start, e.g. ``Ω̃ = 0``)."""
    diag = np.zeros(dof)
    diag[:3], diag[3:6] = position_std ** 2, attitude_std ** 2
    return np.tile(np.diag(diag), (n, 1, 1))


def _edge_terms(edges: Edges, y: Array,
                dist: Array) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Per edge ``k_ij``, ``P_b``, ``B = [b]x`` ``(E, 3, 3)``; per agent ``M_i = Σ_j P_b`` (23),
    ``Q_i = Σ_j k_ij P_b`` (σ_i) and ``A_i = Σ_j d_ij [b]x``, in one sparse product (~30 µs)."""
    k = edges.k[:, None, None]
    P_b = EYE3 - np.einsum('ea,eb->eab', y, y)
    B = so3.hat(y)
    per_edge = (P_b, k * P_b, dist[:, None, None] * B)
    total = edges.sum_by_agent(np.concatenate([t.reshape(-1, 9) for t in per_edge], axis=1))
    M, Q, A = (total[:, 9 * m:9 * (m + 1)].reshape(-1, 3, 3) for m in range(3))
    return k, P_b, B, M, Q, A


def cascade_jacobians(h: float, edges: Edges, y: Array, dist: Array, p_hat: Array,
                      k_R: float, k_p: float) -> Jacobians:
    """The linearised step of the module docstring at the current estimate: ``y`` ``(E, 3)``
    the unit ``R̂_i b^i_ij``, ``dist`` ``(E,)`` ``‖p̂_i − p̂_j‖`` [m], ``p_hat`` ``(N, 3)`` the
    lever arm the attitude correction turns about the origin (moved by the odometry fed
    forward). Returns ``F`` ``(N, 6, 6)``, ``G`` ``(E, 6, 6)`` (neighbour j's error into the
    edge's agent), the maps ``(E, 6, 3)`` of the edge's own and the neighbour's bearing noise,
    and the decay rates ``(N, 6)``, the eigenvalues of ``k_p M_i`` and ``k_R Q_i``."""
    k, P_b, B, M, Q, A = _edge_terms(edges, y, dist)
    Hp = so3.hat(p_hat)                                      # [p_i]x, (N, 3, 3)
    Hp_e = np.take(Hp, edges.agent, axis=0)
    n = p_hat.shape[0]
    F = np.zeros((n, DOF, DOF))
    F[:, :3, :3] = EYE3 - h * k_p * M
    F[:, :3, 3:] = h * k_p * A + h * k_R * Hp @ Q
    F[:, 3:, 3:] = EYE3 - h * k_R * Q
    G = np.zeros((len(y), DOF, DOF))
    G[:, :3, :3] = h * k_p * P_b
    G[:, :3, 3:] = -h * k_R * Hp_e @ (k * P_b)
    G[:, 3:, 3:] = h * k_R * k * P_b
    own = np.zeros((len(y), DOF, 3))          # ν_ij, agent i's own bearing
    own[:, :3] = -h * k_p * dist[:, None, None] * EYE3 + h * k_R * Hp_e @ (k * B)
    own[:, 3:] = -h * k_R * k * B
    theirs = np.zeros((len(y), DOF, 3))       # ν'_ij, in what neighbour j sent
    theirs[:, :3] = -h * k_R * Hp_e @ (k * B)
    theirs[:, 3:] = h * k_R * k * B
    lam = np.linalg.eigvalsh(np.concatenate([k_p * M, k_R * Q]))   # one call for both
    return F, G, own, theirs, np.concatenate([lam[:n], lam[n:]], axis=1)


def propagate(P: Array, h: float, edges: Edges, y: Array, P_nbr: Array, bearing_std: float,
              gyro_noise_density: float, jacobians: Jacobians,
              moved: Array | None = None, odometry_noise_density: float = 0.0,
              held: Array | None = None) -> Array:
    """``P_i⁺ = F P Fᵀ + W + c_i Σ_j G P_j Gᵀ`` of every agent (module docstring) from ``P``
    ``(N, d, d)``, the neighbours' ``P_nbr`` ``(E, 6, 6)`` and the method's ``jacobians``. Moving
    agents: ``moved`` ``(N, 3)``, the fed-forward ``k_v R̂_i δ_i`` [m] (adds ``−[R̂ δ]x`` to
    ``∂e⁺/∂φ``), and the odometry noise ``h N_v² I``. ``held`` ``(E, 2)``: the steps each bearing
    serves (:data:`base.HELD`): m equal draws add up to m² σ², m fresh ones to m σ²."""
    F, G, own, theirs, rates = jacobians
    if moved is not None:
        F = F.copy()
        F[:, :3, 3:6] -= so3.hat(moved)
    n, d = P.shape[0], P.shape[1]
    P_b = EYE3 - np.einsum('ea,eb->eab', y, y)
    m_own, m_theirs = (1.0, 1.0) if held is None else (held[:, 0, None, None],
                                                        held[:, 1, None, None])
    noise = bearing_std ** 2 * (m_own * own @ P_b @ own.transpose(0, 2, 1)
                                + m_theirs * theirs @ P_b @ theirs.transpose(0, 2, 1))
    # c_i: the neighbours' errors are slow and correlated with each other (module docstring).
    rates = np.sort(rates, axis=1)
    r = rates.shape[1]
    slow = np.maximum(rates[:, 0], 1e-9)
    median = 0.5 * (rates[:, (r - 1) // 2] + rates[:, r // 2])   # np.median: 10x the cost
    c = 2.0 / (h * (slow + np.maximum(median, slow)))
    informative = (np.einsum('eii->e', P_nbr) > 0.0).astype(float)
    c = c * np.maximum(np.bincount(edges.agent, weights=informative, minlength=n), 1.0)
    per_edge = noise + np.take(c, edges.agent)[:, None, None] * (G @ P_nbr @ G.transpose(0, 2, 1))
    out = F @ P @ F.transpose(0, 2, 1)
    out += edges.sum_by_agent(per_edge.reshape(-1, d * d)).reshape(n, d, d)
    out[:, 3:6, 3:6] += h * gyro_noise_density ** 2 * EYE3
    if moved is not None:
        out[:, :3, :3] += h * odometry_noise_density ** 2 * EYE3
    return 0.5 * (out + out.transpose(0, 2, 1))


def tran_jacobians(h: float, edges: Edges, y: Array, dist: Array, R_hat: Array,
                   pairs: Any, k_omega: float, k_p: float, k_c: float) -> Jacobians:
    """Tran et al.'s step (:func:`.tran_anderson_ahn.tran_step`) linearised about the truth,
    error ``(e_i, φ_i, Ω̃_i)`` (``Ω̃`` in the body frame; its true value is 0)::

        φ_i⁺ = φ_i − h R̂_i Ω̃_i + w_i
        Ω̃_i⁺ = (1 − h k_ω) Ω̃_i + h R̂_iᵀ (σ_i + σ_c,i)
        e_i⁺ = e_i − h k_p Σ_j (P_b (e_i − e_j) + d_ij (ν_ij − [b]x φ_i))

    with ``σ_i`` of the module docstring and, for two-neighbour followers, ``c = unit(b_1 ×
    b_2)``: with ``s = ‖b_1 × b_2‖``, ``L_1 = −[b_2]x / s``, ``L_2 = [b_1]x / s`` and ``δ_k =
    −[b_k]x (φ_i − φ_jk) + ν_k − ν'_k``, ``σ_c = k_c [c]x (L_1 δ_1 + L_2 δ_2)``. Returns as
    :func:`cascade_jacobians`, 9 rows; the rates: ``k_p M_i``'s and the real parts of the roots
    of ``s² + k_ω s + λ = 0`` for each eigenvalue λ of ``Q_i`` (+ ``k_c P_c``), the attitude
    loop being ``φ̈ + k_ω φ̇ + Q φ = 0`` (with ``R̂`` frozen over the decay)."""
    k, P_b, B, M, Q, A = _edge_terms(edges, y, dist)
    # σ's maps per edge: of φ_i (Q), of φ_j (Gφ), of ν (S) and ν' (−S); the pairs add σ_c.
    Gphi = -k * P_b
    S = k * B
    if len(pairs.agent):
        y1, y2 = y[pairs.first], y[pairs.second]
        cr = so3.cross(y1, y2)
        s = np.linalg.norm(cr, axis=1)
        s = np.where(s > 0.0, s, 1.0)[:, None, None]
        C = so3.hat(cr / s[:, :, 0])
        for first, L, b in ((pairs.first, -so3.hat(y2) / s, y1),
                            (pairs.second, so3.hat(y1) / s, y2)):
            CL = k_c * C @ L
            Gphi[first] += CL @ so3.hat(b)
            S[first] += CL
        Q = Q.copy()
        Q[pairs.agent] += k_c * (EYE3 - np.einsum('na,nb->nab', cr, cr) / s ** 2)
    n = R_hat.shape[0]
    Rt = R_hat.transpose(0, 2, 1)
    Rt_e = np.take(Rt, edges.agent, axis=0)
    F = np.zeros((n, 9, 9))
    F[:, :3, :3] = EYE3 - h * k_p * M
    F[:, :3, 3:6] = h * k_p * A
    F[:, 3:6, 3:6] = EYE3
    F[:, 3:6, 6:] = -h * R_hat
    F[:, 6:, 3:6] = h * Rt @ Q
    F[:, 6:, 6:] = (1.0 - h * k_omega) * EYE3
    E = len(y)
    G = np.zeros((E, 9, DOF))
    G[:, :3, :3] = h * k_p * P_b
    G[:, 6:, 3:] = h * Rt_e @ Gphi
    own = np.zeros((E, 9, 3))
    own[:, :3] = -h * k_p * dist[:, None, None] * EYE3
    own[:, 6:] = h * Rt_e @ S
    theirs = np.zeros((E, 9, 3))
    theirs[:, 6:] = -h * Rt_e @ S
    lam = np.linalg.eigvalsh(np.concatenate([k_p * M, Q]))   # one call for both
    root = np.sqrt(np.maximum(k_omega ** 2 - 4.0 * lam[n:], 0.0))
    rates = np.concatenate([lam[:n], 0.5 * (k_omega - root), 0.5 * (k_omega + root)], axis=1)
    return F, G, own, theirs, rates
