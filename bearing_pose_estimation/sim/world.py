"""The simulated world of the simulator node: the truth (:class:`.truth.Truth`) on a fine
grid, sampled like sensors.

- Truth: stepped every ``simulation.internal_step`` (1 ms by default), far finer than any
  published rate.
- Gyro: each sample is the interval average over the last IMU period,
  ``ω̄ = log(R(t_prev)ᵀ R(t)) / Δt`` (the constant rate that produces the true rotation), plus
  the agent's constant bias and white noise. See :mod:`bearing_pose_estimation.core.gyro`.
- Bearings: instantaneous ``R_i(t)ᵀ b_ij`` to every agent i senses (its neighbours and its
  listeners: sensing is two-way), corrupted by the scenario's bearing noise models.
- Moving-robot sensors, each at its own rate (``sensors:``) and only when the scenario
  simulates it (:meth:`scenario.Scenario.simulates`): odometry, the interval-average body
  twist over the last odometry period (the SE(3) logarithm of the true pose increment divided
  by the period, :func:`core.odometry.twist_of`) plus white noise, with the pose dead-reckoned
  from those twists; instantaneous relative positions, bearing rates and ranges to the agents
  i senses, plus white noise.

Noise comes from :class:`.noise.NoiseModel`, the same models as the batch simulator.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from ..core.odometry import se3_step, twist_of
from ..scenario.model import Scenario
from ..scenario.truth import OnTruth, Truth
from .noise import NoiseModel

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
        # Moving-robot sensors the scenario simulates: name -> internal steps per sample.
        self.sensor_every = {name: rates.ticks(scenario.sensors.spec(name).rate)
                             for name in scenario.sensors.NAMES if scenario.simulates(name)}
        self.truth = Truth(scenario, self.dt)
        self.names = [a.name for a in scenario.agents]
        self.targets = [self._indices(scenario.sensing_targets(a.name)) for a in scenario.agents]
        self.sensor_targets = {name: [self._indices(scenario.sensor_targets(name, a.name))
                                      for a in scenario.agents]
                               for name in scenario.sensors.NAMES if name != 'odometry'}
        self.reset()

    def _indices(self, names: list[str]) -> NDArray[np.intp]:
        return np.array([self.scenario.index[t] for t in names], dtype=np.intp)

    def reset(self) -> None:
        """Back to t = 0, with the noise generators (and gyro biases) re-seeded."""
        n = len(self.scenario.agents)
        self.noise = NoiseModel(self.scenario.noise, n, self.scenario.sensors)
        self.truth.reset()
        self._R_last_imu = self.R.copy()
        self._last_odometry = (self.R.copy(), self.p.copy())
        # The pose dead-reckoned from the published twists, in each agent's odom frame (its
        # body frame at t = 0), as a real odometry source reports it.
        self.odom_R = np.tile(np.eye(3), (n, 1, 1))
        self.odom_p = np.zeros((n, 3))

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
        # One IMU period's increment: a small angle, whose closed form costs a tenth of the
        # quaternion route (the simulator runs this 200 times a second).
        omega = so3.log_small(np.swapaxes(self._R_last_imu, -1, -2) @ self.R) / period
        self._R_last_imu = self.R.copy()
        return self.noise.gyro_rate(omega)

    def bearings(self, i: int) -> tuple[NDArray[np.intp], Array]:
        """Agent i's measured body bearings now: (0-based target indices, ``(n, 3)`` unit
        vectors)."""
        j = self.targets[i]
        owner = np.full(j.shape, i, dtype=np.intp)
        b_body = self.truth.body_bearings(owner, self.truth.world_bearings(owner, j))
        return j, self.noise.bearings(b_body, self.t)

    def odometry(self) -> tuple[Array, Array]:
        """Interval-average body twists of all agents for the odometry period ending now:
        ``(v (N, 3) [m/s], ω (N, 3) [rad/s])``, noise included; :attr:`odom_R`,
        :attr:`odom_p` advance by them."""
        period = self.sensor_every['odometry'] * self.dt
        R0, p0 = self._last_odometry
        v, omega = twist_of(np.swapaxes(R0, -1, -2) @ self.R,
                            np.einsum('nba,nb->na', R0, self.p - p0), period)
        v, omega = self.noise.odometry_twist(v, omega)
        self._last_odometry = (self.R.copy(), self.p.copy())
        R, self.odom_p = se3_step(self.odom_R, self.odom_p, omega, v, period)
        self.odom_R = so3.reorthonormalize(R)
        return v, omega

    def sensed(self, name: str, i: int) -> tuple[NDArray[np.intp], Array]:
        """Agent i's measured ``relative_positions`` ``(n, 3)`` [m], ``bearing_rates``
        ``(n, 3)`` [1/s] or ``ranges`` ``(n,)`` [m] now, to the agents it senses: (0-based
        target indices, values)."""
        j = self.sensor_targets[name][i]
        owner = np.full(j.shape, i, dtype=np.intp)
        measure = {'relative_positions': self.truth.relative_positions,
                   'bearing_rates': self.truth.bearing_rates,
                   'ranges': self.truth.ranges}[name]
        return j, self.noise.sensor(name, measure(owner, j))
