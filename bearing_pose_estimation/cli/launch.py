"""``bearing-pose run``: start one estimator per agent, the monitor and the simulator as
separate ROS 2 processes, wait for the monitor, and stop everything cleanly.

No rclpy here: this module only writes parameter files and starts and stops processes, so it
is usable (and testable) without a DDS stack. :class:`ProcessGroup` is the reusable part: a
context manager that owns child processes, watches them, and stops them in reverse start order
(SIGINT, then SIGTERM, then SIGKILL as a last resort) so that no process is left behind.
"""
from __future__ import annotations

import contextlib
import glob
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import yaml

from ..scenario.model import Scenario

PACKAGE = 'bearing_pose_estimation'
NODE_EXECUTABLES = ('estimator', 'estimators', 'simulator', 'monitor')
# Overrides the executable lookup (a folder holding estimator, simulator, monitor): for tests
# and for trying stand-in or locally modified nodes without reinstalling.
BIN_DIR_ENV = 'BEARING_POSE_BIN_DIR'
# Fast DDS shared-memory segments; a crashed or SIGKILLed participant leaves them behind.
SHM_GLOB = '/dev/shm/fastrtps_*'
# How a node ends whose DDS teardown hung after its work was done (ros.node_main's watchdog):
# a Fast DDS deadlock in deleting the participant, eProsima/Fast-DDS#6502. Nothing else here
# raises it, so the launcher tells it from a crash; the participant's files stay in /dev/shm
# and the launcher removes them.
TEARDOWN_WATCHDOG_SIGNAL = signal.SIGALRM
TEARDOWN_HUNG = -TEARDOWN_WATCHDOG_SIGNAL
CLEAN_EXITS = (0, TEARDOWN_HUNG)
LOG_TAIL_LINES = 20
TIMEOUT_TAIL_LINES = 8    # of every process's log, after a run that timed out
POLL_S = 0.05


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


def private_domain_id() -> int:
    """A per-run ROS_DOMAIN_ID in 1..101 (0, the default everyone uses, is avoided), so two
    runs on one machine do not see each other."""
    return 1 + os.getpid() % 101


def dds_env(domain_id: int, ros_log_dir: Path,
            base: Mapping[str, str] | None = None) -> dict[str, str]:
    """The children's environment: DDS stays on loopback, on our domain; logs in the run dir."""
    env = dict(os.environ if base is None else base)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=str(domain_id),
               ROS_LOG_DIR=str(ros_log_dir), PYTHONUNBUFFERED='1')
    return env


def shm_files() -> set[str]:
    """Fast DDS shared-memory files now (segments, ports and their ``_el`` lock files)."""
    return set(glob.glob(SHM_GLOB))


def _shm_in_use() -> set[str]:
    """Fast DDS files some live process maps (segments, ports) or holds open (locks)."""
    used: set[str] = set()
    prefix = str(Path(SHM_GLOB).parent / 'fastrtps_')
    for maps in glob.glob('/proc/[0-9]*/maps'):
        with contextlib.suppress(OSError):
            for line in Path(maps).read_text().splitlines():
                at = line.find(prefix)
                if at >= 0:
                    used.add(line[at:].removesuffix(' (deleted)'))
    for fd in glob.glob('/proc/[0-9]*/fd/*'):
        with contextlib.suppress(OSError):
            target = os.readlink(fd)
            if target.startswith(prefix):
                used.add(target)
    return used


def leaked_shm(before: set[str], lockless: bool = False) -> list[str]:
    """Fast DDS files created since ``before`` that no live process uses: what a participant
    killed without a clean shutdown leaves (with ``lockless``, also the port files Fast DDS
    keeps after clean exits, :func:`_lockless_port`). Other processes' live files do not
    count, so this works on a machine where other ROS programs (or test runs) are active."""
    new = shm_files() - before
    if not new:
        return []
    used = _shm_in_use()
    return sorted(f for f in new
                  if f not in used and f.removesuffix('_el') not in used
                  and f + '_el' not in used and (lockless or not _lockless_port(f)))


