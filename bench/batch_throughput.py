"""Batch simulator throughput: agent-steps per second on one core, by fleet size.

Fleets from `bearing-pose generate` (seed 0; 8 agents: the paper scenario). Times
`BatchSimulator.step()` (truth, measurements, every observer) after a warm-up; prints the
median over repeats.

    OMP_NUM_THREADS=1 .venv/bin/python bench/batch_throughput.py [--agents 8 100 1000 ...]
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault('OMP_NUM_THREADS', '1')
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from bearing_pose_estimation.scenario.generate import generate_scenario  # noqa: E402
from bearing_pose_estimation.scenario import load_scenario, parse_scenario  # noqa: E402
from bearing_pose_estimation.sim.batch import BatchSimulator  # noqa: E402

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--agents', type=int, nargs='+', default=[8, 100, 1000, 2000, 5000, 10000])
    args = ap.parse_args()
    print('| agents | edges | us per step | agent-steps per second |')
    print('|---|---|---|---|')
    for n in args.agents:
        scenario = (load_scenario(PAPER) if n == 8
                    else parse_scenario(generate_scenario(n, seed=0)))
        sim = BatchSimulator(scenario)
        steps = max(20, min(2000, 200_000 // n))
        for _ in range(5):
            sim.step()
        runs = []
        for _ in range(5):
            t0 = time.perf_counter()
            for _ in range(steps):
                sim.step()
            runs.append((time.perf_counter() - t0) / steps)
        per_step = float(np.median(runs))
        print(f'| {n} | {len(sim.edges)} | {per_step * 1e6:.0f} | {n / per_step:.3g} |',
              flush=True)


if __name__ == '__main__':
    main()
