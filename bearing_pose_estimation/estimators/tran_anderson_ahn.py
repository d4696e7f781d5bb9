"""Tran, Anderson & Ahn (2020): second-order attitude observer with a bearing-only position
observer, in the setting of Boughellaba & Tayebi (:mod:`.bearing_leaders`).

``method: tran_anderson_ahn``. State ``(R̂_i, Ω̃_i, p̂_i)``, ``Ω̃_i(0) = 0``; notation as in
:mod:`.boughellaba_tayebi`, ``d_ij = R̂_j b^j_ij`` and ``y_ij = R̂_i b^i_ij``::

    dR̂_i/dt = R̂_i [ω_i - Ω̃_i]x
    dΩ̃_i/dt = -k_ω Ω̃_i + Σ_j k_ij (R̂_iᵀ d_ij) × b^i_ij  (+ k_c (R̂_iᵀ c) × c^i, two neighbours)
    dp̂_i/dt = -k_p R̂_i Σ_j P_{b^i_ij} R̂_iᵀ (p̂_i - p̂_j) = -k_p Σ_j P_{y_ij} (p̂_i - p̂_j)

A follower with two neighbours j, k adds the direction ``c^i = (b^i_ij × b^i_ik)/‖·‖`` (world
``c = (d_ij × d_ik)/‖·‖``). (9) needs ``K_i = Σ_j k_ij b_ij b_ijᵀ`` (+ ``k_c c cᵀ``) positive
definite, Lemma 2 distinct eigenvalues. The paper gives no gains; ``k_ω ∈ [1, 3]``, ``k_ij ≈
1-2``, ``k_p = 1`` converge on its cube scenario.

Discretisation over a step ``h`` (``ΔR`` the gyro increment)::

    R̂_i ← R̂_i exp(-h Ω̃_i) ΔR_i
    Ω̃_i ← Ω̃_i + h (-k_ω Ω̃_i + torque_i)
    p̂_i ← p̂_i - h k_p Σ_j P_{y_ij} (p̂_i - p̂_j)

Why ``exp(-h Ω̃) ΔR`` in that order: with the truth propagated by the same ``ΔR``, ``R̃ = R R̂ᵀ``
obeys exactly ``R̃⁺ = R̃ exp(h [R̂ Ω̃]x)`` (Lie-Euler): the gyro cancels out of the error
dynamics and the truth (with ``Ω̃ = 0``) is an exact fixed point.

Moving agents (an extension, as in :mod:`.boughellaba_tayebi`: ``v_i`` fed forward with
``k_v``, discretised with the odometry displacement ``δ_i``)::

    p̂_i ← p̂_i + k_v R̂_i δ_i - h k_p Σ_j P_{y_ij} (p̂_i - p̂_j)

The error ``p̃_i = p_i - p̂_i`` has no ``R̃``, so with ``k_v = 1`` the velocity leaves the term
``(I - R̃_iᵀ) ṗ_i``, which vanishes with the attitude error (whose observer ignores positions):
the paper's position dynamics in the limit, and the truth an exact solution (at ``R̂ = R`` the
prediction moves ``p̂`` as ``p⁺ = p + R δ``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from .base import P_OWN, Array, Edges, StepInputs, gain
from .bearing_leaders import (EIGEN_GAP_REL, BearingLeaderEstimator, CovState, fed_forward,
                              position_step, repeated)
from .covariance import CovarianceModel, tran_jacobians


@dataclass(frozen=True)
class TranGains(CovarianceModel):
    """Gains of Tran et al.'s observers; per-edge ``k_ij`` live in :class:`base.Edges`."""

    k_omega: float = gain(2.0, 'damping k_omega of the gyro correction')
    k_p: float = gain(1.0, 'position gain k_p')
    k_c: float = gain(1.0, 'gain k_c of the third direction of two-neighbour followers')
    k_v: float = gain(1.0, 'odometry feed-forward of moving agents (1: on, 0: off)',
                      zero_allowed=True)
    bias_std: float = gain(0.0, 'bearing noise std [rad] whose projector bias the position '
                           'correction removes (0: off, the paper\'s observer; '
                           'bearing_leaders.position_step)', zero_allowed=True)


@dataclass
class TranState(CovState):
    """Adds Tran et al.'s gyro correction ``Ω̃`` ``(N, 3)`` [rad/s], ``Ω̃(0) = 0``; ``P`` is
    ``(N, 9, 9)``, the error ``(e, φ, Ω̃)`` (:func:`.covariance.tran_jacobians`)."""

    Omega_tilde: Array


@dataclass(frozen=True)
class TwoNeighbourPairs:
    """The followers with exactly two neighbours: edge pairs ``(first[m], second[m])`` of agent
    ``agent[m]`` (in edge order, for both ``c^i`` and ``c``: the term does not depend on it)."""

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


def _unit(v: Array) -> Array:
    n = np.sqrt(so3.dot(v, v))
    return v / np.where(n > 0.0, n, 1.0)[:, None]


