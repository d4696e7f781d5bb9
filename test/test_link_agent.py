"""The node logic of ``links = 'communication'`` methods (estimators/link_agent.py) on De Carli
et al.'s scenario: eight robots fed, as their nodes would be, from the simulator node's world
(truth on a 1 ms grid, sensors at their own rates) and each other's messages, reproduce the
batch simulator, and a silent neighbour is left out after the timeout (lost and late messages:
the fault-matrix rows of test_de_carli_faults.py)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bearing_pose_estimation.scenario import parse_scenario
from bearing_pose_estimation.scenario.parse import read_scenario_data
from bearing_pose_estimation.sim.batch import BatchSimulator
from bearing_pose_estimation.sim.world import World
from bearing_pose_estimation.estimators.link_agent import LinkAgentEstimator
from bearing_pose_estimation.scenario.agents import link_estimator_for

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'de_carli_8_quadrotors.yaml'


def scenario():
    data = read_scenario_data(CONFIG)
    data['formation_control']['mode'] = 'exogenous'   # the world owns the truth
    return parse_scenario(data)


class Fleet:
    """Eight robots' logic and the world, connected as over DDS but in one process: every
    message is delivered at once, except those ``lose`` drops (``lose(sender, t)``) and what
    ``silent`` robots would send."""

    def __init__(self, s, lose=None, silent=()) -> None:
        self.s, self.world = s, World(s)
        self.names = [a.name for a in s.agents]
        self.agents: dict[str, LinkAgentEstimator] = {n: link_estimator_for(s, n)
                                                      for n in self.names}
        self.lose = lose or (lambda sender, t: False)
        self.silent = set(silent)
        self.sent = {n: -1 for n in self.names}
        every = self.world.sensor_every
        self.imu_every, self.odom_every = self.world.imu_every, every['odometry']
        self.rel_every = every['relative_positions']
        self._relative_positions()
        for n in self.names:
            self._send(n)

    def _send(self, name: str) -> None:
        est = self.agents[name]
        if name in self.silent or self.sent[name] == est.k:
            return
        self.sent[name] = est.k
        due = [c for c in est.outbox() if est.estimator.due(c, est.t, est.h)]
        if not due or self.lose(name, est.t):
            return
        sent = est.outbox()
        for link in est.links:
            self.agents[link.name].add_neighbour(est.agent_id, est.t,
                                                 {c: sent[c] for c in due})

    def _relative_positions(self) -> None:
        t = self.world.t
        for i, n in enumerate(self.names):
            j, values = self.world.sensed('relative_positions', i)
            ids = j + 1
            assert not self.agents[n].add_relative_positions(t, ids, values)
            for link in self.agents[n].links:
                if n not in self.silent:
                    self.agents[link.name].add_neighbour_measurements(i + 1, t, ids, values)

    def run(self, T: float) -> None:
        for _ in range(int(round(T / self.world.dt))):
            self.world.step()
            t = self.world.t
            if self.world.due(self.imu_every):
                omega = self.world.imu()
                for i, n in enumerate(self.names):
                    self.agents[n].add_gyro(t, omega[i])
            if self.world.due(self.odom_every):
                v, w = self.world.odometry()
                for i, n in enumerate(self.names):
                    self.agents[n].add_odometry(t, v[i], w[i])
                    for link in self.agents[n].links if n not in self.silent else ():
                        self.agents[link.name].add_neighbour_odometry(i + 1, t, v[i], w[i])
            if self.world.due(self.rel_every):
                self._relative_positions()
            progress = True
            while progress:
                progress = False
                for n in self.names:
                    if self.agents[n].advance(1):
                        progress = True
                        self._send(n)


def test_the_robots_logic_reproduces_the_batch_simulator():
    """Fed from the 1 ms world, every robot's state after 2 s equals the batch row: the
    pairing of every input at its instant is exact."""
    s = scenario()
    fleet = Fleet(s)
    fleet.run(2.0)
    batch = BatchSimulator(s)
    for _ in range(int(round(2.0 / batch.h))):
        batch.step()
    for i, n in enumerate(fleet.names):
        est = fleet.agents[n]
        assert abs(est.t - 2.0) < 1e-9
        np.testing.assert_allclose(est.x.p_hat[0], batch.x.p_hat[i], atol=1e-9)
        np.testing.assert_allclose(est.x.z_hat[0], batch.x.z_hat[i], atol=1e-9)
        assert not est.missing or set(est.missing.values()) == {0}, (n, est.missing)


def test_a_silent_neighbour_is_left_out_after_the_timeout():
    """Robot 7 never sends anything: its neighbours wait for it no longer than the neighbour
    timeout of their own clock, then step without it; their relative estimates of it never
    start."""
    s = scenario()
    fleet = Fleet(s, silent={'robot_7'})
    fleet.run(1.5)
    for n in ('robot_3', 'robot_4', 'robot_6'):
        est = fleet.agents[n]
        assert est.t > 0.9, (n, est.t)
        assert est.missing['present'] > 0
        assert 'robot_7' in est.stale_neighbours(est.t)


def test_an_owner_says_when_it_has_no_relative_yaw_yet():
    """De Carli's relative yaw travels only from the pair's owner. Until it has one the owner
    sends zeros, not nothing: "none yet", which the listener's step takes as the batch step
    does, without waiting for a value that will not come (over DDS it waited out the
    wall-clock patience and went on without the neighbour: 5 % off the batch run). A message
    that does not list our pair still says nothing, and zeros from a non-owner are garbage."""
    s = scenario()
    r0, r1 = link_estimator_for(s, 'robot_0'), link_estimator_for(s, 'robot_1')
    owner = next(lk for lk in r1.links if lk.name == 'robot_0')
    assert not owner.owns   # two-way pair: robot_0 (id 1, the lower) owns it
    sent = r0.outbox()
    np.testing.assert_array_equal(sent['relyaw'][2], [0.0, 0.0])   # t = 0: none yet, for id 2
    assert list(sent['relyaw']) == [2]   # robot_0 owns no other pair
    assert r1.add_neighbour(1, 0.0, {'z_hat': sent['z_hat'], 'relyaw': sent['relyaw']}) is None
    value, decided = owner.value_at('relyaw', 0.0)
    assert decided and np.array_equal(value, np.zeros(2))
    assert r1.add_neighbour(1, 0.01, {'relyaw': {2: np.array([0.0, 1.0])}}) is None
    assert np.array_equal(owner.value_at('relyaw', 0.01)[0], [0.0, 1.0])
    assert r1.add_neighbour(1, 0.02, {'relyaw': {99: np.array([1.0, 0.0])}}) == 'not_seen'
    assert r1.add_neighbour(1, 0.02, {'relyaw': {2: np.array([0.0, 3.0])}}) == 'not_unit'
    assert r0.add_neighbour(2, 0.0, {'relyaw': {1: np.zeros(2)}}) == 'zero_vector'


def test_a_link_finds_a_value_by_its_stamp_among_many():
    """``Link.value_at``: j's value stamped t among a full history (a step that waited looks
    back), none between two stamps or before the oldest (decided: a newer one is here), none
    yet after the newest (not decided: it may still come)."""
    s = scenario()
    r1 = link_estimator_for(s, 'robot_1')
    link = next(lk for lk in r1.links if lk.name == 'robot_0')
    stamps = 0.01 * np.arange(300)   # more than the history holds: the oldest drop out
    for t in stamps:
        if t > 0:   # the gyro covers j's stamps: else they are "future"
            assert r1.add_gyro(float(t), np.zeros(3)) is None
        assert r1.add_neighbour(1, float(t), {'z_hat': np.array([np.cos(t), np.sin(t)])}) is None
    kept = stamps[-len(link.history['z_hat']):]
    for t in (kept[0], kept[17], kept[-2], kept[-1]):
        value, decided = link.value_at('z_hat', float(t) + 4e-10)   # rounding: still t
        assert decided and np.array_equal(value, [np.cos(t), np.sin(t)]), t
    for t in (kept[5] + 0.005, kept[0] - 0.01, stamps[0]):
        assert link.value_at('z_hat', float(t)) == (None, True), t
    assert link.value_at('z_hat', float(kept[-1]) + 0.01) == (None, False)
