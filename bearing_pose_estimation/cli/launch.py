"""``bearing-pose run``: start the processes of a run (:mod:`plan.processes`), wait for the
monitor, and stop everything cleanly (:class:`ProcessGroup`). No rclpy. A robot's process that
ends mid-run does not end the run: it is reported with the command that starts it again
(:func:`restart_script`), and a process so started is stopped at the end.
"""
from __future__ import annotations

import contextlib
import glob
import json
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Collection, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from ..plan.dds import (CLEAN_EXITS, DDS_VARIABLES, TEARDOWN_HUNG, clean_shm, dds_env,
                        free_udp_port, shm_files)
from ..plan.processes import (CLOCK_STARTED, LAUNCH_FILE, MARKERS, LaunchError, ProcessSpec,
                              RunConfig, find_executable, fit_agents_per_process, launch_xml,
                              plan_processes, write_params)
from ..scenario.model import Scenario

LOG_TAIL_LINES = 20
TIMEOUT_TAIL_LINES = 8    # of every process's log, after a run that timed out
POLL_S = 0.05
# In the environment of every process of a run: its output directory, so that the run also
# finds and stops at the end a process started again by hand (its restart script).
RUN_MARKER, PROCESS_MARKER = 'BEARING_POSE_RUN', 'BEARING_POSE_PROCESS'
# The processes a run goes on without (robots, and the RViz markers); without the simulator
# (the clock and the truth) or the monitor (the results) it cannot.
SURVIVABLE = ('estimator', 'estimators', MARKERS)
SERVER_READY = '### Server is running ###'   # what fast-discovery-server prints once it listens
SERVER_READY_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class Failure:
    """Why a run stopped early, with the evidence."""

    label: str
    reason: str
    log: Path | None = None
    log_tail: tuple[str, ...] = ()
    timed_out: bool = False

    def format(self) -> str:
        return f'{self.label} {self.reason}' + (
            '' if self.log is None else '; ' + quote_tail(self.log, self.log_tail))


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
        return tuple(path.read_text(errors='replace').splitlines()[-n:])
    except OSError:
        return ()


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
def _handling(signals: tuple[signal.Signals, ...],
              handler: Callable[[int, Any], None]) -> Iterator[None]:
    """``handler`` for ``signals`` while the block runs (only the main thread can set one)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, handler) for s in signals}
    try:
        yield
    finally:
        for s, previous in old.items():
            signal.signal(s, previous)


@contextlib.contextmanager
def _signals_deferred(replay: bool) -> Iterator[None]:
    """Hold SIGINT/SIGTERM while a critical section runs (starting a child, stopping all), so
    an impatient Ctrl-C cannot orphan a process. ``replay`` re-delivers one afterwards."""
    received: list[int] = []

    def hold(signum: int, _frame: Any) -> None:
        if not received and not replay:
            print('bearing-pose: stopping processes, please wait...', file=sys.stderr)
        received.append(signum)

    try:
        with _handling((signal.SIGINT, signal.SIGTERM), hold):
            yield
    finally:
        if replay and received:
            signal.raise_signal(received[0])


class ProcessGroup:
    """Child processes with one lifecycle: leaving the ``with`` block (also by an exception or
    Ctrl-C) stops every child, in reverse start order. Each child runs in its own session (a
    terminal's Ctrl-C reaches only us); signals go to its whole process group."""

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
            return subprocess.Popen(spec.argv, env={**self.env, **dict(spec.env)},
                                    stdin=subprocess.DEVNULL,
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
        """The children the teardown watchdog ended (TEARDOWN_HUNG)."""
        return [name for name, c in self._children.items() if c.proc.poll() == TEARDOWN_HUNG]

    def unclean(self) -> dict[str, int | None]:
        """The children that did not end cleanly (None: still running). Clean is 0, or the
        teardown watchdog's end: the work was done, and :meth:`shutdown` cleans /dev/shm."""
        return {name: code for name, c in self._children.items()
                if (code := c.proc.poll()) not in CLEAN_EXITS}

    def failure(self, name: str, reason: str) -> Failure:
        spec = self._children[name].spec
        return Failure(spec.label, reason, spec.log, log_tail(spec.log))

    def wait_for(self, target: str, timeout: float, watch: Collection[str] = (),
                 survive: Collection[str] = (),
                 on_exit: Callable[[str, int], Failure | None] | None = None) -> Failure | None:
        """Wait until ``target`` exits. None if it exited with 0; a Failure if it exited
        otherwise, if a ``watch``ed child exited non-zero first, or after ``timeout`` s. The
        exit of a child in ``survive``, whatever its code, goes to ``on_exit`` (once), and
        the wait goes on unless that returns a Failure."""
        deadline = time.monotonic() + timeout
        noted: set[str] = set()
        while True:
            code = self.returncode(target)
            if code is not None:
                return None if code in CLEAN_EXITS else self.failure(target, describe_exit(code))
            for name in survive:
                code = self.returncode(name)
                if code is not None and name not in noted:
                    noted.add(name)
                    failure = None if on_exit is None else on_exit(name, code)
                    if failure is not None:
                        return failure
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

    def _proc(self, file: str) -> Iterator[tuple[str, str]]:
        """(name, /proc/<pid>/<file>) of each live child (Linux)."""
        for name, child in self._children.items():
            with contextlib.suppress(OSError):   # already gone
                text = Path(f'/proc/{child.proc.pid}/{file}').read_text()
                yield name, text

    def cpu_seconds(self) -> dict[str, float]:
        """CPU time (user + system) used so far by each live child."""
        tick = os.sysconf('SC_CLK_TCK')
        return {name: sum(int(f) for f in stat.rsplit(')', 1)[1].split()[11:13]) / tick
                for name, stat in self._proc('stat')}   # utime, stime

    def rss_mb(self) -> dict[str, float]:
        """Resident memory [MB] of each live child."""
        return {name: int(line.split()[1]) / 1024.0 for name, status in self._proc('status')
                for line in status.splitlines() if line.startswith('VmRSS:')}

    def stop(self, name: str, grace: float = 10.0, term_grace: float = 5.0) -> int | None:
        """Stop one child as :meth:`shutdown` does; return its exit code (0: clean)."""
        with _signals_deferred(replay=False):
            self._stop([self._children[name]], grace, term_grace)
        self._release(self._children[name])
        self._after_hung_teardowns()
        return self.returncode(name)

    def shutdown(self, grace: float = 10.0, term_grace: float = 5.0) -> list[str]:
        """Stop every child (SIGINT in reverse start order, ``grace`` s in all; SIGTERM,
        ``term_grace`` s; SIGKILL, loudly), the ``stop_last`` ones once the others have exited;
        return who needed SIGKILL. Safe to repeat."""
        children = list(reversed(self._children.values()))
        with _signals_deferred(replay=False):
            killed = [name for last in (False, True) for name in self._stop(
                [c for c in children if c.spec.stop_last == last], grace, term_grace)]
            for child in self._children.values():
                self._release(child)
        self._after_hung_teardowns()
        return killed

    def _after_hung_teardowns(self) -> None:
        """Say which children the teardown watchdog ended (once each); remove the Fast DDS files
        their participants left (:func:`clean_shm`)."""
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
        alive = self._still_running(children)
        if not alive:
            return []
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
            print(f'WARNING: {child.spec.label} (pid {child.proc.pid}) ignored SIGINT and '
                  'SIGTERM; KILLING it with SIGKILL. A DDS process killed this way may '
                  'leave files in /dev/shm.', file=err)
            self._signal(child, signal.SIGKILL)
        self._wait_all(alive, 5.0)
        return [c.spec.name for c in alive]

    @staticmethod
    def _release(child: _Child) -> None:
        """Finish a stopped child's output threads and log."""
        for thread in child.threads:
            thread.join(timeout=2.0)
        if child.tee_log is not None:
            child.tee_log.close()
            child.tee_log = None


def sigterm_as_interrupt() -> contextlib.AbstractContextManager[None]:
    """Treat SIGTERM like Ctrl-C (KeyboardInterrupt): ``kill <pid>`` also stops the children."""
    def interrupt(_signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    return _handling((signal.SIGTERM,), interrupt)


@dataclass
class Death:
    """A robot's process that ended before the run did (the run went on without it)."""

    name: str
    label: str
    how: str                     # describe_exit's words
    wall_s: float                # into the run
    restart: Path                # the script that starts it again
    restarted_pid: int | None = None   # started again by hand, and running at the end

    def record(self) -> dict[str, Any]:
        """For summary.json."""
        return {'process': self.name, 'how': self.how, 'wall_s': round(self.wall_s, 3),
                'restart_script': str(self.restart),
                'running_again_at_the_end': self.restarted_pid is not None}


def restart_command(spec: ProcessSpec, env: Mapping[str, str], run_dir: Path) -> str:
    """``spec``'s command line for any shell, with the DDS variables of ``env``, those that differ
    from ours, PYTHONPATH and the run's markers (:data:`RUN_MARKER`)."""
    changed = {k: v for k, v in env.items()
               if k in (*DDS_VARIABLES, 'PYTHONPATH') or os.environ.get(k) != v}
    changed |= {RUN_MARKER: str(run_dir), PROCESS_MARKER: spec.name}
    return shlex.join(['env', *(f'{k}={v}' for k, v in sorted(changed.items())), *spec.argv])


def restart_script(spec: ProcessSpec, command: str, run_dir: Path) -> Path:
    """``<logs>/restart_<name>.sh``: ``command`` (:func:`restart_command`), its output
    appended to the process's log."""
    path = spec.log.parent / f'restart_{spec.name}.sh'
    path.write_text(f'#!/bin/sh\n# Starts {spec.label} of the run in {run_dir} again, as '
                    '`bearing-pose run` started it.\n# The run stops it at its end (it finds it '
                    f'by {RUN_MARKER}).\nexec {command} >> {shlex.quote(str(spec.log))} 2>&1\n')
    path.chmod(0o755)
    return path


def restarted_processes(run_dir: Path) -> dict[int, str]:
    """pid -> name of the live processes started by a restart script of the run in
    ``run_dir`` (their environment says so; /proc)."""
    want = f'{RUN_MARKER}={run_dir}'.encode()
    name_key = f'{PROCESS_MARKER}='.encode()
    found = {}
    for path in glob.glob('/proc/[0-9]*/environ'):
        try:
            items = Path(path).read_bytes().split(b'\0')
        except OSError:
            continue
        if want in items:
            name = next((i[len(name_key):] for i in items if i.startswith(name_key)), None)
            if name is not None:
                found[int(path.split('/')[2])] = name.decode(errors='replace')
    return found


def stop_restarted(run_dir: Path, grace: float = 10.0, err: IO[str] | None = None
                   ) -> dict[str, int]:
    """Stop (SIGINT; SIGKILL after ``grace`` s, loudly) the processes started again by hand;
    return name -> pid of those that were running."""
    found = restarted_processes(run_dir)
    for pid in found:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGINT)
    deadline = time.monotonic() + grace
    while (left := [pid for pid in found if alive(pid)]) and time.monotonic() < deadline:
        time.sleep(POLL_S)
    for pid in left:
        print(f'WARNING: {found[pid]} (pid {pid}, started again by hand) ignored SIGINT; '
              'KILLING it with SIGKILL', file=err or sys.stderr)
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGKILL)
    return {name: pid for pid, name in found.items()}


def alive(pid: int) -> bool:
    """Running: alive and not a zombie (/proc; no psutil)."""
    try:
        stat = Path(f'/proc/{pid}/stat').read_text()
    except OSError:
        return False
    return stat[stat.rindex(')') + 2] not in 'ZX'


@dataclass
class RunResult:
    """ok: the monitor wrote summary.json, every process then stopped cleanly (none needed
    SIGKILL), and nothing the run left in /dev/shm remains. ``deaths``: the robots' processes
    that ended early (the run went on without them; it is ok, but not a clean run)."""

    ok: bool
    wall_s: float
    failure: Failure | None = None
    killed: list[str] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)   # outputs written by this run
    cpu_s: dict[str, float] = field(default_factory=dict)  # CPU seconds per live process
    rss_mb: dict[str, float] = field(default_factory=dict)  # resident memory per process, at end
    exit_codes: dict[str, int | None] = field(default_factory=dict)  # per process, after stop
    deaths: list[Death] = field(default_factory=list)


