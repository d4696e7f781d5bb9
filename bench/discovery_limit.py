"""How many processes of one domain discover each other on localhost, and how fast; with
simple discovery (as every run here uses by default) or through a Fast DDS discovery server
(``bearing-pose run --discovery-server``).

Every process is one rclpy context, so one DDS participant, on a private domain with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``. Two measurements:

- ``--idle N``: N idle processes, started one at a time (each takes the next participant id),
  then two more: one subscribes to a probe topic, the other publishes it and waits (at most
  ``--wait`` s) until its writer has the reader. Whether and when the pair matched.
- ``--fleet N``: N processes, each with a writer and a reader of the probe topic, imported and
  waiting, then released at once (as ``bearing-pose run`` starts a fleet). When every writer
  had matched all N readers (every pair, both ways): from the release, and from the moment the
  last participant was up (its node and endpoints created); or how many of the N x N matches
  there were after ``--wait`` s.

With ``--discovery-server``, a server (:func:`plan.processes.discovery_server_spec`) is started
first and every process gets ``ROS_DISCOVERY_SERVER``. Every process is stopped with SIGINT
and shuts rclpy down, the server last; what Fast DDS still leaves in /dev/shm is removed and
reported.

    .venv/bin/python bench/discovery_limit.py [--idle 5 30 31 32] [--fleet 32 64]
        [--discovery-server] [--repeat 3] [--wait 30] [--domain-id 92]

Measured 2026-12-06 (BENCHMARKS.md, "Discovery"): the pair matches within a second after 5,
30 or 31 idle processes and never after 32: the 33rd and 34th participants of a domain never
discover each other, which is why ``bearing-pose run`` uses at most 32 processes
(``plan.processes.MAX_PROCESSES``) unless it has a discovery server ("The discovery server").
Through one (2026-12-08), the pair matched after 32, 40 and 64 idle processes; 64 released at
once hang in Fast DDS's shared-memory transport, with or without it.
"""
from __future__ import annotations

import argparse
import contextlib
import glob
import os
import queue
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

from bearing_pose_estimation.cli import launch
from bearing_pose_estimation.plan import dds
from bearing_pose_estimation.plan.processes import discovery_server_spec

CHILD = r'''
import sys, time
import rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import Empty

role, wait, n = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
if role == 'fleet':   # imported: wait for the release
    print('ready', flush=True)
    sys.stdin.readline()
rclpy.init()
node = rclpy.create_node(f'probe_{role}')
try:
    if role in ('pub', 'fleet'):
        pub = node.create_publisher(Empty, '/discovery_probe', 10)
    if role in ('sub', 'fleet'):
        node.create_subscription(Empty, '/discovery_probe', lambda _: None, 10)
    if role in ('pub', 'fleet'):
        t0 = time.monotonic()
        print(f'up {t0}', flush=True)
        while time.monotonic() - t0 < wait and pub.get_subscription_count() < n:
            rclpy.spin_once(node, timeout_sec=0.01)
        print(f'matched {pub.get_subscription_count()} {time.monotonic()}', flush=True)
    else:
        print('up', flush=True)
    while role != 'pub' and rclpy.ok():   # a fleet member serves the others until SIGINT
        rclpy.spin_once(node, timeout_sec=0.2)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
'''


