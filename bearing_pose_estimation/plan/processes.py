"""The process plan of a run: which processes ``bearing-pose run`` starts (and
``launch/fleet.launch.py`` and the ``fleet.launch.xml`` a run writes), with which command
lines, namespaces and parameter files, decided before any process starts.

:mod:`cli.launch` starts and supervises what is planned here; the nodes (:mod:`ros`) read the
parameter files it writes. No rclpy, and nothing here starts a process.
"""
from __future__ import annotations

import os
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from ..scenario.model import Scenario

PACKAGE = 'bearing_pose_estimation'
NODE_EXECUTABLES = ('estimator', 'estimators', 'simulator', 'monitor')
# Overrides the executable lookup (a folder holding estimator, simulator, monitor): for tests
# and for trying stand-in or locally modified nodes without reinstalling.
BIN_DIR_ENV = 'BEARING_POSE_BIN_DIR'


class LaunchError(RuntimeError):
    """The run cannot start or did not finish. The message names the cause and the fix."""


# With ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (every run here), Fast DDS (rclpy 7.1.6's
# rmw_fastrtps) finds the other participants of a domain at the ports of participant ids
# 0-31: two processes that both got an id of 32 or more never discover each other (measured:
# the 33rd and 34th processes of a domain never matched, the 32nd and 33rd did at once;
# BENCHMARKS.md, "Discovery"). A run therefore uses at most this many processes, which also
# leaves any number of observers (RViz, ros2 CLI) able to see the whole fleet.
MAX_PROCESSES = 32


