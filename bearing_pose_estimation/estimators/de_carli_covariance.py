"""Covariance of De Carli et al.'s estimates: the step of :mod:`.de_carli` linearised.

Robot i's pose error in the estimation frame, ``e_i = p̂_i − p_i`` [m] and ``θ_i = ψ̂_i − ψ_i``
[rad] (roll and pitch are known: 0), stored as the ``geometry_msgs/PoseWithCovariance`` 6x6
(:data:`POSE`), after the exact alignment (de-carli-2024.md §6): the common yaw and translation
that nothing observes removed.

**Each pair** ``{o, x}`` (owner o; de_carli.py's stage 1) has its own error ``s = (E_out, ζ,
E_in)``, complex numbers as real pairs: ``E_out = ᵒP̂_ox − ᵒP_ox`` (the owner's horizontal
relative position), ``ζ = ẑ_ox − z_ox`` (the relative yaw, unnormalised) and, two-way, ``E_in =
ˣP̂_xo − ˣP_xo``. Linearising (7)-(8) with the noise of the measurements ``ν, ν'``, of the
odometry displacements ``η_o, η_x`` and of the gyros' yaw increments ``γ_o, γ_x``::

    ζ'     = ζ − k_ψ (conj(δ'_x) (E_out − ν) + δ'_o conj(E_in − ν'))
    E_out⁺ = r_o ((1 − h k_pe) E_out + h k_pe ν + δ_x ζ' − η_o + z η_x) − ι γ_o P̂_out⁺
    ζ⁺     = r_x conj(r_o) ζ' + ι (γ_x − γ_o) ẑ⁺
    E_in⁺  = r_x ((1 − h k_pe) E_in + h k_pe ν' + δ_o conj(ζ') − η_x + conj(z) η_o) − ι γ_x P̂_in⁺

(``r = e^{−ιΔψ}``; a missing measurement drops its terms). It depends on the odometry and the
gains only: both robots of a pair propagate the same covariance (no message), which grows while
the pair is not excited (Theorem 1). The relative yaw's angle error is ``ε_ox = Im(ζ
conj(ẑ))/|ẑ|²``.

**The robot**, per step (stage 3 at its ticks, stage 2 at its ticks, then dead reckoning), with
``v_ij = e_3 × (p̂_j − p̂_i)`` and the fresh measured terms ``c_ij = [i senses j] + [j senses i]``::

    e'  = e_i − h₃ k_p Σ_j (c_ij (e_i − e_j) + ([i senses j] θ_i + [j senses i] θ_j) v_ij
                              + [i senses j] R̂_i ν_ij − [j senses i] R̂_j ν'_ji)       (21)
    θ'  = (|ẑ_i| θ_i + c Σ_j |ẑ_j| (θ_j − ε_ij)) / (|ẑ_i| + c Σ_j |ẑ_j|)             (13)
    e⁺  = e' + θ' e_3 × R̂_i δ_i + R̂_i η_i,     θ⁺ = θ' + γ_i

over the excited pairs of stage 2. As in covariance.py, the neighbours' errors ``(e_j, θ_j)``
and the pairs' ``ε_ij`` enter as slow inputs: white noise of ``1/ρ`` times their covariance per
tick of their stage, ``ρ`` its own decay per tick (``h₃ k_p Σ c_ij`` for the position, ``c Σ
|ẑ_j| / (|ẑ_i| + c Σ |ẑ_j|)`` for the yaw: ``2/(ρ_i + ρ_j)`` with ``ρ_j = ρ_i``). So does the
robot's own yaw in its position (it follows the pairs' slow relative yaws). No covariance
intersection: a consensus's neighbours share no ancestors. NEES: README, "The covariance" (the
neighbours' yaws as very slow inputs, the own yaw through the correlation: 3.83, 1.9-7.7).
"""
from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from .base import Array, Edges

Num = NDArray[Any]   # complex or boolean arrays

