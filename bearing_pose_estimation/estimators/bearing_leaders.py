"""The setting Boughellaba & Tayebi and Tran, Anderson & Ahn share: gyros and bearings, two leaders
that know their pose, followers that each see at least two earlier agents. Sensing is two-way on
every edge: j sends i ``R̂_j b^j_ji`` (formed at one instant, so that attitude and bearing pair in
time) and ``p̂_j``; i uses ``d_ij = R̂_j b^j_ij = -R̂_j b^j_ji``.

Assumption 2 of Boughellaba & Tayebi (Tran et al. assume the same graph class): (a) the sensing
graph is acyclic and every follower is reachable from both leaders; (b) leaders have no neighbours
(enforced when parsing); (d) no two agents are collocated, every follower has ``|N_i| >= 2``
neighbours, all earlier in the agent order, with at least two non-collinear bearings. Each method
adds the spectrum condition of its own lemma (:meth:`Estimator.conditioning`).
"""
from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Callable, Mapping
from typing import ClassVar, TypeVar

import numpy as np
from numpy.typing import NDArray

from ..core import graph, so3, warm_start
from ..core.warm_start import WARM_FLOOR_RAD, WARM_SIGMAS
from .base import (Array, Channel, CheckReport, Edges, EstimateFrame, Estimator, Finding, HELD,
                   Index, P_OWN, POSE_POSITION, Roles, Sensor, State, StepInputs, WarmStart)
from .covariance import DOF, POSE_COV, CovarianceModel, Jacobians, initial_covariance, propagate
from .fleet import Fleet

P_HAT = Channel('p_hat', per='agent', frame='world', doc='p̂_j, the position estimate [m]',
                topic='pose', kind=POSE_POSITION)
WORLD_BEARING = Channel('world_bearing', per='edge', frame='world', unit=True,
                        topic='world_bearings',
                        doc='R̂_j b^j_ji, j\'s bearing to its listener i in the world frame')

# Bearings closer than this to collinear make Σ P_b singular: an error.
COLLINEAR_ERROR_RAD = 1e-6
# Below this angle the position observer is badly conditioned: a warning.
COLLINEAR_WARN_DEG = 5.0
# Eigenvalues closer than this (relative to the largest) count as repeated.
EIGEN_GAP_REL = 1e-6
# check_motion works on (samples × followers) blocks of about this many bearing sets.
MOTION_BLOCK = 200_000
# Along the motion, the local matrix's spectrum is evaluated where one of the follower's
# bearings has turned by this much [deg] since (a formation that keeps its shape costs nothing).
SPECTRUM_STEP_DEG = 0.5


@dataclass
class CovState(State):
    """Adds the covariance ``P`` ``(N, d, d)`` of each agent's error (:mod:`.covariance`)."""

    P: Array


S = TypeVar('S', bound=CovState)
GL = TypeVar('GL', bound=CovarianceModel)


def fed_forward(R_hat: Array, displacement: Array | None, k_v: float) -> Array | None:
    """``k_v R̂_i δ_i`` ``(N, 3)``, the odometry displacement the step feeds forward, or None."""
    if displacement is None or k_v == 0.0:
        return None
    return k_v * np.einsum('nab,nb->na', R_hat, displacement)


def position_step(p_hat: Array, edges: Edges, y: Array, p_hat_nbr: Array, h_k_p: float,
                  bias_std: float, moved: Array | None, p_own: Array | None) -> Array:
    """``p̂_i + k_v R̂_i δ_i - h k_p Σ_j P_{y_ij} (p̂_i - p̂_j)`` ``(N, 3)``, ``P_y e = e - y
    (y·e)/‖y‖²``: the position step of both observers (``moved``: :func:`fed_forward`).
    ``bias_std`` (σ_b > 0) removes the bias of a noisy bearing's projector: with each of the
    two components of the bearing noise of std σ_b, ``E[P_ỹ] y = 2σ_b² y`` to second order,
    so ``P_ỹ − 2σ_b² ỹỹᵀ`` is unbiased there, and the fixed point with it (bench/noise_bias.py:
    2.2 cm of bias down to 0.08 cm on paper_noisy's agent_4)."""
    if p_own is None:
        p_own = np.take(p_hat, edges.agent, axis=0)
    e = p_own - p_hat_nbr
    along = (1.0 + 2.0 * bias_std ** 2) * so3.dot(y, e) / so3.dot(y, y)
    p_next = p_hat - h_k_p * edges.sum_by_agent(e - y * along[:, None])
    return p_next if moved is None else p_next + moved


