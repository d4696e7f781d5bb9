"""The one agent runtime (runtime/agent.py): every method's agent logic without ROS, configured
by the method's declarations, tested by behaviour. Where a behaviour concerns several
communication patterns it runs on each: leader bearings (Boughellaba & Tayebi, Tran et al.),
two-way links (De Carli et al.), two rounds and an anchor (Presenza et al.).

- Own motion: the gyro buffer integrates exactly, forgets, bridges lost samples; an own
  measurement is rotated to the step's instant; a leader follows its known pose.
- A fleet of runtimes fed by the simulator node's world is the batch simulator: exactly where
  every input is paired at its instant (link methods, messages delivered at once), within 2 %
  on netsim (leader bearings).
- The fixed exchange of a simulation: the steps do not depend on the order of arrival, and a
  silent neighbour holds them at most ``link_wait``.
- What neighbours send: a value found by its stamp; an owner's "none yet"; lost values carried
  to their instant; a silent neighbour left out after the timeout.
- Steps run together (an ``estimators`` process) equal each agent's own, bit for bit (but
  Presenza et al.'s covariance: to rounding, a known bug).
- Bad inputs are rejected with their cause and never reach the estimate.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.core.gyro import GyroBuffer
from bearing_pose_estimation.core.motion import in_anchor_frame
from bearing_pose_estimation.estimators import get as estimator_class, methods
from bearing_pose_estimation.estimators.base import Sensor, StepInputs
from bearing_pose_estimation.runtime.agent import reads
from bearing_pose_estimation.runtime.buffers import Exchange, Limits
from bearing_pose_estimation.runtime.faults import LinkFaults
from bearing_pose_estimation.scenario import load_scenario, parse_scenario
from bearing_pose_estimation.scenario.parse import read_scenario_data
from bearing_pose_estimation.scenario.runtimes import agent_specs, runtime_for
from bearing_pose_estimation.sim.batch import BatchSimulator
from bearing_pose_estimation.sim.netsim import Garbage, _Network, run_network
from bearing_pose_estimation.sim.world import World

sys.path.insert(0, str(Path(__file__).resolve().parent))
from presenza_fleet import CAMERA_RATE, ROOT, Fleet  # noqa: E402

CONFIG = ROOT / 'config'
PAPER = CONFIG / 'paper_8_agents.yaml'
LEADER_METHODS = ['boughellaba_tayebi', 'tran_anderson_ahn']


def runtime(scenario, name: str, limits: Limits = Limits(), exchange: Exchange | None = None):
    """Agent ``name``'s runtime as the scenario defines it."""
    spec = agent_specs(scenario)[scenario.index[name]]
    return runtime_for(scenario, spec, limits, exchange)


def de_carli():
    """De Carli et al.'s eight quadrotors, the world owning the truth."""
    data = read_scenario_data(CONFIG / 'de_carli_8_quadrotors.yaml')
    data['formation_control']['mode'] = 'exogenous'
    return parse_scenario(data)


def presenza_camera_rate(duration: float = 2.0):
    """Presenza et al.'s case 1 at 30 Hz, cut to ``duration``."""
    d = yaml.safe_load(CAMERA_RATE.read_text())
    d['duration'] = duration
    return parse_scenario(d)


def paper(method: str = 'boughellaba_tayebi'):
    """The paper's eight static agents, two of them leaders, with ``method``."""
    s = load_scenario(PAPER)
    return s if method == s.method else s.with_method(method)


# ------------------------------------------------------------------------------ own motion
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


def test_a_stale_measurement_is_rotated_to_the_step_time():
    """A bearing measured 20 ms before the state time is rotated with the gyro: the pairing
    error it would cause (|ω| · 20 ms ≈ 0.05 rad here) is gone."""
    scenario = paper()
    world = World(scenario)
    ag = runtime(scenario, 'agent_5')
    i = scenario.index['agent_5']
    j, b0 = world.bearings(i)
    assert ag.add_points(Sensor.BEARINGS, 0.0, j + 1, b0) == []
    while world.t < 0.02 - 1e-9:
        world.step()
        if world.due(world.imu_every):
            ag.add_gyro(world.t, world.imu()[i])
    ag.advance()
    assert ag.t == pytest.approx(0.02)
    _, b_now = world.bearings(i)
    for k, target in enumerate(j + 1):
        aligned = ag.body_measurement(Sensor.BEARINGS, int(target), ag.t)
        assert np.linalg.norm(aligned - b_now[k]) < 1e-9
        assert np.linalg.norm(b0[k] - b_now[k]) > 0.02  # the raw sample really is stale


