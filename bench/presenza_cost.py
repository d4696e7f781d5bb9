"""What Presenza et al.'s method costs: the batch simulator on the paper's case 1 (agent-steps
per second, to set beside other implementations), one robot's two rounds (what its node runs
each step), and the step's floor: the same numpy work with nothing of ours around it.

    OMP_NUM_THREADS=1 .venv/bin/python bench/presenza_cost.py

Medians of 7 timings on config/presenza_case1.yaml (5 robots, 1 ms), after 1 s of simulated
time.
"""
from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault('OMP_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from bearing_pose_estimation.scenario import load_scenario  # noqa: E402
from bearing_pose_estimation.sim.batch import BatchSimulator  # noqa: E402
from de_carli_cost import median_us  # noqa: E402  (bench/ is the script's folder: one timing)

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'presenza_case1.yaml'


def floor_us(n: int, n_edges: int, calls: int) -> float:
    """The step's unavoidable numpy work at this size: the batched 3x3 solves, eigenvalues,
    exponentials and products the update needs (two solves, one eigvalsh, one exp, ~12
    einsums), on arrays of the fleet's shape, with no indexing, masks or Python around them."""
    rng = np.random.default_rng(0)
    M = rng.normal(size=(n, 3, 3))
    S = M @ np.swapaxes(M, -1, -2) + np.eye(3)
    v = rng.normal(size=(n, 3, 1))
    e = rng.normal(size=(n_edges, 3))
    R = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]

    def work() -> None:
        np.linalg.solve(S, v)
        np.linalg.solve(S, v)
        np.linalg.eigvalsh(S)
        for _ in range(6):
            np.einsum('nab,nb->na', R, v[:, :, 0])
            np.einsum('ea,eb->eab', e, e)
        R @ R @ R

    return median_us(work, calls)


def main() -> None:
    scenario = load_scenario(CONFIG)
    sim = BatchSimulator(scenario)
    sim.run(1.0, record_every=0.5)
    n = len(scenario.agents)
    inputs = sim.inputs()
    est = sim.estimator
    print('| what | median [µs] | agent-steps/s |\n|---|---|---|')
    step = median_us(lambda: est.step(sim.x, sim.h, inputs), 1000)
    print(f'| the fleet\'s step, {n} robots ({len(inputs.edges)} links), batch | {step:.0f} | '
          f'{n / step * 1e6:,.0f} |')
    both = median_us(lambda: (est.reply(sim.x, sim.h, inputs), est.step(sim.x, sim.h, inputs)),
                     500)
    print(f'| both rounds (reply + step), {n} robots | {both:.0f} | {n / both * 1e6:,.0f} |')
    full = median_us(sim.step, 300)
    print(f'| BatchSimulator.step(): truth, sensors, both rounds | {full:.0f} | '
          f'{n / full * 1e6:,.0f} |')
    one, x = inputs.agent(1), sim.x.rows([1])
    print(f'| one robot\'s step (robot_2, {len(one.edges)} links) | '
          f'{median_us(lambda: est.step(x, sim.h, one), 2000):.0f} | |')
    print(f'| floor: the step\'s numpy calls alone, {n} robots | '
          f'{floor_us(n, len(inputs.edges), 2000):.0f} | |')


if __name__ == '__main__':
    main()
