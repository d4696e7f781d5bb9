"""Batch simulator: the whole network in one process, vectorised over agents and edges. The
truth is stepped at the estimator step ``h``; every agent's :meth:`Estimator.step` (what a node
calls for its one agent) reads what the method declares, measured at the step's start with
:class:`.noise.NoiseModel`'s noise. Leaders' estimates are their truth."""
from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from ..core.bearing_rates import BearingRateFilter
from ..core.formation import formation_error
from ..core.motion import in_anchor_frame, yaw_of
from ..estimators.base import (ANCHOR_DELTA_R, ANCHOR_DISPLACEMENT, DELTA_R, DISPLACEMENT,
                               IS_ANCHOR, PEER_DELTA_R, PEER_DISPLACEMENT, PINNED, EstimateFrame,
                               Index, Mask, Sensor, State, StepInputs, edge_table, route)
from ..metrics.results import PoseErrors, Recording, pose_errors, to_world
from ..scenario.model import Scenario, initial_estimates
from ..scenario.truth import OnTruth, Truth
from .noise import NoiseModel

Array = NDArray[np.float64]


class BatchSimulator(OnTruth):
    """All agents' estimators in lock-step; ``step`` [s]: default ``1 / scenario.frequency``."""

    def __init__(self, scenario: Scenario, step: float | None = None) -> None:
        self.scenario = scenario
        self.h = float(step if step is not None else scenario.step)
        self.estimator = scenario.estimator()
        self.truth = Truth(scenario, self.h)
        self.n = len(scenario.agents)
        fleet = scenario.fleet()
        self.leader_idx = np.array(fleet.leaders, dtype=np.intp)
        self.follower_idx = np.array(fleet.followers, dtype=np.intp)
        k = np.array([k for nbrs in fleet.neighbours for _, k in nbrs])
        self.table = edge_table(type(self.estimator), self.n, *fleet.sensing_edges(), k,
                                fleet.anchor, fleet.ranged)
        self.edges = self.table.edges(self.n)
        self.edge_nbr = self.table.other
        # Static positions: the world bearings never change (per sensor's rows).
        self._world_bearings: dict[tuple[str | None, bool], Array] = {}
        self.odometry = scenario.simulates('odometry')
        self.reset()

    @property
    def R_hat(self) -> Array:
        """Attitude estimates now, ``(N, 3, 3)`` (assignable, e.g. to start from a guess)."""
        return self.x.R_hat

    @R_hat.setter
    def R_hat(self, value: Array) -> None:
        self.x.R_hat = np.array(value, dtype=float)

    @property
    def p_hat(self) -> Array:
        """Position estimates now, ``(N, 3)`` [m] (assignable)."""
        return self.x.p_hat

    @p_hat.setter
    def p_hat(self, value: Array) -> None:
        self.x.p_hat = np.array(value, dtype=float)

    def true_estimates(self) -> tuple[Array, Array]:
        """The true poses now in the method's estimate frame, ``(R (N,3,3), p (N,3))``."""
        a = self.scenario.anchor_index
        if a is None or self.estimator.frame is not EstimateFrame.ANCHOR_BODY:
            return self.R.copy(), self.p.copy()
        return in_anchor_frame(self.R, self.p, a)

    def reset(self) -> None:
        """Back to t = 0, the initial estimates and re-seeded noise: a run repeats exactly."""
        self.noise = NoiseModel(self.scenario.noise, self.n, self.scenario.sensors)
        self.truth.reset()
        self.x: State = self.estimator.initial_state(*initial_estimates(self.scenario))
        # Bearing rates from consecutive bearings (from_bearings), as each node does: one
        # filter row per link, and the previous step's gyro increments.
        spec = self.scenario.sensors.bearing_rates
        self._rates: BearingRateFilter | None = (
            BearingRateFilter(len(self.edges), spec.tau)
            if spec.from_bearings and Sensor.BEARING_RATES in type(self.estimator).measures
            else None)
        self._prev_delta_R = np.tile(np.eye(3), (self.n, 1, 1))

    def _rows(self, flag: str | None) -> Index:
        """The edges with ``flag`` (None: all)."""
        return (np.arange(len(self.edges)) if flag is None
                else np.flatnonzero(self.table.flags[flag]))

    def measure(self, sensor: Sensor, flag: str | None, theirs: bool = False) -> Array:
        """What the edges with ``flag`` measure now by ``sensor``, noise drawn ``(M, 3)``: each
        edge's agent of the other end, or (``theirs``) the other end of the agent."""
        rows = self._rows(flag)
        owner, target = self.edges.agent[rows], self.edge_nbr[rows]
        if theirs:
            owner, target = target, owner
        if sensor is Sensor.BEARINGS:
            key = (flag, theirs)
            b_world = self._world_bearings.get(key)
            if b_world is None:
                b_world = self.truth.world_bearings(owner, target)
                if not self.truth.moves:   # static positions: the world bearings never change
                    self._world_bearings[key] = b_world
            return self.noise.bearings(self.truth.body_bearings(owner, b_world), self.t)
        if sensor is Sensor.RELATIVE_POSITIONS:
            return self.noise.sensor(sensor.value, self.truth.relative_positions(owner, target))
        if sensor is Sensor.BEARING_RATES:
            return self.noise.sensor(sensor.value, self.truth.bearing_rates(owner, target))
        raise ValueError(f'the batch simulator cannot simulate {sensor.value} per edge')

    def inputs(self) -> StepInputs:
        """What every agent's next step consumes, measured now (module docstring)."""
        est = self.estimator
        cls = type(est)
        agent, other = self.edges.agent, self.edge_nbr
        n_edges = len(self.edges)
        edge: dict[str, Array] = {}
        mask: dict[str, Mask] = {}
        for sensor, flag in cls.measures.items():
            if sensor is Sensor.BEARING_RATES and self._rates is not None:
                continue   # estimated from the bearings below, once the gyro is known
            values = np.zeros((n_edges, 3))
            values[self._rows(flag)] = self.measure(sensor, flag)
            edge[sensor.value] = values
        # The other end's measurement of each edge's agent, where it makes one.
        theirs = np.zeros((n_edges, 3))
        if cls.partner_sensor is not None:
            carrier = next((c for c in cls.sends if c.sensor is cls.partner_sensor), None)
            flag = None if carrier is None else carrier.on
            theirs[self._rows(flag)] = self.measure(cls.partner_sensor, flag, theirs=True)
        delta_R = self.gyro_increment(self.truth.increment())
        values_agent: dict[str, Array] = {DELTA_R: delta_R}
        if self._rates is not None:   # (11) reads back this de-rotated one: β̇ = β̇° - ω × β
            bearings = edge[Sensor.BEARINGS.value]
            sensing = np.zeros(n_edges, dtype=bool)
            sensing[self._rows(cls.measures[Sensor.BEARING_RATES])] = True
            derotated, have = self._rates.update(self.t, bearings, self._prev_delta_R[agent],
                                                 sensing)
            omega = so3.log_small(delta_R) / self.h
            edge[Sensor.BEARING_RATES.value] = np.where(
                have[:, None], derotated - so3.cross(omega[agent], bearings), 0.0)
            mask[Sensor.BEARING_RATES.value] = have   # none before the second bearing
        self._prev_delta_R = delta_R
        if self.odometry:   # R(t)ᵀ (p(t+h) - p(t)), noise averaged over the samples it spans
            values_agent[DISPLACEMENT] = self.noise.odometry_displacement(
                self.truth.displacement(), self.h, self.h * self.scenario.sensors.odometry.rate)
        displacement = values_agent.get(DISPLACEMENT, np.zeros((self.n, 3)))
        if cls.peer_odometry == 'links':
            edge[PEER_DELTA_R], edge[PEER_DISPLACEMENT] = delta_R[other], displacement[other]
        a = self.scenario.anchor_index
        if cls.roles.anchor:
            assert a is not None
            is_anchor = np.arange(self.n) == a
            values_agent.update({
                ANCHOR_DELTA_R: np.repeat(delta_R[a:a + 1], self.n, 0),
                ANCHOR_DISPLACEMENT: np.repeat(displacement[a:a + 1], self.n, 0),
                IS_ANCHOR: is_anchor, PINNED: is_anchor & self.scenario.anchor_pinned})
        reverse = self.table.reverse
        assert self.edges.slot is not None
        slot = None if cls.links == 'sensing' else self.edges.slot[reverse]
        sent = est.outbox(self.x, other, theirs, slot=slot)
        edge.update(route(sent, [c for c in cls.sends if c.round == 1], other))
        inputs = StepInputs(edges=self.edges, agent=values_agent, edge=edge, mask=mask,
                            t=self.t)
        if cls.rounds() == 1:
            return inputs
        second = est.reply(self.x, self.h, inputs)
        return dataclasses.replace(inputs, edge={**edge, **{name: v[reverse]
                                                            for name, v in second.items()}})

    def extra_errors(self) -> dict[str, float]:
        """The recording's extra columns now: each owned link's pair error
        ``<label>_<a>_<b>`` and, under formation control, ``formation_err_<agent>_m``."""
        out: dict[str, float] = {}
        names = [a.name for a in self.scenario.agents]
        per_edge = self.estimator.edge_errors(self.x, self.R, self.edges, self.edge_nbr)
        if per_edge is not None:
            label = self.estimator.edge_error_label
            for e in np.flatnonzero(self.edges.flag('owns')):
                a, b = sorted((int(self.edges.agent[e]), int(self.edge_nbr[e])))
                out[f'{label}_{names[a]}_{names[b]}'] = float(per_edge[e])
        if self.truth.p_star is not None:
            for name, err in zip(names, formation_error(self.p, self.truth.p_star)):
                out[f'formation_err_{name}_m'] = float(err)
        return out

    def gyro_increment(self, delta_R: Array) -> Array:
        """What the gyros report over the step: ``ΔR exp(h (bias + noise))`` (body frame),
        the noise averaged over the IMU samples the step spans (``simulation.imu_rate``)."""
        samples = self.h * self.scenario.simulation.imu_rate
        return self.noise.gyro_increment(delta_R, self.h, samples)

    def step(self) -> None:
        """Advance truth and every estimator by one step ``h``."""
        if self.truth.control is not None and self.truth.control.mode == 'paper':
            self.truth.controller_yaws = yaw_of(self.x.R_hat)
        if not self.truth.v_anchor.is_zero:   # u_i = Q̂_iᵀ v_i(t), held over the step
            self.truth.command(self.x.R_hat)
        inputs = self.inputs()
        self.truth.advance()
        self.x, _ = self.estimator.step(self.x, self.h, inputs,
                                        reorthonormalize=self.truth.reorthonormalizes)
        if len(self.leader_idx):  # leaders know their pose
            self.x = self.estimator.with_known_pose(self.x, self.leader_idx,
                                                    self.R[self.leader_idx],
                                                    self.p[self.leader_idx])

    def errors(self) -> PoseErrors:
        """Errors of the estimating agents now (:func:`metrics.results.pose_errors`)."""
        return pose_errors(self.estimator.frame, self.R, self.p, self.x.R_hat, self.x.p_hat,
                           self.follower_idx, anchor=self.scenario.anchor_index)

    def run(self, duration: float, record_every: float = 0.1,
            progress: Callable[[float, Array, Array], None] | None = None,
            progress_every: float = 10.0) -> Recording:
        """Run from the current state for ``duration`` simulated seconds, recording every
        ``record_every`` [s] (whole steps), ``progress(t, att_err, pos_err)`` every
        ``progress_every``; a moving fleet's also holds :class:`metrics.results.Trajectories`."""
        n_steps = int(round(duration / self.h))
        every = max(1, int(round(record_every / self.h)))
        prog_every = max(1, int(round(progress_every / self.h)))
        tracks = self.truth.moves
        extras = (self.estimator.edge_error_label != '' or self.truth.p_star is not None)
        extra: list[dict[str, float]] = []
        t, rows, p, p_hat = [], [], [], []
        for s in range(n_steps + 1):
            if s % every == 0 or s == n_steps:
                t.append(self.t)
                rows.append(self.errors())
                if extras:
                    extra.append(self.extra_errors())
                if tracks:
                    p.append(self.p.copy())
                    p_hat.append(to_world(self.estimator.frame, self.R, self.p, self.x.R_hat,
                                          self.x.p_hat, self.scenario.anchor_index)[1].copy())
            if progress is not None and s % prog_every == 0 and s:
                progress(self.t, rows[-1].att_err, rows[-1].pos_err)
            if s < n_steps:
                self.step()
        followers = [a.name for a in self.scenario.followers]
        columns = {name: np.array([row[name] for row in extra]) for name in
                   (extra[0] if extra else {})}
        if not tracks:
            return Recording.of(t, followers, rows, extra=columns)
        return Recording.of(t, followers, rows, agents=[a.name for a in self.scenario.agents],
                            leaders=list(self.scenario.leaders), p=p, p_hat=p_hat,
                            extra=columns)