# The pose covariance's rows of (e, θ): x, y, z and yaw.
POSE = np.array([0, 1, 2, 5])
PAIR = 6            # (E_out, ζ, E_in), real and imaginary parts
CONJ = np.diag([1.0, -1.0])
# A relative yaw's error is at most a half-turn: the prior of ζ per component.
ZETA_PRIOR_MAX = 1.0


def cmat(a: Num) -> Array:
    """``(..., 2, 2)``: the real matrix of the multiplication by the complex ``a``."""
    a = np.asarray(a, dtype=complex)
    out = np.empty(a.shape + (2, 2))     # filled in place: np.stack costs 4x as much here
    out[..., 0, 0] = out[..., 1, 1] = a.real
    out[..., 1, 0] = a.imag
    out[..., 0, 1] = -a.imag
    return out


def times_i(a: Num) -> Array:
    """``ι a`` as real pairs ``(..., 2)``: the column a scalar yaw error multiplies."""
    a = np.asarray(a, dtype=complex)
    out = np.empty(a.shape + (2,))
    out[..., 0], out[..., 1] = -a.imag, a.real
    return out


def pair_prior(k: int, relative_std: float, yaw_std: float) -> Array:
    """``(k, 6, 6)``: a new pair's covariance, from one measurement and two initial yaws."""
    P = np.zeros((k, PAIR, PAIR))
    P[:, [0, 1, 4, 5], [0, 1, 4, 5]] = relative_std ** 2
    P[:, [2, 3], [2, 3]] = min(2.0 * yaw_std ** 2, ZETA_PRIOR_MAX)
    return P


def pair_maps(h: float, k_pe: float, k_psi: float, z: Num, z_next: Num,
              d_reg_x: Num, d_reg_o: Num, delta_o: Num, delta_x: Num, dpsi_o: Num,
              dpsi_x: Num, P_out: Num, P_in: Num, out_ok: Num, in_ok: Num,
              two_way: Num) -> tuple[Array, Array]:
    """The pairs' linearised step (module docstring), ``s⁺ = M s + N w`` with ``M`` ``(K, 6, 6)``
    and ``N`` ``(K, 6, 10)`` the map of ``w = (ν, ν', η_o, η_x, γ_o, γ_x)``; per pair ``(K,)``, in
    the owner's orientation: the relative yaw before and after, the regressors ``δ'`` (previous
    step), this step's horizontal displacements and yaw increments, the relative positions the
    gyro noise turns (the measurements: their change is of second order) and the flags."""
    K = len(z)
    f_out, f_in = out_ok.astype(float), (in_ok & two_way).astype(float)
    # The correction of ζ (8), a map of s and of the noise w = (ν, ν', η_o, η_x, γ_o, γ_x).
    A = np.tile(np.eye(PAIR), (K, 1, 1))
    Cx = k_psi * f_out[:, None, None] * cmat(np.conj(d_reg_x))
    Co = k_psi * f_in[:, None, None] * (cmat(d_reg_o) @ CONJ)
    A[:, 2:4, 0:2] = -Cx
    A[:, 2:4, 4:6] = -Co
    B = np.zeros((K, PAIR, 10))
    B[:, 2:4, 0:2] = Cx
    B[:, 2:4, 2:4] = Co
    # The prediction (7) of the corrected state.
    r_o, r_x = cmat(np.exp(-1j * dpsi_o)), cmat(np.exp(-1j * dpsi_x))
    Fp = np.zeros((K, PAIR, PAIR))
    Fp[:, 0:2, 0:2] = r_o * (1.0 - h * k_pe * f_out)[:, None, None]
    Fp[:, 0:2, 2:4] = r_o @ cmat(delta_x)
    Fp[:, 2:4, 2:4] = cmat(np.exp(1j * (dpsi_x - dpsi_o)))
    Fp[:, 4:6, 4:6] = r_x * (1.0 - h * k_pe * f_in)[:, None, None]
    Fp[:, 4:6, 2:4] = r_x @ cmat(delta_o) @ CONJ
    D = np.zeros((K, PAIR, 10))
    D[:, 0:2, 0:2] = h * k_pe * f_out[:, None, None] * r_o
    D[:, 4:6, 2:4] = h * k_pe * f_in[:, None, None] * r_x
    D[:, 0:2, 4:6] = -r_o
    D[:, 0:2, 6:8] = r_o @ cmat(z)
    D[:, 4:6, 6:8] = -r_x * two_way[:, None, None]
    D[:, 4:6, 4:6] = (r_x @ cmat(np.conj(z))) * two_way[:, None, None]
    D[:, 0:2, 8] = -times_i(P_out)
    D[:, 2:4, 8] = -times_i(z_next)
    D[:, 2:4, 9] = times_i(z_next)
    D[:, 4:6, 9] = -times_i(P_in) * two_way[:, None]
    return Fp @ A, Fp @ B + D


