"""What the simulated world costs the simulator node: one internal tick of the truth with the
sensor samples due at it (gyro, bearings), per scenario, as µs per tick and as % of a core per
simulated second.

    OMP_NUM_THREADS=1 .venv/bin/python bench/world_cost.py [SCENARIO ...]

Medians of 7 timings of 500 ticks each, after 200 ticks. Compare trees by running it with
``PYTHONPATH=<worktree>`` alternated with the current one.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault('OMP_NUM_THREADS', '1')

from bearing_pose_estimation.scenario import load_scenario  # noqa: E402
from bearing_pose_estimation.sim.world import World  # noqa: E402
from de_carli_cost import median_us  # noqa: E402  (bench/ is the script's folder: one timing)

CONFIG = Path(__file__).resolve().parents[1] / 'config'
DEFAULT = ('paper_8_agents.yaml', 'paper_8_agents_moving.yaml', 'presenza_case1_30hz.yaml')


def main(files: list[str]) -> None:
    for name in files or [str(CONFIG / f) for f in DEFAULT]:
        scenario = load_scenario(name)
        world = World(scenario)
        n = len(scenario.agents)

        def tick() -> None:
            world.step()
            if world.due(world.imu_every):
                world.imu()
            if world.due(world.bearing_every):
                for i in range(n):
                    world.bearings(i)

        for _ in range(200):
            tick()
        us = median_us(tick, 500)
        print(f'{scenario.name}: {n} agents, {us:.1f} µs per {world.dt * 1e3:g} ms tick, '
              f'{us / world.dt * 1e-4:.1f} % of a core per simulated second')


if __name__ == '__main__':
    main(sys.argv[1:])