@pytest.mark.parametrize('method', LEADER_METHODS)
def test_a_leader_follows_its_known_pose_between_samples(method):
    """Known pose at 50 Hz, gyro at 200 Hz: the leader's estimate is its true pose at every
    step, not only at the pose samples."""
    scenario = paper(method)
    world = World(scenario)
    leader = runtime(scenario, 'agent_1')
    assert leader.leader
    i = scenario.index['agent_1']
    worst, steps = 0.0, 0
    while world.t < 2.0 - 1e-9:
        world.step()
        if world.due(world.imu_every):
            assert leader.add_gyro(world.t, world.imu()[i]) is None
        if world.due(world.truth_every):
            assert leader.add_known_pose(world.t, world.R[i], world.p[i]) is None
        if leader.advance():
            steps += 1
            if abs(leader.t - world.t) < 1e-9:
                worst = max(worst, float(so3.angle(world.R[i] @ leader.R_hat[0].T)))
    assert steps > 100 and worst < 1e-9
    np.testing.assert_array_equal(leader.p_hat[0], world.p[i])


# ------------------------------------------------------------------ a fleet is the batch
def test_the_camera_rate_config_is_case_1_but_for_the_rates_and_the_scheme():
    """What the Presenza fleets here run: the paper's case 1, every rate at 30 Hz."""
    fast = yaml.safe_load(CAMERA_RATE.read_text())
    paper_case = yaml.safe_load((CONFIG / 'presenza_case1.yaml').read_text())
    assert fast['frequency'] == fast['publish_rate'] == 30.0
    assert {spec['rate'] for spec in fast['sensors'].values()} == {30.0}
    assert fast['simulation'] == {'internal_step': pytest.approx(1 / 300), 'imu_rate': 30.0,
                                  'bearing_rate': 30.0, 'ground_truth_rate': 30.0}
    assert fast['gains'] == {**paper_case['gains'], 'preconditioning': 1.0}
    changed = {'name', 'description', 'frequency', 'publish_rate', 'gains', 'sensors',
               'simulation'}
    assert {k: v for k, v in fast.items() if k not in changed} == \
        {k: v for k, v in paper_case.items() if k not in changed}
    assert set(fast['sensors']) == set(paper_case['sensors'])


@pytest.mark.parametrize('make', [de_carli, presenza_camera_rate], ids=['de_carli', 'presenza'])
def test_a_fleet_of_runtimes_is_the_batch_simulator(make):
    """Fed from the world on its fine grid (sensors at their own rates), every message
    delivered at once: every agent's state after T equals the batch row, step for step (each
    input is paired at its instant: the own measurements interpolated, the others' values of
    that instant, both rounds, the other ends' or the anchor's odometry), and nothing was
    missing, carried or taken as still."""
    T = 2.0
    s = make()
    fleet = Fleet(s)
    fleet.run(T)
    batch = BatchSimulator(s)
    for _ in range(int(round(T / batch.h))):
        batch.step()
    for name in fleet.names:
        agent, i = fleet.agents[name], s.index[name]
        assert agent.t == pytest.approx(T) and agent.k == round(T / s.step)   # 400, 60
        np.testing.assert_allclose(agent.p_hat[0], batch.x.p_hat[i], atol=1e-9)
        np.testing.assert_allclose(agent.R_hat[0], batch.x.R_hat[i], atol=1e-9)
        if hasattr(agent.x, 'z_hat'):   # De Carli et al.'s unnormalised yaw
            np.testing.assert_allclose(agent.x.z_hat[0], batch.x.z_hat[i], atol=1e-9)
        assert not +agent.missing, (name, agent.missing)
        assert not agent.incomplete and agent.carried == 0 and agent.anchor_still_steps == 0
    assert set(fleet.causes) <= {None, 'not_seen'}


