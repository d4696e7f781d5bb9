"""The simulated world of the simulator node: the truth (:class:`.truth.Truth`) on a fine
grid, sampled like sensors.

- Truth: stepped every ``simulation.internal_step`` (1 ms by default), far finer than any
  published rate.
- Gyro: each sample is the interval average over the last IMU period,
  ``ω̄ = log(R(t_prev)ᵀ R(t)) / Δt`` (the constant rate that produces the true rotation), plus
  the agent's constant bias and white noise. See :mod:`bearing_pose_estimation.core.gyro`.
- Bearings: instantaneous ``R_i(t)ᵀ b_ij`` to every agent i senses (its neighbours and its
  listeners: sensing is two-way), corrupted by the scenario's bearing noise models.

Noise comes from :class:`.noise.NoiseModel`, the same models as the batch simulator.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from ..scenario.model import Scenario
from .noise import NoiseModel
from .truth import OnTruth, Truth

Array = NDArray[np.float64]


class World(OnTruth):
    """Truth of a scenario on the internal time grid ``t = tick · internal_step``, and its
    sensors."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        rates = scenario.simulation
        self.dt = rates.internal_step
        self.imu_every = rates.ticks(rates.imu_rate)
        self.bearing_every = rates.ticks(rates.bearing_rate)
        self.truth_every = rates.ticks(rates.ground_truth_rate)
        self.truth = Truth(scenario, self.dt)
        self.names = [a.name for a in scenario.agents]
        self.targets = [np.array([scenario.index[t] for t in scenario.sensing_targets(a.name)],
                                 dtype=np.intp) for a in scenario.agents]
        self.reset()

    def reset(self) -> None:
        """Back to t = 0, with the noise generators (and gyro biases) re-seeded."""
        self.noise = NoiseModel(self.scenario.noise, len(self.scenario.agents))
        self.truth.reset()
        self._R_last_imu = self.R.copy()

    @property
    def tick(self) -> int:
        return self.truth.k

    def step(self) -> None:
        """Advance the truth by one internal step."""
        self.truth.advance()

    def due(self, every: int) -> bool:
        return self.tick % every == 0

    def imu(self) -> Array:
        """Interval-average gyro samples of all agents, ``(N, 3)`` [rad/s], for the IMU period
        ending now."""
        period = self.imu_every * self.dt
        omega = so3.log(np.swapaxes(self._R_last_imu, -1, -2) @ self.R) / period
        self._R_last_imu = self.R.copy()
        return self.noise.gyro_rate(omega)

    def bearings(self, i: int) -> tuple[NDArray[np.intp], Array]:
        """Agent i's measured body bearings now: (0-based target indices, ``(n, 3)`` unit
        vectors)."""
        j = self.targets[i]
        owner = np.full(j.shape, i, dtype=np.intp)
        b_body = self.truth.body_bearings(owner, self.truth.world_bearings(owner, j))
        return j, self.noise.bearings(b_body, self.t)
