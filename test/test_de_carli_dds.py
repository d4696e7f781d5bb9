"""De Carli et al. over DDS: the paper's eight quadrotors (exogenous motion) with robot 7
hovering, one process per robot plus the simulator and the monitor, observed from the test
process. One fleet, several checks:

- the errors equal the batch simulator's to 1e-6 (the issue's acceptance: within 5 %);
- the messages on the wire: ẑ_i as a complex number in the fleet's estimation frame, the
  owners' relative yaws in their body frames;
- the pose with its covariance (de_carli_covariance.py, a noise model given) on `pose`, the
  batch simulator's to 1 % (a neighbour's covariance is its newest, not waited for);
- /diagnostics reports each pair's excitation: the pairs only robot 7's motion could excite are
  left out and not excited, the others are in and excited; |ẑ_i| and the stage of each robot.
"""
import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray

from bearing_pose_estimation import msg_defs as wire
from bearing_pose_estimation.msg_defs import cdr
from bearing_pose_estimation.cli import launch
from bearing_pose_estimation.plan.dds import CLEAN_EXITS, dds_env, shm_files
from bearing_pose_estimation.plan.processes import (RunConfig, find_executable, plan_processes,
                                                    write_params)
from bearing_pose_estimation.scenario import load_scenario
from bearing_pose_estimation.scenario.parse import read_scenario_data
from bearing_pose_estimation.sim.batch import BatchSimulator
from bearing_pose_estimation.studies.summary import read_metrics_csv

from ros_helpers import (PATIENT, assert_equals_netsim, assert_no_shm_left, observer,
                         with_parameters)

pytestmark = pytest.mark.dds

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'de_carli_8_quadrotors.yaml'
DOMAIN = int(os.environ['ROS_DOMAIN_ID'])
DURATION = 2.0
# Subscribed once the run is going: the simulator starts when every estimator's topics have
# their expected subscribers, and an early observer would count as one of them.
LATE_TOPICS = {'/robot_0/yaw_estimate': (wire.Vector3Stamped, wire.ESTIMATE_QOS),
               '/robot_0/relative_yaws': (wire.PointCloud2, wire.ESTIMATE_QOS),
               '/robot_0/pose': (wire.PoseWithCovarianceStamped, wire.ESTIMATE_QOS)}
# The covariance's noise model (the scenario has no noise; of the estimate, only the excitation
# monitor reads it: a pair joins the consensus a few steps later).
MODEL = {'relative_position_std': 0.02, 'odometry_noise_density': 1.4e-3,
         'gyro_noise_density': 3.5e-4}


@pytest.fixture(scope='module')
def run(tmp_path_factory):
    """The fleet's run to its end: (scenario file, output dir, observer's messages)."""
    tmp = tmp_path_factory.mktemp('de_carli_dds')
    data = read_scenario_data(CONFIG)
    data['formation_control']['mode'] = 'exogenous'
    for agent in data['agents']:
        if agent['name'] == 'robot_7':
            del agent['formation_position']   # it hovers
    data['gains'].update(MODEL)
    scenario_file = tmp / 'hover.yaml'
    scenario_file.write_text(yaml.safe_dump(data, sort_keys=False))
    scenario = load_scenario(scenario_file)
    cfg = RunConfig(scenario_file=scenario_file, out_dir=tmp / 'out', duration=DURATION,
                    domain_id=DOMAIN, plots=False)
    cfg.logs_dir.mkdir(parents=True)
    params = with_parameters(write_params(scenario, cfg), list(scenario.index), **PATIENT)
    specs = plan_processes(scenario, params, cfg.logs_dir,
                           find_executable)
    shm = shm_files()
    with observer() as obs, launch.ProcessGroup(env=dds_env(DOMAIN, tmp / 'ros')) as g:
        obs.subscribe(DiagnosticArray, '/diagnostics', 50)
        for spec in specs:
            g.start(spec)
        assert obs.spin_until(lambda: _state_time(obs.messages, 'robot_0') > 0.5, 300.0)
        for name, (msg_type, qos) in LATE_TOPICS.items():
            obs.subscribe(msg_type, name, qos)
        assert obs.spin_until(lambda: g.returncode('monitor') is not None, 300.0), \
            'the monitor did not finish'
        assert g.returncode('monitor') in CLEAN_EXITS
        g.shutdown()
        assert g.unclean() == {}
    assert_no_shm_left(g, shm)
    return scenario_file, cfg.out_dir, obs.messages


