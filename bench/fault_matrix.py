"""Fault matrix: what each fault and bad input costs on the paper's 8-agent scenario.

Runs the distributed estimators without DDS (bearing_pose_estimation.sim.netsim: the same
agent runtime as the node, fed like the simulator node feeds it) with one fault per row of
``netsim.fault_cases()`` (the list test/test_robustness.py tests), and compares with the
fault-free run at the same instants. Deterministic; prints a Markdown table.

    .venv/bin/python bench/fault_matrix.py [--duration 60] [--jobs N]
    .venv/bin/python bench/fault_matrix.py --scenario config/de_carli_8_quadrotors.yaml \
        --victim robot_4 --late robot_7 --at 5 --length 2 --late-join 3 --delay 0.05 --duration 20

(a scenario whose formation controller runs in the paper's mode runs in the exogenous one: the
simulated world, like the simulator node, cannot see the estimates).

Columns (measures in netsim):
- re-convergence: time after the fault ends until both mean errors are back at or below the
  fault-free run's at that instant (``netsim.reconvergence_time``; faults with an end only);
- caught up: time after the fault ends from which both stay within 1.5 times the fault-free
  run's at the same instant (``netsim.catch_up_time``);
- cost: seconds of convergence lost by the end, for the error that lost more
  (``netsim.convergence_cost``);
- events: the estimators' time rules that fired (``time_jump``, ``gyro_gap``);
- garbage rejected: corrupted inputs rejected / injected (bearings count per point);
- crashes: the estimator calls are not guarded, so any exception ends that row's run; it is
  counted here and the row reports it instead of errors;
- non-finite estimates: estimates with a NaN/inf, checked after every step of every agent.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from bearing_pose_estimation.sim.netsim import (CATCH_UP_FACTOR, FaultCase, NetRun,
                                                catch_up_time, convergence_cost, fault_cases,
                                                reconvergence_time, run_case)
from bearing_pose_estimation.scenario import Scenario, load_scenario

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'
RECORD_EVERY = 0.5  # [s]: the resolution of the re-convergence and cost columns
HEADER = ('| fault | mean att. error at end [rad] | mean pos. error at end [m] | '
          're-convergence after the fault [s] | caught up after the fault [s] | cost at the end [s] '
          '| time-rule events | garbage rejected | crashes | non-finite estimates |\n'
          '|---|---|---|---|---|---|---|---|---|---|')


def load(path: Path) -> Scenario:
    """The scenario, its formation controller (if any) in the exogenous mode."""
    scenario = load_scenario(path)
    if scenario.formation is not None and scenario.formation.mode == 'paper':
        scenario = dataclasses.replace(scenario, index={}, formation=dataclasses.replace(
            scenario.formation, mode='exogenous'))
    return scenario


def run_row(case: FaultCase, duration: float, path: Path = PAPER) -> NetRun | str:
    """One row, in a worker: its run, or the exception that escaped the estimator logic."""
    try:
        return run_case(load(path), case, duration, RECORD_EVERY)
    except Exception as exc:  # noqa: BLE001 - a crash is a measured outcome here
        return f'{type(exc).__name__}: {exc}'


def format_row(case: FaultCase, run: NetRun | str, ref: NetRun) -> str:
    """The table row of one case."""
    if isinstance(run, str):
        return f'| {case.label} | crashed: {run} | | | | | | | 1 | |'
    rec = run.recording
    att, pos = rec.mean_errors()
    reconv = caught = 'n/a'
    if case.window is not None:
        t = reconvergence_time(rec, ref.recording, case.window[1])
        reconv = 'not by the end' if t is None else f'{t:.1f}'
        t = catch_up_time(rec, ref.recording, case.window[1], CATCH_UP_FACTOR)
        caught = 'not by the end' if t is None else f'{t:.1f}'
    events = ', '.join(f'{k} ×{n}' for k, n in sorted(run.inputs.events.items())) or 'none'
    tally = run.inputs
    garbage = (f'{sum(tally.garbage_rejected.values())} of {tally.garbage_injected}'
               if tally.garbage_injected else 'n/a')
    non_finite = str(run.non_finite_estimates)
    if run.non_finite_steps:
        non_finite += f' ({run.non_finite_steps} steps discarded)'
    return (f'| {case.label} | {att[-1]:.2e} | {pos[-1]:.2e} | {reconv} | {caught} | '
            f'{convergence_cost(rec, ref.recording):.1f} | {events} | {garbage} | 0 | '
            f'{non_finite} |')


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--duration', type=float, default=60.0)
    ap.add_argument('--jobs', type=int, default=os.cpu_count() or 1)
    ap.add_argument('--scenario', type=Path, default=PAPER)
    ap.add_argument('--victim', default='agent_4', help='the agent cut off, paused, restarted')
    ap.add_argument('--late', default='agent_7', help='the agent that joins late')
    ap.add_argument('--at', type=float, default=20.0, help='when the faults start [s]')
    ap.add_argument('--length', type=float, default=5.0, help='how long they last [s]')
    ap.add_argument('--late-join', type=float, default=10.0, help='when --late starts [s]')
    ap.add_argument('--delay', type=float, default=0.2, help='the delayed rows\' delay [s]')
    args = ap.parse_args()
    cases = fault_cases(at=args.at, length=args.length, late_join=args.late_join,
                        victim=args.victim, late=args.late, delay=args.delay)
    wall = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        runs = list(pool.map(run_row, cases, [args.duration] * len(cases),
                             [args.scenario] * len(cases)))
    wall = time.perf_counter() - wall
    ref = runs[0]
    if isinstance(ref, str):
        raise SystemExit(f'the fault-free reference run crashed: {ref}')
    print(HEADER)
    for case, run in zip(cases, runs):
        print(format_row(case, run, ref))
    for case, run in zip(cases, runs):
        if isinstance(run, NetRun) and run.inputs.garbage_rejected:
            causes = ', '.join(f'{k} {n}' for k, n in run.inputs.garbage_rejected.most_common())
            print(f'\n{case.label}: rejected as {causes}; accepted '
                  f'{run.inputs.garbage_accepted}; good inputs rejected: '
                  f'{sum((run.inputs.rejected - run.inputs.garbage_rejected).values())}')
    print(f'\n{len(cases)} rows of {args.duration:g} s, {args.jobs} process(es), '
          f'wall time {wall:.0f} s')


if __name__ == '__main__':
    main()
