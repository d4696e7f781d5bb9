"""What a fleet on a Fast DDS discovery server sees, and what it does when the server dies
(docs/discovery_server.md). One participant per process, on 127.0.0.1, a private domain:

1. A talker (10 Hz on ``/loss_probe``) and, without a reader of that topic, a plain client and
   a super-client (``ROS_SUPER_CLIENT=TRUE``): the nodes and topics each one's graph shows.
2. The server is killed (SIGKILL) while a talker and a listener run: does the listener keep
   receiving? A second listener started while the server is down: does it receive? The server
   started again on the same port (no backup): when does the second listener receive?

    .venv/bin/python bench/discovery_server_loss.py [--domain-id 93] [--down 15] [--redundant]

``--redundant``: a second server (id 1) that stays up; every process lists both.

Every process is stopped with SIGINT, the server last; the files the killed server left in
/dev/shm are removed.
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bearing_pose_estimation.plan import dds
from bearing_pose_estimation.plan.processes import discovery_server_spec

CHILD = r'''
import sys, time
import rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import Int32

role = sys.argv[1]
rclpy.init()
node = rclpy.create_node(role)
got = [0]
try:
    if role == 'talker':
        pub = node.create_publisher(Int32, '/loss_probe', 10)
        node.create_timer(0.1, lambda: pub.publish(Int32(data=1)))
    elif role.startswith('listener'):
        node.create_subscription(Int32, '/loss_probe', lambda _: got.__setitem__(0, got[0] + 1),
                                 10)
        node.create_timer(0.25, lambda: print(f'got {got[0]}', flush=True))
    else:   # an observer: what its graph shows after a while
        end = time.monotonic() + 5.0
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.1)
        print('nodes', sorted(node.get_node_names()), flush=True)
        print('topics', sorted(t for t, _ in node.get_topic_names_and_types()), flush=True)
    while rclpy.ok():
        rclpy.spin_once(node, timeout_sec=0.2)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
'''


class Probe:
    """One probe process; ``got`` is a listener's count so far, ``lines`` what it said."""

    def __init__(self, role: str, env: dict[str, str]) -> None:
        self.role, self.got, self.lines = role, 0, list[str]()
        self.proc = subprocess.Popen([sys.executable, '-c', CHILD, role], env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith('got '):
                self.got = int(line.split()[1])
            else:
                self.lines.append(line.strip())

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:   # a hung Fast DDS teardown (eProsima/Fast-DDS#6502)
            self.proc.kill()
            self.proc.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--domain-id', type=int, default=93)
    ap.add_argument('--down', type=float, default=15.0, help='seconds the server stays down')
    ap.add_argument('--redundant', action='store_true',
                    help='a second server (id 1) that stays up: ROS_DISCOVERY_SERVER="A;B"')
    args = ap.parse_args()
    logs = Path(tempfile.mkdtemp())
    spec = discovery_server_spec(dds.free_udp_port(), logs)
    argvs = [list(spec.argv)]
    if args.redundant:   # id 1 on another port; its place in the list is its id
        argvs.append([*spec.argv[:2], '1', *spec.argv[3:-1], str(dds.free_udp_port())])
    env = dds.dds_env(args.domain_id, logs / 'ros',
                      discovery_server=';'.join(f'127.0.0.1:{a[-1]}' for a in argvs))
    before = dds.shm_files()
    killed: set[str] = set()   # the server's files in /dev/shm when it was killed
    servers = [subprocess.Popen(a, env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL) for a in argvs]
    probes: list[Probe] = []
    t0 = time.monotonic()

    def say(what: str) -> None:
        got = ', '.join(f'{p.role} {p.got}' for p in probes
                        if p.role.startswith('listener'))
        print(f'{time.monotonic() - t0:5.1f} s  {what}  (received: {got})', flush=True)

    try:
        time.sleep(1.0)
        print(f'ROS_DISCOVERY_SERVER={env[dds.DISCOVERY_SERVER_ENV]}', flush=True)
        probes += [Probe('talker', env), Probe('listener_a', env)]
        observers = [Probe('client', env),
                     Probe('super_client', {**env, 'ROS_SUPER_CLIENT': 'TRUE'})]
        while any(len(o.lines) < 2 for o in observers) and time.monotonic() - t0 < 60:
            time.sleep(0.2)
        for o in observers:
            print(f'{o.role:>12}: ' + '; '.join(o.lines), flush=True)
            o.stop()
        say('server up')
        maps = Path(f'/proc/{servers[0].pid}/maps').read_text()
        killed = {w for w in maps.split() if w.startswith('/dev/shm/fastrtps_')}
        servers[0].send_signal(signal.SIGKILL)
        servers[0].wait()
        say('server 0 killed (SIGKILL)')
        time.sleep(5.0)
        say('server 0 down')
        probes.append(Probe('listener_b', env))
        say('listener_b started')
        time.sleep(args.down)
        say('server 0 down')
        servers[0] = subprocess.Popen(argvs[0], env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL)
        restarted, waited = time.monotonic(), probes[-1].got == 0
        while probes[-1].got == 0 and time.monotonic() - restarted < 60:
            time.sleep(0.05)
        say('server 0 started again' + (f'; listener_b received {time.monotonic() - restarted:.1f}'
                                        ' s later' if waited else ''))
        time.sleep(3.0)
        say('server 0 up')
    finally:
        for p in probes:
            p.stop()
        for server in servers:
            server.send_signal(signal.SIGINT)
            server.wait(timeout=20)
        shutil.rmtree(logs, ignore_errors=True)
    left = [f for f in dds.leaked_shm(before) if f.removesuffix('_el') in killed]
    for path in left:
        os.remove(path)
    print(f'removed {len(left)} file(s) the killed server left in /dev/shm', flush=True)


if __name__ == '__main__':
    main()
