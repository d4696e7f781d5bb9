"""A robot restarted over DDS, as on a real fleet: `bearing-pose run` of a scenario, one
estimator's process killed at ``--kill-at`` s of simulated time and started again at
``--restart-at`` s with the command the run printed (its restart script). Prints when the
clock moved on, when the robot published again, and the errors at the end against the clean
run (netsim's, which a fault-free lockstep DDS run equals to 2e-9).

    .venv/bin/python bench/restart_dds.py [--scenario config/paper_8_agents.yaml]
        [--victim agent_4] [--duration 60] [--kill-at 20] [--restart-at 25] [--signal KILL]
        [--domain-id 96] [--harness]

``--harness``: no `bearing-pose run`, which before issue 29 ended the whole run at a death:
the processes in a ProcessGroup, the simulator without lockstep (lockstep froze the clock at
the death) at ``--real-time-factor`` (default 1; on a loaded machine the fleet cannot keep up
and diverges: 0.5), the victim started again with its own command line. It needs only what
main had, so it measures main too (PYTHONPATH=<main checkout>).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rosgraph_msgs.msg import Clock

from bearing_pose_estimation import msg_defs as wire
from bearing_pose_estimation.cli import launch
from bearing_pose_estimation.plan import dds
from bearing_pose_estimation.plan import processes as plan
from bearing_pose_estimation.scenario import load_scenario
from bearing_pose_estimation.sim.netsim import (CATCH_UP_FACTOR, catch_up_time,
                                                 reconvergence_time, run_network)
from bearing_pose_estimation.studies.summary import read_metrics_csv

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test'))
from ros_helpers import Observer, observer  # noqa: E402


class Watch:
    """The run's clock and the victim's estimates, from an observer node."""

    def __init__(self, obs: Observer, victim: str) -> None:
        self.obs, self.victim = obs, victim
        obs.subscribe(Clock, '/clock', wire.CLOCK_QOS)
        obs.subscribe(wire.PoseStamped, f'/{victim}/estimate', wire.ESTIMATE_QOS)
        self.spin_until = obs.spin_until

    @property
    def clock(self) -> float:
        msgs = self.obs.messages['/clock']
        return wire.from_stamp(msgs[-1].clock) if msgs else -1.0

    def newest(self) -> float:
        """The victim's newest estimate time."""
        msgs = self.obs.messages[f'/{self.victim}/estimate']
        return max((wire.from_stamp(m.header.stamp) for m in msgs), default=-1.0)


def pid_of(run_dir: Path, victim: str) -> int:
    """The victim's process: the run's (its environment) with the victim's namespace."""
    want = f'{launch.RUN_MARKER}={run_dir}'.encode()
    for path in Path('/proc').glob('[0-9]*'):
        try:
            env = (path / 'environ').read_bytes().split(b'\0')
            cmd = (path / 'cmdline').read_bytes().split(b'\0')
        except OSError:
            continue
        if want in env and f'__ns:=/{victim}'.encode() in cmd:
            return int(path.name)
    raise RuntimeError(f'no process of {victim} in the run in {run_dir}')


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--scenario', type=Path, default=REPO / 'config' / 'paper_8_agents.yaml')
    ap.add_argument('--victim', default='agent_4')
    ap.add_argument('--duration', type=float, default=60.0)
    ap.add_argument('--kill-at', type=float, default=20.0)
    ap.add_argument('--restart-at', type=float, default=25.0)
    ap.add_argument('--signal', default='KILL', choices=['KILL', 'INT'])
    ap.add_argument('--domain-id', type=int, default=96)
    ap.add_argument('--harness', action='store_true')
    ap.add_argument('--real-time-factor', type=float, default=1.0,
                    help='--harness: the simulator\'s pace (without lockstep, a fleet that cannot '
                    'keep up with it diverges)')
    ap.add_argument('--out', type=Path)
    args = ap.parse_args()
    out = (args.out or Path(tempfile.mkdtemp(prefix='restart_dds_'))).resolve()
    os.environ['ROS_DOMAIN_ID'] = str(args.domain_id)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('ROS_LOG_DIR', str(out / 'ros_bench'))
    sig = signal.Signals[f'SIG{args.signal}']
    shm = dds.shm_files()
    wall0 = time.monotonic()
    marks: dict[str, float] = {}
    try:
        with observer('restart_bench') as obs:
            watch = Watch(obs, args.victim)
            code = (harness if args.harness else cli)(args, out, watch, sig, marks)
    finally:
        left = dds.clean_shm(shm)
    print(f'exit code {code}; wall {time.monotonic() - wall0:.1f} s; output in {out}')
    print(f'killed ({args.signal}) at t = {marks["killed_t"]:.2f} s; restarted at t = '
          f'{marks["restart_t"]:.2f} s, {marks["restart_wall"] - marks["killed_wall"]:.1f} s '
          'of wall time after the kill')
    if 'back_t' in marks:
        print(f'{args.victim} published again at t = {marks["back_t"]:.2f} s '
              f'({marks["back_t"] - marks["restart_t"]:.2f} s of simulated time and '
              f'{marks["back_wall"] - marks["restart_wall"]:.2f} s of wall time after its '
              'restart)')
    else:
        print(f'{args.victim} never published again')
    metrics = read_metrics_csv(out / 'metrics.csv')
    clean = run_network(load_scenario(args.scenario), args.duration, record_every=0.1)
    k = int(np.argmin(abs(clean.t - metrics.t[-1])))
    att, pos = metrics.mean_errors()
    c_att, c_pos = clean.mean_errors()
    print(f'last record t = {metrics.t[-1]:.1f} s: mean attitude error {att[-1]:.3e} rad '
          f'({att[-1] / c_att[k]:.3g} x clean {c_att[k]:.3e}), mean position error '
          f'{pos[-1]:.3e} m ({pos[-1] / c_pos[k]:.3g} x clean {c_pos[k]:.3e})')
    per = ', '.join(f'{n} {metrics.att_err[-1, i] / clean.att_err[k, i]:.3g}/'
                    f'{metrics.pos_err[-1, i] / clean.pos_err[k, i]:.3g}'
                    for i, n in enumerate(metrics.followers))
    print(f'per follower, attitude/position error ratio to clean: {per}')
    # The two re-convergence times of the fault matrix, on the records both runs have.
    rows = [int(np.argmin(abs(clean.t - t))) for t in metrics.t]
    ref = dataclasses.replace(clean, t=clean.t[rows], att_err=clean.att_err[rows],
                              pos_err=clean.pos_err[rows])
    back, caught = (reconvergence_time(metrics, ref, marks['restart_t']),
                    catch_up_time(metrics, ref, marks['restart_t']))
    print(f're-converged (back at the clean run\'s error at the restart) '
          f'{"never" if back is None else f"{back:.1f} s"} after the restart; caught up (within '
          f'{CATCH_UP_FACTOR:g} x the clean run at the same instant) '
          f'{"never" if caught is None else f"{caught:.1f} s"} after it')
    summary = json.loads((out / 'summary.json').read_text())
    print(f'summary.json: complete {summary.get("complete")}, deaths {summary.get("deaths")}')
    if left:
        print(f'left in /dev/shm: {left}')


