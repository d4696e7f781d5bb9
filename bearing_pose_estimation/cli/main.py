"""``bearing-pose``: check, simulate and generate scenarios, compare estimators, run Monte Carlo
and noise studies, and run scenarios over DDS. No file is overwritten without ``--force``.

Exit codes: 0 success; 1 invalid scenario, failed check or refused overwrite; 2 bad command line;
3 a run over DDS finished, but a robot's process ended during it (summary.json: ``deaths``).
"""
from __future__ import annotations

import argparse
import dataclasses
import faulthandler
import os
import re
import shutil
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from .. import __version__, estimators
from ..estimators.base import format_gains
from ..plan.processes import BAG_DIR, DISCOVERY_SERVER, MARKERS, LaunchError
from ..scenario import Scenario, ScenarioError, check_scenario, load_scenario, parse_scenario

if TYPE_CHECKING:
    from .launch import RunResult


def _load_checked(path: str, mode: str | None = None) -> Scenario:
    """Load and check; print warnings; raise ScenarioError listing every error. ``mode``: the
    formation controller's (None: as written)."""
    scenario = load_scenario(path)
    report = check_scenario(scenario)
    for w in report.warnings:
        print(f'{path}: {w}', file=sys.stderr)
    if not report.ok:
        # main() prints the `error:` prefix once.
        raise ScenarioError('\n'.join(f'{path}: {str(e).removeprefix("error: ")}'
                                      for e in report.errors))
    if mode is None or scenario.formation is None:
        return scenario
    print(f'formation control: {mode} mode', file=sys.stderr)
    return dataclasses.replace(scenario, formation=dataclasses.replace(scenario.formation,
                                                                       mode=mode), index={})


def _out_dir(arg: str | Path, outputs: list[str], force: bool) -> Path:
    """Create the output directory; unless ``force``, refuse (ScenarioError) if it already holds
    any of ``outputs`` (relative paths)."""
    out = Path(arg)
    if out.exists() and not out.is_dir():
        raise ScenarioError(f'{out}: --out must be a directory, and this is a file. '
                            'Fix: choose another --out (outputs never overwrite other files)')
    existing = [out / name for name in outputs if (out / name).exists()] if not force else []
    if existing:
        more = f' (and {len(existing) - 1} more of its outputs)' if len(existing) > 1 else ''
        raise ScenarioError(f'{existing[0]}: exists{more}; refusing to overwrite it. '
                            'Fix: pass --force to overwrite, or choose another --out')
    out.mkdir(parents=True, exist_ok=True)
    return out


PLOT_FILES = ['fig2_attitude_error.png', 'fig3_position_error.png']
DIED = 3   # exit code: a run over DDS finished without one of its robots for a while


def _done(text: str, wall: float, files: list[Path]) -> int:
    print(text)
    print(f'wall time {wall:.2f} s; wrote ' + ', '.join(str(f) for f in files))
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    report = check_scenario(scenario)
    print(f'{args.scenario}: {scenario.name}: {len(scenario.agents)} agents '
          f'({len(scenario.followers)} followers), '
          f'{sum(len(a.neighbours) for a in scenario.agents)} sensing edges')
    if text := report.format():
        print(text)
    print(f'{len(report.errors)} error(s), {len(report.warnings)} warning(s)')
    return 0 if report.ok else 1


