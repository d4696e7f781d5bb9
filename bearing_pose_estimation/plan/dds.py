"""The DDS environment of a run's processes, shared by the nodes (:mod:`ros`) and the
launcher (:mod:`cli.launch`): the domain and environment they run in, how a node whose DDS
teardown hung ends (:data:`TEARDOWN_WATCHDOG_SIGNAL`), and the Fast DDS shared-memory files a
participant leaves in /dev/shm. No rclpy.
"""
from __future__ import annotations

import contextlib
import glob
import os
import signal
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import IO

# How a node ends whose DDS teardown hung after its work was done (ros.node_main's watchdog):
# a Fast DDS deadlock in deleting the participant, eProsima/Fast-DDS#6502. Nothing else in a
# run raises it, so the launcher (cli.launch) tells it from a crash; the participant's files
# stay in /dev/shm and the launcher removes them (clean_shm).
TEARDOWN_WATCHDOG_SIGNAL = signal.SIGALRM
TEARDOWN_HUNG = -TEARDOWN_WATCHDOG_SIGNAL
CLEAN_EXITS = (0, TEARDOWN_HUNG)


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
