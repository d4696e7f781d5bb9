"""Presenza, Colombo, Mas & Giribet (2026): bearing-only pose estimation of a moving fleet via
angle rigidity, in the anchor's moving body frame (``method: presenza``).

Equations, corrections, gains and discretisation: ``../shared/estimators/presenza-2026.md``
(§n), the paper's numbers in parentheses. Robot i keeps ``q̂_i`` (``p_hat``) and ``Q̂_i`` (body →
anchor frame, ``R_hat``) and measures the body bearings ``β_ij`` of its out-neighbours ``j ∈
O_i`` (directed) and their rates ``β̇_ij``; the anchor ``a`` also measures the relative positions
``q_b, q_c`` of its two ranged robots. **Sensing robots** have two or more out-neighbours; the
**free robots'** positions come from the angles the sensing robots measure of them, their
attitudes from the velocity the sensing robots reconstruct from bearing rates (11).

One link per communication neighbour; two rounds of messages per step (§10): ``q̂_j`` and the
anchor's ranged ``q_i``, then what each sensing robot j forms for each ``i ∈ O_j``
(:meth:`Presenza.reply`; e.g. ``n_ji`` of (11) with the estimated distance, §4.2).

One step ``h``, everything on the right at the step's start:

- ``ζ_i`` (6): own angle terms ``-Σ α̃_ijk (χ̂_ijk + χ̂_ikj)``, the received ``g_{j→i}`` and the
  anchor term ``κ_s (δ_ia q̂_a + δ_ib (q̂_b - q_b) + δ_ic (q̂_c - q_c))``;
- sensing robots (12): ``Ω_i = Σ_j β_ij × (Q̂_iᵀ q̂_ij)``, ``K̂_i = Σ_j ‖q̂_ij‖ Π(β_ij)``;
- free robots (11), (13): ``P̂_i = Σ_j Π(𝔟̂_ji)``, ``υ̂_i = P̂_i⁻¹ Σ_j n_ji``,
  ``γ̂_i = υ̂_i + u_a + ω_a × q̂_i`` (the anchor-frame velocity ``Q_i u_i``; held while
  ``λ_min(P̂_i) < min_lambda_P``), ``Ω_i = u_i × (Q̂_iᵀ γ̂_i)``, ``K̂_i = S(u_i)ᵀ S(u_i)``;
- corrections, preconditioned with weight ``w`` (``preconditioning``; 0: the paper's explicit
  update, 1: §9's semi-implicit scheme, stable at any step), ``D̂_i`` the diagonal block of the
  Gauss-Newton Hessian::

      Δq_i = -h κ_q (I + 2 w h κ_q D̂_i)⁻¹ ζ_i
      φ_i  =  h κ_Q (I + w h κ_Q K̂_i)⁻¹ Ω_i       (κ_Q: κ_Q^s sensing, κ_Q^f free)

- prediction with the odometry increments, exact for the truth over the step (the anchor
  frame moves by ``ΔR_a``, ``δ_a``): sensing robots move by ``Q̂_i δ_i`` (10), free robots by
  ``h γ̂_i`` (18: they do not use their own ``Q̂_i``, which keeps the cascade)::

      q̂_i ← ΔR_aᵀ (q̂_i + Δq_i + [Q̂_i δ_i | h γ̂_i] - δ_a)
      Q̂_i ← ΔR_aᵀ Q̂_i exp(φ_i) ΔR_i

  As ``h → 0`` this is (16)-(19). Velocities inside the terms (``u_i``, ``ω_i``, ``u_a``,
  ``ω_a``) are the step averages ``δ/h``, ``log(ΔR)/h``.

Covariance: :mod:`.presenza_covariance`. The anchor runs as a sensing robot (its estimate
leaves ``(I, 0)`` and returns, as in the paper) or, pinned, holds ``(I, 0)``.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import lru_cache
from itertools import combinations
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from ..core import angles, so3, warm_start as warm
from ..core.motion import in_anchor_frame
from . import presenza_covariance as cov
from .base import (ANCHOR_DELTA_R, ANCHOR_DISPLACEMENT, IS_ANCHOR, PINNED, POSE_POSITION, Array,
                   Channel, CheckReport, Edges, EstimateFrame, Estimator, Finding, Index, Mask,
                   Motion, Roles, Sensor, State, StepInputs, WarmStart, gain)
from .covariance import POSE_COV, initial_covariance
from .fleet import Fleet

# Every value a robot receives is checked against this bound [m, 1/m, 1/m², m/s].
MAX_VALUE = 1e4
Q_HAT = Channel('q_hat', per='agent', frame='estimate', doc='q̂_j, the position estimate in '
                'the anchor frame [m]', topic='pose', kind=POSE_POSITION, on='senses',
                pairing='exact', bound=MAX_VALUE)
Q_RANGED = Channel('q_ranged', per='edge', frame='body', sensor=Sensor.RELATIVE_POSITIONS,
                   on='ranged_by', pairing='exact', bound=MAX_VALUE,
                   doc='q_i = R_aᵀ (p_i - p_a), the anchor j\'s measurement of its ranged robot '
                       'i (its body frame) [m]; zeros otherwise')
_ROUND_2 = dict(per='edge', frame='estimate', round=2, on='sensed_by', pairing='exact',
                bound=MAX_VALUE)
GRADIENT = Channel('angle_gradient', **_ROUND_2,  # type: ignore[arg-type]
                   doc='g_{j→i} = Σ_{k∈O_j\\{i}} α̃_jik χ̂_jik, sensing robot j\'s angle terms '
                       'of the listener i\'s gradient (6) [1/m]; zeros otherwise')
HESSIAN = Channel('angle_hessian', **_ROUND_2, shape=(6,),  # type: ignore[arg-type]
                  fields=('xx', 'yy', 'zz', 'xy', 'xz', 'yz'),
                  doc='Σ_k χ̂_jik χ̂_jikᵀ, its Gauss-Newton block (§9) [1/m²], as xx, yy, zz, '
                      'xy, xz, yz')
ANCHOR_BEARING = Channel('anchor_bearing', **_ROUND_2,  # type: ignore[arg-type]
                         doc='𝔟̂_ji = Q̂_j β_ji, j\'s bearing of the listener in the anchor '
                             'frame (11); zeros when j is not a sensing robot that sees it')
VELOCITY_TERM = Channel('velocity_term', **_ROUND_2,  # type: ignore[arg-type]
                        doc='n_ji, j\'s term of the listener\'s velocity reconstruction (11) '
                            '[m/s]')

# Distances below this are treated as this (an estimate collapsed onto a neighbour's).
MIN_DISTANCE_M = 1e-9
# A received anchor_bearing counts when its norm is within this of 1 (zeros: not sent).
UNIT_SLACK = 0.5
# Margins below these break the method's assumptions (A3, A5, L2 of §3; dimensionless).
MIN_PROJECTOR_MARGIN = 1e-6
# The explicit update is stable while h λ_max < 2 (§9).
EULER_LIMIT = 2.0


@dataclass(frozen=True)
class PresenzaGains(cov.PresenzaCovarianceModel):
    """Gains of (16)-(19) (§7: κ_Q has different units in the two attitude loops)."""

    kappa_q: float = gain(500.0, 'position gain kappa_q of (16), (18) on the angle part of the '
                                 'gradient [m^2/s]')
    kappa_s: float = gain(0.02, 'anchor-term weight kappa_s of the cost (5) [1/m^2]; its rate '
                                'is kappa_q kappa_s [1/s]')
    kappa_Q_sensing: float = gain(2.0, 'attitude gain kappa_Q of the sensing robots (17) '
                                       '[1/(m s)]')
    kappa_Q_free: float = gain(2.0, 'attitude gain kappa_Q of the free robots (19) [s/m^2]')
    preconditioning: float = gain(1.0, 'weight w of the local preconditioner (notes §9): 0 is '
                                  'the paper\'s explicit update (needs ~100 Hz with its gains), '
                                  '1 the semi-implicit scheme, stable at camera rates',
                                  zero_allowed=True)
    min_lambda_P: float = gain(1e-3, 'a free robot holds its last reconstructed velocity while '
                                     'lambda_min(P_hat_i) of (11) is below this',
                               zero_allowed=True)


@dataclass
class PresenzaState(State):
    """``R_hat`` is ``Q̂_i`` (body → anchor frame), ``p_hat`` is ``q̂_i`` [m]."""

    gamma_hat: Array   # (N, 3) the last anchor-frame velocity Q_i u_i of (13) [m/s]
    P: Array           # (N, 6, 6) the pose covariance, (q̃, φ) (presenza_covariance.py)


@lru_cache(maxsize=64)
def _pairs(agent: bytes, senses: bytes) -> tuple[Index, Index]:
    """The angles of every robot: pairs of its sensing links ``(e1, e2)``, ``e1 < e2``."""
    a = np.frombuffer(agent, dtype=np.intp)
    s = np.frombuffer(senses, dtype=bool)
    pairs = [p for i in np.unique(a) for p in combinations(np.flatnonzero((a == i) & s), 2)]
    e1, e2 = np.array(pairs, dtype=np.intp).reshape(-1, 2).T
    return e1, e2


_triples = lru_cache(maxsize=16)(angles.angle_triples)   # per fleet (fleet_margins)


def _outer(a: Array, b: Array) -> Array:
    return a[:, :, None] * b[:, None, :]


class Presenza(Estimator[PresenzaGains, PresenzaState]):
    """Presenza, Colombo, Mas & Giribet (2026): module docstring."""

    method: ClassVar[str] = 'presenza'
    title: ClassVar[str] = 'Presenza et al.'
    Gains: ClassVar[type] = PresenzaGains
    roles: ClassVar[Roles] = Roles(anchor=True)
    sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.GYRO, Sensor.BEARINGS,
                                                      Sensor.ODOMETRY, Sensor.BEARING_RATES,
                                                      Sensor.RELATIVE_POSITIONS})
    sends: ClassVar[tuple[Channel, ...]] = (
        Q_HAT, Q_RANGED, GRADIENT, HESSIAN, ANCHOR_BEARING, VELOCITY_TERM,
        replace(POSE_COV, on='senses', pairing='exact', bound=MAX_VALUE ** 2), cov.TERM_COV)
    frame: ClassVar[EstimateFrame] = EstimateFrame.ANCHOR_BODY
    edge_gains: ClassVar[bool] = False
    links = 'communication'
    directed_sensing: ClassVar[bool] = True
    measures: ClassVar[Mapping[Sensor, str | None]] = {Sensor.BEARINGS: 'senses',
                                                       Sensor.BEARING_RATES: 'senses'}
    own_pairing = 'interpolated'
    peer_odometry = 'anchor'
    partial_edges: ClassVar[bool] = True
    partner_sensor: ClassVar[Sensor | None] = Sensor.RELATIVE_POSITIONS
    reference_scenario: ClassVar[str] = 'presenza_case1.yaml'
    # Free robots dead-reckon with the step-start velocity (18), terms use step averages: first
    # order in h under motion (~1e-5 after 300 steps of 1 ms in the contract's moving fleet).
    moving_fixed_point_atol: ClassVar[float] = 1e-4

    # --- state and messages
    def initial_state(self, R_hat: Array, p_hat: Array) -> PresenzaState:
        return PresenzaState(R_hat=np.array(R_hat, dtype=float),
                             p_hat=np.array(p_hat, dtype=float),
                             gamma_hat=np.zeros((len(p_hat), 3)), P=self.prior(len(p_hat)))

    def prior(self, n: int) -> Array:
        return initial_covariance(n, self.gains.initial_position_std,
                                  self.gains.initial_attitude_std)

    def missing(self, channel: str) -> Array:
        """A sensed robot's covariance not received: the prior; a sensing robot's terms: 0."""
        if channel == POSE_COV.name:
            return self.prior(1)[0]
        if channel == cov.TERM_COV.name:
            return np.zeros(cov.TERM_COV.shape)
        return super().missing(channel)

    def outbox(self, x: PresenzaState, sender: Index, bearings: Array,
               slot: Index | None = None) -> dict[str, Array]:
        """Round 1: ``q̂_j``, its covariance and, per link, the anchor's measured relative
        position of the listener (``bearings``: zeros where the sender does not range it)."""
        return {'q_hat': x.p_hat.copy(), 'q_ranged': np.array(bearings, dtype=float),
                'pose_cov': x.P.copy()}

    def warm_start(self, x: PresenzaState, inputs: StepInputs) -> WarmStart | None:
        """Where the messages determine the pose (docs/warm_start.md): the anchor's is ``(I, 0)``
        by definition; a ranged robot's position is the anchor's ``q_i``, and a sensing robot's
        attitude then solves Wahba's problem between ``β_ij`` and the directions to the ``q̂_j``
        (2), refused beyond ``WARM_SIGMAS`` of the noise (a free robot's needs its motion: its
        attitude stays). None for the others: no message carries a position to them, only
        angles, which the observer's gradient (6) turns into one over time."""
        g, edges, r = self.gains, inputs.edges, inputs.edge
        if inputs.agent[IS_ANCHOR][0]:
            x0 = self.initial_state(np.eye(3)[None], np.zeros((1, 3)))
            x0.P[:] = 0.0
            return WarmStart(x0, 'accepted: the anchor, (I, 0) by definition')
        if not edges.flag('ranged_by').any():
            return None
        ranged = np.flatnonzero(edges.flag('ranged_by') & inputs.here('q_ranged'))
        if not ranged.size:
            return WarmStart(None, 'not determined: no range from the anchor at this instant')
        q, sig_q = r['q_ranged'][ranged[0]], max(g.relative_position_std, warm.WARM_FLOOR_M)
        x0 = self.initial_state(x.R_hat, q[None])
        x0.P[0] = np.diag([sig_q ** 2] * 3 + [0.0] * 3)
        if np.count_nonzero(edges.flag('senses')) < 2:
            x0.P[0, 3:, 3:] = x.P[0, 3:, 3:]
            return WarmStart(x0, 'accepted: the position from the anchor\'s range (a free '
                                 'robot\'s attitude needs its motion, (13))')
        use = edges.flag('senses') & inputs.here('bearings') & inputs.here('q_hat')
        d = r['q_hat'][use] - q
        dist = np.maximum(np.linalg.norm(d, axis=1), MIN_DISTANCE_M)
        fit = warm.wahba(r['bearings'][use], d / dist[:, None], np.ones(len(d)))
        if fit is None:
            return WarmStart(None, f'not determined: {len(d)} neighbour bearing(s) within '
                                   f'{np.degrees(warm.MIN_SPREAD_RAD):g} deg of a line')
        R, res = fit
        P_j = r[POSE_COV.name][use]
        sigma = np.maximum(np.sqrt(g.bearing_std ** 2 + (np.trace(P_j[:, :3, :3], axis1=1, axis2=2)
                                                         + 3 * sig_q ** 2) / (3 * dist ** 2)),
                           warm.WARM_FLOOR_RAD)
        z = float(np.max(res / sigma))
        residual = f'residual {res.max():.2g} rad ({z:.2g} sigma) from {len(d)} bearings'
        if z > warm.WARM_SIGMAS:
            return WarmStart(None, f'refused: {residual}')
        x0.R_hat[0] = R
        x0.P[0, 3:, 3:] = np.linalg.inv(warm.information(d / dist[:, None], sigma))
        return WarmStart(x0, f'accepted: {residual}')

    def carry(self, values: Mapping[str, Array], motion: Motion) -> dict[str, Array] | None:
        """Values formed at ``t_s`` in the anchor frame at t (moved by ``ΔR_a``, ``δ_a``): a
        position ``ΔR_aᵀ (q - δ_a)`` (the sender still), a vector ``ΔR_aᵀ v``, ``ΔR_aᵀ D ΔR_a``."""
        delta_R_a, delta_a = motion.anchor_delta_R, motion.anchor_displacement
        if delta_R_a is None or delta_a is None:
            return None
        out = {}
        for name, v in values.items():
            if name == 'q_hat':
                out[name] = delta_R_a.T @ (v - delta_a)
            elif name == 'angle_hessian':
                out[name] = so3.sym_pack(delta_R_a.T @ so3.sym_unpack(v) @ delta_R_a)
            elif name == POSE_COV.name:
                turn = np.kron(np.eye(2), delta_R_a.T)
                out[name] = turn @ v @ turn.T
            elif name == cov.TERM_COV.name:
                blocks = so3.sym_unpack(v[:24].reshape(4, 6))
                out[name] = np.concatenate([so3.sym_pack(delta_R_a.T @ blocks @ delta_R_a)
                                            .ravel(), delta_R_a.T @ v[cov.RATE]])
            else:
                out[name] = delta_R_a.T @ v
        return out

    def agent_groups(self, fleet: Fleet) -> dict[str, list[str]]:
        """Sensing robots (two or more out-neighbours) and free robots."""
        sensing = [name for name, nbrs in zip(fleet.names, fleet.neighbours) if len(nbrs) >= 2]
        return {'sensing': sensing, 'free': [name for name in fleet.names if name not in sensing]}

    def fleet_margins(self, fleet: Fleet, R_hat: Array, p_hat: Array) -> dict[str, float]:
        """The check's angle rigidity margin (§2) on the estimates ``q̂``: the gradient flow
        (16) needs it away from 0."""
        out = tuple(tuple(j for j, _ in nbrs) for nbrs in fleet.neighbours)
        return {'angle_rigidity_margin': angles.iar_margin(p_hat, _triples(out))}

    @staticmethod
    def _structure(x: PresenzaState, inputs: StepInputs) -> tuple[Mask, Mask, Mask]:
        """Per link whether its sensing terms are used this step (i senses j and has all it
        needs) and ``sensed_by``; per robot ``sensing`` (a role, whatever this step lacks)."""
        edges = inputs.edges
        senses = edges.flag('senses')
        count = np.bincount(edges.agent[senses], minlength=x.p_hat.shape[0])
        used = (senses & inputs.here('bearings') & inputs.here('bearing_rates')
                & inputs.here('q_hat'))
        return used, edges.flag('sensed_by'), count >= 2

    @staticmethod
    def _motion(h: float, inputs: StepInputs) -> tuple[Array, Array, Array, Array, Array, Array]:
        """Step averages ``ω_i``, ``u_i``, ``ω_a``, ``u_a`` ``(N, 3)`` and ``ΔR_a``, ``δ_a``."""
        a_R, a_d = inputs.agent[ANCHOR_DELTA_R], inputs.agent[ANCHOR_DISPLACEMENT]
        delta = inputs.displacement if inputs.displacement is not None else np.zeros_like(a_d)
        return (so3.log_small(inputs.delta_R) / h, delta / h, so3.log_small(a_R) / h,
                a_d / h, a_R, a_d)

    def _angle_terms(self, x: PresenzaState, inputs: StepInputs, senses: NDArray[np.bool_]
                     ) -> tuple[Array, Array, Array, Array, cov.AngleTerms]:
        """Each robot's own terms of ``ζ_i``, ``D̂_i``, per link what it sends the other end
        (``g``, its Gauss-Newton block), and the angles' Jacobian blocks (the covariance's)."""
        n, n_edges = x.p_hat.shape[0], len(inputs.edges)
        agent = inputs.edges.agent
        e1, e2 = _pairs(agent.tobytes(), np.ascontiguousarray(senses).tobytes())
        terms = cov.angle_terms(x.p_hat, inputs.edge['q_hat'], agent, e1, e2, MIN_DISTANCE_M)
        zeta, D = np.zeros((n, 3)), np.zeros((n, 3, 3))
        g_out, D_out = np.zeros((n_edges, 3)), np.zeros((n_edges, 3, 3))
        if not len(e1):
            return zeta, D, g_out, D_out, terms
        _, _, chi_jk, chi_kj, g_own, c = terms
        i = agent[e1]
        b = inputs.edge['bearings']
        err = c - np.sum(b[e1] * b[e2], axis=1, keepdims=True)     # α̃_ijk
        np.add.at(zeta, i, err * g_own)
        np.add.at(D, i, _outer(g_own, g_own))
        np.add.at(g_out, e1, err * chi_jk)
        np.add.at(g_out, e2, err * chi_kj)
        np.add.at(D_out, e1, _outer(chi_jk, chi_jk))
        np.add.at(D_out, e2, _outer(chi_kj, chi_kj))
        return zeta, D, g_out, D_out, terms

    def reply(self, x: PresenzaState, h: float, inputs: StepInputs) -> dict[str, Array]:
        """Round 2, from each sensing robot to each out-neighbour (zeros on other links)."""
        senses, _, sensing = self._structure(x, inputs)
        agent = inputs.edges.agent
        _, _, g_out, D_out, terms = self._angle_terms(x, inputs, senses)
        send = (senses & sensing[agent])[:, None]
        omega, u, omega_a, u_a, _, _ = self._motion(h, inputs)
        Q = x.R_hat[agent]
        beta = inputs.edge['bearings']
        b_hat = np.einsum('eab,eb->ea', Q, beta)                   # 𝔟̂ = Q̂_j β_ji
        Ru = np.einsum('nab,nb->na', x.R_hat, u)                    # Q̂_j u_j
        upsilon = (Ru - u_a - so3.cross(omega_a, x.p_hat))[agent]  # (10)
        dist = np.linalg.norm(inputs.edge['q_hat'] - x.p_hat[agent], axis=1, keepdims=True)
        g = self.gains
        rates = inputs.edge.get('bearing_rates')
        velocity, b_sent, linear = np.zeros_like(b_hat), np.zeros_like(b_hat), None
        if rates is not None:
            derotated = rates + so3.cross(omega[agent], beta)
            s = np.einsum('eab,eb->ea', Q, derotated)             # Q̂_j (β̇ + ω_j × β)
            r_dot = s - so3.cross(omega_a[agent], b_hat)           # the rate of 𝔟_ji
            velocity = (upsilon - b_hat * np.sum(b_hat * upsilon, axis=1, keepdims=True)
                        + dist * r_dot)
            b_sent = b_hat
            linear = cov.VelocityTerms(b_hat, dist[:, 0], r_dot, s, Q, Ru[agent], omega[agent],
                                       omega_a[agent])
        term_cov = cov.sender_terms(
            len(agent), terms, beta, x.P, inputs.edge[POSE_COV.name], agent, linear,
            g.bearing_std ** 2, g.bearing_rate_std ** 2, g.odometry_noise_density ** 2,
            g.gyro_noise_density ** 2, h)
        return {'angle_gradient': np.where(send, g_out, 0.0),
                'angle_hessian': np.where(send, so3.sym_pack(D_out), 0.0),
                'anchor_bearing': np.where(send, b_sent, 0.0),
                'velocity_term': np.where(send, velocity, 0.0),
                cov.TERM_COV.name: np.where(send, term_cov, 0.0)}

    def step(self, x: PresenzaState, h: float, inputs: StepInputs,
             reorthonormalize: bool = True) -> tuple[PresenzaState, dict[str, Array]]:
        g = self.gains
        senses, sensed_by, sensing = self._structure(x, inputs)
        edges, r = inputs.edges, inputs.edge
        is_anchor: Mask = inputs.agent[IS_ANCHOR].astype(bool)
        ranged_by = edges.flag('ranged_by') & inputs.here('q_ranged')
        agent = edges.agent
        _, u, omega_a, u_a, dR_a, delta_a = self._motion(h, inputs)
        zeta, D, _, _, terms = self._angle_terms(x, inputs, senses)
        # Received angle terms and the anchor term (6), (5).
        into = sensed_by[:, None]
        zeta += edges.sum_by_agent(np.where(into, r['angle_gradient'], 0.0))
        D += self._sum_blocks(edges, np.where(into, r['angle_hessian'], 0.0))
        zeta += g.kappa_s * (is_anchor[:, None] * x.p_hat
                             + edges.sum_by_agent(np.where(
                                 ranged_by[:, None], x.p_hat[agent] - r['q_ranged'], 0.0)))
        anchored = is_anchor | (edges.sum_by_agent(ranged_by[:, None].astype(float))[:, 0] > 0)
        D += g.kappa_s * anchored[:, None, None] * np.eye(3)
        # Sensing robots' innovation (12).
        d_own = np.where(senses[:, None], r['q_hat'] - x.p_hat[agent], 0.0)
        beta = inputs.edge['bearings']
        Q_T_d = np.einsum('eba,eb->ea', x.R_hat[agent], d_own)
        Omega = edges.sum_by_agent(np.where(senses[:, None], so3.cross(beta, Q_T_d), 0.0))
        dist = np.linalg.norm(d_own, axis=1)[:, None, None]
        K = self._sum_blocks(edges, so3.sym_pack(np.where(
            senses[:, None, None], dist * (np.eye(3) - _outer(beta, beta)), 0.0)))
        # Free robots' velocity reconstruction (11) and innovation (13).
        b_in = r['anchor_bearing']
        valid = sensed_by & (np.abs(np.linalg.norm(b_in, axis=1) - 1.0) < UNIT_SLACK)
        P = self._sum_blocks(edges, so3.sym_pack(np.where(valid[:, None, None],
                                                   np.eye(3) - _outer(b_in, b_in), 0.0)))
        nu = edges.sum_by_agent(np.where(valid[:, None], r['velocity_term'], 0.0))
        lam_P = np.linalg.eigvalsh(P)[:, 0]
        ok = (~sensing) & (lam_P > max(g.min_lambda_P, 1e-12))
        upsilon_f = np.linalg.solve(np.where(ok[:, None, None], P, np.eye(3)),
                                    nu[:, :, None])[:, :, 0]
        gamma_new = upsilon_f + u_a + so3.cross(omega_a, x.p_hat)
        gamma_own = np.einsum('nab,nb->na', x.R_hat, u)
        gamma = np.where(sensing[:, None], gamma_own,
                         np.where(ok[:, None], gamma_new, x.gamma_hat))
        Q_T_gamma = np.einsum('nba,nb->na', x.R_hat, gamma)
        Omega = np.where(sensing[:, None], Omega, so3.cross(u, Q_T_gamma))
        K_free = (np.sum(u * u, axis=1)[:, None, None] * np.eye(3) - _outer(u, u))
        K = np.where(sensing[:, None, None], K, K_free)
        # Corrections, preconditioned (§9), then the prediction with the increments.
        w = g.preconditioning
        eye = np.eye(3)
        dq = -h * g.kappa_q * np.linalg.solve(eye + 2.0 * w * h * g.kappa_q * D,
                                              zeta[:, :, None])[:, :, 0]
        kappa_Q = np.where(sensing, g.kappa_Q_sensing, g.kappa_Q_free)[:, None]
        phi = h * kappa_Q * np.linalg.solve(eye + (w * h * kappa_Q)[:, :, None] * K,
                                            Omega[:, :, None])[:, :, 0]
        move = np.where(sensing[:, None], np.einsum('nab,nb->na', x.R_hat, u * h), h * gamma)
        dR_a_T = np.swapaxes(dR_a, -1, -2)
        p_new = np.einsum('nab,nb->na', dR_a_T, x.p_hat + dq + move - delta_a)
        R_new = so3.matmul(dR_a_T, x.R_hat, so3.exp(phi), inputs.delta_R)
        if reorthonormalize:
            R_new = so3.reorthonormalize(R_new)
        gamma_next = np.einsum('nab,nb->na', dR_a_T, gamma)
        hold: Mask = inputs.agent[PINNED].astype(bool)
        if hold.any():
            p_new[hold], R_new[hold] = 0.0, eye
        # The covariance, linearised at the estimate before the step (presenza_covariance.py).
        b_own = np.einsum('eab,eb->ea', x.R_hat[agent], beta)     # Q̂_i β_ij
        P_inv = np.linalg.inv(np.where(ok[:, None, None], P, eye))
        lin = cov.own_linearisation(
            h, g.kappa_q, kappa_Q[:, 0], w, D, so3.matmul(x.R_hat, K, np.swapaxes(x.R_hat, -1, -2)),
            sensing, b_own, agent, senses, move, gamma, omega_a, P_inv, ok, b_in,
            r[cov.TERM_COV.name][:, cov.RATE], valid)
        P_next = cov.propagate(
            x.P, lin, dR_a, agent, used=senses, b_own=b_own, own_bearings=beta, angles=terms,
            d_own=dist[:, 0, 0], P_nbr=r[POSE_COV.name], terms=r[cov.TERM_COV.name],
            sensed_by=sensed_by, valid=valid, ranged_by=ranged_by,
            is_anchor=is_anchor, sensing=sensing, gamma=gamma, R_hat=x.R_hat,
            q_next=p_new, model=g, kappa_s=g.kappa_s, h=h, pinned=hold)
        out = PresenzaState(R_hat=R_new, p_hat=p_new, gamma_hat=gamma_next, P=P_next)
        return out, {'innovation': Omega, 'zeta': zeta, 'lambda_P': np.where(sensing, 0.0, lam_P),
                     'reconstructed': (sensing | ok).astype(float)}

    @staticmethod
    def _sum_blocks(edges: Edges, packed: Array) -> Array:
        """``Σ`` over each robot's links of packed symmetric blocks ``(E, 6)`` → ``(N, 3, 3)``."""
        return so3.sym_unpack(np.column_stack([edges.sum_by_agent(packed[:, :3]),
                                        edges.sum_by_agent(packed[:, 3:])]))

    # --- assumptions
    def check(self, fleet: Fleet) -> CheckReport:
        return check_angle_graph(self.gains, fleet)