def cmd_simulate(args: argparse.Namespace) -> int:
    from ..sim.batch import BatchSimulator
    from ..studies.plots import CASCADE_PLOT, ROLES_CSV, ROLES_PLOT, TRAJECTORY_PLOT, \
        plot_cascade, plot_trajectories, write_plots, write_role_outputs
    from ..studies.summary import format_summary, summarize, write_metrics_csv, write_summary_json

    scenario = _load_checked(args.scenario, args.formation_mode)
    if args.gains:
        from ..studies.compare import parse_gain_overrides
        try:
            given = parse_gain_overrides([f'{scenario.method}:{g}' for g in args.gains])
        except ValueError as exc:
            print(f'bearing-pose simulate: error: {exc}'.replace(f'{scenario.method}:', ''),
                  file=sys.stderr)
            return 2
        scenario = scenario.with_method(scenario.method, **given.get(scenario.method, {}))
        print(f'gains: {format_gains(scenario.gains)}', file=sys.stderr)
    # Moving fleets also get their trajectories drawn (the recording holds them).
    plots = [] if args.no_plots else (PLOT_FILES + ([TRAJECTORY_PLOT] if scenario.moves else [])
                                      + [CASCADE_PLOT])
    groups = scenario.estimator().agent_groups(scenario.fleet())
    roles = ([ROLES_CSV] + ([] if args.no_plots else [ROLES_PLOT])) if groups else []
    out = _out_dir(args.out or f'results/{scenario.name}', ['metrics.csv', 'summary.json']
                   + plots + roles, args.force)
    duration = args.duration if args.duration is not None else scenario.duration
    sim = BatchSimulator(scenario, step=args.step)

    def progress(t: float, att: np.ndarray, pos: np.ndarray) -> None:
        if not args.quiet:
            print(f'  t = {t:7.1f} / {duration:g} s   mean attitude error {att.mean():.2e} rad   '
                  f'mean position error {pos.mean():.2e} m', file=sys.stderr, flush=True)

    print(f'simulating {scenario.name}: {len(scenario.agents)} agents, {duration:g} s at '
          f'h = {sim.h:g} s', file=sys.stderr)
    wall = time.perf_counter()
    rec = sim.run(duration, record_every=args.record_every, progress=progress,
                  progress_every=max(duration / 10.0, sim.h))
    wall = time.perf_counter() - wall
    summary = summarize(rec, scenario=scenario.name, source=scenario.source, mode='batch',
                        step_s=sim.h, wall_time_s=round(wall, 3))
    files = [out / 'metrics.csv', out / 'summary.json']
    write_metrics_csv(rec, files[0])
    write_summary_json(summary, files[1])
    if not args.no_plots:
        files += write_plots(rec, out)
    if TRAJECTORY_PLOT in plots and rec.trajectories is not None:
        files.append(plot_trajectories(rec, out / TRAJECTORY_PLOT,
                                       title=f'{scenario.name}: true and estimated trajectories'))
    if CASCADE_PLOT in plots:
        cascade = plot_cascade(rec, out / CASCADE_PLOT, title=f'{scenario.name}: the cascade')
        files += [cascade] if cascade is not None else []
    files += write_role_outputs(rec, groups, out, title=f'{scenario.name}: errors by role',
                                plot=not args.no_plots)
    return _done(format_summary(summary), wall, files)


def _method_scenarios(args: argparse.Namespace
                      ) -> tuple[Scenario, dict[str, tuple[dict, Scenario]]]:
    """The checked scenario, and per method the derived file content and scenario (``--gains``
    applied); prints each method's own new check warnings (e.g. Tran et al.'s K_i)."""
    from ..scenario import read_scenario_data
    from ..studies.compare import method_scenarios

    mode = getattr(args, 'formation_mode', None)
    scenario = _load_checked(args.scenario, mode)
    data = read_scenario_data(args.scenario)
    if mode is not None and isinstance(data.get('formation_control'), dict):
        data['formation_control']['mode'] = mode
    derived = method_scenarios(data, scenario, args.methods, args.gain_overrides)
    shown = {str(w) for w in check_scenario(scenario).warnings}
    for method, (_, method_scenario) in list(derived.items()):
        report = check_scenario(method_scenario)
        if report.errors:   # its assumptions fail on this scenario (De Carli: yaw-only frames)
            why = f'its check fails: {report.errors[0]}' + (
                f' (and {len(report.errors) - 1} more)' if len(report.errors) > 1 else '')
            if not getattr(args, 'methods_chosen', False):
                raise ScenarioError(f'{method} cannot run on {args.scenario}: {why}')
            print(f'{args.scenario}: not running {method}: {why}', file=sys.stderr)
            del derived[method]
            args.methods.remove(method)
            continue
        for w in report.warnings:
            if str(w) not in shown:
                shown.add(str(w))
                print(f'{args.scenario} ({method}): {w}', file=sys.stderr)
    return scenario, derived


