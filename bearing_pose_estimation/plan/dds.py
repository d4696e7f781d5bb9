"""The DDS environment of a run's processes: domain, environment, how a hung DDS teardown ends,
and the Fast DDS files a participant leaves in /dev/shm. No rclpy.
"""
from __future__ import annotations

import contextlib
import glob
import os
import signal
import socket
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import IO

# How a node ends whose DDS teardown hung after its work was done (ros.node_main's watchdog;
# a Fast DDS deadlock, eProsima/Fast-DDS#6502). Nothing else raises it, so the launcher tells
# it from a crash, and removes the files the participant left in /dev/shm (clean_shm).
TEARDOWN_WATCHDOG_SIGNAL = signal.SIGALRM
TEARDOWN_HUNG = -TEARDOWN_WATCHDOG_SIGNAL
CLEAN_EXITS = (0, TEARDOWN_HUNG)


def private_domain_id() -> int:
    """A per-run ROS_DOMAIN_ID in 1..101 (not the default 0): runs do not see each other."""
    return 1 + os.getpid() % 101


# What dds_env sets (and a restart script carries, with DISCOVERY_SERVER_ENV if set).
DDS_VARIABLES = ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID', 'ROS_LOG_DIR',
                 'PYTHONUNBUFFERED')
# Fast DDS (not rmw) reads it when a participant is created: a participant becomes a client of
# the discovery server at this address and discovers others only through it.
DISCOVERY_SERVER_ENV = 'ROS_DISCOVERY_SERVER'


def dds_env(domain_id: int, ros_log_dir: Path, base: Mapping[str, str] | None = None,
            discovery_server: str | None = None) -> dict[str, str]:
    """The children's environment: DDS stays on loopback, on our domain; logs in the run dir.
    With ``discovery_server`` (``127.0.0.1:<port>``), every participant discovers through it;
    without, a caller's ROS_DISCOVERY_SERVER is dropped (it could point off this machine)."""
    env = dict(os.environ if base is None else base)
    env.update(zip(DDS_VARIABLES, ('LOCALHOST', str(domain_id), str(ros_log_dir), '1')))
    env.pop('ROS_SUPER_CLIENT', None)
    env.pop(DISCOVERY_SERVER_ENV, None)
    if discovery_server:
        env[DISCOVERY_SERVER_ENV] = discovery_server
    return env


def free_udp_port(host: str = '127.0.0.1') -> int:
    """A UDP port nothing is bound to on ``host`` now (for a run's discovery server)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


# Fast DDS shared-memory segments; a crashed or SIGKILLed participant leaves them behind.
SHM_GLOB = '/dev/shm/fastrtps_*'


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
    """Fast DDS files created since ``before`` that no live process uses (what a killed
    participant leaves; with ``lockless``, also :func:`_lockless_port` files)."""
    new = shm_files() - before
    if not new:
        return []
    used = _shm_in_use()
    return sorted(f for f in new
                  if f not in used and f.removesuffix('_el') not in used
                  and f + '_el' not in used and (lockless or not _lockless_port(f)))


def _lockless_port(path: str) -> bool:
    """A shared port file without its ``_el`` lock, which Fast DDS sometimes keeps after clean
    exits (twice in ~40 runs; one run in two or three with 20 to 34 processes of a domain,
    ``bench/discovery_limit.py``, 2026-12-06) and ``fastdds shm clean`` keeps too. A killed
    participant leaves its own segment and lock, which are still reported."""
    name = Path(path).name
    return name.startswith('fastrtps_port') and not name.endswith('_el') \
        and not Path(path + '_el').exists()


def _remove(path: str) -> None:
    with contextlib.suppress(OSError):
        os.remove(path)


def clean_shm(before: set[str], err: IO[str] | None = None) -> list[str]:
    """Remove the Fast DDS files this run left in /dev/shm (:func:`leaked_shm`), saying so
    (lock-less port files silently); return those that remain."""
    err = err or sys.stderr
    unused = leaked_shm(before, lockless=True)   # one scan of /proc
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