def launch_run(scenario: Scenario, cfg: RunConfig, *, bin_dir: Path | None = None) -> RunResult:
    """Write the parameter files, start every process, wait for the monitor, stop the rest
    (Ctrl-C: everything, and propagates). LaunchError: too many processes, a failed start."""
    fit_agents_per_process(len(scenario.agents), cfg.agents_per_process, cfg.rviz,
                           cfg.discovery_server is not None)
    needed = ('estimators' if cfg.agents_per_process > 1 else 'estimator', 'simulator', 'monitor',
              *([MARKERS] if cfg.rviz else []))
    exes = {name: find_executable(name, bin_dir) for name in needed}
    cfg.logs_dir.mkdir(parents=True, exist_ok=True)   # in out_dir
    params = write_params(scenario, cfg)
    port = None if cfg.discovery_server is None else cfg.discovery_server or free_udp_port()
    specs = plan_processes(scenario, params, cfg.logs_dir, exes.__getitem__,
                           cfg.agents_per_process, cfg.fleet_namespace, port)
    server = specs[0] if port is not None else None
    env = dds_env(cfg.domain_id, cfg.logs_dir / 'ros',
                  discovery_server=None if port is None else f'127.0.0.1:{port}'
                  ) | {RUN_MARKER: str(cfg.out_dir)}
    shm_before = shm_files()
    started = time.time()
    (cfg.out_dir / LAUNCH_FILE).write_text(launch_xml(specs, env))
    wall = time.perf_counter()
    result = RunResult(ok=False, wall_s=0.0)
    by_name = {s.name: s for s in specs}

    def died(name: str, code: int) -> Failure | None:
        """A robot's process ended: say so and how to start it again; the run goes on. Before
        the clock started, it failed to start: the run cannot (its log says why)."""
        spec, started = by_name[name], False
        with contextlib.suppress(OSError):
            started = CLOCK_STARTED in by_name['simulator'].log.read_text(errors='replace')
        if not started:
            return group.failure(name, f'{describe_exit(code)} before the clock started')
        command = restart_command(spec, env, cfg.out_dir)
        death = Death(name, spec.label, describe_exit(code), time.perf_counter() - wall,
                      restart_script(spec, command, cfg.out_dir))
        result.deaths.append(death)
        tail = log_tail(spec.log) if code > 0 else ()   # a crash's traceback
        print(f'warning: {spec.label} {death.how} {death.wall_s:.1f} s into the run; the run '
              'goes on without it' + (f'; {quote_tail(spec.log, tail)}' if tail else '')
              + f'.\n  To start it again (its command and DDS environment; output appended '
              f'to its log):\n    sh {death.restart}\n  which runs: {command}',
              file=sys.stderr)
        return None

    try:
        with ProcessGroup(env) as group:
            for spec in specs:
                if spec is server:
                    start_discovery_server(group, spec)
                else:
                    group.start(spec)
            print(f'started {len(specs)} processes (logs in {cfg.logs_dir}); waiting for the '
                  f'monitor (timeout {cfg.wall_timeout:g} s)', file=sys.stderr)
            survive = [s.name for s in specs if s.kind in SURVIVABLE]
            watch = [s.name for s in specs if s.name != 'monitor' and s.name not in survive]
            result.failure = group.wait_for('monitor', cfg.wall_timeout, watch, survive, died)
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
        again = stop_restarted(cfg.out_dir)   # also on Ctrl-C
        for death in result.deaths:
            death.restarted_pid = again.get(death.name)
        result.wall_s = time.perf_counter() - wall
        left_in_shm = clean_shm(shm_before)
    # Top-level outputs this run modified (the slack: timestamps that lag the clock by a tick).
    result.files = sorted(p for p in cfg.out_dir.iterdir()
                          if p.is_file() and p.stat().st_mtime >= started - 0.05)
    if cfg.record and (cfg.bag_dir / 'metadata.yaml').exists():
        result.files.append(cfg.bag_dir)
    if result.failure is None:  # earlier failures were reported when they happened
        result.failure = _failure_after_stop(cfg, specs, result, left_in_shm)
        if result.failure is not None:
            print(f'error: {result.failure.format()}', file=sys.stderr)
    result.ok = result.failure is None
    if result.deaths:
        _report_deaths(cfg, result.deaths)
    return result