def cmd_compare(args: argparse.Namespace) -> int:
    from ..studies import compare
    from ..studies.plots import write_compare_plot
    from ..studies.summary import read_metrics_csv

    scenario, derived = _method_scenarios(args)
    outputs = [f for f in compare.OUTPUT_FILES if not (args.no_plots and f.endswith('.png'))]
    if args.distributed:
        _refuse_paper_mode_over_dds(scenario)
        outputs += [f'{m}/{f}' for m in args.methods
                    for f in ('scenario.yaml', 'metrics.csv', 'summary.json', 'fleet.launch.xml')]
    out = _out_dir(args.out or f'results/{scenario.name}_compare', outputs, args.force)
    duration = args.duration if args.duration is not None else scenario.duration
    print(f'comparing {", ".join(args.methods)} on {scenario.name}: {len(scenario.agents)} '
          f'agents, {duration:g} s, batch simulator{", then over DDS" if args.distributed else ""}',
          file=sys.stderr)
    wall = time.perf_counter()
    runs = compare.run_batch({m: s for m, (_, s) in derived.items()}, duration,
                             args.record_every)
    died = False
    for method, (data, method_scenario) in derived.items() if args.distributed else ():
        method_dir = out / method
        method_dir.mkdir(exist_ok=True)
        scenario_file = method_dir / 'scenario.yaml'
        scenario_file.write_text(f'# {method} on {args.scenario}, derived by bearing-pose compare '
                                 '(method and gains changed)\n'
                                 + yaml.safe_dump(data, sort_keys=False, width=100))
        result = _run_over_dds(method_scenario, scenario_file, method_dir, duration, args)
        if not result.ok:
            print(f'{method} over DDS failed after {result.wall_s:.1f} s; logs in '
                  f'{method_dir / "logs"}', file=sys.stderr)
            return 1
        died = died or bool(result.deaths)
        runs.append(compare.Run(method, 'dds', method_scenario,
                                read_metrics_csv(method_dir / 'metrics.csv')))
    wall = time.perf_counter() - wall
    text = compare.table(compare.rows(runs))
    compare.write_csv(runs, out / 'compare.csv')
    (out / 'compare.md').write_text(f'# {scenario.name}: {", ".join(args.methods)}\n\n' + text)
    files = [out / 'compare.csv', out / 'compare.md']
    if not args.no_plots:
        files.append(write_compare_plot({r.label: r.rec for r in runs}, out / 'compare_errors.png',
                                        frozenset(r.label for r in runs if r.mode == 'dds')))
    return _done(text, wall, files) or (DIED if died else 0)


def cmd_noise_study(args: argparse.Namespace) -> int:
    from ..studies import noise_study as ns

    scenario, derived = _method_scenarios(args)
    try:
        ns.check_frequencies(args.frequencies_hz, scenario)
    except ValueError as exc:
        raise ScenarioError(f'{args.scenario}: {exc}') from exc
    outputs = [f for f in ns.OUTPUT_FILES if not (args.no_plots and f.endswith('.png'))]
    out = _out_dir(args.out or f'results/{scenario.name}_noise_study', outputs, args.force)
    duration = args.duration if args.duration is not None else scenario.duration
    x, y, z = (float(c) for c in np.asarray(args.axis) / np.linalg.norm(args.axis))
    axis = (x, y, z)
    n = len(args.methods) * len(args.amplitudes_deg) * len(args.frequencies_hz)
    jobs = min(args.jobs or os.cpu_count() or 1, n)
    print(f'noise study on {scenario.name}: bearings rot_X(θ0 sin 2πft) b, X = {list(axis)}, θ0 '
          f'in {args.amplitudes_deg} deg, f in {args.frequencies_hz} Hz; {", ".join(args.methods)}'
          f'; {n} runs of {duration:g} s on {jobs} process(es)', file=sys.stderr)

    def progress(done: int, total: int, r: ns.CaseResult) -> None:
        c, v = r.case, r.values
        print(f'  {done}/{total}: {c.method}, θ0 = {c.amplitude_deg:g} deg, f = {c.frequency_hz:g}'
              f' Hz: worst follower within {np.degrees(v["steady_attitude_error_max_rad"]):.3g} '
              f'deg and {v["steady_position_error_max_m"]:.3g} m', file=sys.stderr, flush=True)

    wall = time.perf_counter()
    results = ns.run_study({m: s for m, (_, s) in derived.items()}, args.amplitudes_deg,
                           args.frequencies_hz, duration, jobs, progress, axis)
    wall = time.perf_counter() - wall
    text = ns.table(results)
    ns.write_csv(results, out / 'noise_study.csv')
    (out / 'noise_study.md').write_text(
        f'# {scenario.name}: bearings rot_X(θ0 sin 2πft) b, X = {list(axis)}, {duration:g} s '
        f'runs; bounds and means over the last {ns.STEADY_FRACTION:.0%}\n\n' + text)
    files = [out / 'noise_study.csv', out / 'noise_study.md']
    if not args.no_plots:
        files.append(ns.write_plot(results, out / 'noise_study.png'))
    return _done(text, wall, files)


