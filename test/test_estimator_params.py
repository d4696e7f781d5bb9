"""The nodes' parameters: the estimator without a scenario file (what a real robot may use),
the types a ROS parameter file gives, and the errors and warnings a user sees. Built in-process
(no other node needed), except where the real executable's output is what matters."""
import os
import subprocess
import time

import numpy as np
import pytest
import yaml
from rclpy.parameter import Parameter

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.estimators.base import Sensor
from bearing_pose_estimation import msg_defs as wire
from bearing_pose_estimation.msg_defs import cdr
from bearing_pose_estimation.plan import dds
from bearing_pose_estimation.plan import processes as plan
from bearing_pose_estimation.ros.estimator_node import EstimatorNode
from bearing_pose_estimation.ros.node_main import parameter_overrides
from bearing_pose_estimation.estimators.boughellaba_tayebi import CascadeGains
from bearing_pose_estimation.scenario import ScenarioError
from bearing_pose_estimation.ros.simulator_node import SimulatorNode
from bearing_pose_estimation.estimators.tran_anderson_ahn import TranGains

pytestmark = pytest.mark.dds


def _node(context, **params):
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    return EstimatorNode(namespace='/agent_5', context=context, parameter_overrides=overrides)


EXPLICIT = dict(agent_id=5, neighbours=['agent_1', 'agent_4'], neighbour_ids=[1, 4],
                neighbour_gains=[2.0, 1.0], initial_position=[1.0, 2.0, 3.0],
                initial_orientation=[0.0, 0.0, np.sin(0.25), np.cos(0.25)],
                k_R=1.5, frequency=200.0)


def test_explicit_parameters_build_the_estimator(context):
    node = _node(context, **EXPLICIT)
    try:
        est = node.rt
        assert node.agent == 'agent_5' and est.agent_id == 5 and not est.leader
        assert [(n.name, n.agent_id, n.k) for n in est.peers] == [
            ('agent_1', 1, 2.0), ('agent_4', 4, 1.0)]
        assert est.gains.k_R == 1.5 and est.gains.k_p == 1.0 and est.h == pytest.approx(0.005)
        np.testing.assert_allclose(est.R_hat[0], so3.axis_angle([0, 0, 1], 0.5), atol=1e-12)
        np.testing.assert_array_equal(est.p_hat[0], [1.0, 2.0, 3.0])
        subs = [s.topic_name for s in node.subscriptions]
        assert {'/agent_5/imu', '/agent_5/bearings', '/agent_1/pose',
                '/agent_1/world_bearings', '/agent_4/pose',
                '/agent_4/world_bearings'} <= set(subs)
        # One message per neighbour and period carries p̂_j and P_j: not its estimate too.
        assert subs.count('/agent_1/pose') == 1 and '/agent_1/estimate' not in subs
    finally:
        node.destroy_node()


def test_agents_sharing_a_process_read_the_clock_once(context):
    """An `estimators` process under use_sim_time subscribes to /clock once: the first agent's
    time source sets every agent's clock. An agent on wall time keeps its own clock."""
    from rosgraph_msgs.msg import Clock

    from bearing_pose_estimation.ros.estimator_group import share_clock

    nodes = [EstimatorNode(namespace=f'/agent_{i}', context=context, parameter_overrides=[
        Parameter(k, value=v) for k, v in {**EXPLICIT, 'agent_id': i,
                                           'use_sim_time': i < 8}.items()])
        for i in (5, 6, 7, 8)]
    try:
        clock_subs = lambda: [n.get_name() + n.get_namespace() for n in nodes  # noqa: E731
                              for sub in n.subscriptions if sub.topic_name == '/clock']
        assert len(clock_subs()) == 3      # rclpy's default: one per node on simulated time
        share_clock(nodes)
        assert clock_subs() == ['estimator/agent_5']
        on_clock = next(sub for sub in nodes[0].subscriptions if sub.topic_name == '/clock')
        on_clock.callback(Clock(clock=wire.to_stamp(12.5)))
        assert [n.get_clock().now().nanoseconds for n in nodes[:3]] == [12_500_000_000] * 3
        assert nodes[3].get_clock().now().nanoseconds > 10 ** 18   # wall time, untouched
    finally:
        for node in nodes:
            node.destroy_node()