def _stop(procs: list[subprocess.Popen[str]]) -> list[int]:
    """SIGINT, then SIGTERM, then SIGKILL (a Fast DDS teardown can hang: the nodes have a
    watchdog for it, these probes do not); the pids that needed SIGKILL."""
    killed = []
    for sig, grace in ((signal.SIGINT, 15.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        alive = [p for p in procs if p.poll() is None]
        for proc in alive:
            proc.send_signal(sig)
        deadline = time.monotonic() + grace
        for proc in alive:
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        if sig == signal.SIGKILL:
            killed = [p.pid for p in alive]
    return killed


# A Fast DDS file in /dev/shm: a segment, a port, their locks, a port's named mutex.
_SHM_FILE = re.compile(r'/dev/shm/(?:sem\.)?fastrtps_[^\s/]+')


def _shm_key(path: str) -> str:
    """What a file belongs to: its segment or port (``fastrtps_port7000`` for
    ``sem.fastrtps_port7000_mutex`` and ``fastrtps_port7000_el`` too)."""
    return Path(path).name.removeprefix('sem.').removesuffix('_mutex').removesuffix('_el')


def _shm_used(pids: Iterable[int] | None = None) -> set[str]:
    """The Fast DDS files that the processes ``pids`` (None: all) map or hold open."""
    used: set[str] = set()
    for pid in ['[0-9]*'] if pids is None else [str(p) for p in pids]:
        for maps in glob.glob(f'/proc/{pid}/maps'):
            with contextlib.suppress(OSError):
                used.update(_SHM_FILE.findall(Path(maps).read_text()))
        for fd in glob.glob(f'/proc/{pid}/fd/*'):
            with contextlib.suppress(OSError):
                used.update(_SHM_FILE.findall(os.readlink(fd)))
    return used


@contextlib.contextmanager
def _probes(label: str, domain_id: int, server: bool) -> Iterator[
        tuple[dict[str, str], list[subprocess.Popen[str]]]]:
    """The probes' environment and list (filled by the caller); the probes are stopped, then
    the server, and the files they left in /dev/shm removed."""
    logs = Path(tempfile.mkdtemp())
    spec = discovery_server_spec(dds.free_udp_port(), logs) if server else None
    env = dds.dds_env(domain_id, logs / 'ros', discovery_server=None if spec is None else
                      f'127.0.0.1:{spec.argv[-1]}')
    procs: list[subprocess.Popen[str]] = []
    with launch.ProcessGroup(env, stderr=open(os.devnull, 'w')) as group:
        if spec is not None:
            launch.start_discovery_server(group, spec)
        try:
            yield env, procs
        finally:
            # Only what our processes use: other runs share /dev/shm, and every participant on
            # localhost maps the 7000+ ports, whatever its domain.
            ours = {_shm_key(f) for f in _shm_used([p.pid for p in procs]
                                                    + list(group.pids.values()))}
            killed = len(_stop(procs)) + len(group.shutdown())
    shutil.rmtree(logs, ignore_errors=True)
    ours -= {_shm_key(f) for f in _shm_used()}
    left = sorted(f for f in glob.glob('/dev/shm/*fastrtps_*') if _shm_key(f) in ours)
    for path in left:
        with contextlib.suppress(FileNotFoundError):
            os.remove(path)
    if killed or left:   # Fast DDS keeps a port file after clean exits now and then
        print(f'  ({label}: {killed} process(es) needed SIGKILL; removed {len(left)} file(s) '
              f'left in /dev/shm: {", ".join(Path(f).name for f in left[:4])}'
              f'{", ..." if len(left) > 4 else ""})', flush=True)


_LINES: dict[int, queue.Queue[str]] = {}   # pid -> the probe's stdout lines ('' at its end)
SAID: list[str] = []   # what else a probe printed on stdout (Fast DDS's errors), for a note
HUNG = 'hung'   # what _line returns for a probe that said nothing for too long


def _start(env: dict[str, str], role: str, wait: float, n: int = 1) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, '-c', CHILD, role, str(wait), str(n)], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    lines = _LINES[proc.pid] = queue.Queue()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)
        lines.put('')

    threading.Thread(target=pump, daemon=True).start()
    return proc


def _line(proc: subprocess.Popen[str], word: str, timeout: float) -> list[str]:
    """The probe's next line that starts with ``word``, split ([HUNG] after ``timeout`` s of
    silence: a participant whose creation deadlocked); the lines before it go to SAID."""
    while True:
        try:
            line = _LINES[proc.pid].get(timeout=timeout)
        except queue.Empty:
            return [HUNG]
        if line.startswith(word):
            return line.split()
        assert line, f'probe {proc.pid} ended before saying {word!r}'
        SAID.append(line.strip())


def probe(n_idle: int, wait: float, domain_id: int, server: bool) -> tuple[bool, float]:
    """(matched, seconds) for the probe pair started after ``n_idle`` idle processes."""
    with _probes(f'after {n_idle} idle', domain_id, server) as (env, procs):
        for role in ['idle'] * n_idle + ['sub', 'pub']:   # one at a time: the next id
            procs.append(_start(env, role, wait))
            up = _line(procs[-1], 'up', 120.0)
            assert up != [HUNG], f'probe {procs[-1].pid} hung while starting'
        _, count, matched = _line(procs[-1], 'matched', wait + 60.0)
        return int(count) > 0, float(matched) - float(up[1])


