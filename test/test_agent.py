"""One agent's estimator without ROS: gyro buffering, time alignment, and agreement of a fleet
of per-agent estimators (fed by the simulator node's world model) with the batch simulator."""
from pathlib import Path

import numpy as np
import pytest

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.scenario.agents import estimator_for
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
            assert agent.add_bearings(*item) == []
        else:
            assert agent.add_neighbour(*item) is None
        while agent.advance(1):
            out.append((agent.t, agent.R_hat[0].copy(), agent.p_hat[0].copy()))
    return out


def test_the_fixed_exchange_makes_the_steps_independent_of_the_arrival_order():
    """With an Exchange (the node under use_sim_time), step [t, t + h] uses the own bearings
    measured by t + h and each neighbour's values of its publish instant at or before t, and
    waits for them: whatever the interleaving of the topics, and however far the gyro runs
    ahead (within link_wait), the estimates equal to rounding (1e-12; the gyro buffer's
    segments depend on how far it reaches) those of the order netsim feeds them (an instant's
    bearings before its step, the neighbours' values after). Without it, late inputs change
    them."""
    from bearing_pose_estimation.estimators.agent import Exchange

    scenario = load_scenario(PAPER)
    name = 'agent_6'   # three neighbours
    streams = _streams(scenario, name, 0.5, seed=3)

    def netsim_order() -> list[str]:   # by stamp; at one instant bearings, gyro (the step
        keyed = [(item[0], 1, 'gyro') for item in streams['gyro']]   # runs), neighbours
        keyed += [(item[0], 0, 'bearings') for item in streams['bearings']]
        keyed += [(item[1], 2, nb) for nb in streams if nb not in ('gyro', 'bearings')
                  for item in streams[nb]]
        return [s for _, _, s in sorted(keyed)]

    def shuffled(seed: int) -> list[str]:   # each input late by up to 0.2 s (< link_wait)
        rng = np.random.default_rng(seed)
        arrivals = []
        for s in streams:
            stamps = [item[1] if isinstance(item[0], int) else item[0] for item in streams[s]]
            late = np.maximum.accumulate(stamps + rng.uniform(0.0, 0.2, len(stamps)))
            arrivals += [(a, s) for a in late]   # each topic keeps its order
        return [s for _, s in sorted(arrivals, key=lambda a: a[0])]

    def run(order: list[str], exchange: bool) -> list:
        agent = estimator_for(scenario, name)
        if exchange:
            agent.exchange = Exchange(0.02, 0.02, 0.02)
        steps = _feed(agent, streams, order)
        assert not agent.incomplete
        return steps

    reference = run(netsim_order(), exchange=False)
    assert len(reference) == 50
    for order in (netsim_order(), shuffled(1), shuffled(2)):
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
    from bearing_pose_estimation.estimators.agent import Exchange

    scenario = load_scenario(PAPER)

    def run(streams: dict[str, list]):
        agent = estimator_for(scenario, 'agent_6')
        agent.exchange = Exchange(0.02, 0.02, 0.02)
        order = sorted([(item[0], 1, 'gyro') for item in streams['gyro']]
                       + [(item[0], 0, 'bearings') for item in streams['bearings']]
                       + [(item[1], 2, nb) for nb in ('agent_2', 'agent_4', 'agent_5')
                          for item in streams[nb]])
        steps = _feed(agent, streams, [s for _, _, s in order])
        return agent, steps

    streams = _streams(scenario, 'agent_6', 0.5, seed=3)
    full = streams['agent_4']
    streams['agent_4'] = full[:2] + full[3:]   # its values of t = 0.04 lost
    agent, steps = run(streams)
    assert agent.t == pytest.approx(0.5) and not agent.incomplete

    streams['agent_4'] = full[:2]              # silent after t = 0.02
    agent, steps = run(streams)
    # The step [0.04, 0.05] first waits; every step then runs 0.25 s of gyro late.
    assert agent.awaited == 'agent_4'
    assert agent.t == pytest.approx(0.5 - 0.25, abs=0.011)
    assert agent.incomplete == {'agent_4': len(steps) - 4}


@pytest.mark.parametrize('config, method, moving', [
    ('paper_noisy.yaml', 'boughellaba_tayebi', False),
    ('paper_noisy.yaml', 'tran_anderson_ahn', False),
    ('paper_8_agents_moving.yaml', 'boughellaba_tayebi', True)])