@pytest.mark.parametrize('raw', [True, False])
def test_a_neighbours_pose_gives_its_position_even_with_a_bad_covariance(context, raw):
    """A neighbour's `pose` carries p̂_j and P_j. A covariance that is no covariance is a
    counted rejection of that value only: the position is still used. A pose in another
    frame is rejected whole, once."""
    node = _node(context, raw_messages=raw, **EXPLICIT)
    try:
        node.on_imu(cdr.encode_imu_raw(0.0, 'agent_5', np.zeros(3)))   # creates the estimator
        nb = node.rt.peers[0]
        on_pose = next(s for s in node.subscriptions if s.topic_name == '/agent_1/pose').callback

        def send(t, frame, p, P):
            data = cdr.encode_pose_covariance_raw(t, frame, np.eye(3), p, P)
            on_pose(data if raw else wire.message(data, wire.PoseWithCovarianceStamped))

        good = np.diag([0.1, 0.1, 0.1, 0.01, 0.01, 0.01])
        send(0.0, 'world', [1.0, 2.0, 3.0], good)
        np.testing.assert_array_equal(nb.latest('p_hat'), [1.0, 2.0, 3.0])
        np.testing.assert_array_equal(nb.latest('pose_cov'), good)
        bad = good.copy()
        bad[0, 1] = 5.0                                  # not symmetric
        send(0.01, 'world', [1.5, 2.0, 3.0], bad)
        assert node.rejected['malformed'] == 1
        np.testing.assert_array_equal(nb.latest('p_hat'), [1.5, 2.0, 3.0])
        assert {n: v.newest_stamp for n, v in nb.values.items()} == {'p_hat': 0.01, 'pose_cov': 0.0}
        np.testing.assert_array_equal(nb.latest('pose_cov'), good)   # kept, not replaced
        send(0.02, 'agent_1/odom', [9.0, 9.0, 9.0], good)
        assert node.rejected['wrong_frame'] == 1 and node.rejected['malformed'] == 1
        np.testing.assert_array_equal(nb.latest('p_hat'), [1.5, 2.0, 3.0])
    finally:
        node.destroy_node()


@pytest.mark.parametrize('change, message', [
    (dict(agent_id=0), 'agent_id must be > 0'),
    (dict(neighbour_ids=[1]), 'the same length >= 2'),
    (dict(neighbour_gains=[1.0, -1.0]), 'every gain must be > 0'),
    (dict(initial_orientation=[0.0, 0.0, 0.0, 2.0]), 'unit quaternion'),
    (dict(initial_position=[0.0, float('nan'), 0.0]), 'initial_position'),
])
def test_explicit_parameter_errors_name_the_parameter(context, change, message):
    with pytest.raises(ScenarioError, match=message):
        _node(context, **{**EXPLICIT, **change})


def test_out_of_range_values_are_refused(context):
    """A negative gain or a drop rate above 1 stops the node with the range in the message."""
    with pytest.raises(ScenarioError, match=r'parameter k_R must be in \[0, '):
        _node(context, **{**EXPLICIT, 'k_R': -1.0})
    with pytest.raises(ScenarioError, match=r'parameter inject_drop_rate must be in \[0, 1\]'):
        _node(context, **{**EXPLICIT, 'inject_drop_rate': 2})


def test_integers_are_accepted_where_numbers_are_expected(context):
    """What a ROS user writes in a parameter file: `frequency: 100`, `neighbour_gains: [2, 1]`,
    `initial_position: [1, 2, 3]`. They are used (and stored) as floats."""
    ints = {**EXPLICIT, 'frequency': 200, 'k_R': 2, 'neighbour_gains': [2, 1],
            'initial_position': [1, 2, 3], 'neighbour_timeout': 1}
    node = _node(context, **ints)
    try:
        assert node.rt.h == pytest.approx(0.005) and node.rt.gains == CascadeGains(2.0, 1.0)
        assert [n.k for n in node.rt.peers] == [2.0, 1.0]
        assert node.rt.limits.neighbour_timeout == 1.0
        np.testing.assert_array_equal(node.rt.p_hat[0], [1.0, 2.0, 3.0])
        for name in ('frequency', 'neighbour_gains', 'initial_position'):
            param = node.get_parameter(name)
            assert param.type_ in (Parameter.Type.DOUBLE, Parameter.Type.DOUBLE_ARRAY), name
    finally:
        node.destroy_node()


@pytest.mark.parametrize('change, message', [
    (dict(frequency='fast'), "parameter frequency must be a number, but a string was given "
                             "('fast'). Fix: e.g. `frequency: 1.0`"),
    (dict(neighbour_ids=[1.0, 4.0]), 'parameter neighbour_ids must be a list of integers'),
    (dict(leader=1), 'parameter leader must be true or false, but an integer was given'),
    (dict(agent_id=5.0), 'parameter agent_id must be an integer, but a number was given'),
    (dict(neighbours='agent_1'), 'parameter neighbours must be a list of strings'),
])
def test_a_wrong_type_is_a_one_line_error_with_the_fix(context, change, message):
    with pytest.raises(ScenarioError) as info:
        _node(context, **{**EXPLICIT, **change})
    assert str(info.value).startswith(message) and 'Fix: ' in str(info.value)
    assert '\n' not in str(info.value)


