"""Boughellaba & Tayebi: cascaded attitude/position observer from gyros and bearings.

``method: boughellaba_tayebi`` (the default), in the setting of :mod:`.bearing_leaders`.
Notation: ``[x]x`` is the skew matrix of ``x``; ``P_x = I - x xᵀ/‖x‖²``; ``R̃_i = R_i R̂_iᵀ``.

Equations (3), (23) and their step: README, "The estimator, and how it is discretised". The
position observer is the paper's v2 form, with the estimated world bearing ``R̂_i b^i_ij`` in
the projector (``R̂_i P_{b^i_ij} R̂_iᵀ = P_{R̂_i b^i_ij}``); v1's, with the unknown world bearing
``b_ij``, does not converge (position error near 2.4 on the paper's scenario).

The term ``-k_R [σ_i]x p̂_i`` cancels the attitude correction in ``d(R̃_i p̂_i)/dt``; the
position error is ``p̃_i = p_i - R̃_i p̂_i`` (v1 writes ``R̂_i``: a typo), while ``p̂_i`` itself
converges to ``p_i``; ``dR̃_i/dt = k_R R̃_i [σ_i]x``. Lemma 1 needs three distinct eigenvalues
of ``M_i = Σ_j k_ij b_ij b_ijᵀ`` (a warning: the paper's own agent 8 has {0, 1, 1} and
converges); the paper's (13) is off by ½ (``psi(R̃)ᵀ psi(M R̃) = ½ psi(R̃)ᵀ Q psi(R̃)``, ``Q =
tr(M) I - M``).

Moving agents (an extension: the paper's positions are static): the odometry's body velocity
``v_i`` is fed forward with ``k_v`` (1, the default; 0: the paper's observer), ``+ k_v R̂_i v_i``
in (23'), discretised with the odometry's displacement ``δ_i = R_i(t)ᵀ (p_i(t+h) - p_i(t))`` and
``Q = exp(-h k_R [σ_i]x)``::

    p̂_i ← Q (p̂_i + k_v R̂_i δ_i - h k_p Σ_j P_{R̂_i b^i_ij} (p̂_i - p̂_j))

With ``k_v = 1``, ``p⁺ = p + R δ`` and ``R̃⁺ = R̃ Qᵀ``: ``p̃⁺ = p + R δ - R̃ (p̂ + R̂ δ - h k_p
Σ) = p̃ + h k_p R̃ Σ``, the static recursion exactly, whatever the motion; without it the
estimate lags (a floor of order ``|v| / k_p``). The bearings must stay non-collinear along the
motion (``bearing-pose check`` samples it).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..core import so3
from .base import P_OWN, Array, Edges, StepInputs, gain
from .bearing_leaders import (BearingLeaderEstimator, CovState, fed_forward, position_step,
                              repeated)
from .covariance import CovarianceModel, cascade_jacobians


@dataclass(frozen=True)
class CascadeGains(CovarianceModel):
    """Gains of (3) and (23); per-edge ``k_ij`` live in :class:`base.Edges`."""

    k_R: float = gain(1.0, 'attitude gain k_R of (3)')
    k_p: float = gain(1.0, 'position gain k_p of (23)')
    k_v: float = gain(1.0, 'odometry feed-forward of moving agents (1: on, 0: off)',
                      zero_allowed=True)
    bias_std: float = gain(0.0, 'bearing noise std [rad] whose projector bias the position '
                           "correction removes (0: off, the paper's (23))", zero_allowed=True)


def innovation(R_hat: Array, edges: Edges, b_body: Array, d_world: Array) -> tuple[Array, Array]:
    """Innovation ``σ_i`` ``(N, 3)`` and the estimated world bearings ``y_ij = R̂_i b^i_ij``
    ``(E, 3)``; the arguments as in :func:`cascade_step`."""
    # np.take: ~3x faster than fancy indexing for these row gathers.
    y = np.einsum('eab,eb->ea', np.take(R_hat, edges.agent, axis=0), b_body)
    sigma = edges.sum_by_agent(edges.weighted(so3.cross(d_world, y)))
    return sigma, y


def cascade_step(R_hat: Array, p_hat: Array, delta_R: Array, h: float, edges: Edges,
                 b_body: Array, d_world: Array, p_hat_nbr: Array, gains: CascadeGains,
                 reorthonormalize: bool = True, displacement: Array | None = None,
                 p_own: Array | None = None) -> tuple[Array, Array, Array]:
    """One step ``h`` [s] of every agent (module docstring): ``(R̂, p̂)`` at ``t + h`` and the
    innovation ``σ`` (world frame), from the state and ``delta_R`` ``R(t)ᵀ R(t+h)`` at t and, per
    edge ``(E, 3)``, the own unit ``b^i_ij``, the neighbours' ``R̂_j b^j_ij = -R̂_j b^j_ji``, their
    ``p̂_j`` [m] and the owner's ``p̂_i`` to pair with them (:data:`base.P_OWN`; None: ``p_hat``);
    ``displacement``: the odometry ``δ_i`` [m] (None: static). ``reorthonormalize``: ``Q`` and
    ``ΔR`` are rotations to rounding, so a caller may pull R̂ back every few steps only."""
    sigma, y = innovation(R_hat, edges, b_body, d_world)
    Q = so3.exp(-h * gains.k_R * sigma)
    p_pred = position_step(p_hat, edges, y, p_hat_nbr, h * gains.k_p, gains.bias_std,
                           fed_forward(R_hat, displacement, gains.k_v), p_own)
    R_next = so3.matmul(Q, R_hat, delta_R)
    if reorthonormalize:
        R_next = so3.reorthonormalize(R_next)
    p_next = np.einsum('nab,nb->na', Q, p_pred)
    return R_next, p_next, sigma


class BoughellabaTayebi(BearingLeaderEstimator[CascadeGains, CovState]):
    method: ClassVar[str] = 'boughellaba_tayebi'
    title: ClassVar[str] = 'Boughellaba & Tayebi'
    Gains: ClassVar[type] = CascadeGains
    reference_scenario: ClassVar[str] = 'paper_8_agents.yaml'
    conditioning_label: ClassVar[str] = 'M_i = Σ_j k_ij b_ij b_ijᵀ'

    def initial_state(self, R_hat: Array, p_hat: Array) -> CovState:
        R_hat = np.array(R_hat, dtype=float)
        return CovState(R_hat=R_hat, p_hat=np.array(p_hat, dtype=float),
                        P=self.prior(R_hat.shape[0]))

    def step(self, x: CovState, h: float, inputs: StepInputs,
             reorthonormalize: bool = True) -> tuple[CovState, dict[str, Array]]:
        d_world, p_nbr = self.neighbour_terms(inputs)
        g = self.gains
        R_hat, p_hat, sigma = cascade_step(
            x.R_hat, x.p_hat, inputs.delta_R, h, inputs.edges, inputs.edge['bearings'], d_world,
            p_nbr, g, reorthonormalize, inputs.displacement, inputs.edge.get(P_OWN))
        moved = fed_forward(x.R_hat, inputs.displacement, g.k_v)
        lever = x.p_hat if moved is None else x.p_hat + moved   # what Q turns
        P = self.covariance_step(x, h, inputs, p_nbr, moved, lambda y, dist: cascade_jacobians(
            h, inputs.edges, y, dist, lever, g.k_R, g.k_p))
        return CovState(R_hat=R_hat, p_hat=p_hat, P=P), {'innovation': sigma}

    def conditioning_problem(self, eig: Array) -> str | None:
        if not repeated(eig):
            return None
        eigs = '{' + ', '.join(f'{e:.3g}' for e in eig) + '}'
        return (f'M_i = Σ k_ij b_ij b_ijᵀ has repeated eigenvalues {eigs}: Lemma 1\'s '
                'hypothesis fails (convergence is then not guaranteed)')