def cmd_montecarlo(args: argparse.Namespace) -> int:
    from ..studies import montecarlo as mc
    from ..studies.summary import STEADY_FRACTION, write_summary_json

    scenario = _load_checked(args.scenario)
    out = _out_dir(args.out or f'results/{scenario.name}_montecarlo', list(mc.OUTPUT_FILES),
                   args.force)
    duration = args.duration if args.duration is not None else scenario.duration
    seed = args.seed if args.seed is not None else scenario.noise.seed
    jobs = min(args.jobs or os.cpu_count() or 1, args.runs)
    seeded = ('noise and random initial estimates' if scenario.random_init is not None
              else 'noise; initial estimates as given')
    print(f'monte carlo {scenario.name}: {args.runs} runs of {duration:g} s, seeds {seed}..'
          f'{seed + args.runs - 1} ({seeded}), {jobs} process(es)', file=sys.stderr)

    def progress(done: int, total: int, r: mc.RunResult) -> None:
        v = r.values
        print(f'  {done}/{total} runs done (run {r.run}, seed {r.seed}): steady mean attitude '
              f'error {v["steady_attitude_error_mean_rad"]:.2e} rad, position '
              f'{v["steady_position_error_mean_m"]:.2e} m', file=sys.stderr, flush=True)

    wall = time.perf_counter()
    results = mc.run_montecarlo(args.scenario, args.runs, seed, duration, jobs, progress)
    wall = time.perf_counter() - wall
    summary = mc.summarize(results, scenario=scenario.name, source=scenario.source,
                           first_seed=seed, duration_s=duration, step_s=scenario.step,
                           steady_window_s=STEADY_FRACTION * duration, jobs=jobs,
                           wall_time_s=round(wall, 3))
    files = [out / name for name in mc.OUTPUT_FILES]
    mc.write_runs_csv(results, files[0])
    write_summary_json(summary, files[1])
    mc.write_plot(results, files[2])
    return _done(mc.format_table(summary), wall, files)


def _run_over_dds(scenario: Scenario, scenario_file: Path, out: Path, duration: float,
                  args: argparse.Namespace) -> RunResult:
    """One distributed run (``run``, ``compare --distributed``): a process per agent, the
    simulator and the monitor, on a private (or --domain-id) domain, loopback only."""
    from ..plan import dds, processes
    from . import launch

    domain_id = args.domain_id if args.domain_id is not None else dds.private_domain_id()
    how = 'from --domain-id' if args.domain_id is not None else 'private to this run'
    if args.domain_id is None and os.environ.get('ROS_DOMAIN_ID'):
        how += f"; the caller's ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']} is not used"
    rviz = getattr(args, 'rviz', False)
    server = args.discovery_server or args.discovery_server_port is not None
    per_process = processes.fit_agents_per_process(len(scenario.agents), args.agents_per_process,
                                                   rviz, server)
    if args.agents_per_process is None and per_process > 1:
        print(f'note: {len(scenario.agents)} agents run {per_process} per process, so that '
              f'the run needs at most {processes.MAX_PROCESSES} processes (DDS discovery on '
              'localhost connects no more; --agents-per-process sets it)', file=sys.stderr)
    cfg = processes.RunConfig(
        scenario_file=scenario_file.resolve(), out_dir=out.resolve(), duration=duration,
        domain_id=domain_id, real_time_factor=args.real_time_factor, plots=not args.no_plots,
        timeout=args.timeout, agents_per_process=per_process,
        record=getattr(args, 'record', False), rviz=rviz, fleet_namespace=args.fleet_namespace,
        discovery_server=(args.discovery_server_port or 0) if server else None)
    pace = (f'at most {cfg.real_time_factor:g}x real time' if cfg.real_time_factor > 0
            else 'as fast as the estimators keep up')
    print(f'running {scenario.name} ({scenario.method}) over DDS: {len(scenario.agents)} '
          f'estimators, monitor, simulator; {cfg.duration:g} s simulated, {pace}; '
          f'ROS_DOMAIN_ID={domain_id} ({how}), localhost only', file=sys.stderr)
    try:
        with launch.sigterm_as_interrupt():
            return launch.launch_run(scenario, cfg)
    except KeyboardInterrupt:
        print(f'interrupted: all processes stopped; partial outputs (if any) and logs in {out}',
              file=sys.stderr)
        raise


def _refuse_paper_mode_over_dds(scenario: Scenario) -> None:
    """A simulator node owns the truth and cannot see the estimates: no closed loop."""
    if scenario.formation is not None and scenario.formation.mode == 'paper':
        raise ScenarioError(f'{scenario.source}: formation_control.mode is paper (the '
                            'controller uses the estimated yaws), which a simulator node '
                            'cannot run. Fix: pass --formation-mode exogenous (the true yaws)')
    if problem := scenario.not_distributable():
        raise ScenarioError(f'{scenario.source}: {problem}')


