"""What a run is summed up by, one name per quantity and one steady-state rule, for every output.
The quantities of a :class:`metrics.results.Recording` (:data:`QUANTITIES`; "mean" is over the
estimating agents at one time): ``final_*`` at the last record; ``steady_*_mean_*``, the time
average of the mean error over the last :data:`STEADY_FRACTION` of the run, ``steady_*_max_*`` the
worst agent at any record of it (the radius of the neighbourhood the estimates stay in);
``*_below_*_from_s``, :func:`settling_time` of the mean errors to fixed thresholds (None: never);
``*_settled_from_s``, to ``max(fixed threshold, SETTLE_FACTOR × steady mean)``.

Why: with noise the errors settle on a floor above the fixed thresholds; one relative to the
floor dates when it got there. Why 3: the converged mean attitude error fluctuates up to 2.3 times
its floor (20 runs of ``config/paper_noisy.yaml``); with 2, two "settle" at 41, 42 s, not ~12 s."""
from __future__ import annotations

import csv
import json
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..metrics.results import Recording

Array = NDArray[np.float64]

ATT_THRESHOLD_RAD = 1e-3
POS_THRESHOLD_M = 1e-2
STEADY_FRACTION = 0.25   # the steady-state window: the last quarter of the run
SETTLE_FACTOR = 3.0      # noise-robust convergence: within this factor of the run's floor
QUANTITIES = ('final_attitude_error_mean_rad', 'final_position_error_mean_m',
              'final_attitude_error_max_rad', 'final_position_error_max_m',
              'steady_attitude_error_mean_rad', 'steady_position_error_mean_m',
              'steady_attitude_error_max_rad', 'steady_position_error_max_m',
              'attitude_below_1e-3_rad_from_s', 'position_below_1e-2_m_from_s',
              'attitude_settled_from_s', 'position_settled_from_s')
TIMES = QUANTITIES[-4:]   # the settling times (None: never)


def settling_time(t: Array, err: Array, threshold: float) -> float | None:
    """First time after which ``err`` stays below ``threshold`` (None if it never does)."""
    above = np.flatnonzero(err >= threshold)
    if above.size == 0:
        return round(float(t[0]), 9)
    if above[-1] == err.size - 1:
        return None
    return round(float(t[above[-1] + 1]), 9)  # 14.7, not 14.700000000000001


def quantities(rec: Recording) -> dict[str, float | None]:
    """Every quantity of the module docstring, in :data:`QUANTITIES` order."""
    att, pos = rec.mean_errors()
    window = rec.t >= rec.t[-1] - STEADY_FRACTION * (rec.t[-1] - rec.t[0]) - 1e-9
    steady_att, steady_pos = float(att[window].mean()), float(pos[window].mean())
    return {
        'final_attitude_error_mean_rad': float(att[-1]),
        'final_position_error_mean_m': float(pos[-1]),
        'final_attitude_error_max_rad': float(rec.att_err[-1].max()),
        'final_position_error_max_m': float(rec.pos_err[-1].max()),
        'steady_attitude_error_mean_rad': steady_att,
        'steady_position_error_mean_m': steady_pos,
        'steady_attitude_error_max_rad': float(rec.att_err[window].max()),
        'steady_position_error_max_m': float(rec.pos_err[window].max()),
        'attitude_below_1e-3_rad_from_s': settling_time(rec.t, att, ATT_THRESHOLD_RAD),
        'position_below_1e-2_m_from_s': settling_time(rec.t, pos, POS_THRESHOLD_M),
        'attitude_settled_from_s': settling_time(
            rec.t, att, max(ATT_THRESHOLD_RAD, SETTLE_FACTOR * steady_att)),
        'position_settled_from_s': settling_time(
            rec.t, pos, max(POS_THRESHOLD_M, SETTLE_FACTOR * steady_pos)),
    }


# Recordings' extra columns summed up by their mean over the group: prefix -> summary.json name.
EXTRA_GROUPS = {'rel_yaw_err_': 'relative_yaw_error_mean',
                'formation_err_': 'formation_error_mean_m'}


