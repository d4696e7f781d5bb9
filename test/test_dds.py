"""The distributed system over DDS: real node processes, observed from the test process.

Each test starts the very executables `bearing-pose run` (and `ros2 run`) start, on loopback and
this run's private ROS_DOMAIN_ID (see conftest.py), and stops them with SIGINT.
"""
import csv
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from bearing_pose_estimation import launch
from bearing_pose_estimation import msg_defs as wire
from bearing_pose_estimation.cli import main
from bearing_pose_estimation.scenario import load_scenario
from bearing_pose_estimation.simulator import BatchSimulator
from rosgraph_msgs.msg import Clock

from ros_helpers import observer

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'
DOMAIN = int(os.environ['ROS_DOMAIN_ID'])

THREE_AGENTS = {
    'name': 'wire_test', 'leaders': ['agent_1', 'agent_2'],
    'initial_estimates': {'random': {'seed': 1, 'position_std': 1.0, 'max_angle_deg': 60}},
    'agents': [
        {'name': 'agent_1', 'position': [0, 0, 0], 'angular_velocity': [1, -2, 1]},
        {'name': 'agent_2', 'position': [2, 0, 0],
         'angular_velocity': [{'cos': 3, 'amplitude': -1}, 1, {'sin': 2}]},
        {'name': 'agent_3', 'position': [1, 2, 0], 'angular_velocity': [0.5, 1, {'sin': 9}],
         'neighbours': ['agent_1', 'agent_2']}]}


@pytest.fixture()
def no_leftovers():
    """Every test here must leave no process and no Fast DDS file in /dev/shm."""
    before = launch.shm_files()
    yield
    assert launch.leaked_shm(before) == [], 'Fast DDS files left in /dev/shm'


def _start(group: launch.ProcessGroup, scenario_file: Path, out: Path, duration: float,
           monitor: bool, real_time_factor: float = 0.0) -> None:
    scenario = load_scenario(scenario_file)
    cfg = launch.RunConfig(scenario_file=scenario_file, out_dir=out, duration=duration,
                           domain_id=DOMAIN, plots=False, real_time_factor=real_time_factor)
    cfg.logs_dir.mkdir(parents=True, exist_ok=True)
    specs = launch.plan_processes(scenario, launch.write_params(scenario, cfg), cfg.logs_dir,
                                  launch.find_executable)
    for spec in specs:
        if spec.kind == 'monitor' and not monitor:
            continue
        if spec.kind == 'simulator' and not monitor:
            spec = launch.ProcessSpec(spec.name, spec.kind,
                                      spec.argv + ('-p', 'wait_for_monitor:=false'), spec.log)
        group.start(spec)


def test_messages_on_the_wire(tmp_path, no_leftovers):
    """Types, frames and stamps as msg_defs documents them, and the time consistency of what a
    leader sends: R̂_1 b^1_13 must be the true world bearing at every stamp, although agent_1
    spins at |ω| = 2.4 rad/s (pairing two instants 20 ms apart would be off by ~0.05)."""
    scenario_file = tmp_path / 'three.yaml'
    scenario_file.write_text(yaml.safe_dump(THREE_AGENTS))
    env = launch.dds_env(DOMAIN, tmp_path / 'ros_logs')
    topics = {
        '/agent_3/imu': (wire.Imu, wire.SENSOR_QOS),
        '/agent_3/bearings': (wire.PointCloud2, wire.SENSOR_QOS),
        '/agent_3/estimate': (wire.PoseStamped, wire.ESTIMATE_QOS),
        '/agent_1/world_bearings': (wire.PointCloud2, wire.ESTIMATE_QOS),
        '/agent_1/ground_truth': (wire.PoseStamped, wire.SIM_PUB_QOS),
        '/clock': (Clock, wire.CLOCK_QOS),
    }
    with observer() as obs, launch.ProcessGroup(env=env) as group:
        for name, (msg_type, qos) in topics.items():
            obs.subscribe(msg_type, name, qos)
        # Real-time pacing: a lockstep run goes several times faster than this observer reads.
        _start(group, scenario_file, tmp_path / 'out', duration=30.0, monitor=False,
               real_time_factor=1.0)

        def enough() -> bool:
            # The simulator does not wait for this observer, and under load discovery of each
            # participant can lag: wait until every source has delivered a second of data.
            m = obs.messages
            est, imu = m['/agent_3/estimate'], m['/agent_3/imu']
            return (len(imu) > 100 and len(m['/agent_1/world_bearings']) > 30
                    and all(len(m[t]) > 10 for t in topics)
                    and wire.from_stamp(est[-1].header.stamp)
                    >= wire.from_stamp(est[0].header.stamp) + 1.0)
        assert obs.spin_until(enough, timeout=120), {k: len(v) for k, v in obs.messages.items()}
        group.shutdown()
        codes = {n: group.returncode(n) for n in group.pids}
        bad = {n: c for n, c in codes.items() if c != 0}
        logs = tmp_path / 'out' / 'logs'
        assert not bad, '\n'.join(f'{n} exited {c}:\n' + '\n'.join(launch.log_tail(logs / f'{n}.log', 40))
                                   for n, c in bad.items())

    m = obs.messages
    imu = m['/agent_3/imu']
    stamps = np.array([wire.from_stamp(x.header.stamp) for x in imu])
    assert np.all(np.diff(stamps) > 0)
    np.testing.assert_allclose(np.round(stamps / 0.005) * 0.005, stamps, atol=1e-9)  # 200 Hz
    assert {x.header.frame_id for x in imu} == {'agent_3/base_link'}
    assert imu[0].orientation_covariance[0] == -1.0

    bearings = m['/agent_3/bearings']
    assert {x.header.frame_id for x in bearings} == {'agent_3/base_link'}
    t, ids, vectors = wire.decode_vectors(bearings[-1])
    assert sorted(ids.tolist()) == [1, 2]
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-12)

    est = m['/agent_3/estimate']
    assert {x.header.frame_id for x in est} == {'world'}
    est_stamps = np.array([wire.from_stamp(x.header.stamp) for x in est])
    np.testing.assert_allclose(np.round(est_stamps / 0.02) * 0.02, est_stamps, atol=1e-9)

    truth = m['/agent_1/ground_truth']
    assert truth and {x.header.frame_id for x in truth} == {'world'}
    b_13 = np.array([1.0, 2.0, 0.0]) / np.sqrt(5.0)
    checked = 0
    for msg in m['/agent_1/world_bearings']:
        assert msg.header.frame_id == 'world'
        t, ids, vectors = wire.decode_vectors(msg)
        if t > 0.0:
            row = dict(zip(ids.tolist(), vectors))
            assert sorted(row) == [3]  # a leader senses only its listeners
            np.testing.assert_allclose(row[3], b_13, atol=1e-9)
            checked += 1
    assert checked > 20
    clock = [wire.from_stamp(c.clock) for c in m['/clock']]
    assert clock and np.all(np.diff(clock) > 0)


