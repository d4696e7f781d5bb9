"""Clock floors: what robots whose clocks disagree cost each method's steady state.

Runs each method's reference scenario (its ``reference_scenario`` in config/, or
``--scenario``) in netsim (bearing_pose_estimation.sim.netsim: the node's runtime without DDS)
with every robot's clock off by ``±offset`` (signs alternating over the agents) or drifting by
``±drift`` (``netsim.clock_cases``, the fault matrix's clock rows), and compares the steady
state (the last quarter of the run, ``studies.summary``) with the fault-free run's.
Deterministic; prints a Markdown table.

    .venv/bin/python bench/clock_floor.py [--jobs N]
    .venv/bin/python bench/clock_floor.py --scenario config/de_carli_8_quadrotors.yaml \\
        --offsets 0.001 0.002 0.005 0.01 0.02 0.05

Columns: the mean attitude and position errors over the steady-state window and over the
estimating agents; the same as a multiple of the fault-free run's; the worst agent at any
record of the window; the listeners that flagged a neighbour's clock as ahead by more than
``Limits.max_clock_lead`` (``/diagnostics`` warns about them), with how many neighbours.
"""
from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from bearing_pose_estimation import estimators
from bearing_pose_estimation.sim.netsim import FaultCase, NetRun, clock_cases, run_case
from bearing_pose_estimation.studies.summary import quantities
from fault_matrix import load  # (bench/ is the script's folder: one way to load)

CONFIG = Path(__file__).resolve().parents[1] / 'config'
RECORD_EVERY = 0.1  # [s]
HEADER = ('| method (scenario, run) | clocks | steady att. error [rad] | steady pos. error [m] | '
          '× fault-free (att., pos.) | worst agent (att., pos.) | flagged ahead |\n'
          '|---|---|---|---|---|---|---|')


def run_row(path: Path, case: FaultCase, duration: float) -> NetRun:
    return run_case(load(path), case, duration, RECORD_EVERY)


def format_rows(path: Path, duration: float, cases: list[FaultCase],
                runs: list[NetRun]) -> list[str]:
    """The table rows of one scenario (its fault-free run first)."""
    scenario = load(path)
    ref = quantities(runs[0].recording)
    rows = []
    for case, run in zip(cases, runs):
        q = quantities(run.recording)
        att, pos = q['steady_attitude_error_mean_rad'], q['steady_position_error_mean_m']
        ratio = (f'{att / ref["steady_attitude_error_mean_rad"]:.3g}, '
                 f'{pos / ref["steady_position_error_mean_m"]:.3g}')
        flagged = (f'{len(run.ahead)} agents ({sum(map(len, run.ahead.values()))} '
                   'neighbours)' if run.ahead else 'none')
        rows.append(f'| {scenario.method} ({path.name}, {duration:g} s) | '
                    f'{case.label if case.clocks else "equal (fault-free)"} | {att:.2e} | '
                    f'{pos:.2e} | {ratio} | {q["steady_attitude_error_max_rad"]:.2e}, '
                    f'{q["steady_position_error_max_m"]:.2e} | {flagged} |')
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--scenario', type=Path, nargs='*',
                    help='scenario files (default: every method\'s reference scenario)')
    ap.add_argument('--duration', type=float, help='[s] (default: each scenario\'s)')
    ap.add_argument('--offsets', type=float, nargs='*', default=[0.005, 0.05], help='[s]')
    ap.add_argument('--drift', type=float, default=1e-4,
                    help='[s/s] (1e-4: 100 ppm; 0: no drift row)')
    ap.add_argument('--jobs', type=int, default=os.cpu_count() or 1)
    args = ap.parse_args()
    paths = args.scenario or [CONFIG / estimators.get(m).reference_scenario
                              for m in estimators.methods()]
    cases = [FaultCase('reference', 'none (reference)'),
             *clock_cases(args.offsets, args.drift)]
    durations = [args.duration or load(p).duration for p in paths]
    jobs = [(p, c, d) for p, d in zip(paths, durations) for c in cases]
    wall = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        runs = list(pool.map(run_row, *zip(*jobs)))
    wall = time.perf_counter() - wall
    print(HEADER)
    for k, (path, duration) in enumerate(zip(paths, durations)):
        print('\n'.join(format_rows(path, duration, cases,
                                    runs[k * len(cases):(k + 1) * len(cases)])))
    print(f'\n{len(jobs)} runs, {args.jobs} process(es), wall time {wall:.0f} s')


if __name__ == '__main__':
    main()