def test_tran_anderson_ahn_in_explicit_mode(context):
    """`method: tran_anderson_ahn` with its gains k_omega, k_c, k_p (defaults for the others);
    a gain of the other method, or an unknown method, is an error naming the fix."""
    base = {k: v for k, v in EXPLICIT.items() if k != 'k_R'}
    node = _node(context, **base, method='tran_anderson_ahn', k_omega=3, k_c=0.5)
    try:
        assert node.rt.gains == TranGains(k_omega=3.0, k_p=1.0, k_c=0.5)
        assert [n.k for n in node.rt.peers] == [2.0, 1.0]
    finally:
        node.destroy_node()
    with pytest.raises(ScenarioError, match='parameter k_R is a boughellaba_tayebi gain, but the '
                       'method parameter is tran_anderson_ahn. Fix: remove k_R'):
        _node(context, **EXPLICIT, method='tran_anderson_ahn')
    with pytest.raises(ScenarioError, match='parameter k_omega is a tran_anderson_ahn gain.*'
                       'or set method: tran_anderson_ahn'):
        _node(context, **EXPLICIT, k_omega=2.0)
    with pytest.raises(ScenarioError, match="unknown method 'kalman'. Fix: one of"):
        _node(context, **EXPLICIT, method='kalman')


def test_a_method_other_than_the_scenarios_is_an_error(context, repo_root):
    with pytest.raises(ScenarioError, match='uses method boughellaba_tayebi. Fix: remove'):
        _node(context, scenario_file=str(repo_root / 'config' / 'paper_8_agents.yaml'),
              method='tran_anderson_ahn')


def test_unknown_agent_in_a_scenario_is_an_error(context, repo_root):
    with pytest.raises(ScenarioError, match="agent 'agent_5x' is not in the scenario"):
        _node(context, scenario_file=str(repo_root / 'config' / 'paper_8_agents.yaml'),
              agent='agent_5x')


def test_a_leader_with_an_empty_neighbour_list(context):
    """`neighbours: []` in a parameter file arrives without a type (NOT_SET): an empty list."""
    node = EstimatorNode(namespace='/agent_1', context=context, parameter_overrides=[
        Parameter('agent_id', value=1), Parameter('leader', value=True),
        Parameter('neighbours', Parameter.Type.NOT_SET)])
    try:
        assert node.rt.leader and node.rt.peers == []
        assert '/agent_1/known_pose' in {s.topic_name for s in node.subscriptions}
    finally:
        node.destroy_node()


def test_the_known_pose_subscription_matches_best_effort_and_reliable(context):
    """A leader's known_pose reader is best effort: it matches a mocap driver's best-effort
    publisher and the simulator's reliable one (a reliable reader would miss the first)."""
    node = EstimatorNode(namespace='/agent_1', context=context, parameter_overrides=[
        Parameter('agent_id', value=1), Parameter('leader', value=True)])
    try:
        sub = next(s for s in node.subscriptions if s.topic_name == '/agent_1/known_pose')
        assert sub.qos_profile.reliability == wire.SENSOR_QOS.reliability  # BEST_EFFORT
    finally:
        node.destroy_node()


@pytest.mark.parametrize('raw', [True, False])
def test_messages_as_bytes_or_as_objects_give_the_same_estimate(context, raw):
    """raw_messages (default true): every subscription takes the serialised bytes, decoded
    with msg_defs/cdr.py; false: rclpy's message objects. The same samples give the same
    gyro buffer either way, and bad bytes are a counted rejection, never an exception."""
    node = _node(context, raw_messages=raw, **EXPLICIT)
    try:
        assert node.subscriptions and all(s.raw == raw for s in node.subscriptions)
        for k in range(3):
            data = cdr.encode_imu_raw(0.005 * k, 'agent_5', np.array([0.0, 0.0, 0.1 * k]))
            node.on_imu(data if raw else wire.message(data, wire.Imu))
        assert node.rt.gyro.end == pytest.approx(0.01)
        np.testing.assert_allclose(so3.log(node.rt.gyro.increment(0.0, 0.01)),
                                   [0.0, 0.0, 0.005 * 0.1 + 0.005 * 0.2], atol=1e-12)
        elsewhere = cdr.encode_imu_raw(0.015, 'agent_4', np.zeros(3))   # another body's frame
        node.on_imu(elsewhere if raw else wire.message(elsewhere, wire.Imu))
        assert node.rejected['wrong_frame'] == 1
        if raw:
            node.on_imu(data[:-5])                                  # truncated
            node.on_points(Sensor.BEARINGS, b'\x00\x01\x00\x00garbage')
            assert node.rejected['malformed'] == 2
    finally:
        node.destroy_node()