def test_the_fleet_reproduces_the_batch_simulator(run):
    """Every 0.1 s record equals the batch run's to 1e-6 (the issue asked for 5 %): in lockstep
    every step waits for all its inputs, so the fleet computes what the batch simulator does,
    down to rounding and the wire's float64 quaternion (1e-12 rad). A step that goes on
    without a value (an owner's relative yaw that was never sent, a reader matched after the
    first values: each cost 5 % at t = 0.2 s; a neighbour taken as silent before its first
    values arrive: 7e-4 from t = 0.1 s) breaks it, and its count says which."""
    scenario_file, out, messages = run
    dds = read_metrics_csv(out / 'metrics.csv')
    rec = BatchSimulator(load_scenario(scenario_file)).run(DURATION, record_every=0.1)
    np.testing.assert_allclose(dds.t, rec.t, atol=1e-9)
    att_b, pos_b = rec.mean_errors()
    att_d, pos_d = dds.mean_errors()
    final = {s.name: {kv.key: kv.value for kv in s.values}
             for m in messages['/diagnostics'] for s in m.status if s.name.endswith('/estimator')}
    assert len(final) == 8
    for name, values in final.items():   # every step had every input of its instant
        assert values.get('event_impatient_steps', '0') == '0', name
        assert values['carried'] == '0' and values['incomplete_steps'] == '0', name
        assert values.get('odometry_missing_steps', '0') == '0', name
        assert not [k for k in values if k.startswith(('missing_', 'rejected_'))], values
    np.testing.assert_allclose(pos_d, pos_b, rtol=1e-6)
    np.testing.assert_allclose(att_d, att_b, rtol=1e-6, atol=1e-12)
    assert pos_d[-1] < 0.1 * pos_d[0] and att_d[-1] < 1e-6


def test_the_fleet_equals_netsim(run):
    """The same agent runtime without DDS (netsim) gives every record to metrics.csv's
    rounding: the nodes' inputs, pairing and steps are netsim's."""
    scenario_file, out = run[0], run[1]
    assert_equals_netsim(out / 'metrics.csv', scenario_file)


def test_yaw_estimates_travel_as_complex_numbers_in_the_estimation_frame(run):
    scenario_file, _, messages = run
    frame = wire.estimation_frame(load_scenario(scenario_file).name)
    yaws = messages['/robot_0/yaw_estimate']
    assert yaws and {m.header.frame_id for m in yaws} == {frame}
    moduli = [np.hypot(m.vector.x, m.vector.y) for m in yaws]
    assert min(moduli) < 0.99 and all(m.vector.z == 0.0 for m in yaws)   # ẑ, not an angle
    stamps = sorted(wire.from_stamp(m.header.stamp) for m in yaws)
    assert np.allclose(np.diff(stamps)[:20], 0.01)   # at the consensus rate, 100 Hz
    pairs = messages['/robot_0/relative_yaws']
    assert pairs and {m.header.frame_id for m in pairs} == {'robot_0/base_link'}
    # robot_0 (id 1) owns only the two-way pair with robot_1 (id 2, the lower id owns it):
    # robots 3 and 4 sense robot_0 and own theirs. One unit complex number, for robot_1.
    _, ids, values = cdr.decode_vectors_raw(pairs[-1])
    assert ids.tolist() == [2]
    assert abs(np.hypot(values[0, 0], values[0, 1]) - 1.0) < 1e-12 and values[0, 2] == 0.0