def cmd_run(args: argparse.Namespace) -> int:
    from ..scenario import read_scenario_data

    scenario = _load_checked(args.scenario, args.formation_mode)
    _refuse_paper_mode_over_dds(scenario)
    derived = args.formation_mode is not None and scenario.formation is not None
    processes = ([a.name for a in scenario.agents] + ['simulator', 'monitor']
                 + ([MARKERS] if args.rviz else [])
                 + ([DISCOVERY_SERVER] if args.discovery_server_port or args.discovery_server
                    else []))
    plots = [] if args.no_plots else PLOT_FILES + (['trajectories.png'] if scenario.moves
                                                   else [])
    outputs = (['metrics.csv', 'summary.json', 'fleet.launch.xml'] + plots
               + (['scenario.yaml'] if derived else []) + ([BAG_DIR] if args.record else [])
               + [f'params/{p}.yaml' for p in processes] + [f'logs/{p}.log' for p in processes])
    out = _out_dir(args.out or f'results/{scenario.name}_dds', outputs, args.force)
    if args.record and (out / BAG_DIR).exists():   # --force: a bag is replaced whole
        shutil.rmtree(out / BAG_DIR)
    duration = args.duration if args.duration is not None else scenario.duration
    scenario_file = Path(args.scenario)
    if derived:   # the nodes read the file: write the one with the mode changed
        data = read_scenario_data(args.scenario)
        data['formation_control']['mode'] = args.formation_mode
        scenario_file = out / 'scenario.yaml'
        scenario_file.write_text(f'# {args.scenario} with formation_control.mode: '
                                 f'{args.formation_mode} (bearing-pose run --formation-mode)\n'
                                 + yaml.safe_dump(data, sort_keys=False, width=100))
    result = _run_over_dds(scenario, scenario_file, out, duration, args)
    logs = out.resolve() / 'logs'
    if not result.ok:
        print(f'run failed after {result.wall_s:.1f} s; logs in {logs}', file=sys.stderr)
        return 1
    # The monitor's forwarded output has already shown the summary.
    est_cpu = sum(v for k, v in result.cpu_s.items() if k not in ('simulator', 'monitor'))
    if est_cpu:
        per_agent = est_cpu / len(scenario.agents)
        print(f'CPU: {per_agent:.1f} s per agent on average ({100 * per_agent / result.wall_s:.0f}'
              f' % of a core), simulator {result.cpu_s.get("simulator", float("nan")):.1f} s, '
              f'over {result.wall_s:.1f} s wall for {duration:g} s simulated')
    print(f'wall time {result.wall_s:.1f} s; wrote ' + ', '.join(str(f) for f in result.files)
          + f'; parameter files in {out.resolve() / "params"}; logs in {logs}')
    return DIED if result.deaths else 0


def cmd_export_tum(args: argparse.Namespace) -> int:
    from ..studies.tum import export_tum

    run_dir = Path(args.dir)
    out = Path(args.out) if args.out else run_dir / 'tum'
    existing = sorted(out.glob('*.tum')) if out.is_dir() else []
    if existing and not args.force:
        raise ScenarioError(f'{out}: already holds {len(existing)} TUM file(s), e.g. '
                            f'{existing[0].name}; refusing to overwrite them. Fix: pass --force, '
                            'or choose another --out')
    files = export_tum(run_dir / BAG_DIR, out)
    print(f'wrote {len(files)} TUM trajectories into {out}; e.g. evo_ape tum {files[1]} {files[0]}')
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
    from ..scenario.generate import generate_scenario

    out = Path(args.out)
    if out.exists() and not args.force:
        raise ScenarioError(f'{out}: exists; refusing to overwrite it. '
                            'Fix: choose another --out, or pass --force')
    data = generate_scenario(args.agents, seed=args.seed, max_angle_deg=args.max_angle_deg,
                             speed=args.speed, turn_rate=args.turn_rate)
    scenario = parse_scenario(data, source=str(out))
    report = check_scenario(scenario)
    assert report.ok, report.format()  # the generator only makes valid scenarios
    out.parent.mkdir(parents=True, exist_ok=True)
    moving = f' --speed {args.speed:g} --turn-rate {args.turn_rate:g}' if args.speed > 0 else ''
    header = (f'# Generated by: bearing-pose generate --agents {args.agents} --seed {args.seed}'
              f' --max-angle-deg {args.max_angle_deg:g}{moving}\n')
    out.write_text(header + yaml.safe_dump(data, sort_keys=False, default_flow_style=None,
                                           width=100))
    print(f'wrote {out}: {args.agents} agents, {sum(len(a.neighbours) for a in scenario.agents)}'
          f' sensing edges, {len(report.warnings)} warning(s)')
    return 0