def test_netsim_tracks_the_batch_simulator():
    """The node's logic without DDS (netsim: gyro at 200 Hz, bearings at 50 Hz aligned to each
    step with the gyro, estimator at 100 Hz, neighbour data at 50 Hz): the errors track the
    batch simulator closely, and keep converging."""
    scenario = paper()
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


# ------------------------------------------------------------------ the fixed exchange
def _streams(scenario, name: str, duration: float, seed: int) -> dict[str, list]:
    """Agent ``name``'s inputs over ``duration`` as the simulator sends them, one stream per
    topic (DDS keeps each topic's order, not the order between topics): gyro at 200 Hz,
    bearings at 50 Hz and, from each neighbour j at its 50 Hz publish instants, p̂_j and the
    world bearing b^j_ji (noisy stand-ins: this test is about which values a step uses)."""
    rng = np.random.default_rng(seed)
    world = World(scenario)
    i = scenario.index[name]
    me = scenario.agent_id(name)
    streams: dict[str, list] = {'gyro': [], 'bearings': []}
    for j in scenario.agents[i].neighbours:
        streams[j.name] = []
    while True:   # through t = duration for the bearings and neighbours: the last step reads them
        if world.due(world.bearing_every):
            ids, b = world.bearings(i)
            streams['bearings'].append((world.t, ids + 1, b))
            for nb in scenario.agents[i].neighbours:
                j = scenario.index[nb.name]
                wb = world.p[i] - world.p[j]
                wb = wb / np.linalg.norm(wb) + rng.normal(0, 1e-3, 3)
                streams[nb.name].append((scenario.agent_id(nb.name), world.t, {
                    'p_hat': world.p[j] + rng.normal(0, 0.1, 3),
                    'world_bearing': {me: wb / np.linalg.norm(wb)}}))
        if world.t >= duration - 1e-9:
            return streams
        world.step()
        if world.due(world.imu_every):
            streams['gyro'].append((world.t, world.imu()[i]))


def _feed(agent, streams: dict[str, list], order: list[str]) -> list:
    """Feed the streams in the interleaving ``order`` (a stream name per input), stepping
    after each input as the node does; the estimate after every step."""
    pos = dict.fromkeys(streams, 0)
    out = []
    for name in order:
        item = streams[name][pos[name]]
        pos[name] += 1
        if name == 'gyro':
            assert agent.add_gyro(*item) is None
        elif name == 'bearings':
            assert agent.add_points(Sensor.BEARINGS, *item) == []
        else:
            assert agent.add_message(*item) is None
        while agent.advance(1):
            out.append((agent.t, agent.R_hat[0].copy(), agent.p_hat[0].copy()))
    return out


def _netsim_order(streams: dict[str, list]) -> list[str]:
    """By stamp; at one instant the bearings, the gyro (the step runs), the neighbours."""
    keyed = [(item[0], 1, 'gyro') for item in streams['gyro']]
    keyed += [(item[0], 0, 'bearings') for item in streams['bearings']]
    keyed += [(item[1], 2, nb) for nb in streams if nb not in ('gyro', 'bearings')
              for item in streams[nb]]
    return [s for _, _, s in sorted(keyed)]


