"""Gyro sample buffer: exact body-frame rotation increments between any two times.

A sample ``ω_k`` stamped ``t_k`` is the *interval average* over ``(t_{k-1}, t_k]``,
``R(t_{k-1})ᵀ R(t_k) = exp(ω_k Δ)`` (as delta-angle IMUs give): exact between stamps, where
holding ω over a 10 ms step leaves milliradians of error with the paper's ``sin 9t`` rates. A
stretch of lost samples (a sample more than :data:`GAP_FACTOR` periods after the previous one)
gets the mean of the rates on either side: an error of order ``ω̈ Δ³`` per lost sample instead
of ``ω̇ Δ²``."""
from __future__ import annotations

import bisect
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from . import so3

# Stamps are floats: 0.03 + 0.01 != 0.04. Coverage is judged with this slack [s].
STAMP_TOLERANCE = 1e-9
# An interval longer than this many sampling periods has lost samples (jitter stays below).
GAP_FACTOR = 1.5


class IntervalBuffer:
    """Interval-average samples of one agent: sample k holds over ``(t[k], t[k+1]]``, the first
    from ``start``; samples older than ``horizon`` [s] are dropped."""

    def __init__(self, start: float, horizon: float = 2.0) -> None:
        self.horizon = horizon
        self._t: list[float] = [start]     # interval boundaries: sample k covers (t[k], t[k+1]]
        self._w: list[NDArray[np.float64]] = []
        self._period: float | None = None  # the sampling period, from the last regular interval
        self.bridged = 0                   # gaps of lost samples bridged so far
        # The node asks for the same increments repeatedly (a message's bearings share a stamp).
        self._cache: dict[tuple[str, float, float], NDArray[np.float64]] = {}

    @property
    def start(self) -> float:
        """Earliest time the buffer can integrate from."""
        return self._t[0]

    @property
    def empty(self) -> bool:
        """No sample yet."""
        return not self._w

    @property
    def end(self) -> float:
        """Latest time covered by samples (the newest stamp)."""
        return self._t[-1]

    def add(self, stamp: float, omega: NDArray[np.float64]) -> bool:
        """Append a sample; False (ignored) unless ``stamp`` is newer than the newest."""
        if not stamp > self._t[-1]:
            return False
        omega = np.asarray(omega, dtype=float)
        interval = stamp - self._t[-1]
        if self._period is not None and interval > GAP_FACTOR * self._period and self._w:
            # Samples were lost: bridge the gap with the mean of the rates on either side.
            self._t.append(float(stamp) - self._period)
            self._w.append(0.5 * (self._w[-1] + omega))
            self.bridged += 1
        elif self._w:  # a regular interval (the first one may start before the IMU did)
            self._period = interval
        self._t.append(float(stamp))
        self._w.append(omega)
        drop = bisect.bisect_right(self._t, stamp - self.horizon) - 1
        if 0 < drop < len(self._w):
            del self._t[:drop]
            del self._w[:drop]
        return True

    def reset(self, start: float) -> None:
        """Forget every sample; integrate from ``start`` again."""
        self._t, self._w = [start], []
        self._period = None
        self._cache.clear()

    def covers(self, t0: float, t1: float) -> bool:
        return (self.start - STAMP_TOLERANCE <= min(t0, t1)
                and max(t0, t1) <= self.end + STAMP_TOLERANCE)

    def integrated(self, t0: float, t1: float,
                   compose: Callable[[list[tuple[NDArray[np.float64], float]]],
                                     NDArray[np.float64]],
                   what: str) -> NDArray[np.float64]:
        """``compose(segments(t0, t1))`` (``t0 <= t1``), cached: samples are only appended.
        ValueError naming the buffer (``what``) if it does not cover ``[t0, t1]``."""
        if not self.covers(t0, t1):
            raise ValueError(f'{what} buffer covers [{self.start:.6f}, {self.end:.6f}], '
                             f'not [{t0:.6f}, {t1:.6f}]')
        key = (what, t0, t1)   # one buffer may be integrated several ways
        cached = self._cache.get(key)
        if cached is not None:
            return cached
        value = compose(self.segments(t0, t1))
        if len(self._cache) > 64:
            self._cache.clear()
        self._cache[key] = value
        return value

    def segments(self, t0: float, t1: float) -> list[tuple[NDArray[np.float64], float]]:
        """The samples over ``[t0, t1]`` (``t0 <= t1``, covered) as ``(value, duration)``, in
        time order, the first and last cut at ``t0`` and ``t1``."""
        out = []
        k = max(bisect.bisect_right(self._t, t0) - 1, 0)
        while k < len(self._w) and self._t[k] < t1:
            a, b = max(self._t[k], t0), min(self._t[k + 1], t1)
            if b > a:
                out.append((self._w[k], b - a))
            k += 1
        return out


class GyroBuffer(IntervalBuffer):
    """Interval-average gyro samples of one agent: exact rotation increments."""

    def increment(self, t0: float, t1: float) -> NDArray[np.float64]:
        """``R(t0)ᵀ R(t1)`` (either order); ValueError if not covered."""
        if t1 < t0:
            return self.increment(t1, t0).T
        return self.integrated(t0, t1, _rotation, 'gyro')


def _rotation(segments: list[tuple[NDArray[np.float64], float]]) -> NDArray[np.float64]:
    """The product of ``exp(ω Δ)`` over the segments."""
    if not segments:
        return np.eye(3)
    R = so3.exp(segments[0][0] * segments[0][1])   # not I @ exp(...): the same numbers
    for omega, duration in segments[1:]:
        R = R @ so3.exp(omega * duration)
    return R