def _add_method_options(p: argparse.ArgumentParser) -> None:
    """The scenario and the methods to run with their gains (``compare``, ``noise-study``)."""
    p.add_argument('scenario', help='scenario YAML file')
    p.add_argument('--methods', nargs='+', choices=estimators.methods(), metavar='METHOD',
                   help='methods to run (default: every one the scenario can run, its own first; '
                   f'registered: {", ".join(estimators.methods())})')
    p.add_argument('--gains', action='append', default=[], metavar='METHOD:GAIN=V[,GAIN=V]',
                   help='override gains of one method, e.g. tran_anderson_ahn:k_omega=3,k_c=2 '
                   '(repeatable; k_ij stays per edge)')


def _add_formation_option(p: argparse.ArgumentParser) -> None:
    p.add_argument('--formation-mode', choices=['paper', 'exogenous'],
                   help='formation controller on the estimated (paper) or the true yaws '
                   "(exogenous) (default: the scenario's)")


def _add_output_options(p: argparse.ArgumentParser, suffix: str, per_run: bool = False,
                        jobs: bool = False, plots: bool = True) -> None:
    """The options every study shares (``--out`` defaults to results/<name><suffix>)."""
    p.add_argument('--duration', type=float, metavar='S', help=f'simulated time '
                   f'{"per run " if per_run else ""}[s] (default: the scenario\'s)')
    p.add_argument('--out', metavar='DIR',
                   help=f'output directory (default: results/<scenario name>{suffix})')
    if jobs:
        p.add_argument('--jobs', type=int, metavar='J', help='worker processes (default: cores)')
    if plots:
        p.add_argument('--no-plots', action='store_true', help='skip the PNG plots')
    p.add_argument('--force', action='store_true', help='overwrite outputs already in DIR')


