"""Tran, Anderson & Ahn (2020): second-order attitude observer with a bearing-only position
observer, in the setting of Boughellaba & Tayebi (leaders 1, 2; followers with ≥ 2 earlier
neighbours; j sends ``R̂_j b^j_ji`` and ``p̂_j``). Equations as corrected in
``shared/ESTIMATORS.md``; no rclpy.

Continuous time, state ``(R̂_i, Ω̃_i, p̂_i)`` with ``Ω̃_i(0) = 0``::

    dR̂_i/dt = R̂_i [ω_i - Ω̃_i]x
    dΩ̃_i/dt = -k_ω Ω̃_i + Σ_j k_ij (R̂_iᵀ d_ij) × b^i_ij  (+ k_c (R̂_iᵀ c) × c^i, two neighbours)
    dp̂_i/dt = -k_p R̂_i Σ_j P_{b^i_ij} R̂_iᵀ (p̂_i - p̂_j) = -k_p Σ_j P_{y_ij} (p̂_i - p̂_j)

with ``d_ij = R̂_j b^j_ij`` (what j sends, sign-flipped) and ``y_ij = R̂_i b^i_ij`` (since
``R P_b Rᵀ = P_{R b}``). For a follower with exactly two neighbours j, k the paper adds the
direction ``c^i = (b^i_ij × b^i_ik)/‖·‖`` (body), ``c = (d_ij × d_ik)/‖·‖`` (world).

Discretisation over a step ``h`` (``ΔR`` the gyro increment)::

    R̂_i ← R̂_i exp(-h Ω̃_i) ΔR_i
    Ω̃_i ← Ω̃_i + h (-k_ω Ω̃_i + torque_i)
    p̂_i ← p̂_i - h k_p Σ_j P_{y_ij} (p̂_i - p̂_j)

Why ``exp(-h Ω̃) ΔR`` in that order: with the truth propagated by the same ``ΔR``, the error
``R̃ = R R̂ᵀ`` then obeys exactly ``R̃⁺ = R̃ exp(h [R̂ Ω̃]x)``, the Lie-Euler step of
``dR̃/dt = R̃ [R̂ Ω̃]x``: the gyro cancels out of the error dynamics and the truth (with
``Ω̃ = 0``) is an exact fixed point, as for :func:`observer.cascade_step`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import so3
from .observer import Edges, bearing_pull

Array = NDArray[np.float64]

__all__ = ['TranGains', 'TranStepResult', 'TwoNeighbourPairs', 'tran_step']


@dataclass(frozen=True)
class TranGains:
    """``k_omega`` (k_ω, damping of Ω̃), ``k_p`` (position), ``k_c`` (the extra direction of
    two-neighbour followers); per-edge ``k_ij`` live in :class:`observer.Edges`. All > 0."""

    k_omega: float = 2.0
    k_p: float = 1.0
    k_c: float = 1.0


@dataclass(frozen=True)
class TwoNeighbourPairs:
    """The followers with exactly two neighbours, as edge index pairs ``(first[m], second[m])``
    owned by agent ``agent[m]`` (edge order fixes the sign of ``c``; both ``c^i`` and ``c`` use
    the same order, so the term does not depend on it)."""

    agent: NDArray[np.intp]
    first: NDArray[np.intp]
    second: NDArray[np.intp]

    @staticmethod
    def of(edges: Edges) -> TwoNeighbourPairs:
        counts = np.bincount(edges.agent, minlength=edges.n_agents)
        owners = np.flatnonzero(counts == 2).astype(np.intp)
        order = np.argsort(edges.agent, kind='stable')  # each agent's edges, in edge order
        start = np.searchsorted(edges.agent[order], owners)
        return TwoNeighbourPairs(agent=owners, first=order[start].astype(np.intp),
                                 second=order[start + 1].astype(np.intp))


@dataclass(frozen=True)
class TranStepResult:
    R_hat: Array        # (N, 3, 3) attitude estimates after the step
    Omega_tilde: Array  # (N, 3) gyro-correction state Ω̃ after the step [rad/s]
    p_hat: Array        # (N, 3) position estimates after the step [m]
    torque: Array       # (N, 3) the innovation driving Ω̃ at the start of the step (body)


def _unit(v: Array) -> Array:
    n = np.sqrt(so3.dot(v, v))
    return v / np.where(n > 0.0, n, 1.0)[:, None]


def tran_step(R_hat: Array, Omega_tilde: Array, p_hat: Array, delta_R: Array, h: float,
              edges: Edges, pairs: TwoNeighbourPairs, b_body: Array, d_world: Array,
              p_hat_nbr: Array, gains: TranGains, reorthonormalize: bool = True
              ) -> TranStepResult:
    """Advance the Tran-Anderson-Ahn observers of all agents by one step ``h``.

    Arguments as in :func:`observer.cascade_step`, plus ``Omega_tilde`` ``(N, 3)`` and the
    two-neighbour ``pairs`` (:meth:`TwoNeighbourPairs.of`).
    """
    R_i = np.take(R_hat, edges.agent, axis=0)
    # (R̂_iᵀ d_ij) × b^i_ij, summed with k_ij.
    d_body = np.einsum('eba,eb->ea', R_i, d_world)
    terms = so3.cross(d_body, b_body)
    if not edges.unit_k:
        terms *= edges.k[:, None]
    torque = edges.sum_by_agent(terms)
    if len(pairs.agent):
        c_body = _unit(so3.cross(b_body[pairs.first], b_body[pairs.second]))
        c_world = _unit(so3.cross(d_world[pairs.first], d_world[pairs.second]))
        c_est = np.einsum('nba,nb->na', np.take(R_hat, pairs.agent, axis=0), c_world)
        torque[pairs.agent] += gains.k_c * so3.cross(c_est, c_body)
    pull = bearing_pull(p_hat, edges, np.einsum('eab,eb->ea', R_i, b_body), p_hat_nbr)

    R_next = so3.matmul(R_hat, so3.exp(-h * Omega_tilde), delta_R)
    if reorthonormalize:
        R_next = so3.reorthonormalize(R_next)
    return TranStepResult(R_hat=R_next,
                          Omega_tilde=Omega_tilde + h * (torque - gains.k_omega * Omega_tilde),
                          p_hat=p_hat - h * gains.k_p * pull, torque=torque)