def test_input_frames_rate_limit_diagnostics_and_exchange_parameters(context):
    """imu_frame, bearings_frame and odom_child_frame: the frame_id each input must carry
    (empty: any); max_rate: the gyro rate above which a sample is refused; diagnostics_period:
    the /diagnostics timer; fixed_exchange: the runtime waits for stamped inputs even on the
    wall clock (default: use_sim_time, off here)."""
    zero = np.zeros(3)
    default = _node(context, **EXPLICIT)
    node = _node(context, imu_frame='rig/base_link', bearings_frame='',
                 odom_child_frame='rig/base_link', max_rate=1.0, diagnostics_period=0.25,
                 fixed_exchange=True, **EXPLICIT)
    try:
        assert default.s.exchange is None and node.s.exchange is not None
        assert 250_000_000 in [t.timer_period_ns for t in node.timers]
        assert 250_000_000 not in [t.timer_period_ns for t in default.timers]
        node.on_imu(cdr.encode_imu_raw(0.005, 'agent_5', zero))        # the default frame
        node.on_imu(cdr.encode_imu_raw(0.005, 'rig', [0.0, 0.0, 1.5]))  # above max_rate
        assert node.rejected == {'wrong_frame': 1, 'absurd_rate': 1}
        node.on_imu(cdr.encode_imu_raw(0.005, 'rig', [0.0, 0.0, 0.5]))
        assert node.rt.gyro.end == pytest.approx(0.005)
        node.on_points(Sensor.BEARINGS, cdr.encode_vectors_raw(
            0.005, 'any/camera', np.array([1]), np.array([[1.0, 0.0, 0.0]])))
        node.on_odometry(cdr.encode_odometry_raw(0.005, 'agent_5', zero, zero))
        assert node.rejected == {'wrong_frame': 1, 'absurd_rate': 1, 'malformed': 1}
        node.on_odometry(cdr.encode_odometry_raw(0.005, 'rig', zero, zero))
        assert node.rejected['malformed'] == 1
        default.on_points(Sensor.BEARINGS, cdr.encode_vectors_raw(
            0.005, 'any/camera', np.array([1]), np.array([[1.0, 0.0, 0.0]])))
        assert default.rejected == {'wrong_frame': 1}
    finally:
        node.destroy_node()
        default.destroy_node()


def test_a_late_start_counts_no_input_as_a_fault(context):
    """A process started after t0 (a robot started again mid-run) has a runtime at t0 until its
    first gyro sample: the bearings and neighbour values that come before it are ahead of it,
    early, not bad (event_early_inputs; its health stays OK). The first gyro sample starts its
    time (gyro_gap); from then on a stamp from the future is a rejected input again."""
    from bearing_pose_estimation.runtime.health import OK, WARN, health

    node = _node(context, **EXPLICIT)
    on_pose = next(s for s in node.subscriptions if s.topic_name == '/agent_1/pose').callback

    def bearing(t):
        node.on_points(Sensor.BEARINGS, cdr.encode_vectors_raw(
            t, 'agent_5/base_link', np.array([1]), np.array([[1.0, 0.0, 0.0]])))

    def pose(t):
        on_pose(cdr.encode_pose_covariance_raw(t, 'world', np.eye(3), [1.0, 2.0, 3.0],
                                               0.1 * np.eye(6)))

    try:
        assert node.rt.t == 0.0
        bearing(25.0)
        pose(25.0)
        assert node.rejected == {} and node.events == {'early_inputs': 2}
        assert health(node.rt, node.rejected, node.events).level == OK
        node.on_imu(cdr.encode_imu_raw(25.0, 'agent_5', np.zeros(3)))
        assert node.events['gyro_gap'] == 1 and node.rt.t == pytest.approx(25.0)
        bearing(25.0)
        pose(25.0)
        assert node.rejected == {}
        assert node.rt.peers[0].values['p_hat'].newest_stamp == 25.0
        bearing(40.0)
        pose(40.0)
        assert node.rejected == {'future_stamp': 2}
        assert health(node.rt, node.rejected, node.events).level == WARN
    finally:
        node.destroy_node()


@pytest.mark.parametrize('publish_clock', [True, False])
def test_the_simulator_clock_can_be_turned_off(context, repo_root, publish_clock):
    """`publish_clock: false` (another node owns /clock, e.g. a bag replay): no /clock
    publisher at all; the sensor topics are still there."""
    node = SimulatorNode(context=context, parameter_overrides=[
        Parameter('scenario_file', value=str(repo_root / 'config' / 'paper_8_agents.yaml')),
        Parameter('publish_clock', value=publish_clock)])
    try:
        topics = {p.topic_name for p in node.publishers}
        assert ('/clock' in topics) == publish_clock
        assert node.count_publishers('/clock') == int(publish_clock)
        assert '/agent_3/imu' in topics
    finally:
        node.destroy_node()


def test_the_simulator_s_start_timeout_and_lockstep_lead(context, repo_root, capfd):
    """start_timeout: with nobody matched the simulator gives up, naming what it waited for;
    max_lag: a lockstep clock runs at most that far ahead of the slowest estimate."""
    node = SimulatorNode(context=context, parameter_overrides=[
        Parameter('scenario_file', value=str(repo_root / 'config' / 'paper_8_agents.yaml')),
        Parameter('start_timeout', value=0.0), Parameter('max_lag', value=0.05)])
    try:
        node.on_tick()
        assert node.state == 'failed' and node.failed.result() is False
        err = capfd.readouterr().err
        assert 'not ready after 0 s: unmatched /agent_1/' in err and 'no t0 estimate' in err
        node._start()
        node.progress[:] = 0.2
        node.progress[3] = 0.1    # the slowest estimate
        for _ in range(20):       # a tick advances at most _MAX_SIM_PER_TICK
            node.on_tick()
        assert node.world.t == pytest.approx(0.15)
    finally:
        node.destroy_node()


