"""`bearing-pose run`, bearing_pose_estimation.plan and bearing_pose_estimation.cli.launch, with
stand-in node executables.

The stand-ins are one small Python script installed as `estimator`, `simulator` and `monitor`
in a temp folder (found through $BEARING_POSE_BIN_DIR). Each records its pid, command line,
parameters and DDS environment to $STANDIN_DIR/<name>.json, then behaves as told by
$STANDIN_<NAME> (default: loop until SIGINT; the monitor: write outputs and exit 0).
No rclpy, no DDS: these tests check process management only.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from bearing_pose_estimation.cli import launch
from bearing_pose_estimation.cli.main import main
from bearing_pose_estimation.plan import dds
from bearing_pose_estimation.plan import processes as plan
from bearing_pose_estimation.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / 'config' / 'paper_8_agents.yaml'

STANDIN = '''#!{python}
import json, os, signal, subprocess, sys, time
from pathlib import Path

import yaml

argv = sys.argv[1:]
remaps = dict(argv[i + 1].split(':=', 1) for i, a in enumerate(argv) if a == '-r')
name = remaps.get('__ns', '').strip('/') or remaps['__node']
params_file = argv[argv.index('--params-file') + 1]
params = next(iter(yaml.safe_load(Path(params_file).read_text()).values()))['ros__parameters']
default = 'monitor' if name == 'monitor' else 'loop'
behaviour = os.environ.get('STANDIN_' + name.upper(), default)
record = dict(pid=os.getpid(), argv=sys.argv, params=params, behaviour=behaviour,
              started=time.monotonic(),
              env=dict((k, os.environ.get(k)) for k in
                       ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID', 'ROS_LOG_DIR',
                        'ROS_DISCOVERY_SERVER', 'ROS_SUPER_CLIENT')))


def stop(signum, frame):
    if behaviour == 'monitor':
        write_outputs(partial=True)
    if behaviour == 'teardown_hung':  # what node_main's watchdog does to a deadlocked teardown
        Path(os.environ['STANDIN_SHM'], 'fastrtps_hung').write_text('')
        os.kill(os.getpid(), signal.SIGALRM)
    sys.exit(1 if behaviour == 'unclean' else 0)  # unclean: a teardown that fails


def write_outputs(partial):
    out = Path(params['out_dir'])
    (out / 'metrics.csv').write_text('t,attitude_error_mean_rad,position_error_mean_m\\n')
    summary = {{'final_attitude_error_mean_rad': 1e-3, 'final_attitude_error_max_rad': 2e-3,
               'final_position_error_mean_m': 1e-2, 'final_position_error_max_m': 2e-2,
               'complete': not partial, 'attitude_below_1e-3_rad_from_s': 1.5,
               'position_below_1e-2_m_from_s': None}}
    (out / 'summary.json').write_text(json.dumps(summary))


signal.signal(signal.SIGINT, stop)
signal.signal(signal.SIGUSR1, signal.SIG_IGN)  # the real nodes dump their stacks on it
if behaviour == 'deaf':          # ignores SIGINT, dies on SIGTERM
    signal.signal(signal.SIGINT, signal.SIG_IGN)
if behaviour == 'stubborn':      # ignores SIGINT and SIGTERM: needs SIGKILL
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
if behaviour == 'spawn':         # leaves a grandchild in its process group, then exits
    record['grandchild'] = subprocess.Popen(['sleep', '60']).pid
if behaviour == 'shm':           # leaves a (fake) Fast DDS shared-memory file
    Path(os.environ['STANDIN_SHM'], 'fastrtps_standin').write_text('')
if behaviour == 'port':          # leaves a lock-less port file, as Fast DDS does after clean exits
    Path(os.environ['STANDIN_SHM'], 'fastrtps_port7411').write_text('')
if name == 'simulator' and behaviour != 'no_clock':   # the run has begun
    print('[simulator]: all matched after 0.01 s; clock starts at t = 0', flush=True)
tmp = Path(os.environ['STANDIN_DIR'], name + '.tmp')
tmp.write_text(json.dumps(record))
tmp.rename(tmp.with_suffix('.json'))

if behaviour == 'crash':
    # Crash once the monitor is up (it records itself after installing its SIGINT handler):
    # the test checks that the monitor, stopped because of this crash, writes partial outputs.
    after = os.environ.get('STANDIN_CRASH_AFTER', 'monitor')
    monitor_up = Path(os.environ['STANDIN_DIR'], after + '.json')
    deadline = time.monotonic() + 30
    while not monitor_up.exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    print('boom: something went wrong', flush=True)
    sys.exit(3)
if behaviour == 'spawn':
    sys.exit(0)
if behaviour == 'monitor':
    delay = float(os.environ.get('STANDIN_MONITOR_DELAY', '0.3'))
    until = os.environ.get('STANDIN_MONITOR_UNTIL')   # a file: the end of the simulated time
    while until and not Path(until).exists():
        time.sleep(0.01)
    for k in range(3):
        print(f'  t = {{k}} s progress line', flush=True)
        time.sleep(delay / 3)
    write_outputs(partial=False)
    sys.exit(0)
while True:
    time.sleep(0.05)
'''


# fast-discovery-server: says it runs (or, as $STANDIN_DISCOVERY_SERVER=port_in_use, fails as
# the real one does); on SIGINT records which node stand-ins were still alive.
STANDIN_SERVER = '''#!{python}
import json, os, signal, sys, time
from pathlib import Path

records = Path(os.environ['STANDIN_DIR'])
if os.environ.get('STANDIN_DISCOVERY_SERVER') == 'port_in_use':
    print('Server creation failed with the given settings. Please review locators setup.')
    sys.exit(1)


def alive(pid):
    try:
        stat = Path(f'/proc/{{pid}}/stat').read_text()
    except OSError:
        return False
    return stat[stat.rindex(')') + 2] not in 'ZX'


def stop(signum, frame):
    others = [json.loads(p.read_text()) for p in records.glob('*.json')]
    record['alive_at_stop'] = sorted(r['argv'][0] for r in others if alive(r['pid']))
    (records / 'discovery_server.json').write_text(json.dumps(record))
    sys.exit(0)


record = dict(pid=os.getpid(), argv=sys.argv, started=time.monotonic())
signal.signal(signal.SIGINT, stop)
print('### Server is running ###', flush=True)
while True:
    time.sleep(0.05)
'''


@pytest.fixture
def standins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Install the stand-ins; return the folder where they record themselves."""
    bin_dir, records = tmp_path / 'bin', tmp_path / 'records'
    bin_dir.mkdir()
    records.mkdir()
    for name in plan.NODE_EXECUTABLES + (plan.DISCOVERY_SERVER_EXE,):
        exe = bin_dir / name
        standin = STANDIN_SERVER if name == plan.DISCOVERY_SERVER_EXE else STANDIN
        exe.write_text(standin.format(python=sys.executable))
        exe.chmod(0o755)
    monkeypatch.setenv(plan.BIN_DIR_ENV, str(bin_dir))
    monkeypatch.setenv('STANDIN_DIR', str(records))
    return records


