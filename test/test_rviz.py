"""What RViz and TF users get: the fleet's MarkerArray (msg_defs.rviz, ros/markers_node.py) and
the estimate on TF. tf2_ros is not in the PyPI wheels: a stand-in broadcaster records the
transforms the estimator node sends, built in-process."""
import sys
import types

import numpy as np
import pytest
from rclpy.parameter import Parameter
from visualization_msgs.msg import Marker

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.msg_defs import cdr, rviz
from bearing_pose_estimation.ros.estimator_node import EstimatorNode
from bearing_pose_estimation.ros.markers_node import MarkersNode
from bearing_pose_estimation.scenario import load_scenario

R1, R2 = so3.exp(np.array([0.1, -0.2, 0.3])), so3.exp(np.array([0.0, 0.5, 0.0]))
P = {'a': np.array([0.0, 0.0, 0.0]), 'b': np.array([3.0, 4.0, 0.0]), 'c': np.array([0, 0, 2.0])}


def test_markers_draw_poses_edges_and_bearing_rays():
    b_ab = R1.T @ (P['b'] - P['a']) / 5.0   # what a measures of b, in its body frame
    b_ac = np.array([0.0, 0.0, 1.0])        # c has no estimate yet: a 1 m ray
    msg = rviz.encode_fleet_markers(
        2.5, ['a', 'b', 'c'], 'world', 'world',
        estimates={'a': (R1, P['a']), 'b': (R2, P['b'])},
        truth={'a': (np.eye(3), P['a']), 'c': (np.eye(3), P['c'])},
        edges=[('a', 'b'), ('b', 'a'), ('a', 'c')],
        bearings={'a': (['b', 'c'], np.array([b_ab, b_ac])), 'c': (['a'], np.array([b_ac]))})
    by = {}
    for m in msg.markers:
        by.setdefault(m.ns, []).append(m)
        assert m.header.stamp.sec == 2 and m.header.stamp.nanosec == 500_000_000
    assert set(by) == set(rviz.MARKER_NAMESPACES)
    assert [(m.id, m.type) for m in by['estimate']] == [(0, Marker.ARROW), (1, Marker.ARROW)]
    q = by['estimate'][0].pose.orientation
    np.testing.assert_allclose(so3.from_quat(np.array([q.x, q.y, q.z, q.w])), R1, atol=1e-12)
    assert [m.text for m in by['label']] == ['a', 'b']
    assert [m.id for m in by['truth']] == [0, 2]   # c's truth although it has no estimate
    (edges,), (rays,) = by['edges'], by['bearings']
    assert edges.type == rays.type == Marker.LINE_LIST
    assert len(edges.points) == 4   # a-b both ways; a-c waits for c's estimate
    ends = [np.array([p.x, p.y, p.z]) for p in rays.points]
    assert len(ends) == 4           # a's two rays; c has no estimate to start from
    np.testing.assert_allclose(ends[1], P['b'], atol=1e-12)       # to b's estimate
    np.testing.assert_allclose(ends[3], R1 @ b_ac, atol=1e-12)    # 1 m towards c


@pytest.mark.dds
def test_the_markers_node_draws_what_the_fleet_publishes(context, repo_root):
    paper = repo_root / 'config' / 'paper_8_agents.yaml'
    node = MarkersNode(context=context,
                       parameter_overrides=[Parameter('scenario_file', value=str(paper))])
    try:
        s = load_scenario(paper)
        for a in s.agents:
            node._on_pose(node.estimates, a.name,
                          cdr.encode_pose_raw(1.0, 'world', np.eye(3), a.position + 0.1))
        sensed = [nb.name for nb in s.agents[2].neighbours]
        b = np.array([(s.agents[s.index[n]].position - s.agents[2].position) for n in sensed])
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        ids = np.array([s.agent_id(n) for n in sensed], dtype=np.uint32)
        node._on_bearings('agent_3', cdr.encode_vectors_raw(1.0, 'agent_3/base_link', ids, b))
        msg = node.markers()
        rays = next(m for m in msg.markers if m.ns == 'bearings')
        assert len(rays.points) == 2 * len(sensed)
        edges = next(m for m in msg.markers if m.ns == 'edges')
        assert len(edges.points) == 2 * sum(len(a.neighbours) for a in s.agents)
        assert {m.header.frame_id for m in msg.markers} == {'world'}
    finally:
        node.destroy_node()


@pytest.fixture
def tf_standin(monkeypatch):
    """A tf2_ros module whose TransformBroadcaster records what it is sent."""
    sent = []

    class TransformBroadcaster:
        def __init__(self, node):
            self.node = node

        def sendTransform(self, transform):
            sent.append(transform)

    monkeypatch.setitem(sys.modules, 'tf2_ros',
                        types.SimpleNamespace(TransformBroadcaster=TransformBroadcaster))
    return sent


@pytest.mark.dds
def test_the_estimate_goes_on_tf_when_tf2_ros_is_installed(context, repo_root, tf_standin):
    """world -> agent_5/base_link with the estimate's pose, with every estimate published;
    publish_tf false turns it off."""
    paper = str(repo_root / 'config' / 'paper_8_agents.yaml')
    node = EstimatorNode(namespace='/agent_5', context=context,
                         parameter_overrides=[Parameter('scenario_file', value=paper)])
    try:
        node._publish(grid=True, force=True)
        (tf,) = tf_standin
        assert (tf.header.frame_id, tf.child_frame_id) == ('world', 'agent_5/base_link')
        r, p = tf.transform.rotation, tf.transform.translation
        np.testing.assert_allclose([p.x, p.y, p.z], node.rt.p_hat[0], atol=1e-12)
        np.testing.assert_allclose(so3.from_quat(np.array([r.x, r.y, r.z, r.w])),
                                   node.rt.R_hat[0], atol=1e-12)
    finally:
        node.destroy_node()
    node = EstimatorNode(namespace='/agent_5', context=context,
                         parameter_overrides=[Parameter('scenario_file', value=paper),
                                              Parameter('publish_tf', value=False)])
    try:
        node._publish(grid=True, force=True)
        assert node.tf is None and len(tf_standin) == 1
    finally:
        node.destroy_node()


@pytest.mark.dds
def test_without_tf2_ros_there_is_no_broadcast(context, repo_root, monkeypatch):
    monkeypatch.setitem(sys.modules, 'tf2_ros', None)   # import fails
    paper = str(repo_root / 'config' / 'paper_8_agents.yaml')
    node = EstimatorNode(namespace='/agent_5', context=context,
                         parameter_overrides=[Parameter('scenario_file', value=paper)])
    try:
        assert node.tf is None
    finally:
        node.destroy_node()
