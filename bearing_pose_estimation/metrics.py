"""Run outputs shared by ``bearing-pose simulate`` and the DDS monitor.

- ``metrics.csv``: columns ``t``, ``attitude_error_mean_rad``, ``position_error_mean_m``, then
  ``att_<agent>`` for every follower, then ``pos_<agent>``. Attitude error is the geodesic angle
  of ``R_i R̂_iᵀ`` [rad]; position error is ``‖p_i − p̂_i‖`` [m].
- ``summary.json``: final errors, and the settling times to 1e-3 rad and 1e-2 m (first recorded
  time after which the mean error stays below the threshold).
"""
from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .simulator import Recording

ATT_THRESHOLD_RAD = 1e-3
POS_THRESHOLD_M = 1e-2


def settling_time(t: NDArray[np.float64], err: NDArray[np.float64],
                  threshold: float) -> float | None:
    """First time after which ``err`` stays below ``threshold`` (None if it never does)."""
    above = np.flatnonzero(err >= threshold)
    if above.size == 0:
        return round(float(t[0]), 9)
    if above[-1] == err.size - 1:
        return None
    return round(float(t[above[-1] + 1]), 9)  # 14.7, not 14.700000000000001


def write_metrics_csv(rec: Recording, path: Path) -> None:
    with path.open('w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(['t', 'attitude_error_mean_rad', 'position_error_mean_m']
                   + [f'att_{n}' for n in rec.followers] + [f'pos_{n}' for n in rec.followers])
        att_mean, pos_mean = rec.att_err.mean(axis=1), rec.pos_err.mean(axis=1)
        for k in range(rec.t.size):
            w.writerow([f'{rec.t[k]:.6f}', f'{att_mean[k]:.9e}', f'{pos_mean[k]:.9e}']
                       + [f'{x:.9e}' for x in rec.att_err[k]]
                       + [f'{x:.9e}' for x in rec.pos_err[k]])


def summarize(rec: Recording, **extra: Any) -> dict[str, Any]:
    """The numbers a user reads first; ``extra`` keys (scenario, wall time, ...) are merged in."""
    att_mean, pos_mean = rec.att_err.mean(axis=1), rec.pos_err.mean(axis=1)
    summary: dict[str, Any] = dict(extra)
    summary.update({
        'duration_s': float(rec.t[-1]),
        'final': {
            'attitude_error_mean_rad': float(att_mean[-1]),
            'position_error_mean_m': float(pos_mean[-1]),
            'attitude_error_max_rad': float(rec.att_err[-1].max()),
            'position_error_max_m': float(rec.pos_err[-1].max()),
        },
        'time_to_attitude_error_mean_below_1e-3_rad_s':
            settling_time(rec.t, att_mean, ATT_THRESHOLD_RAD),
        'time_to_position_error_mean_below_1e-2_m_s':
            settling_time(rec.t, pos_mean, POS_THRESHOLD_M),
        'per_agent': {
            name: {
                'final_attitude_error_rad': float(rec.att_err[-1, k]),
                'final_position_error_m': float(rec.pos_err[-1, k]),
                'time_to_attitude_error_below_1e-3_rad_s':
                    settling_time(rec.t, rec.att_err[:, k], ATT_THRESHOLD_RAD),
                'time_to_position_error_below_1e-2_m_s':
                    settling_time(rec.t, rec.pos_err[:, k], POS_THRESHOLD_M),
            } for k, name in enumerate(rec.followers)
        },
    })
    return summary


def write_summary_json(summary: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(summary, indent=2) + '\n')


def format_summary(summary: dict[str, Any]) -> str:
    """A few human lines for the terminal."""
    f = summary['final']
    t_att = summary['time_to_attitude_error_mean_below_1e-3_rad_s']
    t_pos = summary['time_to_position_error_mean_below_1e-2_m_s']

    def when(x: float | None) -> str:
        return 'never' if x is None else f'{x:.1f} s'

    return '\n'.join([
        f'final mean attitude error: {f["attitude_error_mean_rad"]:.3e} rad '
        f'(max {f["attitude_error_max_rad"]:.3e})',
        f'final mean position error: {f["position_error_mean_m"]:.3e} m '
        f'(max {f["position_error_max_m"]:.3e})',
        f'mean attitude error stays below 1e-3 rad after: {when(t_att)}',
        f'mean position error stays below 1e-2 m after: {when(t_pos)}',
    ])
