"""A long run over DDS (issue 15's soak): the paper scenario for 30 simulated minutes, one process
per agent, at lockstep speed. Reports, per process, resident memory after the warm-up and at
the end (its growth); the followers' mean errors over the run (they must stay at their
converged level); every estimator's steps against the duration (none missed) and the steps
that went on without an awaited input; the simulator's lag behind the slowest estimator.

    .venv/bin/python bench/soak.py [config/paper_8_agents.yaml] [--duration 1800]
        [--warmup 120] [--every 20]
"""
from __future__ import annotations

import argparse
import os
import re
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

from bearing_pose_estimation.cli import launch  # noqa: E402
from bearing_pose_estimation.plan import processes as plan  # noqa: E402
from bearing_pose_estimation.runtime.health import INCOMPLETE_LOG  # noqa: E402
from bearing_pose_estimation.scenario import load_scenario  # noqa: E402
from bearing_pose_estimation.studies.summary import read_metrics_csv  # noqa: E402

_STEPS = re.compile(r'(\d+) steps \(([\d.]+) s of state time\)')
_LAG = re.compile(r'slowest estimate behind the clock: median (\S+) ms, max (\S+) ms')


def _processes(marker: str) -> dict[str, int]:
    """Node name -> pid of the processes whose command line names ``marker`` (the run's
    directory: every node's parameter file is in it)."""
    out = {}
    for pid in os.listdir('/proc'):
        if not pid.isdigit():
            continue
        try:
            args = Path(f'/proc/{pid}/cmdline').read_bytes().split(b'\0')
        except OSError:
            continue
        text = [a.decode(errors='replace') for a in args]
        if not any(marker in a for a in text):
            continue
        params = next((a for a in text if a.endswith('.yaml')), '')
        out[Path(params).stem or pid] = int(pid)
    return out


def _rss_mb(pid: int) -> float | None:
    try:
        status = Path(f'/proc/{pid}/status').read_text()
    except OSError:
        return None
    kib = next((line.split()[1] for line in status.splitlines() if line.startswith('VmRSS:')),
               None)
    return None if kib is None else int(kib) / 1024.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('scenario', nargs='?', type=Path,
                    default=Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml')
    ap.add_argument('--duration', type=float, default=1800.0, help='simulated seconds')
    ap.add_argument('--warmup', type=float, default=120.0,
                    help='wall seconds after which memory is the baseline')
    ap.add_argument('--every', type=float, default=20.0, help='memory sampling period [s]')
    args = ap.parse_args()
    scenario = load_scenario(args.scenario)
    with tempfile.TemporaryDirectory(prefix='soak_') as tmp:
        out = Path(tmp) / 'run'
        cfg = plan.RunConfig(scenario_file=args.scenario, out_dir=out, duration=args.duration,
                             domain_id=1 + os.getpid() % 101, plots=False,
                             timeout=3 * args.duration + 300)
        samples: dict[str, list[tuple[float, float]]] = {}
        done = threading.Event()

        def sample() -> None:
            start = time.monotonic()
            while not done.wait(args.every):
                now = time.monotonic() - start
                for name, pid in _processes(str(out)).items():
                    rss = _rss_mb(pid)
                    if rss is not None:
                        samples.setdefault(name, []).append((now, rss))

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        result = launch.launch_run(scenario, cfg)
        done.set()
        sampler.join()
        print(f'\n{args.scenario.name}, {args.duration:g} s simulated in {result.wall_s:.0f} s '
              f'wall (x{args.duration / result.wall_s:.2f}), run ok: {result.ok}\n')
        print('| process | RSS after warm-up | RSS at end | growth |')
        print('|---|---|---|---|')
        for name in sorted(samples):
            series = [(t, r) for t, r in samples[name] if t >= args.warmup]
            if len(series) < 2:
                continue
            print(f'| {name} | {series[0][1]:.1f} MB | {series[-1][1]:.1f} MB | '
                  f'{series[-1][1] - series[0][1]:+.2f} MB |')
        rec = read_metrics_csv(out / 'metrics.csv')
        att, pos = rec.mean_errors()
        print('\n| t [s] | mean attitude error [rad] | mean position error [m] |')
        print('|---|---|---|')
        for t in (10, 60, 300, 600, 1200, args.duration):
            k = int(np.argmin(np.abs(rec.t - t)))
            print(f'| {rec.t[k]:g} | {att[k]:.3e} | {pos[k]:.3e} |')
        late = rec.t >= 300.0
        if late.any():
            print(f'\nafter 300 s: max mean attitude error {att[late].max():.3e} rad, max mean '
                  f'position error {pos[late].max():.3e} m')
        want = int(round(args.duration * scenario.frequency))
        print(f'\nsteps (want {want} per estimator), steps without an awaited input:')
        for log in sorted(cfg.logs_dir.glob('*.log')):
            text = log.read_text()
            steps, inc = _STEPS.search(text), INCOMPLETE_LOG.search(text)
            if steps:
                print(f'  {log.stem}: {steps[1]} steps, {inc[1] if inc else "n/a"}')
        lag = _LAG.search((cfg.logs_dir / 'simulator.log').read_text())
        if lag:
            print(f'simulator: slowest estimate behind the clock, median {lag[1]} ms, '
                  f'max {lag[2]} ms')


if __name__ == '__main__':
    main()
