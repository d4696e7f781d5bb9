"""The simulator node's world: the truth (:class:`scenario.truth.Truth`) stepped every
``simulation.internal_step`` (1 ms by default), sampled with :class:`.noise.NoiseModel`'s noise:
the gyro and odometry as interval averages over their last period (the constant rate, or SE(3)
twist, that gives the true increment), the other sensors instantaneous."""
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
    """Truth of a scenario on the grid ``t = tick · internal_step``, and its sensors."""

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
        # The pose dead-reckoned from the twists, in the odom frame (the body frame at t = 0).
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
        """Gyro samples ``(N, 3)`` [rad/s]: interval averages over the IMU period ending now."""
        period = self.imu_every * self.dt
        # A small angle: its closed form costs a tenth of the quaternion route (at 200 Hz).
        omega = so3.log_small(np.swapaxes(self._R_last_imu, -1, -2) @ self.R) / period
        self._R_last_imu = self.R.copy()
        return self.noise.gyro_rate(omega)

    def bearings(self, i: int) -> tuple[NDArray[np.intp], Array]:
        """Agent i's measured body bearings now: (0-based target indices, ``(n, 3)``)."""
        j = self.targets[i]
        owner = np.full(j.shape, i, dtype=np.intp)
        b_body = self.truth.body_bearings(owner, self.truth.world_bearings(owner, j))
        return j, self.noise.bearings(b_body, self.t)

    def odometry(self) -> tuple[Array, Array]:
        """Interval-average body twists ``(v [m/s], ω [rad/s])`` ``(N, 3)`` over the period
        ending now, noise included; :attr:`odom_R`, :attr:`odom_p` advance by them."""
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
        """Agent i's ``relative_positions`` ``(n, 3)`` [m], ``bearing_rates`` ``(n, 3)`` [1/s]
        or ``ranges`` ``(n,)`` [m] now: (0-based indices of the agents it senses, values)."""
        j = self.sensor_targets[name][i]
        owner = np.full(j.shape, i, dtype=np.intp)
        measure = {'relative_positions': self.truth.relative_positions,
                   'bearing_rates': self.truth.bearing_rates,
                   'ranges': self.truth.ranges}[name]
        return j, self.noise.sensor(name, measure(owner, j))
