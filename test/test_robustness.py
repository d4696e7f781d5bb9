"""Robustness of one agent's estimator (no ROS): every bad input is rejected with a named cause
and never reaches the estimate; the time rules; stale neighbours; faults on the network."""
from pathlib import Path

import numpy as np
import pytest

from bearing_pose_estimation import so3
from bearing_pose_estimation.agent import Limits, estimator_for
from bearing_pose_estimation.netsim import LinkFaults, Outage, run_network
from bearing_pose_estimation.scenario import load_scenario
from bearing_pose_estimation.world import World

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'
SCENARIO = load_scenario(PAPER)


def _fed(name='agent_6', seconds=1.0):
    """agent_6's estimator fed with consistent data for ``seconds``."""
    world = World(SCENARIO)
    est = estimator_for(SCENARIO, name)
    i = SCENARIO.index[name]
    nbr_ids = [nb.agent_id for nb in est.neighbours]
    while world.t < seconds - 1e-9:
        world.step()
        if world.due(world.imu_every):
            assert est.add_gyro(world.t, world.imu()[i]) is None
        if world.due(world.bearing_every):
            j, b = world.bearings(i)
            assert est.add_bearings(world.t, j + 1, b) == []
            for jid in nbr_ids:  # neighbours' messages: exact world bearings, true p̂
                jj = jid - 1
                d = world.p[i] - world.p[jj]
                assert est.add_neighbour(jid, world.t, world.p[jj],
                                         {est.agent_id: d / np.linalg.norm(d)}) is None
        est.advance()
    return world, est


@pytest.mark.parametrize('omega, now, cause', [
    ([np.nan, 0, 0], None, 'non_finite'), ([np.inf, 0, 0], None, 'non_finite'),
    ([100.0, 0, 0], None, 'absurd_rate'), ([0, 0, 0.1], 0.0, 'future_stamp')])
def test_bad_gyro_samples_are_rejected(omega, now, cause):
    _, est = _fed()
    before = (est.R_hat.copy(), est.gyro.end)
    stamp = est.gyro.end + (5.0 if cause == 'future_stamp' else 0.005)
    assert est.add_gyro(stamp, np.array(omega, float), now=now) == cause
    np.testing.assert_array_equal(est.R_hat, before[0])
    assert est.gyro.end == before[1]
    assert est.add_gyro(est.gyro.end - 0.1, np.zeros(3)) == 'out_of_order'