@pytest.mark.parametrize('method', LEADER_METHODS)
def test_the_fixed_exchange_makes_the_steps_independent_of_the_arrival_order(method):
    """With an Exchange (the node under use_sim_time), step [t, t + h] uses the own bearings
    measured by t + h and each neighbour's values of its publish instant at or before t, and
    waits for them: whatever the interleaving of the topics, and however far the gyro runs
    ahead (within link_wait), the estimates equal to rounding (1e-12; the gyro buffer's
    segments depend on how far it reaches) those of the order netsim feeds them (an instant's
    bearings before its step, the neighbours' values after). Without it, late inputs change
    them."""
    scenario = paper(method)
    name = 'agent_6'   # three neighbours
    streams = _streams(scenario, name, 0.5, seed=3)

    def shuffled(seed: int) -> list[str]:   # each input late by up to 0.2 s (< link_wait)
        rng = np.random.default_rng(seed)
        arrivals = []
        for s in streams:
            stamps = [item[1] if isinstance(item[0], int) else item[0] for item in streams[s]]
            late = np.maximum.accumulate(stamps + rng.uniform(0.0, 0.2, len(stamps)))
            arrivals += [(a, s) for a in late]   # each topic keeps its order
        return [s for _, s in sorted(arrivals, key=lambda a: a[0])]

    def run(order: list[str], exchange: bool) -> list:
        agent = runtime(scenario, name,
                        exchange=Exchange(0.02, 0.02, 0.02) if exchange else None)
        steps = _feed(agent, streams, order)
        assert not agent.incomplete
        return steps

    reference = run(_netsim_order(streams), exchange=False)
    assert len(reference) == 50
    for order in (_netsim_order(streams), shuffled(1), shuffled(2)):
        steps = run(order, exchange=True)
        assert len(steps) == 50
        for (t, R, p), (t_ref, R_ref, p_ref) in zip(steps, reference):
            assert t == t_ref
            np.testing.assert_allclose(R, R_ref, rtol=0, atol=1e-12)
            np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-12)
    # Without the exchange, the same shuffled arrival changes the estimate.
    ahead = run(shuffled(1), exchange=False)
    assert max(np.abs(p - p_ref).max() for (_, _, p), (_, _, p_ref) in zip(ahead, reference)) > 1e-6


def test_the_fixed_exchange_waits_for_a_silent_neighbour_at_most_link_wait():
    """A lost message is known lost once a later one from the same neighbour arrives (a
    topic keeps its order): the step reads the neighbour's newest values before it, without
    waiting. A neighbour that falls silent (its process died) holds the steps until the gyro
    is ``link_wait`` (0.25 s) ahead of them; they then go on, counted as incomplete."""
    scenario = paper()

    def run(streams: dict[str, list]):
        agent = runtime(scenario, 'agent_6', exchange=Exchange(0.02, 0.02, 0.02))
        steps = _feed(agent, streams, _netsim_order(streams))
        return agent, steps

    streams = _streams(scenario, 'agent_6', 0.5, seed=3)
    full = streams['agent_4']
    streams['agent_4'] = full[:2] + full[3:]   # its values of t = 0.04 lost
    agent, steps = run(streams)
    assert agent.t == pytest.approx(0.5) and not agent.incomplete

    streams['agent_4'] = full[:2]              # silent after t = 0.02
    agent, steps = run(streams)
    # The step [0.04, 0.05] first waits; every step then runs 0.25 s of gyro late.
    assert agent.awaited == agent.awaited_peer == 'agent_4'
    assert agent.t == pytest.approx(0.5 - 0.25, abs=0.011)
    assert agent.incomplete == {'agent_4': len(steps) - 4}


# ------------------------------------------------------------------ what neighbours send
def test_a_value_is_found_by_its_stamp_among_many():
    """A neighbour's value stamped t among a full history (a step that waited looks back)
    (``Stamped.at``), none between two stamps or before the oldest (decided: a newer one is
    here), none yet after the newest (not decided: it may still come)."""
    r1 = runtime(de_carli(), 'robot_1')
    peer = next(p for p in r1.peers if p.name == 'robot_0')
    stamps = 0.01 * np.arange(300)   # more than the history holds: the oldest drop out
    for t in stamps:
        if t > 0:   # the gyro covers j's stamps: else they are "future"
            assert r1.add_gyro(float(t), np.zeros(3)) is None
        assert r1.add_message(1, float(t), {'z_hat': np.array([np.cos(t), np.sin(t)])}) is None
    hist = peer.values['z_hat']
    kept = stamps[-len(hist.samples):]
    assert len(kept) < len(stamps)
    for t in (kept[0], kept[17], kept[-2], kept[-1]):
        value, decided = hist.at(float(t) + 4e-10)   # rounding: still t
        assert decided and np.array_equal(value, [np.cos(t), np.sin(t)]), t
    for t in (kept[5] + 0.005, kept[0] - 0.01, stamps[0]):
        assert hist.at(float(t)) == (None, True), t
    assert hist.at(float(kept[-1]) + 0.01) == (None, False)