@pytest.mark.parametrize('records', [False, True])
def test_the_simulator_waits_for_the_recorders_readers(context, repo_root, records):
    """With `monitor_records` (run --record) the start waits until the simulator's writers
    have matched the recorder's reader as well as the estimator's: a reader the writer has
    not matched gets nothing, and one matched reader must not pass for the other (CI: an
    estimator that never got its first samples stopped the lockstep clock for good)."""
    import time

    node = SimulatorNode(context=context, parameter_overrides=[
        Parameter('scenario_file', value=str(repo_root / 'config' / 'paper_8_agents.yaml')),
        Parameter('monitor_records', value=records)])
    reader = rclpy_node(context, 'one_reader_each')
    try:
        for pub in node.pub_imu:
            reader.create_subscription(wire.Imu, pub.topic_name, lambda _m: None,
                                       wire.SENSOR_QOS)
        deadline = time.monotonic() + 10.0
        while (min(p.get_subscription_count() for p in node.pub_imu) < 1
               and time.monotonic() < deadline):
            time.sleep(0.01)
        assert ('/agent_1/imu' in node._unmatched()) == records
    finally:
        reader.destroy_node()
        node.destroy_node()


def test_the_monitor_is_ready_once_every_follower_s_t0_estimate_is_in(context, repo_root,
                                                                    tmp_path):
    """/monitor/ready (the simulator's go) needs more than a publisher for each reader: every
    follower's t = 0 estimate, which proves its writer matched the monitor before the clock
    started (a writer that matches later may have dropped t = 0 from its history)."""
    import time

    from bearing_pose_estimation.ros.monitor_node import MonitorNode

    node = MonitorNode(context=context, parameter_overrides=[
        Parameter('scenario_file', value=str(repo_root / 'config' / 'paper_8_agents.yaml')),
        Parameter('out_dir', value=str(tmp_path)), Parameter('plots', value=False)])
    fleet = rclpy_node(context, 'fleet')
    try:
        for sub in node.subscriptions:
            qos = (wire.ESTIMATE_PUB_QOS if sub.topic_name.endswith(wire.ESTIMATE)
                   else wire.SIM_PUB_QOS)
            fleet.create_publisher(wire.PoseStamped, sub.topic_name, qos)
        deadline = time.monotonic() + 10.0
        while (min(s.get_publisher_count() for s in node.subscriptions) < 1
               and time.monotonic() < deadline):
            time.sleep(0.01)
        t0 = cdr.encode_pose_raw(0.0, 'world', np.eye(3), np.zeros(3))
        for k in range(len(node.followers)):
            node.on_ready_check()
            assert not node.ready_timer.is_canceled(), k   # not ready: not announced
            node._on_pose(node._est, k, t0)
        node.on_ready_check()
        assert node.ready_timer.is_canceled()
    finally:
        fleet.destroy_node()
        node.destroy_node()


def test_the_monitor_finishes_without_the_estimate_of_a_robot_that_is_gone(
        context, repo_root, tmp_path, monkeypatch, capfd):
    """The truth of t = duration is in but a follower's estimate is not (its process died and
    was not started again): after END_PATIENCE_S of wall time the monitor writes its outputs
    from the rows it has, naming whose estimate is missing, instead of waiting for ever."""
    import json

    from bearing_pose_estimation.ros import monitor_node

    now = [100.0]
    monkeypatch.setattr(monitor_node.time, 'monotonic', lambda: now[0])
    node = monitor_node.MonitorNode(context=context, parameter_overrides=[
        Parameter('scenario_file', value=str(repo_root / 'config' / 'paper_8_agents.yaml')),
        Parameter('out_dir', value=str(tmp_path)), Parameter('plots', value=False),
        Parameter('duration', value=0.2)])
    try:
        pose = cdr.encode_pose_raw
        for t in (0.1, 0.2):
            for k in range(len(node.watched)):
                node._on_pose(node._truth, k, pose(t, 'world', np.eye(3), np.zeros(3)))
            for k, name in enumerate(node.followers):
                if t < 0.15 or name != 'agent_4':   # agent_4 died after 0.1 s
                    node._on_pose(node._est, k, pose(t, 'world', np.eye(3), np.zeros(3)))
        node.on_end_check()
        now[0] += monitor_node.END_PATIENCE_S - 0.1
        node.on_end_check()
        assert not node.finished.done()
        now[0] += 0.2
        node.on_end_check()
        assert node.finished.done()
        assert 'no estimate of t = 0.2 s from agent_4 after' in capfd.readouterr().err
        summary = json.loads((tmp_path / 'summary.json').read_text())
        assert summary['complete'] is False and summary['duration_s'] == pytest.approx(0.1)
    finally:
        node.destroy_node()