def pair_step(P: Array, maps: tuple[Array, Array], two_way: Num, relative_var: float,
              odometry_var: float, gyro_var: float) -> Array:
    """One step of the pairs' covariances ``P`` ``(K, 6, 6)`` with their :func:`pair_maps`
    (``*_var``: per component and step)."""
    M, N = maps
    var = np.array([relative_var] * 4 + [odometry_var] * 4 + [gyro_var] * 2)
    out = M @ P @ M.transpose(0, 2, 1) + (N * var) @ N.transpose(0, 2, 1)
    out[~two_way, 4:6, :] = 0.0      # a one-way pair has no E_in
    out[~two_way, :, 4:6] = 0.0
    return 0.5 * (out + out.transpose(0, 2, 1))


def yaw_error_var(P: Array, z: Num) -> Array:
    """``(K,)``: the variance of the relative yaw's angle, ``Im(ζ conj(z))/|z|²``."""
    z = np.asarray(z, dtype=complex)
    row = times_i(z) / np.maximum(np.abs(z) ** 2, 1e-24)[:, None]
    return np.einsum('ka,kab,kb->k', row, P[:, 2:4, 2:4], row)


class RobotMaps(NamedTuple):
    """The robots' linearised step (module docstring): the mid-step state ``(e', θ')`` is
    ``F x_i + Σ_j G x_j + eps ε_ij + noise``, then ``x⁺ = C (e', θ') + (R̂ η_i, γ_i)``."""

    F: Array          # (N, 4, 4) of the robot's own (e_i, θ_i)
    G: Array          # (E, 4, 4) of the neighbour's (e_j, θ_j)
    eps: Array        # (E, 4) of the pair's relative yaw error ε_ij
    C: Array          # (N, 4, 4) dead reckoning with the new yaw
    own_noise: Array  # (N, 4, 4) the relative-position measurements' covariance in (e', θ')
    rho: Array        # (N, 2) each stage's decay per tick: position, yaw (0: no tick)