def test_steps_run_together_give_each_agent_its_own_steps_exactly(config, method, moving):
    """advance_together (an estimators process's agents in one call of the method's step)
    against each agent's own steps, on netsim with lost and late neighbour messages (each
    step's neighbours differ) and, moving, odometry: every agent's state, covariance
    included, and step diagnostics bit for bit."""
    from dataclasses import fields

    from bearing_pose_estimation.sim.netsim import Garbage, LinkFaults, _Network, Limits
    scenario = load_scenario(PAPER.parent / config).with_method(method)
    links = LinkFaults(drop_rate=0.2, delay=0.03, seed=3)
    nets = [_Network(scenario, links, (), Garbage(), Limits(), batched=b) for b in (False, True)]
    for net in nets:
        net.start()
    dt = nets[0].world.dt
    for tick in range(1, int(round(1.5 / dt)) + 1):
        for net in nets:
            net.tick(tick * dt)
        for name in nets[0].names:
            a, b = (net.agents[name] for net in nets)
            assert (a.k, a.last.t, a.last.edges_used, a.last.stale) == (
                b.k, b.last.t, b.last.edges_used, b.last.stale), name
            _assert_same_step(a, b, f'{name} at tick {tick}')
    followers = [a for a in nets[1].agents.values() if not a.leader]
    assert all(a.k > 100 for a in followers)
    assert all(a.last.odometry == moving for a in followers)


@pytest.mark.parametrize('config, duration', [('presenza_case1.yaml', 0.5),
                                              ('presenza_noisy.yaml', 1.5)])
def test_robots_of_a_two_round_method_stepped_together_get_their_own_steps_exactly(config,
                                                                                   duration):
    """Presenza et al. (an anchor, bearing rates, two rounds per step; noisy: the covariance
    and odometry): robots stepped together get exactly their own steps."""
    from bearing_pose_estimation.scenario.parse import read_scenario_data
    data = read_scenario_data(PAPER.parent / config)
    net, checked = _link_robots_stepped_both_ways(data, duration, 20)
    assert len(checked) == 20 and max(checked) >= 3, checked


def _assert_same_step(a, b, where: str) -> None:
    """Agents ``a`` (its own step) and ``b`` (stepped together with others) hold the same
    state and step diagnostics, bit for bit; De Carli et al.'s robots keep per-link state in
    as many slots as the most links among those stepped together: ``b``'s extra slots are
    zero."""
    from dataclasses import fields

    for f in fields(a.x):
        own, together = getattr(a.x, f.name), getattr(b.x, f.name)
        if own.shape != together.shape:   # link slots: (1, D, ...)
            assert not np.any(together[:, own.shape[1]:]), f.name
            together = together[:, :own.shape[1]]
        np.testing.assert_array_equal(own, together, err_msg=f'{where}: {f.name}')
    for key, value in a.last.diagnostics.items():
        np.testing.assert_array_equal(value, b.last.diagnostics[key], err_msg=where)


def _link_robots_stepped_both_ways(data: dict, duration: float, checks: int):
    """netsim of scenario ``data`` with lost and late messages: whenever several robots have
    a step ready, copies of them are stepped on their own and by advance_together, and each
    pair compared (``checks`` times). Returns the network and how many robots each check had."""
    import copy

    from bearing_pose_estimation.estimators.agent import advance_together
    from bearing_pose_estimation.scenario import parse_scenario
    from bearing_pose_estimation.sim.netsim import Garbage, LinkFaults, _Network, Limits
    net = _Network(parse_scenario(data), LinkFaults(drop_rate=0.2, delay=0.03, seed=3), (),
                   Garbage(), Limits())
    step_links, checked = net.step_links, []

    def step_and_check(now: float) -> None:
        ready = [a for a in net.agents.values() if a.steps_ready() > 0]
        if len(ready) > 1 and len(checked) < checks:
            alone, together = copy.deepcopy(ready), copy.deepcopy(ready)
            for a in alone:
                a.advance(1)
            assert advance_together(together) == together
            for a, b in zip(alone, together):
                _assert_same_step(a, b, f'{a.agent_id} at {now:.3f} s')
            checked.append(len(ready))
        step_links(now)

    net.step_links = step_and_check
    net.start()
    dt = net.world.dt
    for tick in range(1, int(round(duration / dt)) + 1):
        net.tick(tick * dt)
    return net, checked


def test_robots_of_a_link_method_stepped_together_get_their_own_steps_exactly():
    """De Carli et al.: robots stepped together get exactly their own steps (above)."""
    from bearing_pose_estimation.scenario.parse import read_scenario_data
    data = read_scenario_data(PAPER.parent / 'de_carli_8_quadrotors.yaml')
    data['formation_control']['mode'] = 'exogenous'   # the world owns the truth
    net, checked = _link_robots_stepped_both_ways(data, 0.6, 40)
    assert len(checked) == 40 and max(checked) == 8
    assert all(np.any(a.x.ready_out) for a in net.agents.values())   # per-link state in use
    # Robots with fewer links than others (here all have 3): their state grows to the most.
    x0, x1 = (a.x for a in list(net.agents.values())[:2])
    both = type(x0).stack([x0, x1.grown(5)])
    assert both.P_out.shape[:2] == (2, 5) and not np.any(both.P_out[0, 3:])
    np.testing.assert_array_equal(both.P_out[0, :3], x0.P_out[0])
