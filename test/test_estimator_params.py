"""The estimator node's configuration without a scenario file (what a real robot may use),
and its parameter errors: built in-process, no other node needed."""
import numpy as np
import pytest
from rclpy.exceptions import InvalidParameterValueException
from rclpy.parameter import Parameter

from bearing_pose_estimation import so3
from bearing_pose_estimation.estimator_node import EstimatorNode
from bearing_pose_estimation.scenario import ScenarioError


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
        est = node.est
        assert node.agent == 'agent_5' and est.agent_id == 5 and not est.leader
        assert [(n.name, n.agent_id, n.k) for n in est.neighbours] == [
            ('agent_1', 1, 2.0), ('agent_4', 4, 1.0)]
        assert est.gains.k_R == 1.5 and est.gains.k_p == 1.0 and est.h == pytest.approx(0.005)
        np.testing.assert_allclose(est.R_hat[0], so3.axis_angle([0, 0, 1], 0.5), atol=1e-12)
        np.testing.assert_array_equal(est.p_hat[0], [1.0, 2.0, 3.0])
        subs = {s.topic_name for s in node.subscriptions}
        assert {'/agent_5/imu', '/agent_5/bearings', '/agent_1/estimate',
                '/agent_1/world_bearings', '/agent_4/estimate',
                '/agent_4/world_bearings'} <= subs
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
    """The descriptors' ranges reject a negative gain before the node is built."""
    with pytest.raises(InvalidParameterValueException, match='k_R'):
        _node(context, **{**EXPLICIT, 'k_R': -1.0})


def test_unknown_agent_in_a_scenario_is_an_error(context, repo_root):
    with pytest.raises(ScenarioError, match="agent 'agent_5x' is not in the scenario"):
        _node(context, scenario_file=str(repo_root / 'config' / 'paper_8_agents.yaml'),
              agent='agent_5x')
