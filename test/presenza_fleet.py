"""Helpers for Presenza et al. beyond the batch simulator: the paper's case 1 at a camera rate
(every sensor at the estimator's rate, the preconditioned scheme) and an in-process fleet of
:class:`TwoRoundAgent` fed by the simulator node's :class:`World`, with the messages the nodes
would exchange delivered at once (or dropped, or corrupted, by the caller)."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import yaml

from bearing_pose_estimation.scenario.agents import agent_for
from bearing_pose_estimation.estimators.two_round_agent import TwoRoundAgent
from bearing_pose_estimation.scenario.model import Scenario, initial_estimates
from bearing_pose_estimation.scenario.parse import load_scenario
from bearing_pose_estimation.sim.world import World

ROOT = Path(__file__).resolve().parents[1]


CAMERA_RATE = ROOT / 'config' / 'presenza_case1_30hz.yaml'


def camera_rate_case1(folder: Path, duration: float = 3.0,
                      gains: dict[str, float] | None = None) -> Path:
    """``config/presenza_case1_30hz.yaml`` (case 1 with the estimator and every sensor at
    30 Hz, the preconditioned scheme) cut to ``duration`` [s], with ``gains`` updated,
    written into ``folder``."""
    d = yaml.safe_load(CAMERA_RATE.read_text())
    d['duration'] = duration
    d['gains'].update(gains or {})
    path = folder / CAMERA_RATE.name
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


# deliver(sender, receiver, stamp, values) -> the cause the receiver returned (None: used)
Deliver = Callable[[TwoRoundAgent, TwoRoundAgent, float, dict], str | None]


class Fleet:
    """Every robot's :class:`TwoRoundAgent` and the World that feeds them, as the nodes are
    wired: own sensors, the anchor's odometry and ranges, each robot's estimate (``q_hat``) and
    second round to the robots that read them. ``deliver`` may drop or alter a message."""

    def __init__(self, scenario: Scenario, deliver: Deliver | None = None) -> None:
        self.s = scenario
        self.world = World(scenario)
        self.names = [a.name for a in scenario.agents]
        initial = initial_estimates(scenario)
        self.agents: dict[str, TwoRoundAgent] = {}
        for name in self.names:
            agent = agent_for(scenario, name, initial=initial)
            assert isinstance(agent, TwoRoundAgent)
            self.agents[name] = agent
        self.deliver = deliver or (lambda src, dst, t, values: dst.add_neighbour(
            src.agent_id, t, values))
        self.causes: list[str | None] = []
        for agent in self.agents.values():
            self._send(agent, agent.outbox())
        self._publish()
        self.pump()

    @classmethod
    def load(cls, path: Path, deliver: Deliver | None = None) -> Fleet:
        return cls(load_scenario(path), deliver)

    def _readers(self, sender: TwoRoundAgent) -> list[TwoRoundAgent]:
        return [a for a in self.agents.values()
                if any(lk.agent_id == sender.agent_id for lk in a.links)]

    def _send(self, sender: TwoRoundAgent, values: dict) -> None:
        for reader in self._readers(sender):
            self.causes.append(self.deliver(sender, reader, sender.t, values))

    def _publish(self) -> None:
        """What the simulator node publishes at this internal step."""
        w, t = self.world, self.world.t
        agents = [self.agents[n] for n in self.names]
        if w.due(w.imu_every) and w.tick > 0:
            for agent, omega in zip(agents, w.imu()):
                assert agent.add_gyro(t, omega) is None
        if w.due(w.bearing_every):
            for i, agent in enumerate(agents):
                j, b = w.bearings(i)
                assert agent.add_bearings(t, j + 1, b) == []
        for sensor, every in w.sensor_every.items():
            if not w.due(every) or (sensor == 'odometry' and w.tick == 0):
                continue
            if sensor == 'odometry':
                v, omega = w.odometry()
                for i, agent in enumerate(agents):
                    assert agent.add_odometry(t, v[i], omega[i]) is None
                    if agent.is_anchor:
                        for other in agents:
                            if other is not agent:
                                assert other.add_neighbour_odometry(agent.agent_id, t, v[i],
                                                                    omega[i]) is None
                continue
            for i, agent in enumerate(agents):
                j, values = w.sensed(sensor, i)
                if sensor == 'bearing_rates':
                    assert agent.add_bearing_rates(t, j + 1, values) == []
                elif sensor == 'relative_positions' and len(j):   # the anchor's ranges
                    for other in agents:
                        link = other._by_id.get(agent.agent_id)
                        if link is not None and other.measures_me(link):
                            assert other.add_neighbour_measurements(agent.agent_id, t, j + 1,
                                                                    values) is None

    def pump(self, impatient: bool = False) -> int:
        """Replies and steps until nothing more can run; how many steps ran."""
        ran, progress = 0, True
        while progress:
            progress = False
            for agent in self.agents.values():
                reply = agent.pending_reply(impatient=impatient)
                if reply is not None:
                    progress = True
                    self._send(agent, reply)
                if agent.advance(1, impatient=impatient):
                    progress, ran = True, ran + 1
                    self._send(agent, agent.outbox())
        return ran

    def run(self, until: float, impatient: bool = False) -> None:
        """Advance the world to ``until`` [s], the fleet with it."""
        while self.world.t < until - 1e-9:
            self.world.step()
            self._publish()
            self.pump(impatient)