def _read_metrics(path: Path) -> dict[float, tuple[float, float]]:
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    return {round(float(r['t']), 6): (float(r['attitude_error_mean_rad']),
                                      float(r['position_error_mean_m'])) for r in rows}


def _assert_tracks_batch(dds: dict[float, tuple[float, float]], scenario_file: Path,
                         times: tuple[float, ...]) -> None:
    """Mean attitude and position errors of a DDS run within 10 % of the batch simulator's."""
    rec = BatchSimulator(load_scenario(scenario_file)).run(max(times), record_every=0.1)
    for t in times:
        k = int(round(t / 0.1))
        att_b, pos_b = rec.att_err[k].mean(), rec.pos_err[k].mean()
        assert abs(dds[t][0] - att_b) <= 0.1 * att_b, (t, dds[t][0], att_b)
        assert abs(dds[t][1] - pos_b) <= 0.1 * pos_b, (t, dds[t][1], pos_b)


def test_paper_scenario_converges_over_dds_like_the_batch_simulator(tmp_path, no_leftovers):
    """One process per agent plus simulator and monitor, through `bearing-pose run`: the mean
    errors track the batch simulator within 10 % (the issue's acceptance, here at 10 s and
    20 s to keep the suite short; the 60 s figures are in the README)."""
    out = tmp_path / 'run'
    assert main(['run', str(PAPER), '--duration', '20', '--out', str(out),
                 '--domain-id', str(DOMAIN), '--no-plots']) == 0
    dds = _read_metrics(out / 'metrics.csv')
    rec = BatchSimulator(load_scenario(PAPER)).run(20.0, record_every=0.1)
    for t in (10.0, 20.0):
        k = int(round(t / 0.1))
        att_b, pos_b = rec.att_err[k].mean(), rec.pos_err[k].mean()
        att_d, pos_d = dds[t]
        assert abs(att_d - att_b) <= max(0.1 * att_b, 1e-4), (t, att_d, att_b)
        assert abs(pos_d - pos_b) <= max(0.1 * pos_b, 1e-4), (t, pos_d, pos_b)
    assert dds[20.0][0] < 1e-3 and dds[20.0][1] < 0.15
    assert sorted((out / 'params').glob('*.yaml'))
    assert launch.live_process_groups() is not None  # /proc readable: no_leftovers is meaningful


def test_several_agents_per_process(tmp_path, no_leftovers):
    """`--agents-per-process 4`: two `estimators` processes host the eight agents' nodes; the
    run tracks the batch simulator as closely as one process per agent does."""
    out = tmp_path / 'run'
    assert main(['run', str(PAPER), '--duration', '10', '--out', str(out), '--agents-per-process',
                 '4', '--domain-id', str(DOMAIN), '--no-plots']) == 0
    assert sorted(p.name for p in (out / 'logs').glob('estimators_*.log')) == [
        'estimators_0.log', 'estimators_1.log']
    _assert_tracks_batch(_read_metrics(out / 'metrics.csv'), PAPER, (5.0, 10.0))


def test_tran_method_converges_over_dds_like_the_batch_simulator(tmp_path, no_leftovers):
    """method: tran_anderson_ahn over DDS (four agents per process, to keep it short): the
    nodes run Tran, Anderson & Ahn's observer and track the batch simulator within 10 %."""
    data = yaml.safe_load(PAPER.read_text())
    data['method'] = 'tran_anderson_ahn'
    data['gains'] = {'k_omega': 2.0, 'k_c': 1.0, 'k_p': 1.0}
    scenario_file = tmp_path / 'tran.yaml'
    scenario_file.write_text(yaml.safe_dump(data, sort_keys=False))
    out = tmp_path / 'run'
    assert main(['run', str(scenario_file), '--duration', '10', '--out', str(out),
                 '--agents-per-process', '4', '--domain-id', str(DOMAIN), '--no-plots']) == 0
    assert 'k_omega=2' in (out / 'logs' / 'estimators_0.log').read_text()
    dds = _read_metrics(out / 'metrics.csv')
    _assert_tracks_batch(dds, scenario_file, (5.0, 10.0))
    assert dds[10.0][0] < 0.1 * dds[0.0][0]