def write_rows(path: Path, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    """A CSV file: ``header``, then ``rows``."""
    with path.open('w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)


def write_metrics_csv(rec: Recording, path: Path) -> None:
    att_mean, pos_mean = rec.mean_errors()
    extra = list(rec.extra.values())
    write_rows(path, ['t', 'attitude_error_mean_rad', 'position_error_mean_m']
               + [f'att_{n}' for n in rec.followers] + [f'pos_{n}' for n in rec.followers]
               + list(rec.extra),
               ([f'{rec.t[k]:.6f}', f'{att_mean[k]:.9e}', f'{pos_mean[k]:.9e}']
                + [f'{x:.9e}' for x in rec.att_err[k]] + [f'{x:.9e}' for x in rec.pos_err[k]]
                + [f'{column[k]:.9e}' for column in extra] for k in range(rec.t.size)))


def read_metrics_csv(path: Path) -> Recording:
    """A ``metrics.csv`` back as a :class:`Recording` (the paper's Fig. 2/3 quantities NaN)."""
    with path.open(newline='') as fh:
        reader = csv.reader(fh)
        header = next(reader)
        values = np.array([[float(x) for x in row] for row in reader], dtype=float)
    followers = [h[4:] for h in header if h.startswith('att_')]
    f = len(followers)
    att, pos = values[:, 3:3 + f], values[:, 3 + f:3 + 2 * f]
    nan = np.full_like(att, np.nan)
    extra = {name: values[:, 3 + 2 * f + k] for k, name in enumerate(header[3 + 2 * f:])}
    return Recording(t=values[:, 0], followers=followers, att_err=att, pos_err=pos,
                     att_dist_I=nan, pos_err_paper=nan.copy(), extra=extra)


def summarize(rec: Recording, **extra: Any) -> dict[str, Any]:
    """``summary.json``: ``extra``, the duration, every quantity, per agent errors and times."""
    summary: dict[str, Any] = {**extra, 'duration_s': float(rec.t[-1]), **quantities(rec)}
    for prefix, name in EXTRA_GROUPS.items():
        group = [v for k, v in rec.extra.items() if k.startswith(prefix)]
        if group:
            summary[f'final_{name}'] = float(np.mean([v[-1] for v in group]))
    summary['per_agent'] = {
        name: {
            'final_attitude_error_rad': float(rec.att_err[-1, k]),
            'final_position_error_m': float(rec.pos_err[-1, k]),
            'attitude_below_1e-3_rad_from_s':
                settling_time(rec.t, rec.att_err[:, k], ATT_THRESHOLD_RAD),
            'position_below_1e-2_m_from_s':
                settling_time(rec.t, rec.pos_err[:, k], POS_THRESHOLD_M),
        } for k, name in enumerate(rec.followers)
    }
    return summary


def write_summary_json(summary: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(summary, indent=2) + '\n')


def when(x: float | None) -> str:
    """A settling time for people: ``16.4 s`` or ``never``."""
    return 'never' if x is None else f'{x:.1f} s'


def format_summary(summary: dict[str, Any]) -> str:
    """A few human lines for the terminal."""
    s = summary
    return '\n'.join([
        f'final mean attitude error: {s["final_attitude_error_mean_rad"]:.3e} rad '
        f'(max {s["final_attitude_error_max_rad"]:.3e})',
        f'final mean position error: {s["final_position_error_mean_m"]:.3e} m '
        f'(max {s["final_position_error_max_m"]:.3e})',
        f'mean attitude error stays below 1e-3 rad after: '
        f'{when(s["attitude_below_1e-3_rad_from_s"])}',
        f'mean position error stays below 1e-2 m after: '
        f'{when(s["position_below_1e-2_m_from_s"])}',
        f'steady state (last {STEADY_FRACTION:.0%} of the run, the floor if the errors stop '
        f'falling): mean attitude error {s["steady_attitude_error_mean_rad"]:.3e} rad, mean '
        f'position error {s["steady_position_error_mean_m"]:.3e} m',
    ] + [f'final {name.replace("_", " ").removesuffix(" m")}: {s[f"final_{name}"]:.3e}'
         + (' m' if name.endswith('_m') else '')
         for name in EXTRA_GROUPS.values() if f'final_{name}' in s])
