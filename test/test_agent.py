"""One agent's estimator without ROS: gyro buffering, time alignment, and agreement of a fleet
of per-agent estimators (fed by the simulator node's world model) with the batch simulator."""
from pathlib import Path

import numpy as np
import pytest

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.estimators.agent import estimator_for
from bearing_pose_estimation.core.gyro import GyroBuffer
from bearing_pose_estimation.sim.netsim import run_network
from bearing_pose_estimation.scenario import load_scenario
from bearing_pose_estimation.sim.batch import BatchSimulator
from bearing_pose_estimation.sim.world import World

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'


def test_gyro_buffer_integrates_piecewise_constant_rates_exactly():
    buf = GyroBuffer(start=0.0)
    w1, w2 = np.array([1.0, -2.0, 0.5]), np.array([0.3, 0.0, 3.0])
    assert buf.add(0.005, w1) and buf.add(0.010, w2)
    assert not buf.add(0.010, w1)  # not newer: ignored
    np.testing.assert_allclose(buf.increment(0.0, 0.010), so3.exp(w1 * 0.005) @ so3.exp(w2 * 0.005),
                               atol=1e-15)
    np.testing.assert_allclose(buf.increment(0.002, 0.007),
                               so3.exp(w1 * 0.003) @ so3.exp(w2 * 0.002), atol=1e-15)
    np.testing.assert_allclose(buf.increment(0.007, 0.002), buf.increment(0.002, 0.007).T)
    with pytest.raises(ValueError, match='covers'):
        buf.increment(0.0, 0.011)


def test_gyro_buffer_forgets_old_samples():
    buf = GyroBuffer(start=0.0, horizon=0.1)
    for k in range(1, 101):
        buf.add(k * 0.01, np.zeros(3))
    assert buf.start == pytest.approx(0.9, abs=0.011) and buf.end == pytest.approx(1.0)
    assert not buf.covers(0.5, 1.0) and buf.covers(0.95, 1.0)


def _world_and_agents(scenario):
    world = World(scenario)
    agents = {a.name: estimator_for(scenario, a.name) for a in scenario.agents}
    return world, agents


def test_distributed_logic_matches_batch_simulator():
    """The node's logic without DDS (netsim: gyro at 200 Hz, bearings at 50 Hz aligned to each
    step with the gyro, estimator at 100 Hz, neighbour data at 50 Hz): the errors track the
    batch simulator closely, and keep converging."""
    scenario = load_scenario(PAPER)
    dist = run_network(scenario, 20.0, record_every=0.1)
    rec = BatchSimulator(scenario).run(20.0, record_every=0.1)
    for t in (5.0, 10.0, 20.0):
        k = int(round(t / 0.1))
        j = int(np.argmin(np.abs(dist.t - t)))
        att_b, pos_b = rec.att_err[k].mean(), rec.pos_err[k].mean()
        att_d, pos_d = dist.att_err[j].mean(), dist.pos_err[j].mean()
        assert abs(att_d - att_b) <= 0.02 * att_b, (t, att_d, att_b)
        assert abs(pos_d - pos_b) <= 0.02 * pos_b, (t, pos_d, pos_b)
    assert dist.att_err[-1].mean() < 1e-3 and dist.pos_err[-1].mean() < 0.2


def test_leader_follows_its_known_pose_between_samples():
    """Known pose at 50 Hz, gyro at 200 Hz: the leader's estimate is its true pose at every
    step, not only at the pose samples."""
    scenario = load_scenario(PAPER)
    world, agents = _world_and_agents(scenario)
    leader = agents['agent_1']
    i = scenario.index['agent_1']
    worst = 0.0
    while world.t < 2.0 - 1e-9:
        world.step()
        if world.due(world.imu_every):
            leader.add_gyro(world.t, world.imu()[i])
        if world.due(world.truth_every):
            leader.set_known_pose(world.t, world.R[i], world.p[i])
        if leader.advance():
            if abs(leader.t - world.t) < 1e-9:
                worst = max(worst, float(so3.angle(world.R[i] @ leader.R_hat[0].T)))
    assert worst < 1e-9
    np.testing.assert_array_equal(leader.p_hat[0], world.p[i])


def test_stale_bearing_is_rotated_to_the_step_time():
    """A bearing measured 20 ms before the state time is rotated with the gyro: the pairing
    error it would cause (|ω| · 20 ms ≈ 0.05 rad here) is gone."""
    scenario = load_scenario(PAPER)
    world, agents = _world_and_agents(scenario)
    ag = agents['agent_5']
    i = scenario.index['agent_5']
    j, b0 = world.bearings(i)
    ag.add_bearings(0.0, j + 1, b0)
    while world.t < 0.02 - 1e-9:
        world.step()
        if world.due(world.imu_every):
            ag.add_gyro(world.t, world.imu()[i])
    ag.advance()
    assert ag.t == pytest.approx(0.02)
    _, b_now = world.bearings(i)
    for k, target in enumerate(j + 1):
        aligned = ag.body_bearing(int(target), ag.t)
        assert np.linalg.norm(aligned - b_now[k]) < 1e-9
        assert np.linalg.norm(b0[k] - b_now[k]) > 0.02  # the raw sample really is stale


def test_gyro_buffer_bridges_lost_samples_with_the_neighbouring_rates():
    """Every 10th interval-average sample of ω(t) = (sin 9t, cos 5t, 1) at 200 Hz is lost.
    Bridging each gap with the mean of the rates on either side keeps the increment over 1 s
    20 times closer to the truth than holding the next sample's rate over the gap."""
    dt = 0.005

    def average_rate(t0, t1):  # exact interval average of ω over (t0, t1]
        return np.array([(np.cos(9 * t0) - np.cos(9 * t1)) / 9,
                         (np.sin(5 * t1) - np.sin(5 * t0)) / 5, t1 - t0]) / (t1 - t0)

    full, lossy = GyroBuffer(start=0.0), GyroBuffer(start=0.0)
    held_R = np.eye(3)  # what holding the next rate over the gap would give
    last = 0.0
    for k in range(1, 201):
        t = k * dt
        w = average_rate(t - dt, t)
        full.add(t, w)
        if k % 10 == 5:
            continue  # lost
        lossy.add(t, w)
        held_R = held_R @ so3.exp(w * (t - last))
        last = t
    truth = full.increment(0.0, 1.0)  # exact: these rates are the true interval averages
    bridged, held = (so3.angle(truth.T @ R) for R in (lossy.increment(0.0, 1.0), held_R))
    assert bridged < 5e-5 and held > 3e-4  # measured: 2.3e-5 and 4.5e-4
    # A regular sampling period is not mistaken for a gap, even after one.
    assert np.allclose(np.diff(lossy._t[-5:]), dt)