def _add_dds_options(p: argparse.ArgumentParser) -> None:
    """The options of a distributed run (``run``, ``compare --distributed``)."""
    p.add_argument('--domain-id', type=int, metavar='N',
                   help='ROS_DOMAIN_ID, 0..232 (default: 1 + pid %% 101, private to this run)')
    p.add_argument('--real-time-factor', type=float, default=0.0, metavar='F',
                   help='cap on simulated seconds per wall second (default: 0, no cap)')
    p.add_argument('--agents-per-process', type=int, metavar='K',
                   help='agents per `estimators` process, one node each (default: 1, or the '
                   'fewest that keep the run within the 32 processes DDS discovery connects; '
                   'with --discovery-server: 1)')
    p.add_argument('--discovery-server', action='store_true',
                   help='start a Fast DDS discovery server on 127.0.0.1 and point every process '
                   'at it (ROS_DISCOVERY_SERVER): discovery through it, no 32-process limit; '
                   'for large fleets (docs/discovery_server.md)')
    p.add_argument('--discovery-server-port', type=int, metavar='PORT',
                   help="the server's UDP port (implies --discovery-server; default: a free one)")
    p.add_argument('--fleet-namespace', default='', metavar='NS',
                   help='run every node and topic under /NS/, so that fleets share a domain')
    p.add_argument('--timeout', type=float, metavar='S', help='wall-time safety net [s] '
                   '(default: 10 x duration / F + 120 for F < 1, else 10 x duration + 120)')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='bearing-pose',
        description='Distributed bearing-based pose estimation (Boughellaba & Tayebi; Tran, '
                    'Anderson & Ahn; De Carli et al.; Presenza et al.): check, simulate and '
                    'generate scenarios, compare the estimators, run Monte Carlo and noise '
                    'studies, and run scenarios over DDS. No file is overwritten without --force.')
    parser.add_argument('--version', action='version', version=f'%(prog)s {__version__}')
    sub = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')

    p = sub.add_parser('check', help="check a scenario against the paper's Assumption 2",
                       description="Check a scenario file against its method's assumptions (a "
                       'moving one also along its motion). Exit 0 when valid, 1 otherwise.')
    p.add_argument('scenario', help='scenario YAML file')
    p.set_defaults(func=cmd_check)

    p = sub.add_parser('simulate', help='run the batch simulator; write metrics, summary, plots',
                       description='Run all agents in one process (no ROS). Writes '
                       'DIR/metrics.csv, DIR/summary.json and the plots.')
    p.add_argument('scenario', help='scenario YAML file')
    _add_output_options(p, '')
    p.add_argument('--step', type=float, help='step [s] (default: 1 / scenario frequency)')
    p.add_argument('--gains', action='append', default=[], metavar='GAIN=V[,GAIN=V]',
                   help="override gains of the scenario's method, e.g. k_v=0 (odometry "
                   'feed-forward off) or k_R=2,k_p=0.5 (repeatable)')
    p.add_argument('--record-every', type=float, default=0.1,
                   help='metrics row interval [s], at most 0.5 (default: 0.1)')
    p.add_argument('--quiet', action='store_true', help='no progress lines')
    _add_formation_option(p)
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser('compare', help='run several estimators on one scenario; table and plot',
                       description='Run each method on the same truth, initial estimates and '
                       'noise, in the batch simulator (and over DDS: --distributed). Writes '
                       'DIR/compare.csv, DIR/compare.md and DIR/compare_errors.png.')
    _add_method_options(p)
    _add_output_options(p, '_compare')
    p.add_argument('--record-every', type=float, default=0.1,
                   help='row interval of compare.csv [s], at most 0.5 (default: 0.1)')
    _add_formation_option(p)
    p.add_argument('--distributed', action='store_true', help='also run each method over DDS')
    _add_dds_options(p)
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser('noise-study', help="Tran et al.'s bearing perturbation, per method; "
                       'error bounds', description='Run each method with bearings rot_X(θ0 sin '
                       '2πft) b (Tran, Anderson & Ahn 2020, Section 5.1) for every θ0 and f. '
                       'Writes DIR/noise_study.csv, DIR/noise_study.md and DIR/noise_study.png.')
    _add_method_options(p)
    p.add_argument('--amplitudes-deg', nargs='+', type=float, default=[2.0, 5.0, 10.0],
                   metavar='θ0', help='perturbation amplitudes [deg] (default: 2 5 10)')
    p.add_argument('--frequencies-hz', nargs='+', type=float, default=[1.0, 5.0, 10.0, 25.0],
                   metavar='F', help='perturbation frequencies [Hz] (default: 1 5 10 25)')
    p.add_argument('--axis', nargs=3, type=float, default=[1.0, 0.0, 0.0], metavar=('X', 'Y', 'Z'),
                   help='body axis X of the perturbation rotation (default: 1 0 0)')
    _add_output_options(p, '_noise_study', per_run=True, jobs=True)
    p.set_defaults(func=cmd_noise_study)

    p = sub.add_parser('montecarlo', help='many batch runs with different seeds; statistics',
                       description='Run i uses seed S + i (noise, random initial estimates). '
                       'Writes DIR/runs.csv, DIR/summary.json and DIR/montecarlo.png.')
    p.add_argument('scenario', help='scenario YAML file')
    p.add_argument('--runs', type=int, required=True, metavar='N', help='number of runs (>= 1)')
    p.add_argument('--seed', type=int, metavar='S',
                   help="first seed (default: the scenario's noise.seed)")
    _add_output_options(p, '_montecarlo', per_run=True, jobs=True, plots=False)
    p.set_defaults(func=cmd_montecarlo)

    p = sub.add_parser('run', help='run every agent as its own ROS 2 process over DDS',
                       description='The estimators, monitor and simulator over DDS on localhost. '
                       'Writes DIR/metrics.csv, DIR/summary.json, plots, DIR/params/, DIR/logs/.')
    p.add_argument('scenario', help='scenario YAML file')
    _add_output_options(p, '_dds')
    _add_dds_options(p)
    _add_formation_option(p)
    p.add_argument('--rviz', action='store_true', help='also publish '
                   '/visualization_marker_array (poses, sensing edges, bearings) for RViz')
    p.add_argument('--record', action='store_true', help='also record every topic into '
                   f'DIR/{BAG_DIR}, a rosbag2 (MCAP), for `bearing-pose export-tum`')
    p.set_defaults(func=cmd_run)

    p = sub.add_parser('export-tum', help='TUM trajectories (for evo) from a recorded run',
                       description='Writes AGENT_estimate.tum and AGENT_truth.tum per agent: '
                       '`evo_ape tum DIR/tum/AGENT_truth.tum DIR/tum/AGENT_estimate.tum`.')
    p.add_argument('dir', help='output directory of `bearing-pose run --record`')
    p.add_argument('--out', metavar='OUT', help='where to write the files (default: DIR/tum)')
    p.add_argument('--force', action='store_true', help='overwrite TUM files in OUT')
    p.set_defaults(func=cmd_export_tum)

    p = sub.add_parser('generate', help='write a random valid scenario',
                       description='A random scenario that satisfies Assumption 2, reproducible '
                       'from --seed; with --speed, a fleet that drifts without close approaches.')
    p.add_argument('--agents', type=int, required=True, help='number of agents (>= 3)')
    p.add_argument('--seed', type=int, default=0, help='random seed (default: 0)')
    p.add_argument('--out', required=True, help='output YAML file')
    p.add_argument('--max-angle-deg', type=float, default=90.0,
                   help='largest initial attitude error [deg] (default: 90)')
    p.add_argument('--speed', type=float, default=0.0, metavar='V',
                   help='drift speed [m/s] of every agent (default: 0, a static fleet)')
    p.add_argument('--turn-rate', type=float, default=0.5, metavar='W',
                   help='turning rate of a moving fleet [rad/s] (default: 0.5)')
    p.add_argument('--force', action='store_true', help='overwrite --out if it exists')
    p.set_defaults(func=cmd_generate)
    return parser