def wait_back(watch: Watch, marks: dict[str, float], ended) -> None:
    """Until the run ends, noting when the victim published an estimate of a time after its
    restart."""
    after = marks['restart_t']
    if watch.spin_until(lambda: watch.newest() > after or ended(), 3600) and not ended():
        marks.update(back_t=watch.newest(), back_wall=time.monotonic())
    watch.spin_until(ended, 3600)


def cli(args: argparse.Namespace, out: Path, watch: Watch, sig: signal.Signals,
        marks: dict[str, float]) -> int:
    """`bearing-pose run`, the victim killed, then started again with its restart script."""
    exe = Path(sys.executable).parent / 'bearing-pose'
    run = subprocess.Popen([str(exe), 'run', str(args.scenario), '--duration',
                            str(args.duration), '--out', str(out), '--force', '--no-plots',
                            '--domain-id', str(args.domain_id)], start_new_session=True)
    restarted = None
    try:
        assert watch.spin_until(lambda: watch.clock >= args.kill_at, 600), 'clock never got there'
        os.kill(pid_of(out, args.victim), sig)
        marks.update(killed_t=watch.clock, killed_wall=time.monotonic())
        script = out / 'logs' / f'restart_{args.victim}.sh'
        assert watch.spin_until(script.exists, 60), 'no restart script'
        assert watch.spin_until(lambda: watch.clock >= args.restart_at, 600), 'clock froze'
        marks.update(restart_t=watch.clock, restart_wall=time.monotonic())
        restarted = subprocess.Popen(['sh', str(script)], start_new_session=True)
        wait_back(watch, marks, lambda: run.poll() is not None)
        return run.wait()
    finally:
        for proc in (run, restarted):
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
                proc.wait(60)


def harness(args: argparse.Namespace, out: Path, watch: Watch, sig: signal.Signals,
            marks: dict[str, float]) -> int:
    """The processes in a ProcessGroup, the simulator without lockstep."""
    scenario = load_scenario(args.scenario)
    cfg = plan.RunConfig(scenario_file=args.scenario.resolve(), out_dir=out,
                         duration=args.duration, domain_id=args.domain_id, plots=False,
                         real_time_factor=args.real_time_factor)
    cfg.logs_dir.mkdir(parents=True, exist_ok=True)
    params = plan.write_params(scenario, cfg)
    specs = {s.name: s for s in plan.plan_processes(scenario, params, cfg.logs_dir,
                                                    plan.find_executable)}
    sim = specs['simulator']
    specs['simulator'] = plan.ProcessSpec(sim.name, sim.kind, sim.argv + (
        '-p', 'lockstep:=false'), sim.log)
    with launch.ProcessGroup(env=dds.dds_env(args.domain_id, cfg.logs_dir / 'ros')) as group:
        for spec in specs.values():
            group.start(spec)
        assert watch.spin_until(lambda: watch.clock >= args.kill_at, 600), 'clock never got there'
        os.killpg(group.pids[args.victim], sig)
        marks.update(killed_t=watch.clock, killed_wall=time.monotonic())
        assert watch.spin_until(lambda: watch.clock >= args.restart_at, 600), 'clock froze'
        marks.update(restart_t=watch.clock, restart_wall=time.monotonic())
        group.start(specs[args.victim])
        wait_back(watch, marks, lambda: group.returncode('monitor') is not None)
        group.shutdown()
        return group.returncode('monitor') or 0


if __name__ == '__main__':
    main()