def _estimate_writers(context, names):
    """A node with an estimate writer for each of ``names`` (the estimators alive), once the
    graph shows them."""
    fleet = rclpy_node(context, 'fleet')
    for name in names:
        fleet.create_publisher(wire.PoseStamped, f'/{name}/estimate', wire.ESTIMATE_PUB_QOS)
    for _ in range(1000):   # one context's graph: at once, or nearly
        if all(fleet.count_publishers(f'/{name}/estimate') for name in names):
            break
        time.sleep(0.01)
    return fleet


def test_the_simulator_names_the_estimators_its_clock_waits_for(context, repo_root, capfd,
                                                              monkeypatch):
    """With lockstep_patience 0 (wait for ever), a lockstep clock held by the slowest living
    estimators for LOCKSTEP_PATIENCE_S of wall time gets a warning naming them (a hung run
    says on whom); a moving one does not."""
    from bearing_pose_estimation.ros import simulator_node

    now = [100.0]
    monkeypatch.setattr(simulator_node.time, 'monotonic', lambda: now[0])
    node = SimulatorNode(context=context, parameter_overrides=[
        Parameter('scenario_file', value=str(repo_root / 'config' / 'paper_8_agents.yaml')),
        Parameter('lockstep_patience', value=0.0)])
    fleet = _estimate_writers(context, node.names)
    try:
        node._start()
        node.progress[:] = 0.5
        node.progress[[2, 5]] = 0.1
        for _ in range(20):     # to the lockstep limit
            node.on_tick()
        now[0] += simulator_node.LOCKSTEP_PATIENCE_S - 0.1
        node.on_tick()
        assert 'waited' not in capfd.readouterr().err
        now[0] += 0.2
        node.on_tick()
        err = capfd.readouterr().err
        assert 'for agent_3, agent_6 (newest estimate at t = 0.100 s)' in err, err
        assert not node.absent.any()   # alive: waited for, for ever
        node.progress[[2, 5]] = 0.12   # they moved: the wait starts over
        node.on_tick()
        now[0] += 1.0
        node.on_tick()
        assert 'waited' not in capfd.readouterr().err
    finally:
        fleet.destroy_node()
        node.destroy_node()


def test_the_lockstep_clock_goes_on_without_a_dead_estimator_until_it_is_back(
        context, repo_root, capfd, monkeypatch):
    """An estimator whose estimate writer is gone (a stopped process) holds the clock for
    GRAPH_CHECK_S at most, one whose estimates stopped for lockstep_patience (a killed one,
    which DDS sees only 20 s later); meanwhile the clock leads the others by absent_lag (more
    than their link_wait: a step waiting for the absent one's values goes on). It waits for
    one again once it has stepped rejoin_after since it came back and caught up."""
    from bearing_pose_estimation.ros import simulator_node

    now = [100.0]
    monkeypatch.setattr(simulator_node.time, 'monotonic', lambda: now[0])
    node = SimulatorNode(context=context, parameter_overrides=[
        Parameter('scenario_file', value=str(repo_root / 'config' / 'paper_8_agents.yaml')),
        Parameter('max_lag', value=0.05), Parameter('lockstep_patience', value=3.0)])
    fleet = _estimate_writers(context, [n for n in node.names if n != 'agent_4'])

    def run() -> float:
        for _ in range(100):   # a tick advances at most _MAX_SIM_PER_TICK
            node.on_tick()
        return node.world.t

    try:
        node._start()
        node.progress[:] = 0.2
        node.progress[[3, 5]] = 0.1    # agent_4 died; agent_6 waits for it
        assert run() == pytest.approx(0.15)
        now[0] += simulator_node.GRAPH_CHECK_S
        assert run() == pytest.approx(0.6)   # agent_6 + absent_lag
        err = capfd.readouterr().err
        assert ('the clock stops waiting for agent_4 at t = 0.150 s: its estimate writer is '
                'gone') in err, err
        assert list(node.absent) == [n == 'agent_4' for n in node.names]
        now[0] += 2.9
        assert run() == pytest.approx(0.6)
        now[0] += 0.2   # agent_6 has not moved for lockstep_patience: not waited for either
        assert run() == pytest.approx(0.7)
        assert 'agent_6 at t = 0.600 s: its estimates stopped at t = 0.100 s' in \
            capfd.readouterr().err
        node.progress[:] = 0.65    # agent_6 steps again, and agent_4 is back (restarted)
        node.progress[5] = 0.7
        run()
        assert node.absent[[3, 5]].all()   # caught up, but back for less than rejoin_after
        node.progress[:] = 1.65
        node.progress[5] = 1.7
        run()
        assert 'agent_4 is back (estimates from t = 0.650 s) and has caught up' in \
            capfd.readouterr().err
        assert not node.absent.any()
        assert run() == pytest.approx(1.7)   # max_lag again
    finally:
        fleet.destroy_node()
        node.destroy_node()


