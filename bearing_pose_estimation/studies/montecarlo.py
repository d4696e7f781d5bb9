"""Monte Carlo runs of the batch simulator (``bearing-pose montecarlo``); no rclpy. Run ``i``
(0-based) with first seed ``S`` has ``noise.seed`` and any ``initial_estimates.random.seed`` set
to ``S + i`` (``simulate`` replays it exactly); per run, every quantity of :mod:`.summary`."""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..metrics.results import Recording
from ..scenario.model import Scenario
from ..scenario.parse import load_scenario
from ..sim.batch import BatchSimulator
from .parallel import run_all
from .plots import log_axes, pyplot, save
from .summary import (ATT_THRESHOLD_RAD, POS_THRESHOLD_M, QUANTITIES, SETTLE_FACTOR,
                      STEADY_FRACTION, TIMES, quantities, write_rows)

Array = NDArray[np.float64]

OUTPUT_FILES = ('runs.csv', 'summary.json', 'montecarlo.png')
RECORD_EVERY = 0.1        # [s]; at most duration / 100, so the window holds >= 25 records
RUN_COLUMNS = ('run', 'seed') + QUANTITIES


def reseed(scenario: Scenario, seed: int) -> Scenario:
    """The scenario with ``noise.seed`` and any ``initial_estimates.random.seed`` = ``seed``."""
    random_init = (replace(scenario.random_init, seed=seed)
                   if scenario.random_init is not None else None)
    return replace(scenario, noise=replace(scenario.noise, seed=seed), random_init=random_init)


@dataclass
class RunResult:
    """One run: its mean errors over time and its quantities."""

    run: int
    seed: int
    t: Array
    att_mean: Array
    pos_mean: Array
    values: dict[str, float | None]


def evaluate(rec: Recording, run: int, seed: int) -> RunResult:
    """The per-run quantities of a recording."""
    att, pos = rec.mean_errors()
    return RunResult(run=run, seed=seed, t=rec.t, att_mean=att, pos_mean=pos,
                     values=quantities(rec))


def run_one(scenario_file: str, run: int, seed: int, duration: float) -> RunResult:
    """One run, in a worker: load the file, reseed, simulate, evaluate."""
    scenario = reseed(load_scenario(scenario_file), seed)
    rec = BatchSimulator(scenario).run(duration, record_every=min(RECORD_EVERY, duration / 100))
    return evaluate(rec, run, seed)


def run_montecarlo(scenario_file: str | Path, runs: int, seed: int, duration: float,
                   jobs: int | None = None,
                   progress: Callable[[int, int, RunResult], None] | None = None
                   ) -> list[RunResult]:
    """``runs`` simulations, seeds ``seed ..``, on ``jobs`` processes, in run order."""
    calls = [(str(scenario_file), i, seed + i, duration) for i in range(runs)]
    return run_all(run_one, calls, jobs, progress)


def statistics(values: list[float | None]) -> dict[str, Any]:
    """mean, std (ddof=0), p5, p50, p95 and max over the ``n`` runs with a finite value (None
    without any); ``never_converged`` counts the None ones."""
    finite = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    out: dict[str, Any] = {'n': int(finite.size)}
    if finite.size:
        out.update(mean=float(finite.mean()), std=float(finite.std()),
                   p5=float(np.percentile(finite, 5)), p50=float(np.percentile(finite, 50)),
                   p95=float(np.percentile(finite, 95)), max=float(finite.max()))
    else:
        out.update(dict.fromkeys(('mean', 'std', 'p5', 'p50', 'p95', 'max')))
    out['never_converged'] = sum(v is None for v in values)
    nonfinite = sum(v is not None and not math.isfinite(v) for v in values)
    if nonfinite:
        out['non_finite'] = nonfinite
    return out


def summarize(results: list[RunResult], **extra: Any) -> dict[str, Any]:
    """``summary.json``: ``extra`` (scenario, seeds, ...) and every quantity's statistics."""
    stats = {q: statistics([r.values[q] for r in results]) for q in QUANTITIES}
    return {**extra, 'runs': len(results), 'statistics': stats,
            'runs_never_converged': {q: stats[q]['never_converged'] for q in TIMES}}


