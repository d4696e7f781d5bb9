"""One fleet on several hosts: the processes `bearing-pose run` starts, spread over network
namespaces joined by a bridge (test/netns.py), discovering each other over the subnet and
talking over UDP only, as robots on one LAN would.

Needs root and iproute2 (skipped otherwise, with the reason). Nothing touches the machine's
own interfaces: the namespaces, veths and bridge are the test's, in 198.18.0.0/15, and are
removed when it ends.
"""
import contextlib
import glob
import os
import time
from dataclasses import replace
from pathlib import Path

import pytest

from bearing_pose_estimation.cli import launch
from bearing_pose_estimation.plan.dds import CLEAN_EXITS, dds_env, shm_files
from bearing_pose_estimation.plan.processes import (RunConfig, find_executable, plan_processes,
                                                    write_params)
from bearing_pose_estimation.scenario import load_scenario

import netns
from ros_helpers import (PATIENT, ProcessWatch, assert_equals_netsim, assert_no_shm_left,
                         with_parameters)

pytestmark = pytest.mark.dds

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'
DOMAIN = int(os.environ['ROS_DOMAIN_ID'])
# What robots on a LAN set: discovery by multicast on the subnet, no shared memory (which
# exists only within one computer; namespaces of one machine would still share /dev/shm).
ACROSS_HOSTS = {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET', 'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4'}
# Fast DDS's shared-memory transport segments and ports, and its data-sharing segments.
FAST_DDS_SHM = ('/dev/shm/fastrtps_', '/dev/shm/fast_datasharing')


@pytest.fixture(params=['multicast', 'static_peers'])
def hosts(request):
    """Four hosts on a LAN that forwards multicast, or one that drops it (where the fleet
    names its peers: ROS_STATIC_PEERS)."""
    reason = netns.why_not_available()
    if reason is not None:
        pytest.skip(f'cannot create network namespaces: {reason}')
    with netns.Hosts(4, multicast=request.param == 'multicast') as created:
        yield created
    assert created.existing() == [], 'namespaces left behind'


def fast_dds_shm(pid: int) -> set[str]:
    """Fast DDS shared-memory files a process maps or holds open now."""
    found = set()
    with contextlib.suppress(OSError):
        found.update(word for line in Path(f'/proc/{pid}/maps').read_text().splitlines()
                     for word in line.split()[5:6] if word.startswith(FAST_DDS_SHM))
    for fd in glob.glob(f'/proc/{pid}/fd/*'):
        with contextlib.suppress(OSError):
            if (target := os.readlink(fd)).startswith(FAST_DDS_SHM):
                found.add(target)
    return found


def test_a_fleet_on_four_hosts_equals_netsim(tmp_path, hosts):
    """The paper fleet, lockstep, two `estimators` processes of four agents each, the simulator
    and the monitor, each process on a host of its own: every record equals netsim's (and so
    the loopback run's) to 1e-9, the rounding of metrics.csv. No process of the fleet ever
    mapped or opened a Fast DDS shared-memory file (a loopback run's processes map ~17 each),
    every host sent its share through its own interface, and the fleet stopped cleanly. On a
    LAN that drops multicast, ROS_STATIC_PEERS (every host's address) is enough."""
    scenario = load_scenario(PAPER)
    cfg = RunConfig(scenario_file=PAPER, out_dir=tmp_path / 'out', duration=4.0,
                    domain_id=DOMAIN, plots=False, agents_per_process=4)
    cfg.logs_dir.mkdir(parents=True)
    params = with_parameters(write_params(scenario, cfg), list(scenario.index), **PATIENT)
    specs = plan_processes(scenario, params, cfg.logs_dir, find_executable, 4)
    assert [s.name for s in specs] == ['estimators_0', 'estimators_1', 'monitor', 'simulator']
    on_hosts = [replace(s, argv=hosts.argv(k, s.argv)) for k, s in enumerate(specs)]
    env = {**dds_env(DOMAIN, tmp_path / 'ros'), **ACROSS_HOSTS}
    assert hosts.multicast_reaches(0, 3) == hosts.multicast
    if not hosts.multicast:
        env['ROS_STATIC_PEERS'] = ';'.join(hosts.addresses)
    before = shm_files()
    used: dict[str, set[str]] = {s.name: set() for s in specs}
    with ProcessWatch(str(tmp_path)) as watch, launch.ProcessGroup(env) as group:
        watch.groups.append(group)
        for spec in on_hosts:
            group.start(spec)
        deadline = time.monotonic() + 120.0
        # Sampled until the monitor ends: a participant maps its segments for its whole life,
        # so a sample while every process runs sees them all.
        while group.returncode('monitor') is None and time.monotonic() < deadline:
            for name, pid in group.pids.items():
                used[name] |= fast_dds_shm(pid)
            time.sleep(0.1)
        assert group.returncode('monitor') in CLEAN_EXITS, {
            s.name: launch.log_tail(s.log, 10) for s in specs}
        sent = [hosts.counters(k)['tx']['bytes'] for k in range(len(specs))]
        group.shutdown()
        assert group.unclean() == {}
    assert used == {s.name: set() for s in specs}, 'a process used shared memory'
    assert watch.left() == [], 'processes left behind'
    assert_no_shm_left(group, before)
    assert_equals_netsim(cfg.out_dir / 'metrics.csv', PAPER, rtol=1e-9)
    # Every host talked through its own interface; the simulator's sent at least every gyro
    # sample (8 agents at 200 Hz for 4 s, over 300 bytes each in CDR; 5 MB in all measured).
    assert all(n > 0 for n in sent) and sent[-1] > 8 * 200 * 4 * 300, sent