def fleet(n: int, wait: float, domain_id: int, server: bool) -> dict[str, float]:
    """All-to-all discovery of ``n`` participants released at once: seconds from the release
    until every participant is up (``up``) and until every writer matched every reader
    (``matched``, NaN if not within ``wait``), the share of the n x n matches made, and how
    many participants ``hung`` in their creation (a Fast DDS deadlock: said, not hidden)."""
    with _probes(f'fleet of {n}', domain_id, server) as (env, procs):
        procs += [_start(env, 'fleet', wait, n) for _ in range(n)]
        for proc in procs:
            _line(proc, 'ready', 300.0)   # imported
        released = time.monotonic()
        for proc in procs:
            assert proc.stdin is not None
            proc.stdin.write('go\n')
            proc.stdin.flush()
        # One deadline for all, not one per probe: k hung probes cost 120 s, not k x 120 s.
        by = time.monotonic() + 120.0
        ups = [_line(p, 'up', max(0.1, by - time.monotonic())) for p in procs]
        up = [float(u[1]) for u in ups if u != [HUNG]]
        by = time.monotonic() + wait + 60.0
        ends = [_line(p, 'matched', max(0.1, by - time.monotonic()))
                for p, u in zip(procs, ups) if u != [HUNG]]
        ends = [e for e in ends if e != [HUNG]]
    counts, times = [int(e[1]) for e in ends], [float(e[2]) for e in ends]
    done = len(counts) == n and all(c >= n for c in counts)
    return {'up': max(up) - released, 'hung': n - len(up),
            'matched': max(times) - released if done else float('nan'),
            'after_last_up': max(times) - max(up) if done else float('nan'),
            'share': sum(min(c, n) for c in counts) / n ** 2}


MATCHED = 'matched'


def _median(values: list[float]) -> str:
    """The median of the finite values, and how many there were if not all."""
    done = [v for v in values if v == v]
    if not done:
        return 'never'
    out = f'{statistics.median(done):.2f} s'
    return out if len(done) == len(values) else f'{out} ({len(done)} of {len(values)} runs)'


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--idle', type=int, nargs='*', default=[])
    ap.add_argument('--fleet', type=int, nargs='*', default=[])
    ap.add_argument('--discovery-server', action='store_true',
                    help='discover through a Fast DDS discovery server on 127.0.0.1')
    ap.add_argument('--repeat', type=int, default=1, help='runs per size (medians)')
    ap.add_argument('--wait', type=float, default=30.0, help='seconds discovery may take')
    ap.add_argument('--domain-id', type=int, default=92)
    args = ap.parse_args()
    if not args.idle and not args.fleet:
        args.idle = [5, 30, 31, 32]
    how = 'through a discovery server' if args.discovery_server else 'simple discovery'
    if args.idle:
        print(f'Probe pair after N idle processes, {how}:\n')
        print('| idle processes | the pair are participants | matched | after | each run |')
        print('|---|---|---|---|---|')
    for n in args.idle:
        runs = [probe(n, args.wait, args.domain_id, args.discovery_server)
                for _ in range(args.repeat)]
        print(f'| {n} | {n + 1} and {n + 2} | {sum(m for m, _ in runs)} of {len(runs)} | '
              f'{_median([s if m else float("nan") for m, s in runs])} | '
              f'{", ".join(f"{s:.1f}" if m else "no" for m, s in runs)} |', flush=True)
    if args.fleet:
        print(f'\nFleets of N participants released at once, {how} (medians of {args.repeat}; '
              'matched: every writer has every reader):\n')
        print('| participants | all up | all matched | after the last was up | matches made | '
              'all matched, each run | hung at creation |')
        print('|---|---|---|---|---|---|---|')
    for n in args.fleet:
        fleets = [fleet(n, args.wait, args.domain_id, args.discovery_server)
                for _ in range(args.repeat)]
        print(f'| {n} | {_median([r["up"] for r in fleets])} | '
              f'{_median([r["matched"] for r in fleets])} | '
              f'{_median([r["after_last_up"] for r in fleets])} | '
              f'{100 * statistics.median(r["share"] for r in fleets):.1f} % | '
              f'{", ".join(f"{r[MATCHED]:.2f}" for r in fleets)} | '
              f'{sum(r["hung"] for r in fleets):.0f} |', flush=True)
    if SAID:
        print(f'\nThe probes also printed {len(SAID)} line(s), e.g.:', *sorted(set(SAID))[:5],
              sep='\n  ')


if __name__ == '__main__':
    main()
