"""Bearing rates for robots without a bearing-rate sensor (Presenza et al.'s (11) needs them):
the notes (``presenza-2026.md`` §9) difference consecutive bearings, the older one rotated into
the current body frame with the gyro:

    β̇°_k = Π(β_k) (β_k - ΔRᵀ β_{k-1}) / Δt,      ΔR = R_{k-1}ᵀ R_k (the body's rotation)

``β̇°`` is the *de-rotated* rate, what (11) uses as ``β̇ + ω × β``. A raw difference has noise
about ``σ √2 / Δt``; a low-pass filter of time constant ``tau`` costs more by its lag (case 1,
30 Hz, 1 mrad noise: free robots' attitude error 0.14 rad raw, 0.46 rad at ``tau = 0.1`` s, 1.2
rad at 0.3 s, positions diverge at 1 s). Hence ``tau = 0`` by default."""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


class BearingRateFilter:
    """De-rotated bearing rates of ``n`` tracked bearings (rows, one per sensing link),
    low-pass filtered with time constant ``tau`` [s] (0: raw differences)."""

    def __init__(self, n: int, tau: float) -> None:
        if not tau >= 0.0:
            raise ValueError(f'tau must be >= 0 [s], got {tau!r}')
        self.tau = float(tau)
        self.t_prev = np.full(n, np.nan)
        self.b_prev = np.zeros((n, 3))
        self.rate = np.zeros((n, 3))
        self.started = np.zeros(n, dtype=bool)   # a filtered value exists

    def update(self, t: float, b: Array, delta_R: Array,
               rows: NDArray[np.bool_] | None = None) -> tuple[Array, NDArray[np.bool_]]:
        """Take the bearings ``b`` ``(n, 3)`` at ``t`` (``rows``: default all), ``delta_R`` the
        rotation since each one's previous sample: the rates [1/s] and which rows have one."""
        rows = np.ones(len(b), dtype=bool) if rows is None else np.asarray(rows, dtype=bool)
        have = rows & ~np.isnan(self.t_prev)
        dt = np.where(have, t - np.nan_to_num(self.t_prev), 1.0)[:, None]
        old = np.einsum('nba,nb->na', delta_R, self.b_prev)          # ΔRᵀ β_{k-1}
        d = b - old
        raw = (d - b * np.sum(b * d, axis=1, keepdims=True)) / dt     # Π(β_k) d / Δt
        alpha = 1.0 - np.exp(-dt / self.tau) if self.tau > 0.0 else np.ones_like(dt)
        filtered = np.where(self.started[:, None], self.rate + alpha * (raw - self.rate), raw)
        self.rate = np.where(have[:, None], filtered, self.rate)
        self.started |= have
        self.t_prev = np.where(rows, t, self.t_prev)
        self.b_prev = np.where(rows[:, None], b, self.b_prev)
        return np.where(have[:, None], self.rate, 0.0), have