def after_start(flags: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``flags`` ``(K, ...)`` along the samples without the stretch that holds from sample 0
    (what the check at t = 0 reports): a later onset only."""
    cleared = np.where(flags.all(axis=0), flags.shape[0], np.argmin(flags, axis=0))
    k = np.arange(flags.shape[0]).reshape((-1,) + (1,) * (flags.ndim - 1))
    return flags & (k >= cleared)


def repeated(eig: Array) -> bool:
    """Two eigenvalues (ascending) closer than :data:`EIGEN_GAP_REL` of the largest."""
    return bool(np.min(np.diff(eig)) <= EIGEN_GAP_REL * max(eig[-1], 1e-300))


class BearingLeaderEstimator(Estimator[GL, S]):
    """What the two leader-follower methods share; subclasses give the step and the spectrum
    their lemma needs."""

    roles: ClassVar[Roles] = Roles(leaders=2)
    sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.GYRO, Sensor.BEARINGS,
                                                     Sensor.KNOWN_POSE})
    optional_sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.ODOMETRY})
    measures: ClassVar[Mapping[Sensor, str | None]] = {Sensor.BEARINGS: None}
    partner_sensor: ClassVar[Sensor | None] = Sensor.BEARINGS
    sends: ClassVar[tuple[Channel, ...]] = (P_HAT, WORLD_BEARING, POSE_COV)
    frame: ClassVar[EstimateFrame] = EstimateFrame.WORLD
    conditioning_label: ClassVar[str]      # the local matrix, e.g. 'M_i = Σ_j k_ij b_ij b_ijᵀ'

    def prior(self, n: int, dof: int = DOF) -> Array:
        """The covariance of ``n`` initial estimates (the gains' ``initial_*_std``)."""
        return initial_covariance(n, self.gains.initial_position_std,
                                  self.gains.initial_attitude_std, dof)

    def with_known_pose(self, x: S, rows: Index, R: Array, p: Array) -> S:
        """Leaders: their known pose, exactly (a zero covariance)."""
        x = super().with_known_pose(x, rows, R, p)
        x.P[rows] = 0.0
        return x

    def warm_start(self, x: S, inputs: StepInputs) -> WarmStart:
        """The attitude from Wahba's problem between ``b^i_ij`` and ``d_ij``, the position
        triangulated from the ``p̂_j`` along ``d_ij`` (:mod:`core.warm_start`), with the fit's
        covariance; refused when a residual exceeds :data:`WARM_SIGMAS` of its noise (an
        outlier, a neighbour's bad estimate) or the bearings are (nearly) collinear."""
        b = inputs.edge[Sensor.BEARINGS.value]
        d, p_j = self.neighbour_terms(inputs)
        attitude, position = (warm_start.wahba(b, d, inputs.edges.k),
                              warm_start.triangulate(p_j, d, inputs.edges.k))
        if attitude is None or position is None:
            return WarmStart(None, f'not determined: {len(b)} neighbour bearing(s) within '
                                   f'{np.degrees(warm_start.MIN_SPREAD_RAD):g} deg of a line')
        (R, res_R), (p, res_p) = attitude, position
        P_j = inputs.edge[POSE_COV.name]
        dist = np.linalg.norm(p_j - p, axis=1)
        var = 2.0 * self.gains.bearing_std ** 2 + np.trace(P_j[:, 3:6, 3:6], axis1=1, axis2=2) / 3
        sig_R = np.maximum(np.sqrt(var), WARM_FLOOR_RAD)
        sig_p = np.maximum(np.sqrt(var + np.trace(P_j[:, :3, :3], axis1=1, axis2=2)
                                   / (3.0 * np.maximum(dist, 1e-9) ** 2)), WARM_FLOOR_RAD)
        z = max(float(np.max(res_R / sig_R)), float(np.max(res_p / sig_p)))
        residual = f'residual {max(res_R.max(), res_p.max()):.2g} rad ({z:.2g} sigma)'
        if z > WARM_SIGMAS:
            return WarmStart(None, f'refused: {residual} from {len(b)} neighbours')
        x = self.initial_state(R[None], p[None])
        x.P[0, :3, :3] = np.linalg.inv(warm_start.information(d, sig_p, dist))
        x.P[0, 3:6, 3:6] = np.linalg.inv(warm_start.information(d, sig_R))
        return WarmStart(x, f'accepted: {residual} from {len(b)} neighbours')

    def missing(self, channel: str) -> Array:
        """A neighbour's covariance not received (yet): the prior, what nothing is known of."""
        if channel != POSE_COV.name:
            return super().missing(channel)
        return self.prior(1)[0]

    def outbox(self, x: S, sender: Index, bearings: Array,
               slot: Index | None = None) -> dict[str, Array]:
        """``R̂_j b^j_jl`` per sender row j and listener l, ``p̂_j`` and its covariance."""
        R = np.take(x.R_hat, sender, axis=0)
        return {WORLD_BEARING.name: np.einsum('eab,eb->ea', R, bearings),
                P_HAT.name: x.p_hat, POSE_COV.name: x.P[:, :DOF, :DOF]}

    @staticmethod
    def neighbour_terms(inputs: StepInputs) -> tuple[Array, Array]:
        """``(d_ij = R̂_j b^j_ij (E, 3), p̂_j (E, 3))`` from what the neighbours sent."""
        return -inputs.edge[WORLD_BEARING.name], inputs.edge[P_HAT.name]

    def covariance_step(self, x: S, h: float, inputs: StepInputs, p_nbr: Array, moved: Array | None,
                        jacobians: Callable[[Array, Array], Jacobians]) -> Array:
        """``P⁺`` (:func:`.covariance.propagate`) linearised at the estimate before the step:
        the method's ``jacobians`` at ``y_ij = R̂_i b^i_ij`` and ``d_ij = ‖p̂_i − p̂_j‖``."""
        edges, g = inputs.edges, self.gains
        p_own = inputs.edge.get(P_OWN)
        if p_own is None:
            p_own = np.take(x.p_hat, edges.agent, axis=0)
        y = np.einsum('eab,eb->ea', np.take(x.R_hat, edges.agent, axis=0), inputs.edge['bearings'])
        return propagate(x.P, h, edges, y, inputs.edge[POSE_COV.name], g.bearing_std,
                         g.gyro_noise_density, jacobians(y, np.linalg.norm(p_own - p_nbr, axis=1)),
                         moved, g.odometry_noise_density, inputs.edge.get(HELD))

    # ------------------------------------------------------------------ Assumption 2
    def check(self, fleet: Fleet) -> CheckReport:
        report = CheckReport(spectra_of=self.conditioning_label)
        add = report.findings.append
        names = list(fleet.names)
        nbrs = {names[i]: [names[j] for j, _ in fleet.neighbours[i]] for i in range(fleet.n)}

        cycle = graph.find_cycle(names, nbrs)
        if cycle:
            add(Finding('error', cycle[0], 'neighbours', 'the sensing graph has a cycle: '
                        + ' -> '.join(cycle) + ' (Assumption 2a)',
                        f'remove {cycle[1]} from the neighbours of {cycle[0]} (or another edge '
                        'of the cycle)'))
        leaders = [names[k] for k in fleet.leaders]
        reach = [graph.reachable_from(leader, names, nbrs) for leader in leaders]
        for i in fleet.followers:
            name, neighbours = names[i], fleet.neighbours[i]
            if len(neighbours) < 2:
                add(Finding('error', name, 'neighbours', f'has {len(neighbours)} '
                            'neighbour(s), needs at least 2 (Assumption 2d)',
                            'add an earlier agent it can see'))
            if not cycle:
                for j, _ in neighbours:
                    if j > i:
                        add(Finding('error', name, 'neighbours', f'{names[j]} comes after '
                                    f'{name} in `agents`; neighbours must be earlier '
                                    '(Assumption 2d)',
                                    f'move {names[j]} above {name} in `agents`'))
            for leader, seen in zip(leaders, reach):
                if name not in seen:
                    add(Finding('error', name, 'neighbours', f'not reachable from leader '
                                f'{leader} (Assumption 2a)', f'give {name} or one of its '
                                f'ancestors a path from {leader}'))

            idx = [j for j, _ in neighbours]
            d = fleet.positions[idx] - fleet.positions[i]
            dist = np.linalg.norm(d, axis=1)
            if len(idx) == 0 or np.any(dist < graph.COLLOCATED_M):
                continue  # already reported
            b = d / dist[:, None]
            if len(idx) >= 2:
                widest = float(graph.widest_angles(b))
                if widest < COLLINEAR_ERROR_RAD:
                    add(Finding('error', name, 'neighbours', 'all bearings to its neighbours '
                                'are collinear, so its position is unobservable '
                                '(Assumption 2d)',
                                'add a neighbour off the line through the current ones'))
                elif np.degrees(widest) < COLLINEAR_WARN_DEG:
                    add(Finding('warning', name, 'neighbours', f'bearings are nearly '
                                f'collinear (widest angle {np.degrees(widest):.2f} deg): slow, '
                                'noise-sensitive position estimate',
                                'add a neighbour in another direction'))
            k_ij = np.array([k for _, k in neighbours])
            eig = np.linalg.eigvalsh(self.conditioning(b, k_ij)).astype(np.float64)
            report.spectra[name] = eig
            problem = self.conditioning_problem(eig)
            if problem is not None:
                add(Finding('warning', name, 'neighbours', problem,
                            self.conditioning_fix(eig, names[neighbours[0][0]], len(idx))))
        return report

    # ------------------------------------------------------------------ along the motion
    def check_motion(self, fleet: Fleet, times: Array, positions: Array) -> list[Finding]:
        """Assumption 2d's geometry and the lemma's spectrum along a moving fleet: per follower at
        most one finding for (nearly) collinear bearings and one for its spectrum (every
        :data:`SPECTRUM_STEP_DEG` of bearing turn), each with its first time and worst sample;
        only an onset after t = 0 (else :meth:`check`'s); collocated samples are skipped."""
        by_size: dict[int, list[int]] = {}
        for i in fleet.followers:
            if len(fleet.neighbours[i]) >= 2:
                by_size.setdefault(len(fleet.neighbours[i]), []).append(i)
        found: list[tuple[int, int, Finding]] = []   # (agent index, kind, finding)
        block = max(1, MOTION_BLOCK // max(len(times), 1))
        for group in by_size.values():
            for start in range(0, len(group), block):
                part = group[start:start + block]
                own = np.array(part, dtype=np.intp)
                nbr = np.array([[j for j, _ in fleet.neighbours[i]] for i in part], dtype=np.intp)
                d = positions[:, nbr, :] - positions[:, own, None, :]     # (K, F, M, 3)
                dist = np.linalg.norm(d, axis=-1)
                valid = np.all(dist >= graph.COLLOCATED_M, axis=-1)        # (K, F)
                b = d / np.where(valid[..., None], dist, 1.0)[..., None]
                widest = graph.widest_angles(b)                           # (K, F)
                # Evaluate the spectrum at each SPECTRUM_STEP_DEG of cumulative bearing turn
                # (chords: the angles for small steps) and where a valid stretch starts.
                turned = np.zeros(valid.shape)
                turned[1:] = np.cumsum(np.linalg.norm(np.diff(b, axis=0), axis=-1).max(axis=-1),
                                       axis=0)
                bucket = np.floor(turned / np.radians(SPECTRUM_STEP_DEG))
                spectrum_at = np.ones(valid.shape, dtype=bool)
                spectrum_at[1:] = (bucket[1:] != bucket[:-1]) | ~valid[:-1]
                spectrum_at &= valid
                for f, i in enumerate(part):
                    finding = self._collinear_along(fleet, i, times, widest[:, f], valid[:, f])
                    if finding is not None:
                        found.append((i, 0, finding))
                    finding = self._conditioning_along(fleet, i, times, b[:, f],
                                                       spectrum_at[:, f])
                    if finding is not None:
                        found.append((i, 1, finding))
        return [f for _, _, f in sorted(found, key=lambda x: x[:2])]

    def _collinear_along(self, fleet: Fleet, i: int, times: Array, widest: Array,
                         valid: NDArray[np.bool_]) -> Finding | None:
        """The collinearity finding of follower ``i`` from its widest angle ``(K,)``."""
        name = fleet.names[i]
        deg = np.degrees(widest)
        collinear = after_start(valid & (widest < COLLINEAR_ERROR_RAD))
        nearly = after_start(valid & (deg < COLLINEAR_WARN_DEG))
        if not nearly.any():
            return None
        nbrs = ', '.join(fleet.names[j] for j, _ in fleet.neighbours[i])
        if collinear.any():
            k = int(np.argmax(collinear))
            return Finding('error', name, 'velocity', f'at t = {times[k]:.2f} s its bearings '
                           f'to its neighbours become collinear (widest angle {deg[k]:.2g} deg),'
                           ' so its position is unobservable then (Assumption 2d)',
                           f'change the velocities of {name} or of its neighbours ({nbrs}), '
                           'or add a neighbour off the line through the current ones')
        k = int(np.argmax(nearly))
        when = np.flatnonzero(nearly)
        w = int(when[np.argmin(widest[when])])
        worst = f'widest angle {deg[k]:.2f} deg' + (
            '' if w == k else f', down to {deg[w]:.2f} deg at t = {times[w]:.2f} s')
        return Finding('warning', name, 'velocity', f'at t = {times[k]:.2f} s its bearings '
                       f'become nearly collinear ({worst}): slow, noise-sensitive position '
                       'estimate', f'change the velocities of {name} or of its neighbours '
                       f'({nbrs}), or add a neighbour in another direction')

    def _conditioning_along(self, fleet: Fleet, i: int, times: Array, b: Array,
                            at: NDArray[np.bool_]) -> Finding | None:
        """The spectrum finding of follower ``i`` from its bearings ``(K, M, 3)`` at ``at``."""
        name, neighbours = fleet.names[i], fleet.neighbours[i]
        k_ij = np.array([k for _, k in neighbours])
        samples = np.flatnonzero(at)
        if samples.size == 0:
            return None
        mats = np.stack([self.conditioning(b[k], k_ij) for k in samples])
        eig = np.linalg.eigvalsh(mats).astype(np.float64)
        problem = [self.conditioning_problem(e) for e in eig]
        bad = after_start(np.array([p is not None for p in problem]))
        if not bad.any():
            return None
        first = int(np.argmax(bad))
        when = np.flatnonzero(bad)
        w = int(when[np.argmin([self.conditioning_margin(eig[j]) for j in when])])
        worst = '' if w == first else f' (the worst at t = {times[samples[w]]:.2f} s)'
        return Finding('warning', name, 'velocity', f'at t = {times[samples[first]]:.2f} s'
                       f'{worst} {problem[w]}',
                       self.conditioning_fix(eig[w], fleet.names[neighbours[0][0]],
                                             len(neighbours))
                       + f', or change the velocities of {name} or of its neighbours')

    def conditioning(self, bearings: Array, k: Array) -> Array:
        """``M_i = Σ_j k_ij b_ij b_ijᵀ`` (B&T's Lemma 1; Tran et al. add to it)."""
        return np.einsum('e,ea,eb->ab', k, bearings, bearings)

    def conditioning_margin(self, eig: Array) -> float:
        """The smallest gap of the spectrum ``eig`` (ascending) relative to its largest (both
        lemmas need distinct eigenvalues): ranks the samples of a moving fleet."""
        return float(np.min(np.diff(eig)) / max(eig[-1], 1e-300))

    def conditioning_fix(self, eig: Array, first_neighbour: str, n_neighbours: int) -> str:
        """How to mend the spectrum ``eig`` that :meth:`conditioning_problem` objects to."""
        return (f'use different per-edge gains, e.g. `neighbours: [{{name: {first_neighbour}, '
                'k: 2.0}, ...]`')
