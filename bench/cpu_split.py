"""Where an ``estimators`` process's CPU goes, per agent and simulated second, against what
the same steps cost with no DDS and no other process running.

Runs ``bearing-pose run SCENARIO --agents-per-process K --real-time-factor 1`` with
``BEARING_POSE_CPU_SPLIT=1``: each ``estimators`` process times its callbacks and its steps
and logs the split when it stops (:meth:`ros.step_batch.StepBatch.cpu_split`). Then runs the
same scenario in netsim (``sim.netsim``: the same agents, steps together, no DDS, one process)
and times the same step calls there, and one follower's IMU callback on its own (its node
built in this process, fed encoded samples, no executor). Prints, per part, the CPU in % of one
core per agent at real time and, for the steps and the messages, per call. ``--netsim-only``:
the netsim rows alone (any fleet size; the DDS run needs at least two agents per process).

    OMP_NUM_THREADS=1 .venv/bin/python bench/cpu_split.py [--scenario config/paper_8_agents.yaml]
        [--per-process 8] [--duration 40] [--netsim-only]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TypeVar

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

from bearing_pose_estimation.cli import launch  # noqa: E402
from bearing_pose_estimation.runtime.agent import AgentRuntime  # noqa: E402
from bearing_pose_estimation.ros.estimator_group import CPU_SPLIT_ENV  # noqa: E402
from bearing_pose_estimation.ros.step_batch import read_cpu_split  # noqa: E402
from bearing_pose_estimation.scenario import load_scenario  # noqa: E402
from bearing_pose_estimation.sim import netsim  # noqa: E402
from fleet_scale import run_config  # noqa: E402  (this folder: the same paced run)

T = TypeVar('T', bound=AgentRuntime)


def dds_split(scenario_file: Path, per_process: int, duration: float,
              tmp: Path) -> dict[str, tuple[float, int]]:
    """Summed over the ``estimators`` processes: each part's CPU [s] and its count."""
    cfg = run_config(scenario_file, tmp / 'run', duration, 1 + os.getpid() % 101, per_process)
    os.environ[CPU_SPLIT_ENV] = '1'
    result = launch.launch_run(load_scenario(scenario_file), cfg)
    if not result.ok:
        raise SystemExit(f'the run failed: see {cfg.logs_dir}')
    parts = {k: (0.0, 0) for k in ('messages', 'steps', 'around', 'executor', 'dds')}
    found = 0
    for log in cfg.logs_dir.glob('*.log'):
        split = read_cpu_split(log.read_text())
        if split is not None:
            found += 1
            for key, (seconds, count) in split.items():
                parts[key] = (parts[key][0] + seconds, parts[key][1] + count)
    if not found:
        raise SystemExit(f'no "CPU:" line in {cfg.logs_dir}: one agent per process has no split')
    return parts


def netsim_steps(scenario_file: Path, duration: float) -> tuple[float, int, float]:
    """netsim's step calls (:func:`runtime.together.advance_together`): CPU [s], agent-steps,
    and the whole run's CPU [s] (with its world and exchanges)."""
    spent, steps = [0], [0]
    original = netsim.advance_together

    def timed(agents: Sequence[T]) -> list[T]:
        start = time.thread_time_ns()
        stepped = original(agents)
        spent[0] += time.thread_time_ns() - start
        steps[0] += len(stepped)
        return stepped
    netsim.advance_together = timed
    try:
        start = time.process_time()
        netsim.simulate_network(load_scenario(scenario_file), duration)
        total = time.process_time() - start
    finally:
        netsim.advance_together = original
    return spent[0] * 1e-9, steps[0], total


def imu_callback_us(params_dir: Path, agent: str, samples: int = 4000) -> float:
    """One IMU sample's callback on its own [µs of CPU]: ``agent``'s node built as
    ``estimators`` builds it (its parameter file of the run), fed encoded samples at 200 Hz
    without an executor; the batch's requests are dropped (no step runs)."""
    import numpy as np
    import rclpy
    from bearing_pose_estimation.msg_defs import cdr
    from bearing_pose_estimation.ros.estimator_node import EstimatorNode
    from bearing_pose_estimation.ros.step_batch import StepBatch

    rclpy.init()
    try:
        batch = StepBatch()
        node = EstimatorNode(batch, namespace=f'/{agent}', cli_args=[
            '--ros-args', '--params-file', str(params_dir / f'{agent}.yaml')])
        omega = np.array([0.3, -0.2, 0.5])
        msgs = [cdr.encode_imu_raw(k * 0.005, agent, omega) for k in range(samples + 1)]
        node.on_imu(msgs[0])   # builds the estimator
        start = time.thread_time_ns()
        for msg in msgs[1:]:
            node.on_imu(msg)
            batch.pending.clear()
        spent = time.thread_time_ns() - start
        node.destroy_node()
    finally:
        rclpy.shutdown()
    return spent * 1e-3 / samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--scenario', type=Path, default=Path('config/paper_8_agents.yaml'))
    parser.add_argument('--per-process', type=int, default=8)
    parser.add_argument('--duration', type=float, default=40.0)
    parser.add_argument('--netsim-only', action='store_true',
                        help='only the steps in netsim (no DDS run)')
    args = parser.parse_args()
    scenario = load_scenario(args.scenario)
    n = len(scenario.agents)
    iso_s, iso_steps, iso_total = netsim_steps(args.scenario, args.duration)

    def pct(seconds: float) -> str:
        return f'{100 * seconds / (n * args.duration):.2f} %'

    def print_netsim() -> None:
        print(f'| steps in netsim (no DDS, one process) | {pct(iso_s)} | {iso_steps} '
              f'| {1e6 * iso_s / max(iso_steps, 1):.0f} |')
        print(f'| netsim whole (world, exchanges, steps) | {pct(iso_total)} | | |')

    if args.netsim_only:
        print(f'{args.scenario}, {n} agents, {args.duration:g} s in netsim')
        print('| part | CPU per agent | calls | µs per call |')
        print('|---|---|---|---|')
        return print_netsim()
    with tempfile.TemporaryDirectory() as tmp:
        parts = dds_split(args.scenario, args.per_process, args.duration, Path(tmp))
        follower = next(a.name for a in scenario.agents if a.name not in scenario.leaders)
        imu_us = imu_callback_us(Path(tmp) / 'run' / 'params', follower)

    total = sum(s for s, _ in parts.values())
    print(f'{args.scenario}, {n} agents, {args.per_process} per process, '
          f'{args.duration:g} s at real time')
    print('| part | CPU per agent | calls | µs per call |')
    print('|---|---|---|---|')
    for key, label in (('messages', 'callbacks (decode, check, store)'),
                       ('steps', 'steps (advance_together)'),
                       ('around', 'around the steps (readiness, publishing)'),
                       ('executor', 'executor and the rest of the main thread'),
                       ('dds', 'other threads (DDS)')):
        s, count = parts[key]
        per = f'{1e6 * s / count:.0f}' if count else ''
        print(f'| {label} | {pct(s)} | {count or ""} | {per} |')
    print(f'| all | {pct(total)} | | |')
    print_netsim()
    print(f'| one IMU callback of {follower} on its own (no executor) | | | {imu_us:.0f} |')


if __name__ == '__main__':
    main()
