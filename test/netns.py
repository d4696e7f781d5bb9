"""Hosts for a test: Linux network namespaces on a bridge of their own, as computers on one LAN.

Each host is a namespace with its own ``lo`` and one ``eth0`` (a veth pair whose other end is a
port of a bridge), addressed in 198.18.0.0/15 (RFC 2544, benchmarking: never routed). The bridge
sits in a namespace of its own too, so nothing is created in, or attached to, the root
namespace: the machine's interfaces, addresses and routes are never touched. Everything is
removed on exit, also when the block fails. Needs root (CAP_SYS_ADMIN) and iproute2's ``ip``.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Sequence

SUBNET = '198.18.0.{}/24'
GROUP = '239.255.0.1'   # DDS discovery's multicast group
PROBE_PORT = 7399       # below every DDS port (7400 + 250 domain + ...)

# Run on the receiving host: join GROUP, say so, then read until the sender's unicast datagram
# (sent after its multicast one, on the same path): whether the multicast one came first.
_RECEIVE = f"""
import socket, struct, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(('', {PROBE_PORT}))
s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
             struct.pack('4s4s', socket.inet_aton('{GROUP}'), socket.inet_aton(sys.argv[1])))
s.settimeout(10.0)
print('ready', flush=True)
seen = set()
while b'unicast' not in seen:
    seen.add(s.recv(64))
print(b'multicast' in seen)
"""
_SEND = f"""
import socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(sys.argv[1]))
s.sendto(b'multicast', ('{GROUP}', {PROBE_PORT}))
s.sendto(b'unicast', (sys.argv[2], {PROBE_PORT}))
"""


def _ip(*args: str) -> None:
    subprocess.run(['ip', *args], check=True, capture_output=True, text=True, timeout=10)


def why_not_available() -> str | None:
    """Why this machine cannot give a test namespaces (None: it can), found by creating and
    deleting one."""
    if shutil.which('ip') is None:
        return 'no `ip` (iproute2) on PATH'
    probe = f'bpe{os.getpid()}probe'
    try:
        _ip('netns', 'add', probe)
    except subprocess.CalledProcessError as exc:
        return f'`ip netns add` failed (needs root): {exc.stderr.strip()}'
    _ip('netns', 'delete', probe)
    return None


class Hosts:
    """``n`` namespaces ``<prefix>h<k>`` at 198.18.0.<k + 1>, bridged in ``<prefix>br``. Names
    carry the pid: two test runs never share one. Without ``multicast`` the bridge forwards
    none (a LAN whose switch or Wi-Fi access point drops it). Use as a context manager."""

    def __init__(self, n: int, multicast: bool = True, prefix: str | None = None) -> None:
        prefix = prefix or f'bpe{os.getpid()}'
        self.bridge_ns = f'{prefix}br'
        self.names = [f'{prefix}h{k}' for k in range(n)]
        self.addresses = [SUBNET.format(k + 1).split('/')[0] for k in range(n)]
        self.multicast = multicast
        self._created: list[str] = []

    def __enter__(self) -> Hosts:
        try:
            self._create()
        except BaseException:
            self.remove()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.remove()

    def _add_ns(self, name: str) -> None:
        _ip('netns', 'add', name)
        self._created.append(name)

    def _create(self) -> None:
        br = self.bridge_ns
        self._add_ns(br)
        # No IGMP snooping: multicast goes to every port (an unmanaged switch), or, with
        # mcast_flood off, to none (snooping would forward the groups the hosts join).
        # No STP: the ports forward at once.
        _ip('-n', br, 'link', 'add', 'br0', 'type', 'bridge', 'mcast_snooping', '0',
            'stp_state', '0')
        _ip('-n', br, 'link', 'set', 'br0', 'up')
        for k, host in enumerate(self.names):
            self._add_ns(host)
            _ip('-n', br, 'link', 'add', f'port{k}', 'type', 'veth', 'peer', 'name', 'eth0',
                'netns', host)
            _ip('-n', br, 'link', 'set', f'port{k}', 'master', 'br0', 'up')
            _ip('-n', host, 'link', 'set', 'lo', 'up')
            _ip('-n', host, 'addr', 'add', SUBNET.format(k + 1), 'dev', 'eth0')
            _ip('-n', host, 'link', 'set', 'eth0', 'up')
            if not self.multicast:
                _ip('-n', br, 'link', 'set', f'port{k}', 'type', 'bridge_slave',
                    'mcast_flood', 'off')

    def argv(self, host: int, argv: Sequence[str]) -> tuple[str, ...]:
        """``argv`` run on host ``host`` (``ip netns exec`` execs it: same pid, so signals
        reach the command itself)."""
        return ('ip', 'netns', 'exec', self.names[host], *argv)

    def multicast_reaches(self, src: int, dst: int) -> bool:
        """Whether a datagram host ``src`` sends to DDS discovery's group reaches host ``dst``:
        ``dst`` reads until a unicast datagram that ``src`` sends after it (no waiting on a
        timeout)."""
        receiver = subprocess.Popen(self.argv(dst, [sys.executable, '-c', _RECEIVE,
                                                   self.addresses[dst]]),
                                    stdout=subprocess.PIPE, text=True)
        try:
            assert receiver.stdout is not None and receiver.stdout.readline() == 'ready\n'
            subprocess.run(self.argv(src, [sys.executable, '-c', _SEND, self.addresses[src],
                                           self.addresses[dst]]), check=True, timeout=10)
            out, _ = receiver.communicate(timeout=15)
        finally:
            if receiver.poll() is None:
                receiver.kill()
                receiver.wait()
        return out.strip() == 'True'

    def counters(self, host: int) -> dict[str, dict[str, int]]:
        """A host's ``eth0`` counters so far (``ip -s link``): ``['tx']['bytes']`` is what it
        sent to the other hosts."""
        out = subprocess.run(['ip', '-n', self.names[host], '-s', '-j', 'link', 'show', 'eth0'],
                             check=True, capture_output=True, text=True, timeout=10).stdout
        return json.loads(out)[0]['stats64']

    def remove(self) -> None:
        """Delete every namespace this object created (their veths and the bridge go with
        them), the hosts first. Safe to repeat."""
        for name in reversed(self._created):
            subprocess.run(['ip', 'netns', 'delete', name], check=False, capture_output=True,
                           timeout=10)
        self._created.clear()

    def existing(self) -> list[str]:
        """This object's namespaces that exist now (``ip netns list``)."""
        out = subprocess.run(['ip', 'netns', 'list'], check=True, capture_output=True,
                             text=True, timeout=10).stdout
        listed = {line.split()[0] for line in out.splitlines() if line.strip()}
        return [n for n in (self.bridge_ns, *self.names) if n in listed]