def write_runs_csv(results: list[RunResult], path: Path) -> None:
    # repr: the shortest text that reads back as the same float, so the CSV is exact.
    write_rows(path, RUN_COLUMNS, ([r.run, r.seed] + ['' if r.values[q] is None
                                                      else repr(r.values[q]) for q in QUANTITIES]
                                   for r in results))


def format_table(summary: dict[str, Any]) -> str:
    """The statistics as a small terminal table."""
    labels = {'final_attitude_error_mean_rad': 'final mean attitude error [rad]',
              'final_position_error_mean_m': 'final mean position error [m]',
              'final_attitude_error_max_rad': 'final max attitude error [rad]',
              'final_position_error_max_m': 'final max position error [m]',
              'steady_attitude_error_mean_rad': 'steady attitude error [rad]',
              'steady_position_error_mean_m': 'steady position error [m]',
              'steady_attitude_error_max_rad': 'steady max attitude error [rad]',
              'steady_position_error_max_m': 'steady max position error [m]',
              'attitude_below_1e-3_rad_from_s': 'time to attitude < 1e-3 rad [s]',
              'position_below_1e-2_m_from_s': 'time to position < 1e-2 m [s]',
              'attitude_settled_from_s': f'attitude settled ({SETTLE_FACTOR:g}x floor) [s]',
              'position_settled_from_s': f'position settled ({SETTLE_FACTOR:g}x floor) [s]'}
    cols = ('mean', 'std', 'p5', 'p50', 'p95', 'max')
    lines = [f'{"":32s}' + ''.join(f'{c:>10s}' for c in cols) + f'{"never":>7s}']
    for q in QUANTITIES:
        s = summary['statistics'][q]
        cells = ''.join('      none' if s[c] is None else f'{s[c]:10.3g}' for c in cols)
        never = str(s['never_converged']) if q in TIMES else ''
        lines.append(f'{labels[q]:32s}{cells}{never:>7s}')
    return '\n'.join(lines)


def write_plot(results: list[RunResult], path: Path) -> None:
    """``montecarlo.png``: every run's mean errors (the median bold), steady-state histograms."""
    plt = pyplot()
    floor = 1e-17  # a log axis cannot show exact zeros
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), constrained_layout=True)
    series = (('att_mean', 'mean attitude error [rad]', ATT_THRESHOLD_RAD,
               'steady_attitude_error_mean_rad'),
              ('pos_mean', 'mean position error [m]', POS_THRESHOLD_M,
               'steady_position_error_mean_m'))
    for col, (attr, label, threshold, steady) in enumerate(series):
        ax = axes[0, col]
        curves = [np.maximum(getattr(r, attr), floor) for r in results]
        for r, y in zip(results, curves):
            ax.plot(r.t, y, color='tab:blue', lw=0.6, alpha=0.35)
        n = min(c.size for c in curves)
        ax.plot(results[0].t[:n], np.median(np.stack([c[:n] for c in curves]), axis=0), 'k',
                lw=2.0, label=f'median of {len(results)} runs')
        ax.axhline(threshold, color='tab:red', ls='--', lw=1.0, label=f'threshold {threshold:g}')
        log_axes(ax, label.split(' [')[0] + ', every run', 'time [s]', label)

        ax = axes[1, col]
        v = np.maximum(np.array([r.values[steady] for r in results], dtype=float), floor)
        v = v[np.isfinite(v)]
        if v.size:
            lo, hi = np.log10(v.min()), np.log10(v.max())
            bins = np.logspace(lo - 0.05, hi + 0.05, max(5, min(30, len(v) // 2 + 1)))
            ax.hist(v, bins=bins, color='tab:blue', edgecolor='k', lw=0.5)
            ax.set_xscale('log')
        ax.set(xlabel=f'steady-state {label} (last {STEADY_FRACTION:.0%} of the run)',
               ylabel='runs')
        ax.grid(True, which='both', alpha=0.3)
    save(fig, path)