def main(argv: list[str] | None = None) -> int:
    if argv is None:   # the command itself: `kill -USR1 <pid>` prints its threads' stacks
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == 'generate':
        if args.agents < 3:
            parser.error('--agents must be at least 3 (two leaders and one follower)')
        if not (np.isfinite(args.speed) and args.speed >= 0):
            parser.error('--speed must be a number >= 0 [m/s] (0: a static fleet)')
        if not (np.isfinite(args.turn_rate) and args.turn_rate > 0):
            parser.error('--turn-rate must be a positive number [rad/s]')
    if args.command == 'montecarlo' and args.runs < 1:
        parser.error('--runs must be at least 1')
    if args.command == 'noise-study':
        if any(not (np.isfinite(a) and 0 < a <= 90) for a in args.amplitudes_deg):
            parser.error('--amplitudes-deg must be in (0, 90] degrees')
        if any(not (np.isfinite(f) and f > 0) for f in args.frequencies_hz):
            parser.error('--frequencies-hz must be positive')
        if not (np.all(np.isfinite(args.axis)) and np.linalg.norm(args.axis) > 1e-12):
            parser.error('--axis must be a finite, non-zero vector')
    if getattr(args, 'jobs', None) is not None and args.jobs < 1:   # montecarlo, noise-study
        parser.error('--jobs must be at least 1')
    if args.command in ('compare', 'noise-study'):
        from ..studies.compare import compatible_methods, incompatible, parse_gain_overrides
        try:
            scenario = load_scenario(args.scenario)
        except ScenarioError as exc:
            print(f'error: {exc}', file=sys.stderr)
            return 1
        if args.methods is None:
            args.methods, skipped = compatible_methods(scenario)
            args.methods_chosen = True   # by us: one whose check fails is skipped, not refused
            for method, why in skipped.items():
                print(f'{args.scenario}: not running {method}: {why}', file=sys.stderr)
        for method in args.methods:
            if (reason := incompatible(scenario, method)) is not None:
                parser.error(f'{method} cannot run on {args.scenario}: {reason}')
        try:
            args.gain_overrides = parse_gain_overrides(args.gains)
        except ValueError as exc:
            parser.error(str(exc))
        if stray := sorted(set(args.gain_overrides) - set(args.methods)):
            parser.error(f'--gains sets gains of {stray[0]}, which is not in --methods')
    if getattr(args, 'agents_per_process', None) is not None and args.agents_per_process < 1:
        parser.error('--agents-per-process must be at least 1')
    fleet_ns = getattr(args, 'fleet_namespace', '')
    if fleet_ns and not re.fullmatch(r'[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*',
                                     fleet_ns.strip('/')):
        parser.error(f'--fleet-namespace {fleet_ns!r} is not a ROS namespace: letters, digits '
                     'and underscores, not starting with a digit, segments separated by /')
    port = getattr(args, 'discovery_server_port', None)
    if port is not None and not 1 <= port <= 65535:
        parser.error('--discovery-server-port must be in 1..65535 (leave it out: a free one)')
    if getattr(args, 'domain_id', None) is not None and not 0 <= args.domain_id <= 232:
        parser.error('--domain-id must be in 0..232 (ROS 2 domain ids)')
    rtf = getattr(args, 'real_time_factor', None)
    if rtf is not None and not (np.isfinite(rtf) and rtf >= 0):
        parser.error('--real-time-factor must be a number >= 0 (0: no cap)')
    if getattr(args, 'record_every', None) is not None and args.record_every > 0.5:
        parser.error('--record-every must be at most 0.5 s (metrics rows every 0.5 s of '
                     'simulated time at least)')
    for name in ('duration', 'step', 'record_every', 'timeout'):
        value = getattr(args, name, None)
        if value is not None and not (np.isfinite(value) and value > 0):
            parser.error(f'--{name.replace("_", "-")} must be a positive number')
    try:
        return args.func(args)
    except (ScenarioError, LaunchError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