def tran_step(R_hat: Array, Omega_tilde: Array, p_hat: Array, delta_R: Array, h: float,
              edges: Edges, pairs: TwoNeighbourPairs, b_body: Array, d_world: Array,
              p_hat_nbr: Array, gains: TranGains, reorthonormalize: bool = True,
              displacement: Array | None = None, p_own: Array | None = None
              ) -> tuple[Array, Array, Array, Array]:
    """One step ``h`` of every agent: ``(R̂, Ω̃, p̂)`` at ``t + h`` and the torque driving Ω̃ at
    t (body frame); arguments as in :func:`.boughellaba_tayebi.cascade_step`, with
    ``Omega_tilde`` ``(N, 3)`` and the two-neighbour ``pairs``."""
    R_i = np.take(R_hat, edges.agent, axis=0)
    # (R̂_iᵀ d_ij) × b^i_ij, summed with k_ij.
    d_body = np.einsum('eba,eb->ea', R_i, d_world)
    torque = edges.sum_by_agent(edges.weighted(so3.cross(d_body, b_body)))
    if len(pairs.agent):
        c_body = _unit(so3.cross(b_body[pairs.first], b_body[pairs.second]))
        c_world = _unit(so3.cross(d_world[pairs.first], d_world[pairs.second]))
        c_est = np.einsum('nba,nb->na', np.take(R_hat, pairs.agent, axis=0), c_world)
        torque[pairs.agent] += gains.k_c * so3.cross(c_est, c_body)
    p_next = position_step(p_hat, edges, np.einsum('eab,eb->ea', R_i, b_body), p_hat_nbr,
                           h * gains.k_p, gains.bias_std,
                           fed_forward(R_hat, displacement, gains.k_v), p_own)
    R_next = so3.matmul(R_hat, so3.exp(-h * Omega_tilde), delta_R)
    if reorthonormalize:
        R_next = so3.reorthonormalize(R_next)
    return (R_next, Omega_tilde + h * (torque - gains.k_omega * Omega_tilde), p_next, torque)


class TranAndersonAhn(BearingLeaderEstimator[TranGains, TranState]):
    method: ClassVar[str] = 'tran_anderson_ahn'
    title: ClassVar[str] = 'Tran, Anderson & Ahn'
    Gains: ClassVar[type] = TranGains
    reference_scenario: ClassVar[str] = 'tran_cube.yaml'
    conditioning_label: ClassVar[str] = 'K_i = Σ_j k_ij b_ij b_ijᵀ, + k_c c cᵀ with two neighbours'
    _pairs: tuple[Edges, TwoNeighbourPairs] | None = None   # a fleet's, computed once

    def initial_state(self, R_hat: Array, p_hat: Array) -> TranState:
        R_hat = np.array(R_hat, dtype=float)
        return TranState(R_hat=R_hat, p_hat=np.array(p_hat, dtype=float),
                         P=self.prior(R_hat.shape[0], dof=9),
                         Omega_tilde=np.zeros((R_hat.shape[0], 3)))

    def pairs(self, edges: Edges) -> TwoNeighbourPairs:
        if self._pairs is None or self._pairs[0] is not edges:
            self._pairs = (edges, TwoNeighbourPairs.of(edges))
        return self._pairs[1]

    def step(self, x: TranState, h: float, inputs: StepInputs,
             reorthonormalize: bool = True) -> tuple[TranState, dict[str, Array]]:
        d_world, p_nbr = self.neighbour_terms(inputs)
        g = self.gains
        pairs = self.pairs(inputs.edges)
        R_hat, Omega, p_hat, torque = tran_step(
            x.R_hat, x.Omega_tilde, x.p_hat, inputs.delta_R, h, inputs.edges,
            pairs, inputs.edge['bearings'], d_world, p_nbr, g, reorthonormalize,
            displacement=inputs.displacement, p_own=inputs.edge.get(P_OWN))
        P = self.covariance_step(
            x, h, inputs, p_nbr, fed_forward(x.R_hat, inputs.displacement, g.k_v),
            lambda y, dist: tran_jacobians(h, inputs.edges, y, dist, x.R_hat, pairs, g.k_omega,
                                           g.k_p, g.k_c))
        return TranState(R_hat=R_hat, p_hat=p_hat, P=P, Omega_tilde=Omega), {'innovation': torque}

    def conditioning(self, bearings: Array, k: Array) -> Array:
        """``K_i = Σ_j k_ij b_ij b_ijᵀ`` (+ ``k_c c cᵀ``, ``c = b_ij × b_ik``, two neighbours)."""
        K = super().conditioning(bearings, k)
        if len(bearings) == 2:
            c = np.cross(bearings[0], bearings[1])
            if np.linalg.norm(c) > 0:
                K += self.gains.k_c * np.outer(c, c) / (c @ c)
        return K

    def conditioning_problem(self, eig: Array) -> str | None:
        eigs = '{' + ', '.join(f'{e:.3g}' for e in eig) + '}'
        if eig[0] <= EIGEN_GAP_REL * max(eig[-1], 1e-300):
            return (f'K_i = Σ k_ij b_ij b_ijᵀ is singular (eigenvalues {eigs}): its bearings '
                    'are coplanar, so Tran et al.\'s attitude observer cannot converge (K_i '
                    'must be positive definite, (9))')
        if repeated(eig):
            return (f'K_i = Σ k_ij b_ij b_ijᵀ (+ k_c c cᵀ) has repeated eigenvalues {eigs}: '
                    'Tran et al.\'s Lemma 2 hypothesis fails (convergence is then not '
                    'guaranteed)')
        return None

    def conditioning_fix(self, eig: Array, first_neighbour: str, n_neighbours: int) -> str:
        if eig[0] <= EIGEN_GAP_REL * max(eig[-1], 1e-300):
            return 'add a neighbour out of the plane of the current ones'
        return (super().conditioning_fix(eig, first_neighbour, n_neighbours)
                + (' or another gains.k_c' if n_neighbours == 2 else ''))
