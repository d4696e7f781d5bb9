"""Batch simulator: the whole network in one process, vectorised over agents and edges.

The truth is :class:`.truth.Truth` stepped at the estimator step ``h``. Each step, every agent's
estimator advances with the scenario's method (:meth:`estimators.base.Estimator.step`, the
same function the estimator node calls for its one agent) on measurements taken at the step's
start:

- own bearings ``b^i_ij = R_iᵀ b_ij`` (+ bearing noise);
- what each neighbour j sends i (:meth:`Estimator.outbox`), formed from j's state and its own
  measurement ``b^j_ji = R_jᵀ b_ji`` (+ noise) at the same instant;
- the gyro increment ``ΔR exp(h (bias + noise))`` over the step;
- for moving fleets (when the scenario simulates odometry), the odometry displacement over the
  step ``δ = R(t)ᵀ (p(t+h) - p(t))`` (+ noise), the exact integral of what the samples report.

Noise (all off by default) comes from :class:`.noise.NoiseModel`, the same models the
simulator node's world uses; a scenario and its ``noise.seed`` give the same run.

Leaders (for methods that have them) know their pose: their estimate is their truth.

Methods whose robots talk both ways over every sensing edge (``links = 'communication'``, De
Carli et al.) step over communication links instead (:func:`estimators.base.communication_links`):
each robot's own relative positions ``ⁱp_ij = R_iᵀ (p_j - p_i)`` (+ noise) to the robots it
senses, what each neighbour sends formed from its state and its own measurement of the robot
(where it senses it), and the neighbour's gyro increment and odometry over the step. In the
formation controller's ``paper`` mode the truth moves with the estimated yaws (a closed loop).
Their recordings add each pair's error (:meth:`Estimator.edge_errors`) and, under formation
control, each robot's formation error (:func:`core.formation.formation_error`).

Two-round methods (``rounds = 2``, Presenza et al.) step over the same links, the anchor's
ranged robots linked too: own bearings and bearing rates of the robots each senses (directed
sensing), the round-1 channels (:meth:`Estimator.outbox`; the anchor's relative positions of
its ranged robots), then the round-2 channels each robot forms from them
(:meth:`Estimator.reply`), and the anchor's gyro increment and odometry for every robot
(:class:`estimators.base.AnchorInputs`). Agents with ``anchor_estimate`` velocities move with
the commands their estimates give (:meth:`scenario.truth.Truth.command`, a closed loop).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from ..core.bearing_rates import BearingRateFilter
from ..core.formation import formation_error
from ..core.motion import in_anchor_frame, yaw_of
from ..estimators.base import (AnchorInputs, Edges, EstimateFrame, LinkInputs, State, StepInputs,
                               communication_links, route)
from ..metrics.results import PoseErrors, Recording, pose_errors, to_world
from ..scenario.model import Scenario, initial_estimates
from ..scenario.truth import OnTruth, Truth
from .noise import NoiseModel

Array = NDArray[np.float64]


class BatchSimulator(OnTruth):
    """Simulate a scenario with all agents' estimators in lock-step.

    Args:
        scenario: a parsed scenario (run :func:`scenario.check_scenario` first).
        step: integration / estimator step [s]; default ``1 / scenario.frequency``.
    """

    def __init__(self, scenario: Scenario, step: float | None = None) -> None:
        self.scenario = scenario
        self.h = float(step if step is not None else scenario.step)
        self.estimator = scenario.estimator()
        self.truth = Truth(scenario, self.h)
        agents = scenario.agents
        self.n = len(agents)
        self.leader_idx = np.array([scenario.index[name] for name in scenario.leaders],
                                   dtype=np.intp)
        self.follower_idx = np.array([scenario.index[a.name] for a in scenario.followers],
                                     dtype=np.intp)
        owner, nbr, k = [], [], []
        for a in agents:
            for nb in a.neighbours:
                owner.append(scenario.index[a.name])
                nbr.append(scenario.index[nb.name])
                k.append(nb.k)
        self.links = None
        anchor = scenario.anchor_index
        self._ranged = ([(anchor, scenario.index[r]) for r in scenario.ranged]
                        if anchor is not None else [])
        if self.estimator.links == 'communication':
            self.links = communication_links(np.array(owner, np.intp), np.array(nbr, np.intp),
                                             self.n, also=self._ranged)
            owner, nbr = list(self.links['agent']), list(self.links['other'])
            k = [1.0] * len(owner)
        self.edge_nbr = np.array(nbr, dtype=np.intp)
        self.edges = Edges(agent=np.array(owner, dtype=np.intp), k=np.array(k), n_agents=self.n)
        # Both ends of every edge measure: i its b^i_ij, j its b^j_ji.
        self._ends = np.concatenate([self.edges.agent, self.edge_nbr])
        self._other_ends = np.concatenate([self.edge_nbr, self.edges.agent])
        # Static positions: the world bearings never change.
        self._ends_b_world = (None if self.truth.moves
                              else self.truth.world_bearings(self._ends, self._other_ends))
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
        """The true poses now in the method's estimate frame, ``(R (N,3,3), p (N,3))``: the
        world's, or the anchor's body frame for methods with an anchor."""
        a = self.scenario.anchor_index
        if a is None or self.estimator.frame is not EstimateFrame.ANCHOR_BODY:
            return self.R.copy(), self.p.copy()
        return in_anchor_frame(self.R, self.p, a)

    def reset(self) -> None:
        """Back to t = 0: true attitudes, the scenario's initial estimates, and the noise
        generators (and gyro biases) re-seeded, so a run after reset repeats exactly."""
        self.noise = NoiseModel(self.scenario.noise, self.n, self.scenario.sensors)
        self.truth.reset()
        self.x: State = self.estimator.initial_state(*initial_estimates(self.scenario))
        # Bearing rates estimated from consecutive bearings (sensors.bearing_rates
        # .from_bearings), as each robot's node does: one filter row per link, and the
        # previous step's gyro increments (the rotation between two bearings).
        spec = self.scenario.sensors.bearing_rates
        self._rates: BearingRateFilter | None = (
            BearingRateFilter(len(self.edges), spec.tau)
            if spec.from_bearings and self.links is not None else None)
        self._prev_delta_R = np.tile(np.eye(3), (self.n, 1, 1))

    def inputs(self) -> StepInputs:
        """What every agent's next step consumes, measured now (noise drawn)."""
        if self.estimator.rounds == 2:
            return self.two_round_inputs()
        if self.links is not None:
            return self.link_inputs()
        b_world = (self._ends_b_world if self._ends_b_world is not None
                   else self.truth.world_bearings(self._ends, self._other_ends))
        both = self.truth.body_bearings(self._ends, b_world)
        n_edges = len(self.edges)
        b_own = self.noise.bearings(both[:n_edges], self.t)
        b_theirs = self.noise.bearings(both[n_edges:], self.t)
        sent = self.estimator.outbox(self.x, self.edge_nbr, b_theirs)
        displacement = None
        if self.odometry:
            displacement = self.odometry_displacement()
        return StepInputs(delta_R=self.gyro_increment(self.truth.increment()), edges=self.edges,
                          bearings=b_own,
                          received=route(sent, self.estimator.sends, self.edge_nbr),
                          displacement=displacement)

    def link_inputs(self) -> StepInputs:
        """:meth:`inputs` of a ``links = 'communication'`` method."""
        assert self.links is not None
        agent, other = self.edges.agent, self.edge_nbr
        senses, sensed_by = self.links['senses'], self.links['sensed_by']
        y = self.noise.sensor('relative_positions',
                              self.truth.relative_positions(agent, other)) * senses[:, None]
        theirs = self.noise.sensor('relative_positions', self.truth.relative_positions(
            other, agent)) * sensed_by[:, None]
        assert self.edges.slot is not None
        sent = self.estimator.outbox(self.x, other, theirs,
                                     slot=self.edges.slot[self.links['reverse']])
        delta_R = self.gyro_increment(self.truth.increment())
        displacement = self.odometry_displacement()
        links = LinkInputs(senses=senses, sensed_by=sensed_by, owns=self.links['owns'],
                           relative_positions=y, other_delta_R=delta_R[other],
                           other_displacement=displacement[other])
        return StepInputs(delta_R=delta_R, edges=self.edges, bearings=np.zeros((len(agent), 3)),
                          received=route(sent, self.estimator.sends, other),
                          displacement=displacement, links=links, t=self.t)

    def two_round_inputs(self) -> StepInputs:
        """:meth:`inputs` of a two-round method (module docstring)."""
        assert self.links is not None
        agent, other = self.edges.agent, self.edge_nbr
        senses, sensed_by = self.links['senses'], self.links['sensed_by']
        pairs = set(self._ranged)
        ranges = np.array([(int(i), int(j)) in pairs for i, j in zip(agent, other)], bool)
        ranged_by = ranges[self.links['reverse']]
        sensing = np.flatnonzero(senses)
        bearings = np.zeros((len(agent), 3))
        rates = np.zeros((len(agent), 3))
        if len(sensing):
            owner, target = agent[sensing], other[sensing]
            b = self.truth.body_bearings(owner, self.truth.world_bearings(owner, target))
            bearings[sensing] = self.noise.bearings(b, self.t)
            if self._rates is None:
                rates[sensing] = self.noise.sensor('bearing_rates',
                                                   self.truth.bearing_rates(owner, target))
        delta_R = self.gyro_increment(self.truth.increment())
        measured = None
        if self._rates is not None:   # (11) reads back this de-rotated one: β̇ = β̇° - ω × β
            derotated, have = self._rates.update(self.t, bearings, self._prev_delta_R[agent],
                                                 senses)
            omega = so3.log_small(delta_R) / self.h
            rates = np.where(have[:, None], derotated - so3.cross(omega[agent], bearings), 0.0)
            measured = have | ~senses   # no rate before the second bearing
        self._prev_delta_R = delta_R
        # The anchor's measurement of each ranged robot, on the anchor → robot link.
        ranged_measured = np.zeros((len(agent), 3))
        if ranged_by.any():
            theirs = np.flatnonzero(ranged_by)
            ranged_measured[theirs] = self.noise.sensor('relative_positions',
                                                 self.truth.relative_positions(
                                                     other[theirs], agent[theirs]))
        assert self.edges.slot is not None
        sent = self.estimator.outbox(self.x, other, ranged_measured,
                                     slot=self.edges.slot[self.links['reverse']])
        displacement = self.odometry_displacement()
        a = self.scenario.anchor_index
        assert a is not None
        is_anchor = np.arange(self.n) == a
        anchor = AnchorInputs(is_anchor=is_anchor, delta_R=np.repeat(delta_R[a:a + 1], self.n, 0),
                              displacement=np.repeat(displacement[a:a + 1], self.n, 0),
                              ranges=ranges, ranged_by=ranged_by,
                              pinned=self.scenario.anchor_pinned)
        links = LinkInputs(senses=senses, sensed_by=sensed_by, owns=self.links['owns'],
                           relative_positions=np.zeros((len(agent), 3)),
                           other_delta_R=delta_R[other], other_displacement=displacement[other],
                           measured=measured)
        first = [c for c in self.estimator.sends if c.round == 1]
        inputs = StepInputs(delta_R=delta_R, edges=self.edges, bearings=bearings,
                            received=route(sent, first, other), displacement=displacement,
                            links=links, t=self.t, bearing_rates=rates, anchor=anchor)
        second = self.estimator.reply(self.x, self.h, inputs)
        reverse = self.links['reverse']
        received = dict(inputs.received)
        received.update({name: v[reverse] for name, v in second.items()})
        return dataclasses.replace(inputs, received=received)

    def extra_errors(self) -> dict[str, float]:
        """The recording's columns beyond the pose errors, now: each pair's error (one
        column per owned link, ``<label>_<a>_<b>``) and, under formation control, each robot's
        formation error ``formation_err_<agent>_m``."""
        out: dict[str, float] = {}
        names = [a.name for a in self.scenario.agents]
        per_edge = self.estimator.edge_errors(self.x, self.R, self.edges, self.edge_nbr)
        if per_edge is not None:
            label = self.estimator.edge_error_label
            for e in np.flatnonzero(self.links['owns'] if self.links is not None
                                    else np.ones(len(self.edges), bool)):
                a, b = sorted((int(self.edges.agent[e]), int(self.edge_nbr[e])))
                out[f'{label}_{names[a]}_{names[b]}'] = float(per_edge[e])
        if self.truth.p_star is not None:
            for name, err in zip(names, formation_error(self.p, self.truth.p_star)):
                out[f'formation_err_{name}_m'] = float(err)
        return out

    def odometry_displacement(self) -> Array:
        """What odometry reports of the step, ``R(t)ᵀ (p(t+h) - p(t))`` ``(N, 3)`` [m], noise
        averaged over the samples the step spans (``sensors.odometry.rate``)."""
        samples = self.h * self.scenario.sensors.odometry.rate
        return self.noise.odometry_displacement(self.truth.displacement(), self.h, samples)

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
        """Run from the current state for ``duration`` seconds of simulated time.

        Args:
            duration: simulated time [s].
            record_every: record interval [s], rounded to a whole number of steps.
            progress: called as ``progress(t, att_err, pos_err)`` every ``progress_every``
                simulated seconds.

        When the fleet moves, the recording also holds every agent's true and estimated
        positions at the record times (:class:`metrics.results.Trajectories`; the estimates in
        the world frame, aligned as for the errors).
        """
        n_steps = int(round(duration / self.h))
        every = max(1, int(round(record_every / self.h)))
        prog_every = max(1, int(round(progress_every / self.h)))
        tracks = self.truth.moves
        extras = self.links is not None or self.truth.p_star is not None
        extra: list[dict[str, float]] = []
        t, rows = [], []
        p: list[Array] = []
        p_hat: list[Array] = []
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