def test_an_owner_says_when_it_has_no_relative_yaw_yet():
    """De Carli's relative yaw travels only from the pair's owner. Until it has one the owner
    sends zeros, not nothing: "none yet", which the listener's step takes as the batch step
    does, without waiting for a value that will not come (over DDS it waited out the
    wall-clock patience and went on without the neighbour: 5 % off the batch run). A message
    that does not list our pair still says nothing."""
    s = de_carli()
    r0, r1 = runtime(s, 'robot_0'), runtime(s, 'robot_1')
    owner = next(p for p in r1.peers if p.name == 'robot_0')
    assert not owner.flags['owns']   # two-way pair: robot_0 (id 1, the lower) owns it
    sent = r0.outbox()
    np.testing.assert_array_equal(sent['relyaw'][2], [0.0, 0.0])   # t = 0: none yet, for id 2
    assert list(sent['relyaw']) == [2]   # robot_0 owns no other pair
    assert r1.add_message(1, 0.0, {'z_hat': sent['z_hat'], 'relyaw': sent['relyaw']}) is None
    value, decided = owner.values['relyaw'].at(0.0)
    assert decided and np.array_equal(value, np.zeros(2))
    assert r1.add_message(1, 0.01, {'relyaw': {2: np.array([0.0, 1.0])}}) is None
    assert np.array_equal(owner.values['relyaw'].at(0.01)[0], [0.0, 1.0])
    assert r1.add_message(1, 0.02, {'relyaw': {99: np.array([1.0, 0.0])}}) == 'not_seen'
    assert r1.add_message(1, 0.02, {'relyaw': {2: np.array([0.0, 3.0])}}) == 'not_unit'


def test_zeros_from_a_pair_s_non_owner_are_garbage():
    """Only the owner of a pair sends its relative yaw: zeros from the other robot are not
    "none yet" but a zero vector, rejected (as before the one runtime)."""
    s = de_carli()
    r0 = runtime(s, 'robot_0')   # owns its pair with robot_1 (id 2)
    assert r0.add_message(2, 0.0, {'relyaw': {1: np.zeros(2)}}) == 'zero_vector'


def _errors(fleet: Fleet) -> tuple[np.ndarray, np.ndarray]:
    """Per robot position [m] and attitude [rad] errors in the anchor frame, now."""
    R, p = in_anchor_frame(fleet.world.R, fleet.world.p, fleet.s.index[fleet.s.anchor])
    agents = [fleet.agents[n] for n in fleet.names]
    p_hat = np.stack([a.p_hat[0] for a in agents])
    R_hat = np.stack([a.R_hat[0] for a in agents])
    return (np.linalg.norm(p_hat - p, axis=1),
            so3.angle(R @ np.swapaxes(R_hat, -1, -2)))


def test_lost_messages_are_carried_to_their_instant_and_the_fleet_still_converges():
    """Presenza et al.: robot 1's second round to robot 4 at one step and robot 3's estimate
    at another are lost: each waiting step goes on once the own sensors are link_wait ahead,
    with the sender's newest values carried to its instant by the anchor's motion."""
    T = 2.0
    h = 1.0 / 30.0

    def lossy(src, dst, t, values):
        if src.agent_id == 1 and dst.agent_id == 4 and abs(t - 10 * h) < 1e-9:
            return 'dropped'
        if src.agent_id == 3 and 'q_hat' in values and abs(t - 20 * h) < 1e-9:
            return 'dropped'
        return dst.add_message(src.agent_id, t, values)

    fleet = Fleet(presenza_camera_rate(T), lossy)
    before = _errors(fleet)
    fleet.run(T)
    a = fleet.agents
    assert fleet.causes.count('dropped') > 1
    # The four round-2 values robot 1 sent robot 4 at that step, carried together (the
    # counter counts the edges and rounds carried, not the values).
    assert a['robot_4'].carried == 1 and not +a['robot_4'].missing
    # Robots 1 and 2 sense robot 3: its newest estimate stands in for the lost one.
    assert a['robot_1'].carried >= 1 and a['robot_2'].carried >= 1
    for agent in a.values():
        assert np.all(np.isfinite(agent.p_hat)) and np.all(np.isfinite(agent.R_hat))
        assert agent.t > T - 0.3   # behind by at most link_wait and a step
    pos, att = _errors(fleet)
    assert pos.mean() < 0.6 * before[0].mean() and att.mean() < 0.6 * before[1].mean()