@pytest.fixture
def small(tmp_path: Path) -> Path:
    """A valid 3-agent scenario (2 leaders, 1 follower): 5 processes, quick to start."""
    path = tmp_path / 'small.yaml'
    assert main(['generate', '--agents', '3', '--out', str(path)]) == 0
    return path


def records(folder: Path) -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in folder.glob('*.json')}


def assert_all_gone(recs: dict[str, dict]) -> None:
    pids = [r['pid'] for r in recs.values()] + [r['grandchild'] for r in recs.values()
                                                 if 'grandchild' in r]
    assert pids and not [p for p in pids if launch.alive(p)]


def wait_for_records(folder: Path, n: int, timeout: float = 10.0) -> dict[str, dict]:
    deadline = time.monotonic() + timeout
    while len(recs := records(folder)) < n:
        assert time.monotonic() < deadline, f'only {sorted(recs)} started'
        time.sleep(0.05)
    return recs


# ----------------------------------------------------------------------------- set-up
def test_params_files_have_the_ros2_layout(tmp_path):
    scenario = load_scenario(PAPER)
    cfg = plan.RunConfig(scenario_file=PAPER, out_dir=tmp_path, duration=12.0, domain_id=7,
                         real_time_factor=2.0, plots=False)
    files = plan.write_params(scenario, cfg)
    assert set(files) == {f'agent_{k}' for k in range(1, 9)} | {'simulator', 'monitor'}
    assert all(f.parent == tmp_path / 'params' for f in files.values())
    assert yaml.safe_load(files['agent_3'].read_text()) == {'/agent_3/estimator': {
        'ros__parameters': {'scenario_file': str(PAPER), 'agent': 'agent_3',
                            'use_sim_time': True}}}
    assert yaml.safe_load(files['simulator'].read_text()) == {'/simulator': {
        'ros__parameters': {'scenario_file': str(PAPER), 'duration': 12.0,
                            'real_time_factor': 2.0, 'use_sim_time': False}}}
    assert yaml.safe_load(files['monitor'].read_text()) == {'/monitor': {
        'ros__parameters': {'scenario_file': str(PAPER), 'duration': 12.0,
                            'out_dir': str(tmp_path), 'plots': False, 'use_sim_time': True}}}
    recorded = plan.write_params(scenario, dataclasses.replace(cfg, record=True))
    assert yaml.safe_load(recorded['monitor'].read_text())['/monitor']['ros__parameters'][
        'bag'] == str(tmp_path / 'bag')