def _lockless_port(path: str) -> bool:
    """A shared port file without its ``_el`` lock. Fast DDS sometimes keeps one after every
    process exited cleanly: rarely in runs (twice in ~40), but in one run out of two or three
    with 20 to 34 processes of one domain (``bench/discovery_limit.py``, 2026-12-06), and
    ``fastdds shm clean`` does not count it as a zombie. What a killed participant leaves is
    its own segment and lock, which are still reported."""
    name = Path(path).name
    return name.startswith('fastrtps_port') and not name.endswith('_el') \
        and not Path(path + '_el').exists()


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


# ----------------------------------------------------------------------------- processes
@dataclass(frozen=True)
class Failure:
    """Why a run stopped early, with the evidence."""

    label: str
    reason: str
    log: Path | None = None
    log_tail: tuple[str, ...] = ()
    timed_out: bool = False

    def format(self) -> str:
        text = f'{self.label} {self.reason}'
        if self.log is not None:
            text += '; ' + quote_tail(self.log, self.log_tail)
        return text


@dataclass
class _Child:
    spec: ProcessSpec
    proc: subprocess.Popen
    tee_log: IO[str] | None = None    # the log, when our threads write it (forward)
    threads: list[threading.Thread] = field(default_factory=list)


def describe_exit(code: int) -> str:
    """Popen's return code in words (negative means killed by that signal)."""
    if code == TEARDOWN_HUNG:
        return ('was ended by its teardown watchdog: its work was done, then deleting its DDS '
                'participant hung (a Fast DDS deadlock, eProsima/Fast-DDS#6502)')
    if code < 0:
        with contextlib.suppress(ValueError):
            return f'was killed by {signal.Signals(-code).name}'
        return f'was killed by signal {-code}'
    return f'exited with code {code}'


def log_tail(path: Path, n: int = LOG_TAIL_LINES) -> tuple[str, ...]:
    """The last lines of a log, for a failure report (empty if unreadable)."""
    try:
        lines = path.read_text(errors='replace').splitlines()
    except OSError:
        return ()
    return tuple(lines[-n:])


def quote_tail(path: Path, lines: tuple[str, ...]) -> str:
    """``last N line(s) of LOG:`` and the lines, quoted one per line."""
    return f'last {len(lines)} line(s) of {path}:' + ''.join(f'\n  | {line}' for line in lines)


def live_process_groups() -> dict[int, list[int]]:
    """Process group id -> live (non-zombie) member pids, from /proc. A child's own children
    stay in its group, so this also finds anything a crashed child left behind."""
    groups: dict[int, list[int]] = {}
    for stat in glob.glob('/proc/[0-9]*/stat'):
        try:
            data = Path(stat).read_text()
        except OSError:
            continue
        fields = data[data.rindex(')') + 2:].split()
        if fields[0] not in ('Z', 'X'):
            groups.setdefault(int(fields[2]), []).append(int(stat.split('/')[2]))
    return groups