def test_rclpy_still_exposes_the_parameter_overrides(context):
    """node_main.parameter_overrides reads rclpy's private `_parameter_overrides` (no public
    accessor): the unknown-key warning depends on it."""
    node = _node(context, **EXPLICIT)
    try:
        assert parameter_overrides(node)['agent_id'].value == 5
    finally:
        node.destroy_node()


def _run_estimator(tmp_path, params: str, timeout: float = 30.0) -> subprocess.CompletedProcess:
    """Start the real `estimator` executable with a parameter file (as the README tells users)
    and return its result; it is stopped with SIGINT if it is still running after
    ``timeout`` s."""
    path = tmp_path / 'params.yaml'
    path.write_text(params)
    argv = [str(plan.find_executable('estimator')), '--ros-args', '-r', '__ns:=/agent_5',
            '--params-file', str(path)]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=dds.dds_env(int(os.environ['ROS_DOMAIN_ID']), tmp_path / 'ros'))
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(2)
        out, _ = proc.communicate(timeout=20)
    return subprocess.CompletedProcess(argv, proc.returncode, out)


@pytest.mark.parametrize('line, message', [
    ('frequency: fast', 'parameter frequency must be a number, but a string was given '
                        "('fast'). Fix: e.g. `frequency: 1.0`"),
    # Declared by rclpy itself, so rclpy raises: still one line, with a fix.
    ('use_sim_time: 1', "parameter error: Trying to set parameter 'use_sim_time' to '1'"),
])
def test_the_executable_reports_a_wrong_type_in_one_line(tmp_path, line, message):
    """A wrong type in a parameter file: exit code 1, one fatal line naming the parameter and
    the fix, no traceback (integer gains, `[2, 1]`, are not an error)."""
    shm = dds.shm_files()
    result = _run_estimator(tmp_path, f"""/agent_5/estimator:
  ros__parameters:
    agent_id: 5
    neighbours: [agent_1, agent_4]
    neighbour_ids: [1, 4]
    neighbour_gains: [2, 1]
    {line}
""")
    assert result.returncode == 1, result.stdout
    assert 'Traceback' not in result.stdout
    fatal = [x for x in result.stdout.splitlines() if 'FATAL' in x]
    assert len(fatal) == 1 and message in fatal[0] and 'Fix: ' in fatal[0], result.stdout
    assert dds.leaked_shm(shm) == []


def test_the_readme_explicit_parameter_file_is_valid(context, repo_root, tmp_path):
    """The README's explicit-mode example ("On real robots") builds the estimator it says."""
    readme = (repo_root / 'README.md').read_text()
    block = next(b.split('\n', 1)[1] for b in readme.split('```yaml')[1:]
                 if '/agent_4/estimator:' in b).split('```')[0]
    path = tmp_path / 'agent_4.yaml'
    path.write_text(block)
    node = EstimatorNode(namespace='/agent_4', context=context,
                         cli_args=['--ros-args', '--params-file', str(path)])
    try:
        assert node.rt is None and node.s.start_time < 0  # starts at the first gyro sample
        assert node.s.spec.agent_id == 4 and node.s.gains == TranGains(2.0, 1.0, 0.5)
        assert [(n.name, n.agent_id, n.k) for n in node.s.spec.peers] == [
            ('agent_1', 1, 1.0), ('agent_2', 2, 2.0)]
    finally:
        node.destroy_node()


def test_parameters_read_their_effective_values(context, repo_root):
    """`ros2 param get` tells the truth: the rates and gains read the values the node runs
    (the scenario's; explicit mode: 100 Hz, 50 Hz, the method's defaults, or those given)."""
    node = _node(context, scenario_file=str(repo_root / 'config' / 'paper_8_agents.yaml'))
    try:
        values = {n: node.get_parameter(n).value for n in ('k_R', 'k_p', 'frequency',
                                                           'publish_rate', 'sensor_timeout')}
        assert values == {'k_R': 1.0, 'k_p': 1.0, 'frequency': 100.0, 'publish_rate': 50.0,
                          'sensor_timeout': 0.5}
        assert not node.has_parameter('k_omega')   # another method's gain: not declared
    finally:
        node.destroy_node()
    explicit = {k: v for k, v in EXPLICIT.items() if k != 'k_R'}
    node = _node(context, **explicit, method='tran_anderson_ahn', k_omega=2.0)
    try:
        gains = {n: node.get_parameter(n).value for n in ('k_omega', 'k_c', 'k_p')}
        assert gains == {'k_omega': 2.0, 'k_c': 1.0, 'k_p': 1.0}
        assert node.get_parameter('frequency').value == 200.0   # EXPLICIT sets it
        assert node.get_parameter('publish_rate').value == 50.0
    finally:
        node.destroy_node()


