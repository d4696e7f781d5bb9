"""What De Carli et al.'s method costs: one robot's step (what its node runs at 200 Hz), the
node logic's input pairing, the whole fleet's batch step, and netsim's world with eight robots.

    OMP_NUM_THREADS=1 .venv/bin/python bench/de_carli_cost.py

Medians of 7 timings on config/de_carli_8_quadrotors.yaml (exogenous motion), after 1 s of
simulated time (every pair started, every stage running).
"""
from __future__ import annotations

import os
import statistics
import time
from pathlib import Path

os.environ.setdefault('OMP_NUM_THREADS', '1')

from bearing_pose_estimation.scenario import parse_scenario  # noqa: E402
from bearing_pose_estimation.scenario.parse import read_scenario_data  # noqa: E402
from bearing_pose_estimation.sim.batch import BatchSimulator  # noqa: E402
from bearing_pose_estimation.sim.netsim import simulate_network  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'de_carli_8_quadrotors.yaml'


def median_us(fn, calls: int) -> float:
    times = []
    for _ in range(7):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        times.append((time.perf_counter() - t0) / calls * 1e6)
    return statistics.median(times)


def main() -> None:
    data = read_scenario_data(CONFIG)
    data['formation_control']['mode'] = 'exogenous'
    scenario = parse_scenario(data)
    sim = BatchSimulator(scenario)
    for _ in range(200):
        sim.step()
    inputs = sim.inputs()
    est = sim.estimator
    print('| what | median [µs] |\n|---|---|')
    for i in (0, 4):   # robot_0: 3 links; robot_4: 3 links, senses all three
        one, x = inputs.agent(i), sim.x.rows([i])
        print(f'| one robot\'s step (robot_{i}, {len(one.edges)} links) | '
              f'{median_us(lambda: est.step(x, sim.h, one), 2000):.0f} |')
    print(f'| the fleet\'s step, 8 robots, batch | '
          f'{median_us(lambda: est.step(sim.x, sim.h, inputs), 2000):.0f} |')
    print(f'| BatchSimulator.step(), truth and measurements included | '
          f'{median_us(sim.step, 400):.0f} |')
    t0 = time.perf_counter()
    simulate_network(scenario, 1.0, 0.5)
    wall = time.perf_counter() - t0
    print(f'| netsim, 8 robots\' node logic and the 1 ms world, per simulated second | '
          f'{wall * 1e6:.0f} |')


if __name__ == '__main__':
    main()