def test_plan_starts_estimators_then_monitor_then_simulator(tmp_path):
    scenario = load_scenario(PAPER)
    params = {n: tmp_path / f'{n}.yaml' for n in [a.name for a in scenario.agents]
              + ['monitor', 'simulator']}
    specs = plan.plan_processes(scenario, params, tmp_path, lambda n: Path('/x') / n)
    assert [s.name for s in specs] == [f'agent_{k}' for k in range(1, 9)] + ['monitor',
                                                                             'simulator']
    assert specs[0].argv == ('/x/estimator', '--ros-args', '-r', '__ns:=/agent_1', '-r',
                             '__node:=estimator', '-r', 'known_pose:=ground_truth',
                             '--params-file', str(tmp_path / 'agent_1.yaml'))
    assert 'known_pose:=ground_truth' not in specs[2].argv   # agent_3 is a follower
    assert specs[9].argv == ('/x/simulator', '--ros-args', '-r', '__node:=simulator',
                             '--params-file', str(tmp_path / 'simulator.yaml'))
    assert [s.forward for s in specs] == [False] * 8 + [True, False]


def test_executable_lookup_follows_ros2_run(tmp_path, monkeypatch):
    monkeypatch.delenv(plan.BIN_DIR_ENV, raising=False)
    prefixes = [tmp_path / 'ws1', tmp_path / 'ws2']
    venv_bin = tmp_path / 'venv' / 'bin'
    monkeypatch.setenv('AMENT_PREFIX_PATH', os.pathsep.join(map(str, prefixes)))
    monkeypatch.setattr(sys, 'executable', str(venv_bin / 'python'))
    with pytest.raises(plan.LaunchError, match='scripts/dev.sh setup.*colcon build'):
        plan.find_executable('estimator')
    for exe in (venv_bin / 'estimator', prefixes[1] / 'lib' / plan.PACKAGE / 'estimator'):
        exe.parent.mkdir(parents=True)
        exe.write_text('#!/bin/sh\n')
        exe.chmod(0o755)
        assert plan.find_executable('estimator') == exe   # the colcon install wins
    assert plan.find_executable('estimator', bin_dir=venv_bin) == venv_bin / 'estimator'


def test_bad_command_lines_exit_2(capsys):
    for bad in (['--domain-id', '300'], ['--real-time-factor', '-1'], ['--timeout', '0'],
                ['--duration', 'nan'], ['--discovery-server-port', '0']):
        with pytest.raises(SystemExit) as exc:
            main(['run', str(PAPER), *bad])
        assert exc.value.code == 2
    assert '--domain-id must be in 0..232' in capsys.readouterr().err


