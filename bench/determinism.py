"""Simulation runs that do not depend on the machine's load (issue 15): the same scenario over
DDS twice, once on an idle machine and once with every core kept busy by other processes, each
against netsim (the same agent logic without DDS, deterministic).

With ``fixed_exchange`` (the estimator nodes' default under ``use_sim_time``) every step uses
the inputs of fixed instants and waits for them, so the three agree to the rounding of
``metrics.csv`` (10 significant digits) or, for errors below 1e-4, of the doubles (states
known to ~1e-16 of the positions, and the fleet adds the roundings up: an error of 1e-6 is
then known to ~1e-8 of itself). Prints, per run, the largest relative difference of any
follower's attitude and position error at any recorded time, the wall time, and the steps
that went on without an awaited input.

    .venv/bin/python bench/determinism.py [config/paper_8_agents.yaml] [--duration 20]
        [--agents 12] [--load 2]
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

from bearing_pose_estimation.cli import launch  # noqa: E402
from bearing_pose_estimation.metrics.results import Recording  # noqa: E402
from bearing_pose_estimation.plan import processes as plan  # noqa: E402
from bearing_pose_estimation.runtime.health import INCOMPLETE_LOG  # noqa: E402
from bearing_pose_estimation.scenario import load_scenario  # noqa: E402
from bearing_pose_estimation.scenario.generate import generate_scenario  # noqa: E402
from bearing_pose_estimation.sim.netsim import run_network  # noqa: E402
from bearing_pose_estimation.studies.summary import read_metrics_csv  # noqa: E402

FLOOR = 1e-4   # [rad, m]: below, differences are absolute


def _burn(stop: mp.synchronize.Event) -> None:
    x = 0.0
    while not stop.is_set():
        for _ in range(10000):
            x = x * 1.0000001 + 1.0


def difference(a: Recording, b: Recording) -> tuple[float, float]:
    """The largest difference of any follower's error at any common time: relative where the
    error is at least ``FLOOR``, absolute below (where the wire's quaternions, exact to
    ~1e-16, dominate: an attitude error of 1e-7 rad is known to ~1e-9 of itself)."""
    ka = np.round(a.t * 1e6).astype(np.int64)
    kb = np.round(b.t * 1e6).astype(np.int64)
    _, ia, ib = np.intersect1d(ka, kb, return_indices=True)
    assert ia.size >= min(ka.size, kb.size) - 1, 'different record times'
    rel = small = 0.0
    for x, y in ((a.att_err[ia], b.att_err[ib]), (a.pos_err[ia], b.pos_err[ib])):
        big = np.abs(y) >= FLOOR
        if big.any():
            rel = max(rel, float(np.max(np.abs(x - y)[big] / np.abs(y[big]))))
        if (~big).any():
            small = max(small, float(np.max(np.abs(x - y)[~big])))
    return rel, small


def _fmt(d: tuple[float, float]) -> str:
    return f'{d[0]:.1e} ({d[1]:.0e})'


def run_dds(scenario_file: Path, out: Path, duration: float, domain: int,
            load: int) -> tuple[Recording, float, list[str]]:
    cfg = plan.RunConfig(scenario_file=scenario_file, out_dir=out, duration=duration,
                         domain_id=domain, plots=False, timeout=20 * duration + 300)
    scenario = load_scenario(scenario_file)
    stop = mp.Event()
    burners = [mp.Process(target=_burn, args=(stop,), daemon=True) for _ in range(load)]
    for p in burners:
        p.start()
    try:
        t0 = time.monotonic()
        result = launch.launch_run(scenario, cfg)
        wall = time.monotonic() - t0
    finally:
        stop.set()
        for p in burners:
            p.join()
    assert result.ok, f'the run failed: see {cfg.logs_dir}'
    incomplete = []
    for log in sorted(cfg.logs_dir.glob('agent_*.log')):
        m = INCOMPLETE_LOG.search(log.read_text())
        if m and m[1] != '0':
            incomplete.append(f'{log.stem}: {m[1]}')
    return read_metrics_csv(out / 'metrics.csv'), wall, incomplete


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('scenario', nargs='?', type=Path,
                    default=Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml')
    ap.add_argument('--duration', type=float, default=20.0, help='simulated seconds')
    ap.add_argument('--agents', type=int, help='instead of a file: a generated fleet of this '
                    'size (scenario.generate, seed 0: random attitudes, per-edge gains)')
    ap.add_argument('--load', type=int, default=os.cpu_count() or 2,
                    help='busy processes during the loaded run (default: one per core)')
    args = ap.parse_args()
    tmp_dir = tempfile.TemporaryDirectory(prefix='determinism_')
    if args.agents:
        args.scenario = Path(tmp_dir.name) / f'fleet_{args.agents}.yaml'
        args.scenario.write_text(yaml.safe_dump(generate_scenario(args.agents, seed=0),
                                                sort_keys=False))
    scenario = load_scenario(args.scenario)
    net = run_network(scenario, args.duration, record_every=0.1)
    domain = 1 + os.getpid() % 101
    print(f'{args.scenario.name}, {args.duration:g} s, {scenario.method}: the largest relative '
          'difference of any follower\'s errors at any 0.1 s record (in brackets: the largest '
          f'absolute one [rad, m] where an error is below {FLOOR:g})\n')
    print('| run | vs netsim | vs the idle run | wall | steps without an awaited input |')
    print('|---|---|---|---|---|')
    with tmp_dir as tmp:
        idle = None
        for name, load in (('idle', 0), (f'{args.load} busy processes', args.load)):
            rec, wall, incomplete = run_dds(args.scenario, Path(tmp) / name.split()[0],
                                            args.duration, domain, load)
            vs_idle = '' if idle is None else _fmt(difference(rec, idle))
            idle = idle or rec
            print(f'| {name} | {_fmt(difference(rec, net))} | {vs_idle} | {wall:.1f} s | '
                  f'{"; ".join(incomplete) or "none"} |', flush=True)


if __name__ == '__main__':
    main()
