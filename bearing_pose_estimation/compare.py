"""Several estimators on one scenario, side by side (``bearing-pose compare``); no rclpy.

Each method runs in the batch simulator on the same scenario: same truth, same initial
estimates, same noise seed. Only ``method`` changes. Each method's gains are the scenario's
(``gains:`` holds the gains of the scenario's own method; the other methods use their defaults,
shown in the table).
"""
from __future__ import annotations

import csv
import dataclasses
from pathlib import Path
from typing import Any

from .agent import gains_for
from .metrics import ATT_THRESHOLD_RAD, POS_THRESHOLD_M, settling_time
from .scenario import METHODS, Scenario
from .simulator import BatchSimulator, Recording

OUTPUT_FILES = ('compare.csv', 'compare.md', 'compare_errors.png')


def run_methods(scenario: Scenario, methods: list[str], duration: float,
                record_every: float = 0.1) -> dict[str, Recording]:
    """One batch run per method; every run starts from the same state."""
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f'unknown method {unknown[0]!r}; use one of: {", ".join(METHODS)}')
    return {m: BatchSimulator(dataclasses.replace(scenario, method=m)).run(
        duration, record_every=record_every) for m in methods}


def rows(scenario: Scenario, recs: dict[str, Recording]) -> list[dict[str, Any]]:
    """Per method: gains, final mean and max errors, settling times of the mean errors."""
    out = []
    for method, rec in recs.items():
        att, pos = rec.att_err.mean(axis=1), rec.pos_err.mean(axis=1)
        gains = gains_for(dataclasses.replace(scenario, method=method))
        out.append({
            'method': method,
            'gains': ', '.join(f'{k}={v:g}' for k, v in vars(gains).items()),
            'final_attitude_error_mean_rad': float(att[-1]),
            'final_position_error_mean_m': float(pos[-1]),
            'final_attitude_error_max_rad': float(rec.att_err[-1].max()),
            'final_position_error_max_m': float(rec.pos_err[-1].max()),
            'attitude_settles_s': settling_time(rec.t, att, ATT_THRESHOLD_RAD),
            'position_settles_s': settling_time(rec.t, pos, POS_THRESHOLD_M),
        })
    return out


def write_csv(recs: dict[str, Recording], path: Path) -> None:
    """``t`` then, per method, its mean attitude [rad] and position [m] errors."""
    methods = list(recs)
    t = recs[methods[0]].t
    with path.open('w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(['t'] + [f'{m}_{q}' for m in methods
                            for q in ('attitude_error_mean_rad', 'position_error_mean_m')])
        for k, tk in enumerate(t):
            w.writerow([f'{tk:.6f}'] + [f'{x:.9e}' for m in methods
                                        for x in (recs[m].att_err[k].mean(),
                                                  recs[m].pos_err[k].mean())])


def table(rows_: list[dict[str, Any]], duration: float) -> str:
    """The comparison as a Markdown table."""
    def when(x: float | None) -> str:
        return 'never' if x is None else f'{x:.1f} s'

    lines = [f'| method | gains | mean attitude error at {duration:g} s [rad] | mean position '
             f'error at {duration:g} s [m] | attitude < {ATT_THRESHOLD_RAD:g} rad from | '
             f'position < {POS_THRESHOLD_M:g} m from |', '|---|---|---|---|---|---|']
    for r in rows_:
        lines.append(f"| {r['method']} | {r['gains']} | {r['final_attitude_error_mean_rad']:.3e} "
                     f"| {r['final_position_error_mean_m']:.3e} | "
                     f"{when(r['attitude_settles_s'])} | {when(r['position_settles_s'])} |")
    return '\n'.join(lines) + '\n'