def test_the_pose_carries_the_batch_simulator_s_covariance(run):
    scenario_file, _, messages = run
    frame = wire.estimation_frame(load_scenario(scenario_file).name)
    poses = messages['/robot_0/pose']
    assert poses and {m.header.frame_id for m in poses} == {frame}
    t, P = cdr.decode_covariance_raw(poses[-1])
    sim = BatchSimulator(load_scenario(scenario_file))
    while sim.t < t - 1e-9:
        sim.step()
    assert sim.t == pytest.approx(t, abs=1e-9)
    assert np.all(P[3:5] == 0.0) and np.all(P[:, 3:5] == 0.0)   # roll and pitch known
    # 7e-5 measured: the neighbours' covariances are their newest, a publish period old at
    # most, and change slowly.
    assert np.linalg.norm(P - sim.x.P[0]) < 1e-2 * np.linalg.norm(sim.x.P[0]), (P, sim.x.P[0])


def _state_time(messages, robot: str) -> float:
    value = _last_status(messages, robot).get('state_time_s', 'n/a')
    return -1.0 if value == 'n/a' else float(value)


def _last_status(messages, robot: str) -> dict[str, str]:
    for msg in reversed(messages['/diagnostics']):
        for st in msg.status:
            if st.name == f'{robot}/estimator':
                return {kv.key: kv.value for kv in st.values}
    return {}


def test_diagnostics_report_each_pair_s_excitation(run):
    """Robot 7 hovers: robots 4 and 6 report their pairs with it left out of the consensus and
    not excited (their edges sense robot 7 alone, which has not moved), robot 3 its pair with
    robot 7 in and excited (robot 3 moves); every robot reports |ẑ_i| and its stage."""
    _, _, messages = run
    for robot, other, excited in (('robot_4', 'robot_7', False), ('robot_6', 'robot_7', False),
                                  ('robot_3', 'robot_7', True), ('robot_0', 'robot_1', True)):
        status = _last_status(messages, robot)
        value = status[f'excitation_{other}']
        assert value.endswith('not excited now') != excited, (robot, value)
        assert (float(value.split()[0]) > 0.0) == excited, (robot, value)
        assert ('in the consensus' in value) == excited, (robot, value)
        assert ('left out' in value) != excited, (robot, value)
        assert 0.0 < float(status['z_modulus']) <= 1.0
        assert status['stage'] in ('relative_yaw', 'yaw', 'position', 'converged')


def test_robots_sharing_a_process_step_together_to_the_same_records(run, tmp_path):
    """Four robots per `estimators` process, as `--agents-per-process 4` plans them: each
    process runs its robots' steps in one call of the method's step (ros/step_batch.py), and
    every record equals the one-process-per-robot fleet's (the fixed exchange makes both
    independent of when messages arrive; patient, as the fixture's: a loaded machine can stall
    a process past the default neighbour_wait)."""
    scenario_file, out, _ = run
    scenario = load_scenario(scenario_file)
    cfg = RunConfig(scenario_file=scenario_file, out_dir=tmp_path / 'shared', duration=DURATION,
                    domain_id=DOMAIN, plots=False)
    cfg.logs_dir.mkdir(parents=True)
    params = with_parameters(write_params(scenario, cfg), list(scenario.index), **PATIENT)
    specs = plan_processes(scenario, params, cfg.logs_dir, find_executable,
                           agents_per_process=4)
    shm = shm_files()
    with launch.ProcessGroup(env=dds_env(DOMAIN, tmp_path / 'ros')) as g:
        for spec in specs:
            g.start(spec)
        failure = g.wait_for('monitor', 300.0, watch=[s.name for s in specs])
        assert failure is None, failure
        g.shutdown()
        assert g.unclean() == {}
    assert_no_shm_left(g, shm)
    alone, together = (read_metrics_csv(d / 'metrics.csv') for d in (out, cfg.out_dir))
    np.testing.assert_array_equal(together.t, alone.t)
    np.testing.assert_allclose(together.pos_err, alone.pos_err, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(together.att_err, alone.att_err, rtol=1e-9, atol=1e-15)
    for log in ('estimators_0.log', 'estimators_1.log'):
        text = (cfg.logs_dir / log).read_text()
        per_round = float(text.split(' agents per round)')[0].rsplit('(', 1)[1])
        assert per_round > 1.5, (log, text[-300:])