@pytest.mark.parametrize('make, silent, listeners', [
    (de_carli, 'robot_7', ('robot_3', 'robot_4', 'robot_6')),
    (presenza_camera_rate, 'robot_3', ('robot_1', 'robot_2'))], ids=['de_carli', 'presenza'])
def test_a_silent_neighbour_is_left_out_after_the_timeout(make, silent, listeners):
    """An agent that never sends anything: the agents that read it wait for it no longer than
    the neighbour timeout of their own clock, then step without it (counted as missing, by
    what)."""
    s = make()
    fleet = Fleet(s, silent={silent})
    fleet.run(1.5)
    for n in listeners:
        agent = fleet.agents[n]
        peer = next(p for p in agent.peers if p.name == silent)
        assert not peer.values and agent.t > 0.9, (n, agent.t)
        assert silent in agent.stale_neighbours(agent.t)
        sent = [c.name for c in agent.channels.values() if reads(peer.flags, c)
                and not c.optional]
        assert sent and all(agent.missing[c] > 0 for c in sent), (n, agent.missing)


# ------------------------------------------------------------------ steps run together
def _assert_same_step(a, b, where: str, rounding: tuple[str, ...] = ()) -> None:
    """Agents ``a`` (its own step) and ``b`` (stepped together with others) hold the same
    state and step diagnostics, bit for bit (the fields ``rounding``: to rounding); De Carli
    et al.'s robots keep per-link state in as many slots as the most links among those
    stepped together: ``b``'s extra slots are zero."""
    for f in dataclasses.fields(a.x):
        own, together = getattr(a.x, f.name), getattr(b.x, f.name)
        if own.shape != together.shape:   # link slots: (1, D, ...)
            assert not np.any(together[:, own.shape[1]:]), f.name
            together = together[:, :own.shape[1]]
        if f.name in rounding:
            np.testing.assert_allclose(own, together, rtol=1e-12, atol=1e-15 * np.abs(own).max(),
                                       err_msg=f'{where}: {f.name}')
        else:
            np.testing.assert_array_equal(own, together, err_msg=f'{where}: {f.name}')
    assert a.last.diagnostics.keys() == b.last.diagnostics.keys()
    for key, value in a.last.diagnostics.items():
        np.testing.assert_array_equal(value, b.last.diagnostics[key], err_msg=where)


def _networks_stepped_both_ways(scenario, duration: float, links: LinkFaults, check):
    """netsim of ``scenario`` twice, its agents' steps run one by one and together; after
    every tick ``check(agent stepped alone, the same stepped together, where)`` for each
    agent. Returns the network stepped together and how many agents shared each call."""
    sizes: list[int] = []
    stack = StepInputs.stack

    def counted(parts, same_t=True):
        sizes.append(len(parts))
        return stack(parts, same_t)
    nets = [_Network(scenario, links, (), Garbage(), Limits(), batched=b) for b in (False, True)]
    for net in nets:
        net.start()
    dt = nets[0].world.dt
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(StepInputs, 'stack', staticmethod(counted))
        for tick in range(1, int(round(duration / dt)) + 1):
            for net in nets:
                net.tick(tick * dt)
            for name in nets[0].names:
                a, b = (net.agents[name] for net in nets)
                assert (a.k, a.last.t, a.last.edges_used, a.last.stale) == (
                    b.k, b.last.t, b.last.edges_used, b.last.stale), name
                check(a, b, f'{name} at tick {tick}')
    return nets[1], sizes


PRESENZA_P = ('P',)   # see test_presenza_covariances_stepped_together_are_bit_exact