def test_bad_bearings_are_rejected_point_by_point():
    _, est = _fed()
    t = est.gyro.end + 0.001
    ids = np.array([2, 4, 5, 1, 6, 99])
    b = np.array([[1.0, 0, 0], [np.nan, 0, 0], [0, 0, 0], [0, 2.0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    causes = est.add_bearings(t, ids, b)
    assert sorted(causes) == sorted(['non_finite', 'zero_vector', 'not_unit', 'unknown_id',
                                     'unknown_id'])  # 6 is itself, 99 does not exist
    assert est.add_bearings(t, np.array([2]), np.array([[0, 1.0, 0]])) == ['out_of_order']
    assert est.add_bearings(t + 10.0, np.array([2]), np.array([[0, 1.0, 0]])) == ['future_stamp']
    assert est.add_bearings(-5.0, np.array([2]), np.array([[0, 1.0, 0]])) == ['stale']


def test_bad_neighbour_messages_are_rejected():
    _, est = _fed()
    t = est.gyro.end
    me = est.agent_id
    ok = {me: np.array([0.0, 0.0, 1.0])}
    assert est.add_neighbour(7, t, np.zeros(3), ok) == 'unknown_id'  # not a neighbour of 6
    assert est.add_neighbour(2, t, np.zeros(3), {9: np.ones(3)}) == 'not_seen'
    assert est.add_neighbour(2, t, np.array([np.nan, 0, 0]), ok) == 'non_finite'
    assert est.add_neighbour(2, t, np.zeros(3), {me: np.zeros(3)}) == 'zero_vector'
    assert est.add_neighbour(2, t, np.zeros(3), {me: np.array([0, 0, 3.0])}) == 'not_unit'
    assert est.add_neighbour(2, t + 10.0, np.zeros(3), ok) == 'future_stamp'
    assert est.add_neighbour(2, t - 0.1, np.zeros(3), ok) == 'out_of_order'
    assert est.set_known_pose(t, np.full((3, 3), np.nan), np.zeros(3)) == 'non_finite'


def test_garbage_never_reaches_the_estimate():
    """Random garbage in every input, interleaved with good data: the estimate stays finite,
    on SO(3), and the node keeps stepping."""
    world, est = _fed(seconds=0.5)
    rng = np.random.default_rng(3)
    i = SCENARIO.index['agent_6']
    junk = [np.nan, np.inf, -np.inf, 1e300, -1e300, 0.0, 1e-300]
    for _ in range(400):
        world.step()
        if world.due(world.imu_every):
            est.add_gyro(world.t, world.imu()[i])
        bad = rng.choice(junk, size=3)
        est.add_gyro(world.t + rng.uniform(-2, 2), bad)
        est.add_bearings(world.t + rng.uniform(-2, 2), rng.integers(0, 12, 3), rng.choice(junk, (3, 3)))
        est.add_neighbour(int(rng.integers(1, 9)), world.t + rng.uniform(-2, 2),
                          rng.choice(junk, 3), {6: rng.choice(junk, 3)})
        est.advance()
        assert np.all(np.isfinite(est.R_hat)) and np.all(np.isfinite(est.p_hat))
    assert so3.orthonormality_error(est.R_hat[0]) < 1e-12
    assert est.t > 0.8 and est.non_finite_steps == 0


def test_clock_jump_back_restarts_from_the_initial_estimate():
    world, est = _fed(seconds=3.0)
    assert est.t == pytest.approx(3.0)
    assert est.add_gyro(0.005, np.zeros(3)) == 'time_jump'
    np.testing.assert_array_equal(est.R_hat[0], est.R0)
    np.testing.assert_array_equal(est.p_hat[0], est.p0)
    assert est.t == pytest.approx(0.01)  # next grid instant: the step grid stays aligned
    assert all(nb.stamp is None for nb in est.neighbours)


def test_gyro_gap_restarts_time_and_keeps_the_estimate():
    world, est = _fed(seconds=1.0)
    R, p = est.R_hat.copy(), est.p_hat.copy()
    assert est.add_gyro(7.0033, np.zeros(3)) == 'gyro_gap'
    np.testing.assert_array_equal(est.R_hat, R)
    np.testing.assert_array_equal(est.p_hat, p)
    assert est.t == pytest.approx(7.01)
    assert est.add_gyro(7.0133, np.zeros(3)) is None and est.advance() == 0
    assert est.add_gyro(7.0233, np.zeros(3)) is None and est.advance() == 1


def test_silent_neighbour_goes_stale_and_comes_back():
    world, est = _fed(seconds=1.0)
    assert est.last.edges_used == 3 and est.last.stale == ()
    i = SCENARIO.index['agent_6']
    limits = Limits()
    silent_from = world.t
    while world.t < silent_from + limits.neighbour_timeout + 0.1:  # agent_2 silent
        world.step()
        if world.due(world.imu_every):
            est.add_gyro(world.t, world.imu()[i])
        if world.due(world.bearing_every):
            j, b = world.bearings(i)
            est.add_bearings(world.t, j + 1, b)
            for jid in (4, 5):
                d = world.p[i] - world.p[jid - 1]
                est.add_neighbour(jid, world.t, world.p[jid - 1], {6: d / np.linalg.norm(d)})
        est.advance()
    assert est.last.stale == ('agent_2',) and est.last.edges_used == 2
    d = world.p[i] - world.p[1]
    est.add_neighbour(2, world.t, world.p[1], {6: d / np.linalg.norm(d)})
    world.step()
    est.add_gyro(world.t, world.imu()[i]) if world.due(world.imu_every) else None
    while est.steps_ready() == 0:
        world.step()
        if world.due(world.imu_every):
            est.add_gyro(world.t, world.imu()[i])
    est.advance()
    assert est.last.stale == () and est.last.edges_used == 3


def test_lossy_and_late_links_still_converge():
    """30 % of neighbour messages lost and the rest 200 ms late: still converges, a little
    slower (the README's fault matrix has the figures)."""
    rec = run_network(SCENARIO, 30.0, record_every=1.0,
                      links=LinkFaults(drop_rate=0.3, delay=0.2, seed=2))
    att, pos = rec.att_err.mean(axis=1), rec.pos_err.mean(axis=1)
    assert att[-1] < 5e-4 and pos[-1] < 0.05
    assert att[-1] < 0.01 * att[5] and pos[-1] < 0.05 * pos[5]


def test_restarted_agent_reconverges():
    """agent_4 (a neighbour of 5, 6 and 7) killed at 10 s and restarted at 12 s from its
    initial estimate: errors jump, then converge again."""
    rec = run_network(SCENARIO, 30.0, record_every=1.0,
                      outages=(Outage('agent_4', 10.0, 12.0, restart=True),))
    att = rec.att_err.mean(axis=1)
    k = {int(round(t)): n for n, t in enumerate(rec.t)}
    assert att[k[13]] > 3 * att[k[10]]  # the restart really hurt
    assert att[k[30]] < 0.05 * att[k[13]]
    assert np.all(np.isfinite(rec.att_err)) and np.all(np.isfinite(rec.pos_err))