@contextlib.contextmanager
def _signals_deferred(replay: bool) -> Iterator[None]:
    """Hold SIGINT/SIGTERM while a critical section runs (starting a child, stopping all), so
    an impatient Ctrl-C cannot orphan a process. ``replay`` re-delivers one afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def hold(signum: int, _frame: Any) -> None:
        if not received and not replay:
            print('bearing-pose: stopping processes, please wait...', file=sys.stderr)
        received.append(signum)

    old = {s: signal.signal(s, hold) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
        if replay and received:
            signal.raise_signal(received[0])


class ProcessGroup:
    """Child processes with one lifecycle. Use as a context manager: leaving the block (also by
    an exception or Ctrl-C) stops every child, in reverse start order.

    Each child runs in its own session, so a terminal's Ctrl-C reaches only us and we stop the
    children in order; signals go to the child's whole process group.
    """

    def __init__(self, env: Mapping[str, str] | None = None, *,
                 stdout: IO[str] | None = None, stderr: IO[str] | None = None) -> None:
        self.env = dict(os.environ if env is None else env)
        self._stdout = stdout    # None: sys.stdout at the time of writing (pytest capture)
        self._stderr = stderr
        self._children: dict[str, _Child] = {}
        self._lock = threading.Lock()
        self._shm_before = shm_files()
        self._hung_reported: set[str] = set()

    def __enter__(self) -> ProcessGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    # --------------------------------------------------------------- start and inspect
    def start(self, spec: ProcessSpec) -> subprocess.Popen:
        """Start one child; its output goes to ``spec.log`` (and ours if ``spec.forward``).
        A name whose process has stopped may be started again (a restart)."""
        old = self._children.get(spec.name)
        if old is not None:
            if self._still_running([old]):
                raise ValueError(f'{spec.name}: already running')
            self._release(old)
        spec.log.parent.mkdir(parents=True, exist_ok=True)
        with _signals_deferred(replay=True):
            if spec.forward:
                log = spec.log.open('w', encoding='utf-8')
                try:
                    proc = self._popen(spec, subprocess.PIPE, subprocess.PIPE)
                except LaunchError:
                    log.close()
                    raise
                child = _Child(spec, proc, log)
                child.threads = [self._tee(proc.stdout, log, lambda: self._stdout or sys.stdout),
                                 self._tee(proc.stderr, log, lambda: self._stderr or sys.stderr)]
            else:
                with spec.log.open('wb') as log_bytes:
                    child = _Child(spec, self._popen(spec, log_bytes, subprocess.STDOUT))
            self._children[spec.name] = child
        return child.proc

    def _popen(self, spec: ProcessSpec, stdout: Any, stderr: Any) -> subprocess.Popen:
        try:
            return subprocess.Popen(spec.argv, env=self.env, stdin=subprocess.DEVNULL,
                                    stdout=stdout, stderr=stderr, start_new_session=True)
        except OSError as exc:
            raise LaunchError(f'{spec.label}: cannot start {spec.argv[0]}: {exc}') from exc

    def _tee(self, pipe: IO[bytes] | None, log: IO[str],
             target: Callable[[], IO[str]]) -> threading.Thread:
        """Copy lines from a child's pipe to its log and to one of our streams, live."""
        def pump() -> None:
            assert pipe is not None
            forwarding = True
            with pipe:
                for raw in pipe:  # keep draining even if we cannot forward: a full pipe
                    line = raw.decode('utf-8', errors='replace')  # would block the child
                    with self._lock:
                        log.write(line)
                        log.flush()
                        if forwarding:
                            try:
                                out = target()
                                out.write(line)
                                out.flush()
                            except (OSError, ValueError):   # e.g. `bearing-pose run | head`
                                forwarding = False

        thread = threading.Thread(target=pump, daemon=True)
        thread.start()
        return thread

    @property
    def pids(self) -> dict[str, int]:
        return {name: c.proc.pid for name, c in self._children.items()}

    def returncode(self, name: str) -> int | None:
        return self._children[name].proc.poll()

    def hung_teardowns(self) -> list[str]:
        """The children the teardown watchdog ended (TEARDOWN_HUNG): their participants'
        files may stay in /dev/shm while another process still uses them (:func:`clean_shm`
        removes them once none does)."""
        return [name for name, c in self._children.items() if c.proc.poll() == TEARDOWN_HUNG]

    def unclean(self) -> dict[str, int | None]:
        """The children that did not end cleanly, with their codes (None: still running).
        Clean is exit code 0, or the teardown watchdog's end (TEARDOWN_HUNG): the work was
        done and :meth:`shutdown` removed what the hung participant left in /dev/shm."""
        codes = {name: c.proc.poll() for name, c in self._children.items()}
        return {name: code for name, code in codes.items() if code not in CLEAN_EXITS}

    def failure(self, name: str, reason: str) -> Failure:
        spec = self._children[name].spec
        return Failure(spec.label, reason, spec.log, log_tail(spec.log))

    # --------------------------------------------------------------- wait
    def wait_for(self, target: str, timeout: float,
                 watch: Collection[str] = ()) -> Failure | None:
        """Wait until ``target`` exits. None if it exited with 0; a Failure if it exited
        otherwise, if a ``watch``ed child exited non-zero first, or after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        noted: set[str] = set()
        while True:
            code = self.returncode(target)
            if code is not None:
                return None if code in CLEAN_EXITS else self.failure(target, describe_exit(code))
            for name in watch:
                code = self.returncode(name)
                if code not in (None, *CLEAN_EXITS):
                    return self.failure(name, f'{describe_exit(code)} early')
                if code is not None and name not in noted:
                    noted.add(name)
                    print(f'note: {self._children[name].spec.label} exited (code {code}) '
                          f'before {target} finished', file=self._stderr or sys.stderr)
            if time.monotonic() >= deadline:
                return Failure(target, f'did not finish within the {timeout:g} s timeout',
                               timed_out=True)
            time.sleep(POLL_S)

    # --------------------------------------------------------------- stop
    def _still_running(self, children: list[_Child]) -> list[_Child]:
        """Children whose leader runs, or whose process group still has live members."""
        groups = live_process_groups()
        return [c for c in children if c.proc.poll() is None or c.proc.pid in groups]

    def _signal(self, child: _Child, sig: signal.Signals) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(child.proc.pid, sig)

    def _wait_all(self, children: list[_Child], timeout: float) -> list[_Child]:
        """Wait until all have exited (leader reaped, group empty); return the rest."""
        deadline = time.monotonic() + timeout
        while True:
            children = self._still_running(children)
            if not children or time.monotonic() >= deadline:
                return children
            time.sleep(POLL_S)

    def cpu_seconds(self) -> dict[str, float]:
        """CPU time (user + system) used so far by each live child, from /proc (Linux)."""
        tick = os.sysconf('SC_CLK_TCK')
        out = {}
        for name, child in self._children.items():
            try:
                fields = Path(f'/proc/{child.proc.pid}/stat').read_text().rsplit(')', 1)[1].split()
            except OSError:
                continue  # already gone
            out[name] = (int(fields[11]) + int(fields[12])) / tick  # utime, stime
        return out

    def rss_mb(self) -> dict[str, float]:
        """Resident memory [MB] of each live child, from /proc (Linux)."""
        out = {}
        for name, child in self._children.items():
            try:
                status = Path(f'/proc/{child.proc.pid}/status').read_text()
            except OSError:
                continue  # already gone
            kib = next((line.split()[1] for line in status.splitlines()
                        if line.startswith('VmRSS:')), None)
            if kib is not None:
                out[name] = int(kib) / 1024.0
        return out

    def stop(self, name: str, grace: float = 10.0, term_grace: float = 5.0) -> int | None:
        """Stop one child as :meth:`shutdown` does; return its exit code (0: clean)."""
        with _signals_deferred(replay=False):
            self._stop([self._children[name]], grace, term_grace)
        self._release(self._children[name])
        self._after_hung_teardowns()
        return self.returncode(name)

    def shutdown(self, grace: float = 10.0, term_grace: float = 5.0) -> list[str]:
        """Stop every child: SIGINT in reverse start order, up to ``grace`` s in total; then
        SIGTERM and ``term_grace`` s more; then SIGKILL, reported loudly. Returns the names
        that needed SIGKILL. Safe to call more than once."""
        with _signals_deferred(replay=False):
            killed = self._stop(list(reversed(self._children.values())), grace, term_grace)
            for child in self._children.values():
                self._release(child)
        self._after_hung_teardowns()
        return killed

    def _after_hung_teardowns(self) -> None:
        """Say which children the teardown watchdog ended (once each), and remove the Fast
        DDS files their participants left: created since this group started, used by no live
        process."""
        hung = [self._children[name] for name in self.hung_teardowns()
                if name not in self._hung_reported]
        if not hung:
            return
        err = self._stderr or sys.stderr
        for child in hung:
            self._hung_reported.add(child.spec.name)
            print(f'note: {child.spec.label} {describe_exit(TEARDOWN_HUNG)}; counted as a clean '
                  f'stop. Its stacks are in {child.spec.log}', file=err)
        clean_shm(self._shm_before, err)

    def _stop(self, children: list[_Child], grace: float, term_grace: float) -> list[str]:
        err = self._stderr or sys.stderr
        killed: list[str] = []
        alive = self._still_running(children)
        for child in alive:
            self._signal(child, signal.SIGINT)
        alive = self._wait_all(alive, grace)
        if alive:
            print(f'warning: still running {grace:g} s after SIGINT, sending SIGTERM: '
                  + ', '.join(c.spec.label for c in alive) + ' (their logs get a stack dump)',
                  file=err)
            for child in alive:  # the nodes dump their threads' stacks on SIGUSR1
                self._signal(child, signal.SIGUSR1)
            time.sleep(0.5)
            for child in alive:
                self._signal(child, signal.SIGTERM)
            alive = self._wait_all(alive, term_grace)
        for child in alive:
            killed.append(child.spec.name)
            print(f'WARNING: {child.spec.label} (pid {child.proc.pid}) ignored SIGINT and '
                  'SIGTERM; KILLING it with SIGKILL. A DDS process killed this way may '
                  'leave files in /dev/shm.', file=err)
            self._signal(child, signal.SIGKILL)
        self._wait_all(alive, 5.0)
        return killed

    @staticmethod
    def _release(child: _Child) -> None:
        """Finish a stopped child's output threads and log."""
        for thread in child.threads:
            thread.join(timeout=2.0)
        if child.tee_log is not None:
            child.tee_log.close()
            child.tee_log = None


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Treat SIGTERM like Ctrl-C (KeyboardInterrupt), so ``kill <pid>`` also stops the
    children cleanly instead of orphaning them."""
    def interrupt(_signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


# ----------------------------------------------------------------------------- the run
@dataclass
class RunResult:
    """ok: the monitor finished and wrote summary.json, every process then stopped with exit
    code 0 (none needed SIGKILL), and nothing the run left in /dev/shm remains (what it
    leaves is removed)."""

    ok: bool
    wall_s: float
    failure: Failure | None = None
    killed: list[str] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)   # outputs written by this run
    cpu_s: dict[str, float] = field(default_factory=dict)  # CPU seconds per live process
    rss_mb: dict[str, float] = field(default_factory=dict)  # resident memory per process, at end
    exit_codes: dict[str, int | None] = field(default_factory=dict)  # per process, after stop


def launch_run(scenario: Scenario, cfg: RunConfig, *, bin_dir: Path | None = None) -> RunResult:
    """Write the parameter files, start every process, wait for the monitor, stop the rest.
    Ctrl-C (KeyboardInterrupt) stops everything and propagates.

    Raises:
        LaunchError: more processes than discovery on localhost connects
            (:func:`fit_agents_per_process`), a missing executable, a failed start.
    """
    fit_agents_per_process(len(scenario.agents), cfg.agents_per_process, cfg.rviz)
    needed = ('estimators' if cfg.agents_per_process > 1 else 'estimator', 'simulator', 'monitor',
              *([MARKERS] if cfg.rviz else []))
    exes = {name: find_executable(name, bin_dir) for name in needed}
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    cfg.logs_dir.mkdir(parents=True, exist_ok=True)
    params = write_params(scenario, cfg)
    specs = plan_processes(scenario, params, cfg.logs_dir, exes.__getitem__,
                           cfg.agents_per_process, cfg.fleet_namespace)
    env = dds_env(cfg.domain_id, cfg.logs_dir / 'ros')
    shm_before = shm_files()
    started = time.time()
    (cfg.out_dir / LAUNCH_FILE).write_text(launch_xml(specs, env))
    wall = time.perf_counter()
    result = RunResult(ok=False, wall_s=0.0)
    try:
        with ProcessGroup(env) as group:
            for spec in specs:
                group.start(spec)
            print(f'started {len(specs)} processes (logs in {cfg.logs_dir}); waiting for the '
                  f'monitor (timeout {cfg.wall_timeout:g} s)', file=sys.stderr)
            watch = [s.name for s in specs if s.name != 'monitor']
            result.failure = group.wait_for('monitor', cfg.wall_timeout, watch)
            if result.failure is not None:
                hint = ('; stopping everything. Fix: check the logs; if the run is only slow, '
                        'raise --timeout') if result.failure.timed_out else ''
                print(f'error: {result.failure.format()}{hint}', file=sys.stderr)
            result.cpu_s = group.cpu_seconds()
            result.rss_mb = group.rss_mb()
            result.killed = group.shutdown()
            result.exit_codes = {s.name: group.returncode(s.name) for s in specs}
            if result.failure is not None and result.failure.timed_out:
                # A hang is in whichever process waits: every log's end says who (the
                # simulator names the agent its clock waits for), also where the logs vanish.
                for spec in specs:
                    print(quote_tail(spec.log, log_tail(spec.log, TIMEOUT_TAIL_LINES)),
                          file=sys.stderr)
    finally:
        result.wall_s = time.perf_counter() - wall
        left_in_shm = clean_shm(shm_before)
    result.files = _fresh_files(cfg.out_dir, started)
    if cfg.record and (cfg.bag_dir / 'metadata.yaml').exists():
        result.files.append(cfg.bag_dir)
    if result.failure is None:  # earlier failures were reported when they happened
        result.failure = _failure_after_stop(cfg, specs, result, left_in_shm)
        if result.failure is not None:
            print(f'error: {result.failure.format()}', file=sys.stderr)
    result.ok = result.failure is None
    return result


def _failure_after_stop(cfg: RunConfig, specs: list[ProcessSpec], result: RunResult,
                        left_in_shm: list[str]) -> Failure | None:
    """A run whose monitor finished is clean only if the monitor wrote its summary, every
    process stopped with exit code 0 and nothing it left in /dev/shm remains."""
    if cfg.out_dir / 'summary.json' not in result.files:
        return Failure('monitor', f'exited with code 0 but wrote no '
                       f'{cfg.out_dir / "summary.json"}')
    if cfg.record and cfg.bag_dir not in result.files:
        return Failure('monitor', f'exited with code 0 but finished no bag in {cfg.bag_dir}')
    unclean = [s for s in specs if result.exit_codes.get(s.name) not in (*CLEAN_EXITS, None)]
    if unclean:
        s = unclean[0]
        more = f' (and {len(unclean) - 1} more process(es))' if len(unclean) > 1 else ''
        code = result.exit_codes[s.name]
        assert code is not None  # `unclean` holds only processes that exited
        return Failure(s.label, f'{describe_exit(code)} when stopped at '
                       f'the end of the run{more}', s.log, log_tail(s.log))
    if left_in_shm:
        return Failure('the run', f'left {len(left_in_shm)} file(s) in /dev/shm that could '
                       'not be removed')
    return None


def _remove(path: str) -> None:
    with contextlib.suppress(OSError):
        os.remove(path)


def clean_shm(before: set[str], err: IO[str] | None = None) -> list[str]:
    """Remove the Fast DDS files this run left in /dev/shm (created since ``before``, used by
    no live process: what a participant that was never released leaves, e.g. after the
    teardown watchdog ended a Fast DDS deadlock), saying so; return those that remain. The
    lock-less port files Fast DDS keeps after clean exits go too, silently."""
    err = err or sys.stderr
    # One scan of /proc. Fast DDS's own lock-less port files (:func:`_lockless_port`), kept
    # after clean exits, are not a failure, but litter once no process uses them (large fleets
    # leave them often): removed without a word.
    unused = leaked_shm(before, lockless=True)
    leaked = [f for f in unused if not _lockless_port(f)]
    for f in unused:
        _remove(f)
    remaining = [f for f in leaked if os.path.exists(f)]
    if len(remaining) < len(leaked):
        print(f'warning: removed {len(leaked) - len(remaining)} Fast DDS shared-memory file(s) '
              f'that a process of this run left in /dev/shm ({", ".join(leaked[:3])}): it did '
              'not release its DDS participant; its log says why', file=err)
    if remaining:
        fastdds = Path(sys.executable).parent / 'fastdds'
        tool = str(fastdds) if fastdds.exists() else 'fastdds'
        print(f'warning: could not remove {len(remaining)} of them ({", ".join(remaining[:3])}).'
              f' Fix: `{tool} shm clean` (removes only segments no process uses)',
              file=err)
    return remaining


def _fresh_files(out_dir: Path, since: float) -> list[Path]:
    """Top-level outputs modified by this run (params/ and logs/ are listed separately)."""
    # The slack covers file systems whose timestamps lag the wall clock by a tick.
    return sorted(p for p in out_dir.iterdir()
                  if p.is_file() and p.stat().st_mtime >= since - 0.05)