def test_a_run_stays_within_the_processes_discovery_connects():
    """Two processes of a domain whose DDS participant ids are both 32 or more never discover
    each other on localhost (BENCHMARKS.md, "Discovery"): a run needs at most 32 processes,
    agents share processes when they must, and a K that needs more is an error naming the
    fix."""
    assert plan.fit_agents_per_process(30, None) == 1                  # 30 + 2 = 32
    assert plan.fit_agents_per_process(31, None) == 2                  # 16 + 2
    assert plan.fit_agents_per_process(30, None, rviz=True) == 2       # fleet_markers too
    assert plan.fit_agents_per_process(100, None) == 4                 # 25 + 2
    assert plan.fit_agents_per_process(100, 8) == 8
    with pytest.raises(plan.LaunchError, match=r'40 agents at 1 per process need 42 '
                       r'processes.*Fix: --agents-per-process 2 or more.*--discovery-server'):
        plan.fit_agents_per_process(40, 1)
    # Through a discovery server every process discovers every other (BENCHMARKS.md, "The
    # discovery server"): any --agents-per-process goes.
    assert plan.fit_agents_per_process(40, 1, discovery_server=True) == 1
    # Left to itself, it still keeps within 32: 64 processes started at once hang in Fast
    # DDS's shared-memory transport, server or not.
    assert plan.fit_agents_per_process(100, None, rviz=True, discovery_server=True) == 4
    assert plan.fit_agents_per_process(100, 8, discovery_server=True) == 8


def test_large_fleets_share_processes(tmp_path, monkeypatch, capsys):
    """`run` on 40 agents runs them 2 per process (a note says why), and with
    --agents-per-process 1 refuses to start, with the fix."""
    big = tmp_path / 'big.yaml'
    assert main(['generate', '--agents', '40', '--out', str(big)]) == 0
    started = []
    monkeypatch.setattr(launch, 'launch_run', lambda scenario, cfg, **_: (
        started.append(cfg), launch.RunResult(ok=False, wall_s=0.0))[1])
    assert main(['run', str(big), '--out', str(tmp_path / 'one'), '--duration', '1',
                 '--agents-per-process', '1']) == 1
    err = capsys.readouterr().err
    assert 'need 42 processes' in err and 'Fix: --agents-per-process 2 or more' in err
    assert not started
    main(['run', str(big), '--out', str(tmp_path / 'out'), '--duration', '1'])
    assert '40 agents run 2 per process' in capsys.readouterr().err
    assert [cfg.agents_per_process for cfg in started] == [2]
    assert started[0].discovery_server is None
    # With its own discovery server: one process per agent, 42 processes.
    for i, extra in enumerate((['--discovery-server'], ['--discovery-server-port', '11811'])):
        assert main(['run', str(big), '--out', str(tmp_path / f'server_{i}'), '--duration', '1',
                     '--agents-per-process', '1', *extra]) == 1   # the stand-in launch_run
        assert 'per process' not in capsys.readouterr().err
    assert [(c.agents_per_process, c.discovery_server) for c in started[1:]] == [(1, 0),
                                                                                 (1, 11811)]


