"""The Tran, Anderson & Ahn (2020) noise experiment for several methods (``noise-study``):
every bearing is ``rot_X(θ0 sin 2πft) · b`` (Section 5.1: θ0 up to 10°, f from 1 to 25 Hz),
replacing the file's ``bearing_perturbation``; one batch run per method and (θ0, f), and its
``steady_*`` quantities. Bearings are sampled once per step ``h``: frequencies above ``1/(4h)``
would alias and are refused."""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import cast
from pathlib import Path

import numpy as np

from ..scenario.model import BearingPerturbation, Scenario
from ..sim.batch import BatchSimulator
from .parallel import run_all
from .plots import log_axes, pyplot, save
from .summary import STEADY_FRACTION, quantities, write_rows

OUTPUT_FILES = ('noise_study.csv', 'noise_study.md', 'noise_study.png')
RECORD_EVERY = 0.01      # [s]; fine enough to catch the peaks of a 25 Hz perturbation
QUANTITIES = ('steady_attitude_error_mean_rad', 'steady_position_error_mean_m',
              'steady_attitude_error_max_rad', 'steady_position_error_max_m')
COLUMNS = ('method', 'amplitude_deg', 'frequency_hz') + QUANTITIES


@dataclass(frozen=True)
class Case:
    method: str
    amplitude_deg: float
    frequency_hz: float
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)   # X, unit (body frame)


@dataclass(frozen=True)
class CaseResult:
    case: Case
    values: dict[str, float]


def check_frequencies(frequencies_hz: Sequence[float], scenario: Scenario) -> None:
    """ValueError if a frequency is not resolved by the estimator step (< 4 samples/period)."""
    limit = 0.25 / scenario.step
    bad = [f for f in frequencies_hz if f > limit + 1e-9]
    if bad:
        raise ValueError(f'frequency {bad[0]:g} Hz is above {limit:g} Hz, a quarter of the '
                         f'scenario\'s estimator rate {1 / scenario.step:g} Hz; the bearings '
                         'would be aliased. Fix: raise `frequency:` in the scenario, or use '
                         'lower frequencies')


def run_case(scenario: Scenario, case: Case, duration: float) -> CaseResult:
    """One run (in a worker process) with the case's perturbation: the steady-state quantities."""
    bp = BearingPerturbation(amplitude_deg=case.amplitude_deg, frequency_hz=case.frequency_hz,
                             axis=case.axis)
    noise = dataclasses.replace(scenario.noise, bearing_perturbation=bp)
    sim = BatchSimulator(dataclasses.replace(scenario, noise=noise))
    values = quantities(sim.run(duration, record_every=max(RECORD_EVERY, scenario.step)))
    return CaseResult(case, {q: float(cast(float, values[q])) for q in QUANTITIES})


def run_study(scenarios: dict[str, Scenario], amplitudes_deg: Sequence[float],
              frequencies_hz: Sequence[float], duration: float, jobs: int | None = None,
              progress: Callable[[int, int, CaseResult], None] | None = None,
              axis: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> list[CaseResult]:
    """Every (method, θ0, f) about ``axis`` on ``jobs`` processes, in that order."""
    cases = [Case(m, a, f, axis) for m in scenarios for a in amplitudes_deg
             for f in frequencies_hz]
    return run_all(run_case, [(scenarios[c.method], c, duration) for c in cases], jobs,
                   progress)


def write_csv(results: list[CaseResult], path: Path) -> None:
    write_rows(path, COLUMNS, ([r.case.method, f'{r.case.amplitude_deg:g}',
                                f'{r.case.frequency_hz:g}']
                               + [f'{r.values[q]:.6e}' for q in QUANTITIES] for r in results))


def table(results: list[CaseResult]) -> str:
    """Markdown: one row per (θ0, f), the methods side by side (attitude in degrees)."""
    methods = list(dict.fromkeys(r.case.method for r in results))
    by = {(r.case.method, r.case.amplitude_deg, r.case.frequency_hz): r.values for r in results}
    head = ['θ0 [deg]', 'f [Hz]'] + [f'{m}: {q}' for m in methods
                                     for q in ('attitude bound [deg]', 'position bound [m]',
                                               'steady mean attitude [deg]',
                                               'steady mean position [m]')]
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for a, f in dict.fromkeys((r.case.amplitude_deg, r.case.frequency_hz) for r in results):
        cells = [f'{a:g}', f'{f:g}']
        for m in methods:
            v = by[(m, a, f)]
            cells += [f'{np.degrees(v["steady_attitude_error_max_rad"]):.3g}',
                      f'{v["steady_position_error_max_m"]:.3g}',
                      f'{np.degrees(v["steady_attitude_error_mean_rad"]):.3g}',
                      f'{v["steady_position_error_mean_m"]:.3g}']
        lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines) + '\n'


def write_plot(results: list[CaseResult], path: Path) -> Path:
    """Neighbourhood radius (worst follower) against f, per method and θ0, attitude and position."""
    plt = pyplot()
    fig, (att, pos) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    methods = list(dict.fromkeys(r.case.method for r in results))
    amplitudes = list(dict.fromkeys(r.case.amplitude_deg for r in results))
    styles = ('-o', '--s', ':^', '-.v')  # one per method; one colour per θ0
    for k, m in enumerate(methods):
        for c, a in enumerate(amplitudes):
            rs = [r for r in results if r.case.method == m and r.case.amplitude_deg == a]
            f = [r.case.frequency_hz for r in rs]
            style = dict(color=f'C{c}', label=f'{m}, θ0 = {a:g}°', ms=4)
            att.plot(f, [np.degrees(r.values['steady_attitude_error_max_rad']) for r in rs],
                     styles[k % len(styles)], **style)
            pos.plot(f, [r.values['steady_position_error_max_m'] for r in rs],
                     styles[k % len(styles)], **style)
    window = f' (last {STEADY_FRACTION:.0%} of the run)'
    for ax, title, ylabel in ((att, 'Attitude error bound', 'worst follower [deg]'),
                              (pos, 'Position error bound', 'worst follower [m]')):
        log_axes(ax, title + window, 'perturbation frequency f [Hz]', ylabel, log_x=True,
                 legend_size=7)
    return save(fig, path)