def robot_maps(edges: Edges, h3: float, k_p: float, position: bool, c_yaw: float | None,
               d_nbr: Array, y_term: Array, m_term: Array, z_own: Num, z_nbr: Num,
               active: Array, moved: Array | None, relative_var: float) -> RobotMaps:
    """:class:`RobotMaps` of a step: ``position`` at a stage-3 tick, ``c_yaw`` stage 2's ``c =
    h₂ k_z`` at its ticks (else None); per edge ``d_nbr`` ``p̂_j − p̂_i``, the fresh terms
    ``y_term`` (i senses j), ``m_term`` (j senses i), ``active`` (excited); ``moved`` ``R̂_i δ_i``
    (None: no odometry). The measurement noise is isotropic: ``R̂`` drops out."""
    n, E = len(z_own), len(edges.agent)
    ag = edges.agent
    eye = np.eye(3)
    v = np.zeros((E, 3))                # e_3 × (p̂_j − p̂_i)
    v[:, :2] = times_i(d_nbr[:, 0] + 1j * d_nbr[:, 1])
    F = np.tile(np.eye(4), (n, 1, 1))
    G = np.zeros((E, 4, 4))
    own_noise = np.zeros((n, 4, 4))
    eps = np.zeros((E, 4))
    rho = np.zeros((n, 2))
    if position:
        cnt = y_term + m_term
        rho[:, 0] = h3 * k_p * np.bincount(ag, weights=cnt, minlength=n)
        F[:, 0:3, 0:3] = (1.0 - rho[:, 0])[:, None, None] * eye
        F[:, 0:3, 3] = -h3 * k_p * edges.sum_by_agent(y_term[:, None] * v)
        G[:, 0:3, 0:3] = (h3 * k_p * cnt)[:, None, None] * eye
        G[:, 0:3, 3] = -h3 * k_p * m_term[:, None] * v
        # ν (own) and ν' (the neighbour's): white, isotropic per component.
        noise = relative_var * (h3 * k_p) ** 2 * cnt
        own_noise[:, 0:3, 0:3] = np.bincount(ag, weights=noise, minlength=n)[:, None, None] * eye
    if c_yaw is not None:
        w_own = np.abs(z_own)
        w = c_yaw * np.abs(z_nbr) * active
        total = np.maximum(w_own + np.bincount(ag, weights=w, minlength=n), 1e-300)
        F[:, 3, 3] = w_own / total
        rho[:, 1] = 1.0 - w_own / total
        G[:, 3, 3] = w / total[ag]
        eps[:, 3] = -w / total[ag]
    C = np.tile(np.eye(4), (n, 1, 1))
    if moved is not None:
        C[:, 0:2, 3] = times_i(moved[:, 0] + 1j * moved[:, 1])
    return RobotMaps(F, G, eps, C, own_noise, rho)


def robot_step(P: Array, P_nbr: Array, edges: Edges, maps: RobotMaps, eps_var: Array,
               odometry: bool, odometry_var: float, gyro_var: float) -> Array:
    """One step of the robots' pose covariances ``P`` ``(N, 6, 6)`` from the neighbours'
    ``P_nbr`` ``(E, 6, 6)``, the step's maps and the pairs' relative-yaw variances ``eps_var``
    ``(E,)`` (``*_var``: per component and step)."""
    F, G, eps, C, own_noise, rho = maps
    n, E = P.shape[0], len(edges.agent)
    ag = edges.agent
    # The slow inputs (module docstring): 1/ρ times their covariance per tick of the stage
    # they enter; the robot's own yaw in its position is one of them, so F loses that column
    # (its correlation with the fast consensus that F describes would average it away).
    inv = 1.0 / np.maximum(rho, 1e-12)
    row = np.sqrt(inv[:, [0, 0, 0, 1]])   # per row of (e', θ')
    G = np.take(C, ag, axis=0) @ (G * np.take(row, ag, axis=0)[:, :, None])
    eps = np.einsum('eab,eb->ea', np.take(C, ag, axis=0), eps * np.take(row, ag, axis=0))
    own_yaw = F[:, 0:3, 3].copy()
    F = F.copy()
    F[:, 0:3, 3] = 0.0
    F = C @ F
    Pn = P_nbr[:, POSE[:, None], POSE]
    Pi = P[:, POSE[:, None], POSE]
    per_edge = G @ Pn @ G.transpose(0, 2, 1) + eps_var[:, None, None] * np.einsum(
        'ea,eb->eab', eps, eps)
    out4 = F @ Pi @ F.transpose(0, 2, 1) + C @ own_noise @ C.transpose(0, 2, 1)
    out4[:, 0:3, 0:3] += (inv[:, 0] * Pi[:, 3, 3])[:, None, None] * np.einsum(
        'na,nb->nab', own_yaw, own_yaw)
    out4 += edges.sum_by_agent(per_edge.reshape(E, 16)).reshape(n, 4, 4)
    if odometry:
        out4[:, 0:3, 0:3] += odometry_var * np.eye(3)
    out4[:, 3, 3] += gyro_var
    out = np.zeros_like(P)
    out[:, POSE[:, None], POSE] = 0.5 * (out4 + out4.transpose(0, 2, 1))
    return out
