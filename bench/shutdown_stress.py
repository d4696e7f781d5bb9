"""Shutdown stress: start a 4-agent fleet and the simulator, stop them all with SIGINT, repeat.

Counts the rounds in which some process did not exit 0 (crash, hang, exception), needed the
teardown watchdog (node_main.TEARDOWN_TIMEOUT_S) or left Fast DDS files in /dev/shm, and prints
the log of each such process. Before the spin loop stopped on its own (node_main._StopRequest)
about one round in twelve failed (SIGSEGV, a hang in ``destroy_node``, ``take_message``
raising); the hang inside Fast DDS's node destruction remains (see BENCHMARKS.md).

    .venv/bin/python bench/shutdown_stress.py [--rounds 50] [--run-for 3]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import yaml

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 101))

from bearing_pose_estimation.cli import launch  # noqa: E402
from bearing_pose_estimation.plan import dds  # noqa: E402
from bearing_pose_estimation.plan import processes as plan  # noqa: E402
from bearing_pose_estimation.scenario import load_scenario  # noqa: E402

FOUR = {
    'name': 'four', 'leaders': ['agent_1', 'agent_2'],
    'initial_estimates': {'random': {'seed': 3, 'position_std': 1.0, 'max_angle_deg': 45}},
    'agents': [
        {'name': 'agent_1', 'position': [0, 0, 0], 'angular_velocity': [0.3, -0.5, 0.2]},
        {'name': 'agent_2', 'position': [2, 0, 0], 'angular_velocity': [0, 0.4, 0]},
        {'name': 'agent_3', 'position': [1, 2, 0], 'angular_velocity': [0, 0, 0.5],
         'neighbours': ['agent_1', 'agent_2']},
        {'name': 'agent_4', 'position': [1, 1, 2], 'angular_velocity': [0.2, 0, 0],
         'neighbours': ['agent_2', 'agent_3']}]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--rounds', type=int, default=50)
    ap.add_argument('--run-for', type=float, default=3.0, help='seconds before the SIGINT')
    args = ap.parse_args()
    domain = int(os.environ['ROS_DOMAIN_ID'])
    bad, stop_s = 0, []
    with tempfile.TemporaryDirectory(prefix='shutdown_stress_') as tmp_dir:
        tmp = Path(tmp_dir)
        scenario_file = tmp / 'four.yaml'
        scenario_file.write_text(yaml.safe_dump(FOUR))
        scenario = load_scenario(scenario_file)
        for k in range(args.rounds):
            cfg = plan.RunConfig(scenario_file=scenario_file, out_dir=tmp / f'round_{k}',
                                 duration=600.0, domain_id=domain, plots=False,
                                 real_time_factor=0.5)
            cfg.logs_dir.mkdir(parents=True)
            specs = plan.plan_processes(scenario, plan.write_params(scenario, cfg),
                                        cfg.logs_dir, plan.find_executable)
            specs = [s if s.name != 'simulator' else plan.ProcessSpec(
                s.name, s.kind, s.argv + ('-p', 'wait_for_monitor:=false', '-p',
                                          'lockstep:=false'), s.log)
                     for s in specs if s.name != 'monitor']
            shm_before = dds.shm_files()
            with launch.ProcessGroup(env=dds.dds_env(domain, tmp / 'ros')) as group:
                for spec in specs:
                    group.start(spec)
                time.sleep(args.run_for)
                t0 = time.monotonic()
                group.shutdown()
                stop_s.append(time.monotonic() - t0)
                failed = group.unclean()
                hung = [n for n in group.pids if group.returncode(n) == dds.TEARDOWN_HUNG]
            leaked = dds.leaked_shm(shm_before)  # after the group removed the hung ones'
            print(f'round {k}: {"ok" if not failed else f"FAILED {failed}"}, '
                  f'stopped in {stop_s[-1]:.2f} s'
                  + (f'; teardown watchdog fired in {hung}' if hung else '')
                  + (f'; {len(leaked)} file(s) left in /dev/shm' if leaked else ''), flush=True)
            if failed or hung or leaked:
                bad += 1
                for spec in specs:
                    if spec.name in failed or spec.name in hung:
                        print(f'--- {spec.name} log ---\n{Path(spec.log).read_text()[-4000:]}')
    stop_s.sort()
    print(f'{bad} bad rounds of {args.rounds}; median stop {stop_s[len(stop_s) // 2]:.2f} s, '
          f'max {stop_s[-1]:.2f} s')


if __name__ == '__main__':
    main()