def _eig(bearings: Array) -> Array:
    """Ascending eigenvalues of ``Σ Π(β)`` of unit vectors ``(M, 3)``."""
    return np.asarray(np.linalg.eigvalsh(angles.projector_sum(bearings)), dtype=np.float64)


def check_angle_graph(gains: PresenzaGains, fleet: Fleet) -> CheckReport:
    """The assumptions at t = 0 (§2, §3): the anchor senses, A3, angle rigidity (Definition
    1), A5, L2, and the explicit update's step limit (§9)."""
    report = CheckReport(spectra_of='Σ_j Π(β_ij) (sensing robots, A5) and P_i = Σ_j Π(𝔮_ji) '
                                    '(free robots, L2)')
    names = list(fleet.names)
    n = len(names)
    out = [[j for j, _ in nbrs] for nbrs in fleet.neighbours]
    sensing = [len(o) >= 2 for o in out]
    # The true positions at t = 0 in the estimate frame: the anchor's body frame.
    q = (fleet.positions if fleet.anchor is None
         else in_anchor_frame(fleet.attitudes, fleet.positions, fleet.anchor)[1])
    a = fleet.anchor if fleet.anchor is not None else 0
    ranged = list(fleet.ranged)

    def unit(i: int, j: int) -> Array:
        d = q[j] - q[i]
        return d / max(float(np.linalg.norm(d)), 1e-300)

    if not sensing[a]:
        report.findings.append(Finding(
            'error', names[a], 'neighbours', 'the anchor must be a sensing robot (two or more '
            'bearings; Sec. III)', 'give the anchor at least two neighbours'))
    if len(ranged) == 2:
        m = angles.projector_sum(np.array([unit(a, r) for r in ranged]))
        a3 = float(np.linalg.eigvalsh(m)[0])
        report.margins['A3 λ_min(Π(β_ab) + Π(β_ac))'] = a3
        if a3 < MIN_PROJECTOR_MARGIN:
            report.findings.append(Finding(
                'error', names[a], 'anchor.ranged', f'{names[ranged[0]]} and '
                f'{names[ranged[1]]} are aligned seen from the anchor (A3 margin {a3:.3g})',
                'range two robots in different directions'))
    triples = angles.angle_triples(out)
    report.margins['angles |A|'] = float(len(triples))
    if len(triples) < 3 * n - 7:
        report.findings.append(Finding(
            'error', names[a], 'neighbours', f'{len(triples)} angles, fewer than 3N - 7 = '
            f'{3 * n - 7}: the framework cannot be angle rigid', 'give the sensing robots more '
            'neighbours (each pair of a robot\'s neighbours is one angle)'))
    for i in range(n):
        if sensing[i]:
            eig = _eig(np.array([unit(i, j) for j in out[i]]))
            report.spectra[names[i]] = eig
            if eig[0] < MIN_PROJECTOR_MARGIN:
                report.findings.append(Finding(
                    'error', names[i], 'neighbours', f'its bearings are collinear (A5 margin '
                    f'{eig[0]:.3g}): its attitude is not observable', 'give it a neighbour '
                    'off the line of the others'))
            continue
        seen_by = [j for j in range(n) if sensing[j] and i in out[j]]
        eig = _eig(np.array([unit(j, i) for j in seen_by])) if seen_by else np.zeros(3)
        report.spectra[names[i]] = eig
        if len(seen_by) < 2 or eig[0] < MIN_PROJECTOR_MARGIN:
            who = ', '.join(names[j] for j in seen_by) or 'no sensing robot'
            report.findings.append(Finding(
                'error', names[i], 'neighbours', f'a free robot must be seen by two sensing '
                f'robots along non-collinear bearings (Lemma 2; seen by {who}, L2 margin '
                f'{eig[0]:.3g})', 'add it to the neighbours of another sensing robot'))
    if len(triples) >= 3 * n - 7 and len(triples):
        margin = angles.iar_margin(q, triples)
        report.margins['angle rigidity σ_{3N-7}/σ_1 (normalised)'] = margin
        lam = np.linalg.eigvalsh(angles.hessian(q, triples, gains.kappa_s, a, ranged))
        report.margins['κ_q λ_1(H) [1/s]'] = gains.kappa_q * float(lam[0])
        report.margins['κ_q λ_max(H) [1/s]'] = gains.kappa_q * float(lam[-1])
        if margin < angles.IAR_TOLERANCE:
            report.findings.append(Finding(
                'error', names[a], 'neighbours', f'the framework is not infinitesimally angle '
                f'rigid (σ_3N-7/σ_1 = {margin:.3g} on normalised positions)',
                'add bearings (neighbours) until the angles fix the shape'))
        elif gains.preconditioning == 0.0:
            rate = gains.kappa_q * float(lam[-1])
            sens = [i for i in range(n) if sensing[i]]
            if sens:
                k_max = max(float(np.linalg.eigvalsh(sum(
                    np.linalg.norm(q[j] - q[i]) * (np.eye(3) - np.outer(unit(i, j), unit(i, j)))
                    for j in out[i]))[-1]) for i in sens)
                rate = max(rate, gains.kappa_Q_sensing * k_max)
            limit = EULER_LIMIT / rate
            report.margins['explicit update step limit [s]'] = limit
            if fleet.step >= limit:
                report.findings.append(Finding(
                    'error', 'gains', 'preconditioning', f'the explicit update (w = 0) '
                    f'diverges at h = {fleet.step:.3g} s: its limit is {limit:.3g} s (§9)',
                    f'set gains.preconditioning: 1, or frequency above {1.0 / limit:.3g} Hz'))
    return report
