"""Presenza et al.'s per-robot logic (:class:`TwoRoundAgent`, what each estimator node runs)
against the batch simulator, without DDS: five agents fed by the simulator node's World, the
nodes' messages delivered in-process (``presenza_fleet.Fleet``).

- With every message delivered, the fleet is the batch simulator, step for step: the two
  rounds, the anchor's odometry and ranges reach each robot as the batch routes them.
- A lost second-round message, a lost estimate, a silent anchor: the step goes on without
  them once the own sensors are ``link_wait`` ahead, says what it left out, and the estimate
  stays finite and converging.
- Bad inputs are rejected with their cause and never reach the estimate.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.core.motion import in_anchor_frame
from bearing_pose_estimation.sim.batch import BatchSimulator

sys.path.insert(0, str(Path(__file__).resolve().parent))
from presenza_fleet import CAMERA_RATE, ROOT, Fleet, camera_rate_case1  # noqa: E402

T = 2.0


@pytest.fixture(scope='module')
def case1(tmp_path_factory):
    return camera_rate_case1(tmp_path_factory.mktemp('presenza'), duration=T)


def _errors(fleet: Fleet) -> tuple[np.ndarray, np.ndarray]:
    """Per robot position [m] and attitude [rad] errors in the anchor frame, now."""
    R, p = in_anchor_frame(fleet.world.R, fleet.world.p, fleet.s.index[fleet.s.anchor])
    agents = [fleet.agents[n] for n in fleet.names]
    p_hat = np.stack([a.p_hat[0] for a in agents])
    R_hat = np.stack([a.R_hat[0] for a in agents])
    return (np.linalg.norm(p_hat - p, axis=1),
            so3.angle(R @ np.swapaxes(R_hat, -1, -2)))


def test_the_camera_rate_config_is_case_1_but_for_the_rates_and_the_scheme():
    fast = yaml.safe_load(CAMERA_RATE.read_text())
    paper = yaml.safe_load((ROOT / 'config' / 'presenza_case1.yaml').read_text())
    assert fast['frequency'] == fast['publish_rate'] == 30.0
    assert {spec['rate'] for spec in fast['sensors'].values()} == {30.0}
    assert fast['simulation'] == {'internal_step': pytest.approx(1 / 300), 'imu_rate': 30.0,
                                  'bearing_rate': 30.0, 'ground_truth_rate': 30.0}
    assert fast['gains'] == {**paper['gains'], 'preconditioning': 1.0}
    changed = {'name', 'description', 'frequency', 'publish_rate', 'gains', 'sensors',
               'simulation'}
    assert {k: v for k, v in fast.items() if k not in changed} == \
        {k: v for k, v in paper.items() if k not in changed}
    assert set(fast['sensors']) == set(paper['sensors'])


def test_the_fleet_of_agents_is_the_batch_simulator(case1):
    fleet = Fleet.load(case1)
    fleet.run(T)
    batch = BatchSimulator(fleet.s)
    batch.run(T, record_every=0.1)
    for name in fleet.names:
        agent, i = fleet.agents[name], fleet.s.index[name]
        assert agent.t == pytest.approx(T) and agent.k == 60
        np.testing.assert_allclose(agent.p_hat[0], batch.x.p_hat[i], atol=1e-9)
        np.testing.assert_allclose(agent.R_hat[0], batch.x.R_hat[i], atol=1e-9)
        assert not agent.missing and agent.carried == 0 and agent.anchor_still_steps == 0
    assert set(fleet.causes) <= {None, 'not_seen'}


def test_lost_messages_are_left_out_and_the_fleet_still_converges(case1):
    """Robot 1's second round to robot 4 at one step and robot 3's estimate at another are
    lost: each waiting step goes on once the own sensors are link_wait ahead, with the
    sender's newest values carried to its instant by the anchor's motion."""
    h = 1.0 / 30.0

    def lossy(src, dst, t, values):
        if src.agent_id == 1 and dst.agent_id == 4 and abs(t - 10 * h) < 1e-9:
            return 'dropped'
        if src.agent_id == 3 and 'q_hat' in values and abs(t - 20 * h) < 1e-9:
            return 'dropped'
        return dst.add_neighbour(src.agent_id, t, values)

    fleet = Fleet.load(case1, lossy)
    before = _errors(fleet)
    fleet.run(T)
    a = fleet.agents
    # The four round-2 values robot 1 sent robot 4 at that step.
    assert a['robot_4'].carried == 4 and not a['robot_4'].missing
    # Robots 1 and 2 sense robot 3: its newest estimate stands in for the lost one.
    assert a['robot_1'].carried >= 1 and a['robot_2'].carried >= 1
    for agent in a.values():
        assert np.all(np.isfinite(agent.p_hat)) and np.all(np.isfinite(agent.R_hat))
        assert agent.t > T - 0.3   # behind by at most link_wait and a step
    pos, att = _errors(fleet)
    assert pos.mean() < 0.6 * before[0].mean() and att.mean() < 0.6 * before[1].mean()


def test_bad_inputs_are_rejected_with_their_cause(case1):
    fleet = Fleet.load(case1)
    r1 = fleet.agents['robot_1']     # the anchor: it senses robots 2..5
    r4 = fleet.agents['robot_4']     # a free robot, ranged by nobody
    t = r1.gyro.end
    ids = np.array([2, 3, 4, 5, 9])
    bad = np.array([[0.0, 0.0, 1.5], [np.nan, 0, 1], [0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]])
    assert r1.add_bearings(t + 0.01, ids, bad) == ['not_unit', 'non_finite', 'zero_vector',
                                                   'unknown_id']
    rates = np.array([[0, 0, 1e3], [np.inf, 0, 0], [0, 0, 0.1], [0, 0, 0.1], [0, 0, 0]])
    assert r1.add_bearing_rates(t + 0.01, ids, rates) == ['absurd_value', 'non_finite',
                                                         'unknown_id']
    assert r4.add_neighbour_odometry(1, t + 0.01, [np.nan, 0, 0], [0, 0, 0]) == 'non_finite'
    assert r4.add_neighbour_odometry(1, t + 0.01, [0, 0, 0], [0, 0, 100.0]) == 'absurd_rate'
    assert r4.add_neighbour_odometry(1, t + 0.01, [1e3, 0, 0], [0, 0, 0]) == 'absurd_speed'
    assert r4.add_neighbour_odometry(2, t + 0.01, [0, 0, 0], [0, 0, 0]) == 'unknown_id'
    assert r4.add_neighbour(1, t, {'angle_gradient': {4: np.array([np.nan, 0, 0])}}) \
        == 'non_finite'
    assert r4.add_neighbour(1, t, {'angle_hessian': {4: np.zeros(3)}}) == 'malformed'
    assert r4.add_neighbour(1, t, {'no_such_channel': {4: np.zeros(3)}}) == 'unknown_channel'
    fleet.run(1.0)
    for agent in fleet.agents.values():
        assert np.all(np.isfinite(agent.p_hat)) and np.all(np.isfinite(agent.R_hat))
        assert agent.k == 30