@pytest.mark.parametrize('make, duration, together, rounding', [
    (lambda: load_scenario(CONFIG / 'paper_noisy.yaml'), 1.5, 6, ()),
    (lambda: load_scenario(CONFIG / 'paper_noisy.yaml').with_method('tran_anderson_ahn'),
     1.5, 6, ()),
    (lambda: load_scenario(CONFIG / 'paper_8_agents_moving.yaml'), 1.5, 6, ()),
    (de_carli, 0.6, 8, ()),
    (lambda: load_scenario(CONFIG / 'presenza_case1.yaml'), 0.5, 5, PRESENZA_P),
    (lambda: load_scenario(CONFIG / 'presenza_noisy.yaml'), 1.5, 5, PRESENZA_P)],
    ids=['boughellaba_tayebi', 'tran_anderson_ahn', 'moving', 'de_carli', 'presenza',
         'presenza_noisy'])
def test_steps_run_together_give_each_agent_its_own_steps_exactly(make, duration, together,
                                                                  rounding):
    """advance_together (an estimators process's agents in one call of the method's step)
    against each agent's own steps, on netsim with lost and late neighbour messages (each
    step's neighbours differ) and, moving, odometry; two rounds and an anchor (Presenza et
    al.; noisy: the covariance); per-link state (De Carli et al.): every agent's state,
    covariance included, and step diagnostics bit for bit, at every tick. Up to ``together``
    agents shared one call."""
    scenario = make()
    net, sizes = _networks_stepped_both_ways(
        scenario, duration, LinkFaults(drop_rate=0.2, delay=0.03, seed=3),
        lambda a, b, where: _assert_same_step(a, b, where, rounding))
    assert max(sizes) == together, sizes
    followers = [a for a in net.agents.values() if not a.leader]
    # Stepping on, at most link_wait behind their own sensors.
    assert all(a.k >= 0.9 * (duration - Limits().link_wait) / scenario.step for a in followers)
    assert all(a.last.odometry == scenario.simulates('odometry') for a in followers)
    if scenario.method == 'de_carli':
        assert all(np.any(a.x.ready_out) for a in net.agents.values())   # per-link state in use
        # Robots with fewer links than others (here all have 3): their state grows to the
        # most.
        x0, x1 = (a.x for a in list(net.agents.values())[:2])
        both = type(x0).stack([x0, x1.grown(5)])
        assert both.P_out.shape[:2] == (2, 5) and not np.any(both.P_out[0, 3:])
        np.testing.assert_array_equal(both.P_out[0, :3], x0.P_out[0])


