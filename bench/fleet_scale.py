"""Distributed fleet at scale: real time or not, deadline misses, CPU, memory, discovery.

For each fleet size N (generated, seed 0) and agents-per-process K, runs the whole system over
DDS on loopback (`bearing-pose run` with ``--real-time-factor 1``: the clock may not run faster
than the wall, and lockstep slows it when estimators fall behind) and reports:

- speed: simulated / wall seconds once the clock started (1.00: real time);
- missed: share of the simulator's ticks at which the slowest estimator's last estimate was
  more than two publish periods behind the clock (a missed deadline);
- CPU per agent [% of a core] (estimator processes only) and of the simulator;
- memory: resident set size per estimator process and per agent;
- discovery: wall seconds from start until every estimator had matched the simulator;
- the mean errors of the followers at the end (the run converges or not).

A fleet "runs in real time" when speed >= 0.99 and missed < 1 %.

    .venv/bin/python bench/fleet_scale.py [--agents 8 16 32] [--per-process 1 4]
        [--frequency 50] [--publish-rate 50] [--imu-rate 50] [--duration 20]
        [--executor events|draining|rclpy] [--discovery-server] [--domain-id N]

With ``--discovery-server`` the runs discover through their own Fast DDS discovery server
(``bearing-pose run --discovery-server``), and may use more than 32 processes.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import tempfile
from pathlib import Path

import yaml

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

from bearing_pose_estimation.cli import launch  # noqa: E402
from bearing_pose_estimation.plan import processes as plan  # noqa: E402
from bearing_pose_estimation.scenario.generate import generate_scenario  # noqa: E402
from bearing_pose_estimation.ros.node_main import (  # noqa: E402
    DEFAULT_EXECUTOR, EXECUTOR_ENV, EXECUTORS)
from bearing_pose_estimation.scenario import load_scenario  # noqa: E402

_DONE = re.compile(r'reached t = \S+ s in (?P<wall>\S+) s wall \(x(?P<speed>\S+) real time\).*'
                   r'in (?P<missed>\S+) % of ticks')
_MATCHED = re.compile(r'all matched after (?P<s>\S+) s')


def run_config(scenario_file: Path, out_dir: Path, duration: float, domain_id: int,
               agents_per_process: int = 1, discovery_server: bool = False) -> plan.RunConfig:
    """A fleet run as this bench makes it: paced at real time (``--real-time-factor 1``), no
    plots, a generous timeout."""
    return plan.RunConfig(scenario_file=scenario_file, out_dir=out_dir, duration=duration,
                          domain_id=domain_id, real_time_factor=1.0, plots=False,
                          agents_per_process=agents_per_process, timeout=20 * duration + 300,
                          discovery_server=0 if discovery_server else None)


def simulator_stats(log: str) -> dict[str, float]:
    """From a simulator's log: ``speed`` (simulated / wall seconds) and ``missed`` [% of
    ticks] once it reached the end, ``discovery_s`` once it started the clock."""
    out: dict[str, float] = {}
    if (m := _DONE.search(log)):
        out.update(speed=float(m['speed']), missed=float(m['missed']))
    if (m := _MATCHED.search(log)):
        out['discovery_s'] = float(m['s'])
    return out


def run_one(n: int, k: int, args: argparse.Namespace, tmp: Path) -> dict[str, float | str]:
    data = generate_scenario(n, seed=0)
    data['frequency'] = args.frequency
    data['publish_rate'] = args.publish_rate
    data['simulation'] = {'imu_rate': args.imu_rate}
    if args.position_std is not None:
        data['initial_estimates']['random']['position_std'] = args.position_std
    scenario_file = tmp / f'fleet_{n}.yaml'
    scenario_file.write_text(yaml.safe_dump(data, sort_keys=False))
    scenario = load_scenario(scenario_file)
    cfg = run_config(scenario_file, tmp / f'run_{n}_{k}', args.duration, args.domain_id, k,
                     args.discovery_server)
    result = launch.launch_run(scenario, cfg)
    row: dict[str, float | str] = {'agents': n, 'per_process': k, 'ok': str(result.ok)}
    row.update(simulator_stats((cfg.logs_dir / 'simulator.log').read_text()))
    others = ('simulator', 'monitor', plan.DISCOVERY_SERVER)
    est = {name: cpu for name, cpu in result.cpu_s.items() if name not in others}
    row['cpu_agent_pct'] = 100 * sum(est.values()) / n / result.wall_s
    row['cpu_sim_pct'] = 100 * result.cpu_s.get('simulator', float('nan')) / result.wall_s
    rss = [v for name, v in result.rss_mb.items() if name not in others]
    row['rss_process_mb'] = sum(rss) / max(len(rss), 1)
    row['rss_agent_mb'] = sum(rss) / n
    summary = cfg.out_dir / 'summary.json'
    if summary.exists():
        final = json.loads(summary.read_text())
        row.update(att_err=final['final_attitude_error_mean_rad'],
                   pos_err=final['final_position_error_mean_m'])
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--agents', type=int, nargs='+', default=[8, 16, 32])
    ap.add_argument('--per-process', type=int, nargs='+', default=[1, 4])
    ap.add_argument('--frequency', type=float, default=50.0, help='estimator rate [Hz]')
    ap.add_argument('--imu-rate', type=float, default=50.0, help='gyro samples [Hz]')
    ap.add_argument('--duration', type=float, default=20.0, help='simulated seconds')
    ap.add_argument('--publish-rate', type=float, default=50.0,
                    help='estimates and world bearings sent to neighbours [Hz]')
    ap.add_argument('--position-std', type=float, help='initial position error std [m]')
    ap.add_argument('--executor', choices=sorted(EXECUTORS), default=DEFAULT_EXECUTOR,
                    help=f'executor of every node (default: {DEFAULT_EXECUTOR}, as in production)')
    ap.add_argument('--discovery-server', action='store_true',
                    help="discovery through the run's own Fast DDS discovery server")
    ap.add_argument('--domain-id', type=int, default=1 + os.getpid() % 101)
    args = ap.parse_args()
    os.environ[EXECUTOR_ENV] = args.executor  # the children inherit it
    print(f'estimators at {args.frequency:g} Hz, publishing at {args.publish_rate:g} Hz, gyro at '
          f'{args.imu_rate:g} Hz, {args.executor} executor, {args.duration:g} s simulated, '
          '--real-time-factor 1'
          f'{", through a discovery server" if args.discovery_server else ""}\n')
    print('| agents | agents/process | speed | missed | CPU/agent | simulator CPU | '
          'RSS/process | RSS/agent | discovery | errors at end (rad, m) |')
    print('|---|---|---|---|---|---|---|---|---|---|')
    with tempfile.TemporaryDirectory(prefix='fleet_scale_') as tmp:
        for n in args.agents:
            for k in args.per_process:
                if k > n:
                    continue
                r = run_one(n, k, args, Path(tmp))
                print(f"| {n} | {k} | {r.get('speed', float('nan')):.2f}x | "
                      f"{r.get('missed', float('nan')):.1f} % | {r['cpu_agent_pct']:.0f} % | "
                      f"{r['cpu_sim_pct']:.0f} % | {r['rss_process_mb']:.0f} MB | "
                      f"{r['rss_agent_mb']:.0f} MB | {r.get('discovery_s', float('nan')):.1f} s"
                      f" | {r.get('att_err', float('nan')):.1e}, "
                      f"{r.get('pos_err', float('nan')):.1e} |"
                      + ('' if r['ok'] == 'True' else ' (run failed)'), flush=True)


if __name__ == '__main__':
    main()
