"""Batch simulator: the whole network in one process, vectorised over agents and edges.

The truth is :class:`.truth.Truth` stepped at the estimator step ``h``. Each step, every agent's
estimator advances with the scenario's method (:meth:`estimators.base.Estimator.step`, the
same function the estimator node calls for its one agent) on measurements taken at the step's
start:

- own bearings ``b^i_ij = R_iᵀ b_ij`` (+ bearing noise);
- what each neighbour j sends i (:meth:`Estimator.outbox`), formed from j's state and its own
  measurement ``b^j_ji = R_jᵀ b_ji`` (+ noise) at the same instant;
- the gyro increment ``ΔR exp(h (bias + noise))`` over the step.

Noise (all off by default) comes from :class:`.noise.NoiseModel`, the same models the
simulator node's world uses; a scenario and its ``noise.seed`` give the same run.

Leaders (for methods that have them) know their pose: their estimate is their truth.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ..estimators.base import Edges, State, StepInputs, route
from ..scenario.model import Scenario, initial_estimates
from ..studies.results import PoseErrors, Recording, pose_errors
from .noise import NoiseModel
from .truth import OnTruth, Truth

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
        self.edge_nbr = np.array(nbr, dtype=np.intp)
        self.edges = Edges(agent=np.array(owner, dtype=np.intp), k=np.array(k), n_agents=self.n)
        # Both ends of every edge measure: i its b^i_ij, j its b^j_ji (static positions).
        self._ends = np.concatenate([self.edges.agent, self.edge_nbr])
        self._ends_b_world = self.truth.world_bearings(self._ends,
                                                       np.concatenate([self.edge_nbr,
                                                                       self.edges.agent]))
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

    def reset(self) -> None:
        """Back to t = 0: true attitudes, the scenario's initial estimates, and the noise
        generators (and gyro biases) re-seeded, so a run after reset repeats exactly."""
        self.noise = NoiseModel(self.scenario.noise, self.n)
        self.truth.reset()
        self.x: State = self.estimator.initial_state(*initial_estimates(self.scenario))

    def inputs(self) -> StepInputs:
        """What every agent's next step consumes, measured now (noise drawn)."""
        both = self.truth.body_bearings(self._ends, self._ends_b_world)
        n_edges = len(self.edges)
        b_own = self.noise.bearings(both[:n_edges], self.t)
        b_theirs = self.noise.bearings(both[n_edges:], self.t)
        sent = self.estimator.outbox(self.x, self.edge_nbr, b_theirs)
        return StepInputs(delta_R=self.gyro_increment(self.truth.increment()), edges=self.edges,
                          bearings=b_own,
                          received=route(sent, self.estimator.sends, self.edge_nbr))

    def gyro_increment(self, delta_R: Array) -> Array:
        """What the gyros report over the step: ``ΔR exp(h (bias + noise))`` (body frame),
        the noise averaged over the IMU samples the step spans (``simulation.imu_rate``)."""
        samples = self.h * self.scenario.simulation.imu_rate
        return self.noise.gyro_increment(delta_R, self.h, samples)

    def step(self) -> None:
        """Advance truth and every estimator by one step ``h``."""
        inputs = self.inputs()
        self.truth.advance()
        self.x, _ = self.estimator.step(self.x, self.h, inputs,
                                        reorthonormalize=self.truth.reorthonormalizes)
        if len(self.leader_idx):  # leaders know their pose
            self.x = self.estimator.with_known_pose(self.x, self.leader_idx,
                                                    self.R[self.leader_idx],
                                                    self.p[self.leader_idx])

    def errors(self) -> PoseErrors:
        """Errors of the estimating agents now (:func:`studies.results.pose_errors`)."""
        return pose_errors(self.estimator.frame, self.R, self.p, self.x.R_hat, self.x.p_hat,
                           self.follower_idx)

    def run(self, duration: float, record_every: float = 0.1,
            progress: Callable[[float, Array, Array], None] | None = None,
            progress_every: float = 10.0) -> Recording:
        """Run from the current state for ``duration`` seconds of simulated time.

        Args:
            duration: simulated time [s].
            record_every: record interval [s], rounded to a whole number of steps.
            progress: called as ``progress(t, att_err, pos_err)`` every ``progress_every``
                simulated seconds.
        """
        n_steps = int(round(duration / self.h))
        every = max(1, int(round(record_every / self.h)))
        prog_every = max(1, int(round(progress_every / self.h)))
        t, rows = [], []
        for s in range(n_steps + 1):
            if s % every == 0 or s == n_steps:
                t.append(self.t)
                rows.append(self.errors())
            if progress is not None and s % prog_every == 0 and s:
                progress(self.t, rows[-1].att_err, rows[-1].pos_err)
            if s < n_steps:
                self.step()
        return Recording.of(t, [a.name for a in self.scenario.followers], rows)
