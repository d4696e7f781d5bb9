"""Batch simulator: the whole network in one process, vectorised over agents and edges.

Truth: positions are static; every attitude follows ``dR_i/dt = R_i [ω_i(t)]x``, propagated by
the 4th-order Magnus increment (:func:`motion.magnus_increment`). Each step, every follower's
observer advances with :func:`observer.cascade_step`, the same function the estimator node calls
(or, for ``method: tran_anderson_ahn``, :func:`tran.tran_step`, as the node does), on
measurements taken at the step's start:

- own bearings ``b^i_ij = R_iᵀ b_ij`` (+ bearing noise),
- what neighbour j would send: ``R̂_j b^j_ij = -R̂_j b^j_ji`` with j's own measurement
  ``b^j_ji = R_jᵀ b_ji`` (+ noise) and ``p̂_j``, all at the same instant,
- the gyro increment ``ΔR exp(h (bias + noise))`` over the step.

Noise (all off by default) comes from :class:`noise.NoiseModel`, the same models the
simulator node's world uses; a scenario and its ``noise.seed`` give the same run.

Leaders know their pose: their estimate is their truth.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import so3
from .motion import OmegaProfile, magnus_increment
from .noise import NoiseModel
from .agent import gains_for
from .observer import REORTHONORMALIZE_EVERY, Edges, cascade_step
from .scenario import Scenario, initial_estimates
from .tran import TranGains, TwoNeighbourPairs, tran_step

Array = NDArray[np.float64]


def pose_errors(R: Array, p: Array, R_hat: Array, p_hat: Array) -> tuple[Array, Array, Array, Array]:
    """Errors of poses ``(n, 3, 3)``, ``(n, 3)`` and their estimates: ``(att_err, pos_err,
    att_dist_I, pos_err_paper)`` as defined in :class:`Recording`."""
    R_tilde = R @ np.swapaxes(R_hat, -1, -2)
    p_tilde = p - np.einsum('nab,nb->na', R_tilde, p_hat)
    return (so3.angle(R_tilde), np.linalg.norm(p - p_hat, axis=1), so3.dist_I(R_tilde),
            np.linalg.norm(p_tilde, axis=1))


@dataclass
class Recording:
    """Errors of every follower at the recorded times.

    ``att_err`` is the geodesic angle of ``R_i R̂_iᵀ`` [rad]; ``pos_err`` is ``‖p_i − p̂_i‖`` [m];
    ``att_dist_I`` is the paper's ``|R̃_i|_I`` (Fig. 2) and ``pos_err_paper`` its
    ``‖p̃_i‖ = ‖p_i − R̃_i p̂_i‖`` (Fig. 3). Arrays are ``(K, F)`` for K records, F followers.
    """

    t: Array
    followers: list[str]
    att_err: Array
    pos_err: Array
    att_dist_I: Array
    pos_err_paper: Array


class BatchSimulator:
    """Simulate a scenario with all agents' observers in lock-step.

    Args:
        scenario: a parsed scenario (run :func:`graph.check_scenario` first).
        step: integration / estimator step [s]; default ``1 / scenario.frequency``.
    """

    def __init__(self, scenario: Scenario, step: float | None = None) -> None:
        self.scenario = scenario
        self.h = float(step if step is not None else scenario.step)
        agents = scenario.agents
        self.n = len(agents)
        self.omega = OmegaProfile([a.angular_velocity for a in agents])
        self.p = np.stack([a.position for a in agents])
        self.leader_idx = np.array([scenario.index[name] for name in scenario.leaders])
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
        d = self.p[self.edge_nbr] - self.p[self.edges.agent]
        self.b_world = d / np.linalg.norm(d, axis=1, keepdims=True)  # b_ij, static
        self._ends = np.concatenate([self.edges.agent, self.edge_nbr])
        self._ends_b_world = np.concatenate([self.b_world, -self.b_world])
        self.gains = gains_for(scenario)  # its type selects the observer, as in the node
        self.pairs = (TwoNeighbourPairs.of(self.edges) if isinstance(self.gains, TranGains)
                      else None)
        # Constant rates (common in generated fleets): the truth's increment never changes.
        self._constant_delta_R = (magnus_increment(self.omega, 0.0, self.h)
                                  if self.omega.is_constant else None)
        self.reset()

    def reset(self) -> None:
        """Back to t = 0: true attitudes, the scenario's initial estimates, and the noise
        generators (and gyro biases) re-seeded, so a run after reset repeats exactly."""
        self.noise = NoiseModel(self.scenario.noise, self.n)
        self.t = 0.0
        self.k = 0
        self.R = np.stack([a.attitude for a in self.scenario.agents])
        self.R_hat, self.p_hat = initial_estimates(self.scenario)
        self.Omega_tilde = np.zeros((self.n, 3))  # Tran et al.'s Ω̃(0) = 0

    def measure(self) -> tuple[Array, Array]:
        """Own body bearings ``b^i_ij`` and neighbours' world bearings ``R̂_j b^j_ij`` now."""
        # Both ends' body bearings in one product: R_iᵀ b_ij and b^j_ji = R_jᵀ b_ji = -R_jᵀ b_ij.
        both = np.einsum('eba,eb->ea', np.take(self.R, self._ends, axis=0), self._ends_b_world)
        b_own, b_theirs = both[:len(self.edges)], both[len(self.edges):]
        b_own = self.noise.bearings(b_own, self.t)
        b_theirs = self.noise.bearings(b_theirs, self.t)
        d_world = -np.einsum('eab,eb->ea', np.take(self.R_hat, self.edge_nbr, axis=0), b_theirs)
        return b_own, d_world

    def gyro_increment(self, delta_R: Array) -> Array:
        """What the gyros report over the step: ``ΔR exp(h (bias + noise))`` (body frame),
        the noise averaged over the IMU samples the step spans (``simulation.imu_rate``)."""
        samples = self.h * self.scenario.simulation.imu_rate
        return self.noise.gyro_increment(delta_R, self.h, samples)

    def step(self) -> None:
        """Advance truth and every observer by one step ``h``."""
        delta_R = self._constant_delta_R
        if delta_R is None:
            delta_R = magnus_increment(self.omega, self.t, self.h)
        b_own, d_world = self.measure()
        fix = (self.k + 1) % REORTHONORMALIZE_EVERY == 0
        p_nbr = np.take(self.p_hat, self.edge_nbr, axis=0)
        if isinstance(self.gains, TranGains):
            res = tran_step(self.R_hat, self.Omega_tilde, self.p_hat,
                            self.gyro_increment(delta_R), self.h, self.edges, self.pairs, b_own,
                            d_world, p_nbr, self.gains, reorthonormalize=fix)
            self.Omega_tilde = res.Omega_tilde
            self.Omega_tilde[self.leader_idx] = 0.0
        else:
            res = cascade_step(self.R_hat, self.p_hat, self.gyro_increment(delta_R), self.h,
                               self.edges, b_own, d_world, p_nbr, self.gains,
                               reorthonormalize=fix)
        self.R = so3.matmul(self.R, delta_R)
        if fix:
            self.R = so3.reorthonormalize(self.R)
        self.R_hat, self.p_hat = res.R_hat, res.p_hat
        # Leaders know their pose (Assumption 2b).
        self.R_hat[self.leader_idx] = self.R[self.leader_idx]
        self.p_hat[self.leader_idx] = self.p[self.leader_idx]
        self.k += 1
        self.t = self.k * self.h

    def errors(self) -> tuple[Array, Array, Array, Array]:
        """Followers' ``(att_err, pos_err, att_dist_I, pos_err_paper)`` now (see Recording)."""
        f = self.follower_idx
        return pose_errors(self.R[f], self.p[f], self.R_hat[f], self.p_hat[f])

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
                progress(self.t, rows[-1][0], rows[-1][1])
            if s < n_steps:
                self.step()
        cols = [np.array(c) for c in zip(*rows)]
        return Recording(t=np.array(t), followers=[a.name for a in self.scenario.followers],
                         att_err=cols[0], pos_err=cols[1], att_dist_I=cols[2],
                         pos_err_paper=cols[3])