def test_steps_of_different_instants_run_together_exactly(monkeypatch):
    """An ``estimators`` process flushes agents a step apart in one round: a method whose step
    does not read its time (not ``timed_step``) runs them in one call, each getting its own
    step bit for bit. agent_4 is held back every other step in both networks (with noise and
    covariances), so it and those waiting for it lag a step."""
    import bearing_pose_estimation.sim.netsim as netsim

    scenario = load_scenario(CONFIG / 'paper_noisy.yaml')
    real, stack = netsim.advance_together, StepInputs.stack
    nets = [_Network(scenario, LinkFaults(), (), Garbage(), Limits()) for _ in range(2)]
    alone = {id(a) for a in nets[0].agents.values()}
    ready_at, stacked_at = [], []   # how many instants: ready in one round, in one call
    per_step = nets[0].per_step
    tick = 0

    def held(agents):
        agents = [a for a in agents if not (a.name == 'agent_4' and tick // per_step % 2)]
        if id(agents[0]) in alone:
            return [a for a in agents if a.advance(1)]
        ready_at.append(len({a.t for a in agents if a.steps_ready() > 0 and not a.leader}))
        return real(agents)

    def counted(parts, same_t=True):
        stacked_at.append(len({p.t for p in parts}))
        return stack(parts, same_t)
    monkeypatch.setattr(netsim, 'advance_together', held)
    monkeypatch.setattr(StepInputs, 'stack', staticmethod(counted))
    for net in nets:
        net.start()
    for tick in range(1, int(round(0.5 / scenario.step)) * nets[0].per_step + 1):
        for net in nets:
            net.tick(tick * nets[0].world.dt)
        for name in nets[0].names:
            a, b = (net.agents[name] for net in nets)
            assert (a.k, a.last.t) == (b.k, b.last.t), name
            _assert_same_step(a, b, f'{name} at tick {tick}', ())
    assert max(ready_at) > 1 and max(stacked_at) > 1, (ready_at, stacked_at)


@pytest.mark.parametrize('method', methods())
def test_a_step_that_reads_its_time_says_so(method):
    """``timed_step`` (only steps of one instant share a call) is declared exactly by the
    methods whose step depends on its start time: the same inputs stamped one to three steps
    later give another state."""
    cls = estimator_class(method)
    sim = BatchSimulator(load_scenario(CONFIG / cls.reference_scenario))
    for _ in range(3):
        sim.step()
    inputs = sim.inputs()
    first, _ = sim.estimator.step(sim.x, sim.h, inputs)
    later = [sim.estimator.step(sim.x, sim.h,
                                dataclasses.replace(inputs, t=inputs.t + s * sim.h))[0]
             for s in (1, 2, 3)]
    differs = any(not np.array_equal(getattr(first, f.name), getattr(x, f.name))
                  for x in later for f in dataclasses.fields(first))
    assert differs == cls.timed_step, method


def test_presenza_covariances_stepped_together_are_bit_exact():
    """Presenza et al.'s sensing robots (the anchor among them) stepped together: their
    covariance is exactly their own steps' too, as every other state is."""
    def same_covariance(a, b, where):
        np.testing.assert_array_equal(a.x.P, b.x.P, err_msg=where)
    _networks_stepped_both_ways(load_scenario(CONFIG / 'presenza_case1.yaml'), 0.01,
                                LinkFaults(), same_covariance)


# ------------------------------------------------------------------ bad inputs
def test_bad_inputs_are_rejected_with_their_cause():
    """Presenza et al.'s inputs (the leader-bearing methods': test_robustness.py): own bearings
    and bearing rates point by point, the anchor's odometry, the others' channels; the fleet
    then steps on, finite."""
    fleet = Fleet(presenza_camera_rate())
    r1 = fleet.agents['robot_1']     # the anchor: it senses robots 2..5
    r4 = fleet.agents['robot_4']     # a free robot, ranged by nobody
    t = r1.gyro.end
    ids = np.array([2, 3, 4, 5, 9])
    bad = np.array([[0.0, 0.0, 1.5], [np.nan, 0, 1], [0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]])
    assert r1.add_points(Sensor.BEARINGS, t + 0.01, ids, bad) == [
        'not_unit', 'non_finite', 'zero_vector', 'unknown_id']
    rates = np.array([[0, 0, 1e3], [np.inf, 0, 0], [0, 0, 0.1], [0, 0, 0.1], [0, 0, 0]])
    assert r1.add_points(Sensor.BEARING_RATES, t + 0.01, ids, rates) == [
        'absurd_value', 'non_finite', 'unknown_id']
    assert r4.add_peer_odometry(1, t + 0.01, [np.nan, 0, 0], [0, 0, 0]) == 'non_finite'
    assert r4.add_peer_odometry(1, t + 0.01, [0, 0, 0], [0, 0, 100.0]) == 'absurd_rate'
    assert r4.add_peer_odometry(1, t + 0.01, [1e3, 0, 0], [0, 0, 0]) == 'absurd_speed'
    assert r4.add_peer_odometry(2, t + 0.01, [0, 0, 0], [0, 0, 0]) == 'unknown_id'
    assert r4.add_message(1, t, {'angle_gradient': {4: np.array([np.nan, 0, 0])}}) \
        == 'non_finite'
    assert r4.add_message(1, t, {'angle_hessian': {4: np.zeros(3)}}) == 'malformed'
    assert r4.add_message(1, t, {'no_such_channel': {4: np.zeros(3)}}) == 'unknown_channel'
    fleet.run(1.0)
    for agent in fleet.agents.values():
        assert np.all(np.isfinite(agent.p_hat)) and np.all(np.isfinite(agent.R_hat))
        assert agent.k == 30