def _report_deaths(cfg: RunConfig, deaths: list[Death]) -> None:
    """The deaths, at the end of the run's output and in its summary.json (``deaths``): the
    errors are not a clean run's."""
    for d in deaths:
        again = (f'started again by hand, running until the end (pid {d.restarted_pid})'
                 if d.restarted_pid is not None else
                 f'not running at the end (never started again, or it ended again); {d.restart}'
                 ' starts it')
        print(f'note: {d.label} {d.how} {d.wall_s:.1f} s into the run; {again}',
              file=sys.stderr)
    summary = cfg.out_dir / 'summary.json'
    with contextlib.suppress(OSError, ValueError):
        data = json.loads(summary.read_text())
        data['deaths'] = [d.record() for d in deaths]
        summary.write_text(json.dumps(data, indent=2) + '\n')


def start_discovery_server(group: ProcessGroup, spec: ProcessSpec) -> None:
    """Start the server and wait until it listens (a client that starts earlier would find it
    only at its next retry); LaunchError if it exits or stays silent."""
    group.start(spec)
    deadline = time.monotonic() + SERVER_READY_TIMEOUT_S
    while SERVER_READY not in spec.log.read_text(errors='replace'):
        code = group.returncode(spec.name)
        if code is not None or time.monotonic() > deadline:
            why = (describe_exit(code) if code is not None else
                   f'did not say it runs within {SERVER_READY_TIMEOUT_S:g} s')
            raise LaunchError(f'{spec.label} {why}; {quote_tail(spec.log, log_tail(spec.log))}\n'
                              'Fix: another --discovery-server-port (or leave it out: a free one)')
        time.sleep(POLL_S)
    print(f'discovery server on 127.0.0.1:{spec.argv[-1]}: every process discovers through it '
          f'(ROS_DISCOVERY_SERVER; log {spec.log})', file=sys.stderr)


def _failure_after_stop(cfg: RunConfig, specs: list[ProcessSpec], result: RunResult,
                        left_in_shm: list[str]) -> Failure | None:
    """Why a run whose monitor finished is not clean (see :class:`RunResult`), or None."""
    if cfg.out_dir / 'summary.json' not in result.files:
        return Failure('monitor', f'exited with code 0 but wrote no '
                       f'{cfg.out_dir / "summary.json"}')
    if cfg.record and cfg.bag_dir not in result.files:
        return Failure('monitor', f'exited with code 0 but finished no bag in {cfg.bag_dir}')
    dead = {d.name for d in result.deaths}   # reported as deaths: not a failure to stop
    unclean = [s for s in specs if s.name not in dead
               and result.exit_codes.get(s.name) not in (*CLEAN_EXITS, None)]
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