def processes_needed(n_agents: int, agents_per_process: int, rviz: bool = False) -> int:
    """The processes of a run: the estimators', the monitor, the simulator (and
    fleet_markers with ``rviz``)."""
    return -(-n_agents // max(1, agents_per_process)) + 2 + int(rviz)


def fit_agents_per_process(n_agents: int, requested: int | None, rviz: bool = False) -> int:
    """``requested`` agents per process, or for None the fewest that keep the run within
    :data:`MAX_PROCESSES` (1 when one process per agent fits).

    Raises:
        LaunchError: ``requested`` needs more processes than discovery on localhost allows.
    """
    fewest = next(k for k in range(1, max(n_agents, 1) + 1)
                  if processes_needed(n_agents, k, rviz) <= MAX_PROCESSES)
    if requested is None:
        return fewest
    if processes_needed(n_agents, requested, rviz) > MAX_PROCESSES:
        raise LaunchError(
            f'{n_agents} agents at {requested} per process need '
            f'{processes_needed(n_agents, requested, rviz)} processes, but DDS discovery on '
            f'localhost connects at most {MAX_PROCESSES} processes of a domain (the others '
            f'would never match). Fix: --agents-per-process {fewest} or more (or leave it out)')
    return requested


# ----------------------------------------------------------------------------- set-up
def find_executable(name: str, bin_dir: Path | None = None) -> Path:
    """Locate a node executable as ``ros2 run`` would: each ``AMENT_PREFIX_PATH`` prefix's
    ``lib/<package>/`` (colcon install), then the running interpreter's ``bin/`` (pip editable
    install into .venv). ``bin_dir`` (or ``$BEARING_POSE_BIN_DIR``) replaces both."""
    bin_dir = bin_dir if bin_dir is not None else _env_path(BIN_DIR_ENV)
    if bin_dir is not None:
        candidates = [Path(bin_dir) / name]
    else:
        prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
        candidates = [Path(p) / 'lib' / PACKAGE / name for p in prefixes]
        candidates.append(Path(sys.executable).parent / name)
    for path in candidates:
        if path.is_file() and os.access(path, os.X_OK):
            return path
    looked = ', '.join(str(p) for p in candidates)
    raise LaunchError(f"cannot find the node executable '{name}' (looked in: {looked}). "
                      'Fix: run scripts/dev.sh setup (installs it into .venv/bin), or '
                      '`colcon build` and `source install/setup.bash`')


def _env_path(var: str) -> Path | None:
    value = os.environ.get(var)
    return Path(value) if value else None


BAG_DIR = 'bag'   # `run --record`: the rosbag2 directory in the output directory
MARKERS = 'fleet_markers'   # `run --rviz`: the process (and node) that draws the fleet


@dataclass(frozen=True)
class RunConfig:
    """Everything ``bearing-pose run`` decides before starting processes. Paths absolute."""

    scenario_file: Path
    out_dir: Path
    duration: float
    domain_id: int
    real_time_factor: float = 0.0  # cap on sim seconds per wall second; 0: none (lockstep)
    plots: bool = True
    agents_per_process: int = 1    # >1: `estimators` processes, each running that many agents
    timeout: float | None = None   # wall seconds; None: see wall_timeout
    record: bool = False           # the monitor records a rosbag2 into bag_dir
    rviz: bool = False             # also run fleet_markers (RViz markers of the fleet)
    fleet_namespace: str = ''      # every topic under /<it>/ (two fleets side by side)

    @property
    def wall_timeout(self) -> float:
        """Safety net only: 10x the expected wall time plus two minutes of start-up."""
        if self.timeout is not None:
            return self.timeout
        slowdown = 1.0 / self.real_time_factor if 0.0 < self.real_time_factor < 1.0 else 1.0
        return 10.0 * self.duration * slowdown + 120.0

    @property
    def params_dir(self) -> Path:
        return self.out_dir / 'params'

    @property
    def logs_dir(self) -> Path:
        return self.out_dir / 'logs'

    @property
    def bag_dir(self) -> Path:
        return self.out_dir / BAG_DIR


def write_params(scenario: Scenario, cfg: RunConfig) -> dict[str, Path]:
    """One standard ROS 2 parameter file per process (``/<ns>/<node>: ros__parameters:``),
    so a real robot can be started with the same file. Returns process name -> file."""
    cfg.params_dir.mkdir(parents=True, exist_ok=True)
    scenario_file = str(cfg.scenario_file)
    ns = _fleet_ns(cfg.fleet_namespace)
    files: dict[str, dict[str, Any]] = {
        agent.name: {f'{ns}/{agent.name}/estimator': {'ros__parameters': {
            'scenario_file': scenario_file, 'agent': agent.name, 'use_sim_time': True}}}
        for agent in scenario.agents
    }
    files['simulator'] = {f'{ns}/simulator': {'ros__parameters': {
        'scenario_file': scenario_file, 'duration': float(cfg.duration),
        'real_time_factor': float(cfg.real_time_factor), 'use_sim_time': False,
        **({'monitor_records': True} if cfg.record else {})}}}
    files['monitor'] = {f'{ns}/monitor': {'ros__parameters': {
        'scenario_file': scenario_file, 'duration': float(cfg.duration),
        'out_dir': str(cfg.out_dir), 'plots': bool(cfg.plots), 'use_sim_time': True,
        **({'bag': str(cfg.bag_dir)} if cfg.record else {})}}}
    if cfg.rviz:
        files[MARKERS] = {f'{ns}/{MARKERS}': {'ros__parameters': {
            'scenario_file': scenario_file, 'use_sim_time': True}}}
    paths = {}
    for name, content in files.items():
        paths[name] = cfg.params_dir / f'{name}.yaml'
        paths[name].write_text(yaml.safe_dump(content, sort_keys=False))
    return paths


@dataclass(frozen=True)
class ProcessSpec:
    """One child: ``name`` is unique in its group and names its log file."""

    name: str
    kind: str                   # 'estimator', 'simulator', 'monitor', ...
    argv: tuple[str, ...]
    log: Path
    forward: bool = False       # also copy its stdout/stderr to ours, live

    @property
    def label(self) -> str:
        return self.name if self.name == self.kind else f'{self.kind} {self.name}'


def _fleet_ns(fleet: str) -> str:
    """``/team_a`` for the fleet namespace ``team_a``; empty for none."""
    return f'/{fleet.strip("/")}' if fleet.strip('/') else ''


def estimator_groups(agents: Sequence[str], agents_per_process: int) -> dict[str, list[str]]:
    """The ``estimators`` processes of :func:`plan_processes` for ``agents_per_process`` > 1:
    name (``estimators_<g>``) -> its consecutive agents."""
    return {f'estimators_{g}': list(agents[start:start + agents_per_process])
            for g, start in enumerate(range(0, len(agents), agents_per_process))}


def plan_processes(scenario: Scenario, params: Mapping[str, Path], logs_dir: Path,
                   exe: Callable[[str], Path], agents_per_process: int = 1,
                   fleet: str = '') -> list[ProcessSpec]:
    """Command lines in start order: estimators, monitor, simulator (the simulator waits for
    every subscriber to match before it starts the clock at t = 0). With
    ``agents_per_process`` > 1, consecutive agents share an ``estimators`` process. With a
    ``fleet`` namespace, every node runs under it and reads its simulator's clock there."""
    specs = []
    agents = [a.name for a in scenario.agents]
    ns = _fleet_ns(fleet)
    clock = ['-r', f'/clock:={ns}/clock'] if ns else []
    if agents_per_process <= 1:
        for agent in agents:
            argv = [str(exe('estimator')), '--ros-args', '-r', f'__ns:={ns}/{agent}',
                    '-r', '__node:=estimator', *clock]
            if agent in scenario.leaders:  # leaders read their known pose from the truth
                argv += ['-r', 'known_pose:=ground_truth']
            argv += ['--params-file', str(params[agent])]
            specs.append(ProcessSpec(agent, 'estimator', tuple(argv), logs_dir / f'{agent}.log'))
    else:
        for name, group in estimator_groups(agents, agents_per_process).items():
            argv = [str(exe('estimators')), '--params-dir', str(params[group[0]].parent)]
            argv += ['--fleet-namespace', fleet.strip('/')] if ns else []
            for agent in group:
                if agent in scenario.leaders:
                    argv += ['--leader', agent]
            argv += group
            specs.append(ProcessSpec(name, 'estimators', tuple(argv), logs_dir / f'{name}.log'))
    for name in ('monitor', MARKERS, 'simulator'):
        if name not in params:   # fleet_markers: only with --rviz
            continue
        argv = [str(exe(name)), '--ros-args', '-r', f'__node:={name}',
                *(['-r', f'__ns:={ns}', *clock] if ns else []),
                '--params-file', str(params[name])]
        specs.append(ProcessSpec(name, name, tuple(argv), logs_dir / f'{name}.log',
                                 forward=name == 'monitor'))
    return specs


LAUNCH_FILE = 'fleet.launch.xml'
# The environment a run sets for its children that a launch file must set too.
_LAUNCH_ENV = ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')


@dataclass(frozen=True)
class LaunchNode:
    """One process of :func:`plan_processes` as a launch file starts it (``launch_ros``'s
    ``Node`` arguments): its executable, node name and namespace (None: the process names
    its own nodes), remappings, parameter files, ``-p`` parameters and other arguments."""

    executable: str
    name: str | None
    namespace: str | None
    remappings: tuple[tuple[str, str], ...]
    parameter_files: tuple[str, ...]
    parameters: tuple[tuple[str, str], ...]
    arguments: tuple[str, ...]


def launch_nodes(specs: list[ProcessSpec]) -> list[LaunchNode]:
    """The processes ``specs`` as launch-file nodes: what their command lines say, read back
    (the one source for ``fleet.launch.xml`` and the installed ``launch/fleet.launch.py``)."""
    nodes = []
    for spec in specs:
        rest = list(spec.argv[1:])
        cut = rest.index('--ros-args') if '--ros-args' in rest else len(rest)
        ros, args = rest[cut + 1:], rest[:cut]
        name = namespace = None
        remaps, files, params = [], [], []
        for flag, value in zip(ros[::2], ros[1::2]):
            if flag == '-r':
                src, dst = value.split(':=', 1)
                if src == '__ns':
                    namespace = dst.lstrip('/')
                elif src == '__node':
                    name = dst
                else:
                    remaps.append((src, dst))
            elif flag == '--params-file':
                files.append(value)
            elif flag == '-p':
                key, val = value.split(':=', 1)
                params.append((key, val))
            else:
                raise ValueError(f'{spec.label}: {flag} has no launch-file form')
        nodes.append(LaunchNode(Path(spec.argv[0]).name, name, namespace, tuple(remaps),
                                tuple(files), tuple(params), tuple(args)))
    return nodes


def launch_xml(specs: list[ProcessSpec], env: Mapping[str, str]) -> str:
    """The processes ``specs`` (as :func:`plan_processes` plans them) as a ROS 2 XML launch
    file: one ``<node>`` each (:func:`launch_nodes`), and the DDS environment of ``env``
    (loopback discovery, the run's domain) set first. ``ros2 launch`` on a Jazzy install then
    starts the same fleet as ``bearing-pose run``."""
    import xml.etree.ElementTree as ET

    root = ET.Element('launch')
    for key in _LAUNCH_ENV:
        if key in env:
            ET.SubElement(root, 'set_env', name=key, value=env[key])
    for n in launch_nodes(specs):
        node = ET.SubElement(root, 'node', pkg=PACKAGE, exec=n.executable, output='screen')
        for attr, value in (('namespace', n.namespace), ('name', n.name),
                            ('args', ' '.join(n.arguments) or None)):
            if value is not None:
                node.set(attr, value)
        for src, dst in n.remappings:
            ET.SubElement(node, 'remap', {'from': src, 'to': dst})
        for path in n.parameter_files:
            ET.SubElement(node, 'param', {'from': path})
        for key, value in n.parameters:
            ET.SubElement(node, 'param', {'name': key, 'value': value})
    ET.indent(root)
    return ('<?xml version="1.0"?>\n<!-- Written by bearing-pose run: the same processes, '
            'namespaces, remappings and parameter files. ros2 launch ' + LAUNCH_FILE
            + ' -->\n' + ET.tostring(root, encoding='unicode') + '\n')
