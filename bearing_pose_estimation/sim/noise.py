"""Measurement noise of both simulators (:class:`scenario.Noise`, :class:`scenario.Sensors`).
Bearings get, in this order, the deterministic ``rot_X(θ0 sin(2π f t)) b`` (t the measurement
time), a random rotation perpendicular to them and outliers. A batch step of ``h`` gets ``h``
times the noise averaged over the samples it spans. Every draw comes from generators seeded by
``noise.seed``, one stream each for the bias, the gyro white noise, the bearings and each
moving-robot sensor: same scenario, seed and calls, same measurements."""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from ..scenario.model import Noise, Sensors

Array = NDArray[np.float64]


def perturb_bearings(b: Array, std: float, rng: np.random.Generator) -> Array:
    """Rotate each unit bearing by a small random rotation perpendicular to it: the rotation
    vector is ``N(0, std² P_b)``, each of its two components orthogonal to ``b`` of standard
    deviation ``std`` [rad]."""
    if std == 0.0:
        return b
    phi = std * rng.normal(size=b.shape)
    phi -= b * np.sum(phi * b, axis=-1, keepdims=True)
    return np.einsum('eab,eb->ea', so3.exp(phi), b)


class NoiseModel:
    """The scenario's noise for a fleet of ``n_agents`` (row i of any gyro array is agent i);
    ``bias`` ``(n_agents, 3)``: the constant body-frame gyro biases [rad/s]."""

    def __init__(self, noise: Noise, n_agents: int, sensors: Sensors = Sensors()) -> None:
        self.noise = noise
        self.sensors = sensors
        # Children are keyed by index: the first three streams stay those of a static scenario.
        bias_ss, gyro_ss, bearing_ss, *rest = np.random.SeedSequence(noise.seed).spawn(
            3 + len(Sensors.NAMES))
        self.gyro_rng = np.random.default_rng(gyro_ss)
        self.bearing_rng = np.random.default_rng(bearing_ss)
        self.sensor_rng = {name: np.random.default_rng(ss)
                           for name, ss in zip(Sensors.NAMES, rest)}
        self.bias = np.tile(np.asarray(noise.gyro_bias, dtype=float), (n_agents, 1))
        if noise.gyro_bias_std > 0.0:
            self.bias += noise.gyro_bias_std * np.random.default_rng(bias_ss).normal(
                size=(n_agents, 3))
        self.has_bias = bool(np.any(self.bias != 0.0))

    def _gyro_error(self, shape: tuple[int, ...], samples: float = 1.0) -> Array | None:
        """bias + white noise averaged over ``samples`` IMU samples; None if both are zero."""
        std = self.noise.gyro_std / math.sqrt(samples)
        if std == 0.0:
            return self.bias if self.has_bias else None
        return self.bias + std * self.gyro_rng.normal(size=shape)

    def gyro_rate(self, omega: Array) -> Array:
        """Measured rates ``(n_agents, 3)`` from true rates: ``ω + bias + noise``."""
        err = self._gyro_error(omega.shape)
        return omega if err is None else omega + err

    def gyro_increment(self, delta_R: Array, h: float, samples: float = 1.0) -> Array:
        """What the gyros report over a step ``h`` spanning ``samples`` IMU samples:
        ``ΔR exp(h (bias + noise))``, the noise being the average of those samples' noise
        (``gyro_std`` is per IMU sample, so both simulators see the same noise density)."""
        err = self._gyro_error((delta_R.shape[0], 3), max(samples, 1.0))
        return delta_R if err is None else delta_R @ so3.exp(h * err)

    def bearings(self, b: Array, t: float) -> Array:
        """Measured body bearings ``(n, 3)`` from true unit bearings ``b`` at time ``t`` [s]."""
        nz = self.noise
        bp = nz.bearing_perturbation   # θ0 sin(2π f t) [rad]
        if bp is not None:
            angle = math.radians(bp.amplitude_deg) * math.sin(2.0 * math.pi * bp.frequency_hz * t)
            b = b @ so3.axis_angle(bp.axis, angle).T
        b = perturb_bearings(b, nz.bearing_std, self.bearing_rng)
        if nz.outlier_probability == 0.0 or b.shape[0] == 0:
            return b
        hit = self.bearing_rng.random(b.shape[0]) < nz.outlier_probability   # a uniform unit
        v = self.bearing_rng.normal(size=(int(np.count_nonzero(hit)), 3))   # vector instead
        b = b.copy()
        b[hit] = v / np.linalg.norm(v, axis=1, keepdims=True)
        return b

    def _white(self, sensor: str, x: Array, std: float) -> Array:
        return x if std == 0.0 else x + std * self.sensor_rng[sensor].normal(size=x.shape)

    def sensor(self, name: str, x: Array) -> Array:
        """Measured relative positions, bearing rates or ranges (``name``) from true ``x``:
        white noise of the sensor's ``std`` on each component."""
        return self._white(name, x, self.sensors.spec(name).std)

    def odometry_twist(self, v: Array, omega: Array) -> tuple[Array, Array]:
        """Measured interval-average body velocity ``v`` [m/s] and rate ``omega`` [rad/s]."""
        spec = self.sensors.odometry
        return (self._white('odometry', v, spec.std),
                self._white('odometry', omega, spec.angular_std))

    def odometry_displacement(self, delta: Array, h: float, samples: float = 1.0) -> Array:
        """What odometry reports of the displacements ``delta`` ``(N, 3)`` over a step ``h``
        spanning ``samples`` odometry samples: ``h`` times the averaged velocity noise."""
        std = self.sensors.odometry.std / math.sqrt(max(samples, 1.0))
        return self._white('odometry', delta, h * std)