def test_missing_executables_name_the_fix(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(plan.BIN_DIR_ENV, str(tmp_path))
    assert main(['run', str(PAPER), '--out', str(tmp_path / 'out')]) == 1
    assert "cannot find the node executable 'estimator'" in capsys.readouterr().err


# ----------------------------------------------------------------------------- runs
def test_run_succeeds_and_leaves_nothing_behind(standins, tmp_path, monkeypatch, capsys):
    shm = tmp_path / 'shm'
    shm.mkdir()
    monkeypatch.setattr(dds, 'SHM_GLOB', str(shm / 'fastrtps_*'))
    monkeypatch.setenv('STANDIN_SHM', str(shm))
    monkeypatch.setenv('ROS_DOMAIN_ID', '0')
    monkeypatch.setenv('ROS_DISCOVERY_SERVER', '192.0.2.1:11811')   # not this run's
    out = tmp_path / 'out'
    assert main(['run', str(PAPER), '--out', str(out), '--duration', '5']) == 0
    captured = capsys.readouterr()
    recs = records(standins)
    assert set(recs) == {f'agent_{k}' for k in range(1, 9)} | {'simulator', 'monitor'}
    assert_all_gone(recs)
    domain = str(1 + os.getpid() % 101)      # private, not the caller's 0
    for rec in recs.values():
        assert rec['env'] == {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
                              'ROS_DOMAIN_ID': domain, 'ROS_LOG_DIR': str(out / 'logs' / 'ros'),
                              'ROS_DISCOVERY_SERVER': None, 'ROS_SUPER_CLIENT': None}
    assert f'ROS_DOMAIN_ID={domain}' in captured.err
    assert recs['agent_2']['params']['agent'] == 'agent_2'
    assert 'known_pose:=ground_truth' in recs['agent_2']['argv']
    assert recs['monitor']['params']['out_dir'] == str(out)
    # The monitor's progress (and its summary) is forwarded live and kept in its log; `run`
    # adds the files it wrote.
    assert '  t = 2 s progress line' in captured.out
    assert '  t = 2 s progress line' in (out / 'logs' / 'monitor.log').read_text()
    assert str(out / 'summary.json') in captured.out
    assert {p.name for p in (out / 'logs').glob('*.log')} == {f'{n}.log' for n in recs}
    assert 'shared-memory' not in captured.err and 'error' not in captured.err
    # The same fleet for `ros2 launch`: one node per process it started, the same arguments.
    nodes = _launched(out / plan.LAUNCH_FILE)
    assert {n['name'] for n in nodes.values()} == set(recs)
    for name, rec in recs.items():
        assert nodes[name]['argv'] == _ros_args(rec['argv']), name
    env = dict(_env(out / plan.LAUNCH_FILE))
    assert env == {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST', 'ROS_DOMAIN_ID': domain}


def _ros_args(argv: list[str]) -> list[str]:
    """A command line's ROS arguments in launch-file order: remaps (namespace and node name
    included), then parameter files."""
    ros = argv[argv.index('--ros-args') + 1:]
    pairs = list(zip(ros[::2], ros[1::2]))
    return ([f'-r {v}' for f, v in pairs if f == '-r']
            + [f'--params-file {v}' for f, v in pairs if f == '--params-file'])


def _launched(path: Path) -> dict[str, dict]:
    """The nodes of a launch file, by namespace (or name): their exec and arguments."""
    import xml.etree.ElementTree as ET

    out = {}
    for node in ET.parse(path).getroot().iter('node'):
        assert node.get('pkg') == 'bearing_pose_estimation'
        ns, name = node.get('namespace'), node.get('name')
        argv = ([f'-r __ns:=/{ns}'] if ns else []) + [f'-r __node:={name}']
        argv += [f'-r {r.get("from")}:={r.get("to")}' for r in node.iter('remap')]
        argv += [f'--params-file {q.get("from")}' for q in node.iter('param')]
        out[ns or name] = {'name': ns or name, 'exec': node.get('exec'), 'argv': argv}
    return out


def _env(path: Path) -> list[tuple[str, str]]:
    import xml.etree.ElementTree as ET

    return [(e.get('name'), e.get('value')) for e in ET.parse(path).getroot().iter('set_env')]


def test_run_with_its_own_discovery_server(standins, tmp_path, capsys):
    """`--discovery-server`: the server starts first, on 127.0.0.1, and says it runs before any
    node starts; every node gets its address, the simulator (which counts readers in the
    graph) as a super client; the server stops last, cleanly; fleet.launch.xml starts the
    same."""
    out = tmp_path / 'out'
    assert main(['run', str(PAPER), '--out', str(out), '--duration', '5',
                 '--discovery-server']) == 0
    err = capsys.readouterr().err
    recs = records(standins)
    server = recs.pop('discovery_server')
    assert_all_gone({**recs, 'discovery_server': server})
    port = server['argv'][-1]
    assert server['argv'][1:] == ['-i', '0', '-l', '127.0.0.1', '-p', port] and int(port) > 0
    assert f'discovery server on 127.0.0.1:{port}' in err
    assert server['started'] < min(r['started'] for r in recs.values())
    assert server['alive_at_stop'] == []   # every node had exited
    for name, rec in recs.items():
        assert rec['env']['ROS_DISCOVERY_SERVER'] == f'127.0.0.1:{port}', name
        assert rec['env']['ROS_SUPER_CLIENT'] == ('TRUE' if name == 'simulator' else None)
    assert (out / 'logs' / 'discovery_server.log').read_text().startswith(
        '### Server is running ###')
    assert ('ROS_DISCOVERY_SERVER', f'127.0.0.1:{port}') in _env(out / plan.LAUNCH_FILE)
    import xml.etree.ElementTree as ET

    root = ET.parse(out / plan.LAUNCH_FILE).getroot()
    assert [e.get('cmd') for e in root.iter('executable')] == [
        f'fast-discovery-server -i 0 -l 127.0.0.1 -p {port}']
    assert [(n.get('exec'), e.get('name'), e.get('value')) for n in root.iter('node')
            for e in n.iter('env')] == [('simulator', 'ROS_SUPER_CLIENT', 'TRUE')]


def test_a_discovery_server_that_cannot_start_stops_the_run(standins, tmp_path, monkeypatch,
                                                            capsys):
    monkeypatch.setenv('STANDIN_DISCOVERY_SERVER', 'port_in_use')
    assert main(['run', str(PAPER), '--out', str(tmp_path / 'out'),
                 '--discovery-server-port', '11811']) == 1
    err = capsys.readouterr().err
    assert 'error: discovery_server exited with code 1' in err
    assert '| Server creation failed' in err and 'Fix: another --discovery-server-port' in err
    assert records(standins) == {}   # no node started


@pytest.mark.parametrize('behaviour, there_before, warning', [
    ('shm', 'fastrtps_someone_else', 'removed 1 Fast DDS shared-memory file(s)'),
    ('port', 'fastrtps_port7000', None),
])
def test_run_removes_the_shm_files_it_left(standins, tmp_path, monkeypatch, capsys, behaviour,
                                           there_before, warning):
    """A process that never released its DDS participant (e.g. ended by the teardown watchdog)
    leaves Fast DDS files in /dev/shm: the run removes those it created that no process uses,
    says so, and still succeeds. Fast DDS also sometimes keeps a shared port file without its
    lock after every process exited cleanly (often with 20-34 processes, BENCHMARKS.md
    "Discovery"): not a failure, so no warning, but the run does not leave it behind either.
    Files that were there before the run are not touched."""
    shm = tmp_path / 'shm'
    shm.mkdir()
    (shm / there_before).write_text('')
    monkeypatch.setattr(dds, 'SHM_GLOB', str(shm / 'fastrtps_*'))
    monkeypatch.setenv('STANDIN_SHM', str(shm))
    monkeypatch.setenv('STANDIN_SIMULATOR', behaviour)
    assert main(['run', str(PAPER), '--out', str(tmp_path / 'out'), '--duration', '5']) == 0
    err = capsys.readouterr().err
    if warning:
        assert warning in err
    else:
        assert 'shared-memory' not in err
    assert sorted(p.name for p in shm.iterdir()) == [there_before]


def test_a_teardown_ended_by_the_watchdog_counts_as_clean(standins, tmp_path, monkeypatch,
                                                         capsys):
    """A node whose DDS teardown deadlocked (Fast DDS, after its work was done) is ended by
    its watchdog with SIGALRM: the run says so, removes what its participant left in /dev/shm,
    and succeeds. Any other signal is a failure (below)."""
    shm = tmp_path / 'shm'
    shm.mkdir()
    monkeypatch.setattr(dds, 'SHM_GLOB', str(shm / 'fastrtps_*'))
    monkeypatch.setenv('STANDIN_SHM', str(shm))
    monkeypatch.setenv('STANDIN_AGENT_4', 'teardown_hung')
    assert main(['run', str(PAPER), '--out', str(tmp_path / 'out'), '--duration', '5']) == 0
    err = capsys.readouterr().err
    assert ('note: estimator agent_4 was ended by its teardown watchdog: its work was done, '
            'then deleting its DDS participant hung') in err
    assert 'removed 1 Fast DDS shared-memory file(s)' in err
    assert list(shm.iterdir()) == []
    assert_all_gone(records(standins))


@pytest.mark.parametrize('culprit, behaviour, message', [
    ('SIMULATOR', 'shm', 'error: the run left 1 file(s) in /dev/shm that could not be removed'),
    ('AGENT_5', 'unclean', 'error: estimator agent_5 exited with code 1 when stopped at the '
                           'end of the run'),
    ('AGENT_6', 'stubborn', 'error: estimator agent_6 was killed by SIGKILL when stopped'),
])
def test_run_that_does_not_stop_cleanly_fails(standins, tmp_path, monkeypatch, capsys,
                                              culprit, behaviour, message):
    """The monitor finished and wrote its outputs, but a process left Fast DDS files in
    /dev/shm that cannot be removed, exited non-zero, or needed SIGKILL when stopped: the run
    is reported as failed (exit 1), with the cure for /dev/shm."""
    shm = tmp_path / 'shm'
    shm.mkdir()
    monkeypatch.setattr(dds, 'SHM_GLOB', str(shm / 'fastrtps_*'))
    monkeypatch.setenv('STANDIN_SHM', str(shm))
    monkeypatch.setenv(f'STANDIN_{culprit}', behaviour)
    if behaviour == 'shm':  # a file the run may not remove
        monkeypatch.setattr(dds, '_remove', lambda path: None)
    monkeypatch.setattr(launch.ProcessGroup, 'shutdown',
                        functools.partialmethod(launch.ProcessGroup.shutdown, grace=0.5,
                                                term_grace=0.5))
    out = tmp_path / 'out'
    assert main(['run', str(PAPER), '--out', str(out), '--duration', '5']) == 1
    err = capsys.readouterr().err
    assert message in err
    if behaviour == 'shm':
        assert 'shm clean' in err
    assert (out / 'summary.json').exists()
    assert_all_gone(records(standins))


def test_a_robot_that_dies_is_reported_and_can_be_started_again(standins, tmp_path,
                                                               monkeypatch, capsys):
    """An estimator that crashes does not end the run: the run says which, how, and the
    command that starts it again (written to logs/restart_<name>.sh: its command line and DDS
    environment). Started again with it, the robot runs until the run's end, which stops it
    too. The run's exit code (3) and summary.json (deaths) say what happened."""
    monkeypatch.setenv('STANDIN_AGENT_3', 'crash')
    monkeypatch.setenv('STANDIN_CRASH_AFTER', 'simulator')   # once the clock runs
    monkeypatch.setenv('STANDIN_MONITOR_UNTIL', str(tmp_path / 'the_end'))
    out = tmp_path / 'out'
    script = out / 'logs' / 'restart_agent_3.sh'
    first: dict = {}

    def robot_started_again() -> None:   # the user, in another terminal
        deadline = time.monotonic() + 60
        while not script.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        first.update(records(standins)['agent_3'])
        (standins / 'agent_3.json').unlink()
        subprocess.Popen(['sh', str(script)], env={**os.environ, 'STANDIN_AGENT_3': 'loop'})
        wait_for_records(standins, 10, timeout=30)
        (tmp_path / 'the_end').touch()

    user = threading.Thread(target=robot_started_again)
    user.start()
    try:
        assert main(['run', str(PAPER), '--out', str(out), '--domain-id', '77']) == 3
    finally:
        (tmp_path / 'the_end').touch()
        user.join()
    err = capsys.readouterr().err
    assert 'warning: estimator agent_3 exited with code 3' in err and 'run goes on' in err
    assert '| boom: something went wrong' in err
    assert f'sh {script}' in err
    recs = records(standins)
    again = recs['agent_3']
    assert again['pid'] != first['pid'] and again['argv'] == first['argv']
    assert again['env'] == first['env'] and again['env']['ROS_DOMAIN_ID'] == '77'
    assert_all_gone(recs)   # the one started again by hand too
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['complete'] is True   # the monitor was not stopped
    assert [(d['process'], d['how'], d['running_again_at_the_end'])
            for d in summary['deaths']] == [('agent_3', 'exited with code 3', True)]
    assert f'started again by hand, running until the end (pid {again["pid"]})' in err


def test_a_robot_that_cannot_start_ends_the_run(standins, tmp_path, monkeypatch, capsys):
    """An estimator that ends before the simulator started the clock did not start (a bad
    parameter, a crash at start-up): the run cannot begin, and ends at once with its log."""
    monkeypatch.setenv('STANDIN_AGENT_3', 'crash')
    monkeypatch.setenv('STANDIN_SIMULATOR', 'no_clock')
    monkeypatch.setenv('STANDIN_MONITOR_DELAY', '60')
    t0 = time.monotonic()
    assert main(['run', str(PAPER), '--out', str(tmp_path / 'out')]) == 1
    assert time.monotonic() - t0 < 45   # not when the monitor would finish (60 s here)
    err = capsys.readouterr().err
    assert 'estimator agent_3 exited with code 3 before the clock started' in err
    assert '| boom: something went wrong' in err and 'restart_agent_3.sh' not in err
    assert_all_gone(records(standins))


def test_the_simulator_dying_ends_the_run(standins, tmp_path, monkeypatch, capsys):
    """Without the simulator (the clock, the truth and the sensors) nothing can go on: its
    death ends the run at once, and every process is stopped (the monitor writes what it
    has)."""
    monkeypatch.setenv('STANDIN_SIMULATOR', 'crash')
    monkeypatch.setenv('STANDIN_MONITOR_DELAY', '60')
    out = tmp_path / 'out'
    t0 = time.monotonic()
    assert main(['run', str(PAPER), '--out', str(out), '--domain-id', '77']) == 1
    # Reported as soon as it happens, not when the monitor would finish (60 s here).
    assert time.monotonic() - t0 < 45
    err = capsys.readouterr().err
    assert 'simulator exited with code 3 early' in err
    assert '| boom: something went wrong' in err
    assert_all_gone(records(standins))
    assert json.loads((out / 'summary.json').read_text())['complete'] is False


def test_timeout_stops_the_run(standins, small, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv('STANDIN_MONITOR_DELAY', '60')
    assert main(['run', str(small), '--out', str(tmp_path / 'out'), '--timeout', '1']) == 1
    err = capsys.readouterr().err
    assert 'monitor did not finish within the 1 s timeout' in err
    # Whoever hung says so in its log: every process's last lines are shown.
    logs = tmp_path / 'out' / 'logs'
    for name in ('simulator', 'monitor'):
        assert f'line(s) of {logs / name}.log:' in err, err
    assert_all_gone(records(standins))


def test_shutdown_escalates_and_reports_sigkill(standins, tmp_path, monkeypatch, capsys):
    """SIGINT, then SIGTERM, then SIGKILL (named loudly); a grandchild left in a child's
    process group is stopped too."""
    params = tmp_path / 'p.yaml'
    params.write_text('/x:\n  ros__parameters: {}\n')
    exe = Path(os.environ[plan.BIN_DIR_ENV]) / 'simulator'
    behaviours = ['loop', 'deaf', 'stubborn', 'spawn']
    for b in behaviours:
        monkeypatch.setenv(f'STANDIN_{b.upper()}', b)
    with launch.ProcessGroup() as group:
        for b in behaviours:
            group.start(plan.ProcessSpec(b, 'standin', (str(exe), '--ros-args', '-r',
                                         f'__node:={b}', '--params-file', str(params)),
                                         tmp_path / 'logs' / f'{b}.log'))
        recs = wait_for_records(standins, len(behaviours))
        assert launch.alive(recs['spawn']['grandchild'])
        killed = group.shutdown(grace=0.5, term_grace=0.5)
    assert killed == ['stubborn']
    assert group.returncode('loop') == 0
    assert group.returncode('deaf') == -signal.SIGTERM
    assert group.returncode('stubborn') == -signal.SIGKILL
    err = capsys.readouterr().err
    assert 'sending SIGTERM: ' in err and 'standin stubborn' in err
    assert 'KILLING it with SIGKILL' in err
    assert_all_gone(recs)


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_interrupting_run_stops_every_child(standins, small, tmp_path, monkeypatch, sig):
    monkeypatch.setenv('STANDIN_MONITOR_DELAY', '60')
    out = tmp_path / 'out'
    run = subprocess.Popen([sys.executable, '-m', 'bearing_pose_estimation.cli.main', 'run',
                            str(small), '--out', str(out)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        recs = wait_for_records(standins, 5)
        run.send_signal(sig)
        stdout, stderr = run.communicate(timeout=20)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 130, stderr
    assert 'interrupted: all processes stopped' in stderr
    assert '  t = 0 s progress line' in stdout
    assert_all_gone(recs)
    assert json.loads((out / 'summary.json').read_text())['complete'] is False


def test_leaked_shm_ignores_files_live_processes_use(tmp_path, monkeypatch):
    """Only orphans count as leaks: another program's live segment (here, held open by this
    process) does not, so the check works beside other ROS programs and test runs."""
    monkeypatch.setattr(dds, 'SHM_GLOB', str(tmp_path / 'fastrtps_*'))
    before = dds.shm_files()
    live = tmp_path / 'fastrtps_port7001_el'
    orphan = tmp_path / 'fastrtps_0123abcd'
    live.write_bytes(b'\0')
    orphan.write_bytes(b'\0')
    port = tmp_path / 'fastrtps_port7002'  # Fast DDS's own lock-less port file: not a leak
    port.write_bytes(b'\0')
    with live.open('rb'):
        assert dds.leaked_shm(before) == [str(orphan)]
    assert dds.leaked_shm(before) == sorted([str(live), str(orphan)])