def test_gains_and_limits_are_set_live_and_validated(context, repo_root, tmp_path):
    """A running node takes new gains and input limits from the next step on, all or
    nothing; a gain the method's check refuses (De Carli's position correction whose Euler
    step diverges), a non-positive one, one out of range, or a read-only parameter is refused
    with the reason, and nothing changes."""
    node = _node(context, scenario_file=str(repo_root / 'config' / 'paper_8_agents.yaml'))
    try:
        est = node.rt
        ok = node.set_parameters([Parameter('k_R', value=2.0),
                                  Parameter('sensor_timeout', value=0.2)])
        assert [r.successful for r in ok] == [True, True]
        assert est.gains.k_R == 2.0 and est.gains.k_p == 1.0
        assert est.limits.sensor_timeout == 0.2 and node.s.limits.sensor_timeout == 0.2
        assert node.get_parameter('k_R').value == 2.0
        refused = node.set_parameters_atomically([Parameter('k_R', value=3.0),
                                                  Parameter('k_p', value=0.0)])
        assert not refused.successful and 'parameter.k_p: must be > 0' in refused.reason
        assert not node.set_parameters([Parameter('k_R', value=-1.0)])[0].successful  # range
        frozen = node.set_parameters([Parameter('frequency', value=50.0)])[0]
        assert not frozen.successful and 'read-only' in frozen.reason
        assert est.gains.k_R == 2.0 and node.get_parameter('k_R').value == 2.0
        assert node.s.step == pytest.approx(0.01)
    finally:
        node.destroy_node()
    data = yaml.safe_load((repo_root / 'config' / 'de_carli_8_quadrotors.yaml').read_text())
    data['formation_control']['mode'] = 'exogenous'
    (tmp_path / 'de_carli.yaml').write_text(yaml.safe_dump(data))
    node = _node(context, scenario_file=str(tmp_path / 'de_carli.yaml'), agent='robot_4')
    try:
        assert node.set_parameters([Parameter('k_z', value=20.0)])[0].successful
        diverging = node.set_parameters([Parameter('k_p', value=1e4)])[0]
        assert not diverging.successful and 'k_p' in diverging.reason, diverging.reason
        assert node.rt.gains.k_p == 1.0 and node.rt.gains.k_z == 20.0
    finally:
        node.destroy_node()


def test_a_stalled_agent_takes_messages_the_executor_was_not_told_of(context):
    """An agent whose state and gyro have not moved for a check period while its clock is
    ahead (``on_watch``) takes what its subscriptions hold: here samples no executor was
    spun for, as when the executor misses a notification. They are handled (the step runs)
    and counted; the first check only notes the state, so a healthy agent takes nothing."""
    import time

    node = EstimatorNode(namespace='/agent_1', context=context, parameter_overrides=[
        Parameter('agent_id', value=1), Parameter('leader', value=True)])
    sender = rclpy_node(context, 'imu_sender')
    try:
        pub = sender.create_publisher(wire.Imu, '/agent_1/imu', wire.SIM_PUB_QOS)
        deadline = time.monotonic() + 10.0
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        for t in (0.005, 0.01):
            pub.publish(cdr.encode_imu_raw(t, 'agent_1', np.array([0.0, 0.0, 0.2])))
        node.on_watch()   # notes (k, gyro end): nothing taken yet
        assert node.rt.gyro.end == 0.0 and not node.events['taken_while_stalled']
        while node.events['taken_while_stalled'] < 2 and time.monotonic() < deadline:
            node.on_watch()
            time.sleep(0.01)
        assert node.events['taken_while_stalled'] == 2
        assert node.rt.gyro.end == pytest.approx(0.01) and node.rt.k == 1
    finally:
        sender.destroy_node()
        node.destroy_node()


def rclpy_node(context, name):
    from rclpy.node import Node

    return Node(name, context=context)


def test_a_neighbour_whose_clock_runs_ahead_is_flagged(context):
    """On its own (wall) clock the node hands the runtime ``now`` with every neighbour input:
    a pose stamped 0.5 s ahead is used, counted as ahead and reported in /diagnostics by name
    and lead; ``max_clock_lead`` is a live parameter."""
    from bearing_pose_estimation.runtime.health import OK, WARN, health

    node = _node(context, start_time=-1.0, **EXPLICIT)   # t = 0: its first gyro sample
    try:
        now = node._now()
        for t in (now, now + 0.005):
            node.on_imu(cdr.encode_imu_raw(t, 'agent_5', np.zeros(3)))
        on_pose = next(s for s in node.subscriptions if s.topic_name == '/agent_1/pose').callback
        on_pose(cdr.encode_pose_covariance_raw(node._now() + 0.5, 'world', np.eye(3),
                                               np.zeros(3), np.eye(6)))
        assert not node.rejected and dict(node.rt.ahead) == {'agent_1': 1}
        assert 0.4 < node.rt.leads['agent_1'] <= 0.5
        report = health(node.rt, node.rejected, node.events)
        assert report.level == WARN and 'clock ahead of ours: agent_1 by 0.' in report.message
        assert node.set_parameters([Parameter('max_clock_lead', value=1.0)])[0].successful
        assert health(node.rt, node.rejected, node.events).level == OK
    finally:
        node.destroy_node()
