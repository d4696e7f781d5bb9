"""Odometry sample buffer: exact body-frame displacements between any two times. As for the gyro
(:mod:`core.gyro`), a sample ``(v_k, ω_k)`` stamped ``t_k`` is the *interval average* over
``(t_{k-1}, t_k]``, the constant twist whose SE(3) exponential is the true pose increment
(displacement ``J(ω_k Δ) v_k Δ``, :func:`so3.jacobian_apply`): exact between stamps for any
motion, where a held velocity leaves an O(h) bias (de-carli-2024.md §7)."""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import so3
from .gyro import IntervalBuffer

Array = NDArray[np.float64]


def twist_of(delta_R: Array, delta_p: Array, duration: float) -> tuple[Array, Array]:
    """The interval-average twist ``(v, ω)`` of a body-frame pose increment: the SE(3)
    logarithm divided by ``duration``."""
    phi = so3.log(delta_R)
    return so3.jacobian_inv_apply(phi, delta_p) / duration, phi / duration


def se3_step(R: Array, p: Array, omega: Array, v: Array,
             duration: float) -> tuple[Array, Array]:
    """The pose ``(R, p)`` (``(..., 3, 3)``, ``(..., 3)``) carried over ``duration`` by the
    constant body twist ``(v, ω)``: ``p + R J(ω Δ) v Δ``, ``R exp(ω Δ)``."""
    if np.ndim(R) == 2:   # one pose (a buffer's segments): plain products are cheaper
        return R @ so3.exp(omega * duration), p + R @ so3.jacobian_apply(omega * duration,
                                                                          v * duration)
    p = p + np.einsum('...ab,...b->...a', R, so3.jacobian_apply(omega * duration, v * duration))
    return so3.matmul(R, so3.exp(omega * duration)), p


class OdometryBuffer(IntervalBuffer):
    """Interval-average odometry twists of one agent, each sample ``(ω, v)`` a 6-vector."""

    def add_twist(self, stamp: float, v: Array, omega: Array) -> bool:
        """Append a sample; False (ignored) unless ``stamp`` is newer than the newest."""
        return self.add(stamp, np.concatenate([np.asarray(omega, dtype=float),
                                               np.asarray(v, dtype=float)]))

    def displacement(self, t0: float, t1: float) -> Array:
        """``R(t0)ᵀ (p(t1) - p(t0))`` [m], ``t0 <= t1``; ValueError if not covered."""
        return self.integrated(t0, t1, _pose, 'odometry')[9:]

    def rotation(self, t0: float, t1: float) -> Array:
        """``R(t0)ᵀ R(t1)`` (``t0 <= t1``) of an agent whose gyro this receiver does not see."""
        return self.integrated(t0, t1, _pose, 'odometry')[:9].reshape(3, 3)


def _pose(segments: list[tuple[Array, float]]) -> Array:
    """The product of the segments' SE(3) exponentials (samples ``(ω, v)``), as its rotation
    (row-major) and translation stacked in one 12-vector: one pass, one cache entry."""
    R, p = np.eye(3), np.zeros(3)
    for sample, duration in segments:
        R, p = se3_step(R, p, sample[:3], sample[3:], duration)
    return np.concatenate([R.reshape(9), p])
