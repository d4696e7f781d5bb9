"""Helpers beyond the batch simulator: Presenza et al.'s case 1 at a camera rate (every sensor
at the estimator's rate, the preconditioned scheme) and an in-process fleet of agent runtimes
(:class:`runtime.agent.AgentRuntime`, any method) fed by the simulator node's :class:`World`,
each message the nodes would exchange (what the table of subscriptions, ``runtime/table.py``,
says each agent reads) delivered at once, or dropped, or altered, by the caller."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import yaml

from bearing_pose_estimation.estimators.base import Sensor
from bearing_pose_estimation.runtime.agent import AgentRuntime
from bearing_pose_estimation.runtime.table import ODOM_TOPIC, subscriptions
from bearing_pose_estimation.scenario.model import Scenario
from bearing_pose_estimation.scenario.runtimes import agent_specs, runtime_for
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
Deliver = Callable[[AgentRuntime, AgentRuntime, float, dict], str | None]

POINT_SENSORS = (Sensor.BEARINGS, Sensor.RELATIVE_POSITIONS, Sensor.BEARING_RATES)


class Fleet:
    """Every agent's runtime and the World that feeds them, as the nodes are wired: own
    sensors (gyro, point sensors, odometry, a leader's known pose), and from the others what
    the table says each reads: their channels (round 1 after each of their steps, the
    channels a listener's step reads then; round 2 as soon as its first round is in), their
    point sensor readings and their odometry. ``deliver`` may drop or alter a channel
    message; ``silent`` agents send nothing at all (their process cut off the network)."""

    def __init__(self, scenario: Scenario, deliver: Deliver | None = None,
                 silent: tuple[str, ...] | set[str] = ()) -> None:
        self.s = scenario
        self.world = World(scenario)
        self.names = [a.name for a in scenario.agents]
        specs = agent_specs(scenario)
        method = type(scenario.estimator())
        self.agents: dict[str, AgentRuntime] = {spec.name: runtime_for(scenario, spec)
                                                for spec in specs}
        self.readers: dict[tuple[str, str], list[AgentRuntime]] = {}
        for spec in specs:
            for sub in subscriptions(method, spec):
                self.readers.setdefault((sub.source, sub.topic), []).append(
                    self.agents[spec.name])
        self.topics: dict[int, dict[str, list[str]]] = {}   # round -> topic -> channels
        for c in method.sends:
            if c.sensor is None:
                self.topics.setdefault(c.round, {}).setdefault(c.topic, []).append(c.name)
        read = {c.sensor for c in method.sends if c.sensor is not None}
        self.point_sensors = [s for s in POINT_SENSORS if s in method.measures or s in read]
        self.deliver = deliver or (lambda src, dst, t, values: dst.add_message(
            src.agent_id, t, values))
        self.silent = set(silent)
        self.causes: list[str | None] = []
        self.sent_k = dict.fromkeys(self.names, -1)
        self._sense()
        for agent in self.agents.values():
            self._publish(agent, every=True)
        self.pump()

    def _send(self, sender: AgentRuntime, topic: str, values: dict) -> None:
        for reader in self.readers.get((sender.name, topic), ()):
            self.causes.append(self.deliver(sender, reader, sender.t, values))

    def _publish(self, agent: AgentRuntime, every: bool = False) -> None:
        """Round 1 at the agent's state time, once per step: the channels a listener's step
        reads at this instant (``every``: all of them, as a node announces its t0 state)."""
        if agent.name in self.silent or self.sent_k[agent.name] == agent.k:
            return
        self.sent_k[agent.name] = agent.k
        sent = agent.outbox()
        for topic, names in self.topics.get(1, {}).items():
            content = {n: sent[n] for n in names
                       if (every or agent.sends_now(n, True))
                       and not (isinstance(sent[n], dict) and not sent[n])}
            if content:
                self._send(agent, topic, content)

    def _reply(self, agent: AgentRuntime, reply: dict) -> None:
        if agent.name in self.silent:
            return
        for r, topics in self.topics.items():
            for topic, names in topics.items() if r > 1 else ():
                content = {n: reply[n] for n in names if n in reply}
                if content:
                    self._send(agent, topic, content)

    def _sense(self) -> None:
        """What the simulator node publishes at this internal step."""
        w, t = self.world, self.world.t
        agents = [self.agents[n] for n in self.names]
        if w.due(w.imu_every) and w.tick > 0:
            for agent, omega in zip(agents, w.imu()):
                assert agent.add_gyro(t, omega) is None
        every = w.sensor_every.get('odometry')
        if every is not None and w.due(every) and w.tick > 0:
            for agent, v, omega in zip(agents, *w.odometry()):
                assert agent.add_odometry(t, v, omega) is None
                if agent.name not in self.silent:
                    for reader in self.readers.get((agent.name, ODOM_TOPIC), ()):
                        assert reader.add_peer_odometry(agent.agent_id, t, v, omega) is None
        for sensor in self.point_sensors:
            every = (w.bearing_every if sensor is Sensor.BEARINGS
                     else w.sensor_every.get(sensor.value))
            if every is None or not w.due(every):
                continue
            for i, agent in enumerate(agents):
                j, values = (w.bearings(i) if sensor is Sensor.BEARINGS
                             else w.sensed(sensor.value, i))
                assert agent.add_points(sensor, t, j + 1, values) == []
                if agent.name not in self.silent:
                    for reader in self.readers.get((agent.name, sensor.value), ()):
                        assert reader.add_peer_points(agent.agent_id, sensor, t, j + 1,
                                                      values) is None
        if w.due(w.truth_every):
            for name in self.s.leaders:
                i = self.s.index[name]
                assert self.agents[name].add_known_pose(t, w.R[i], w.p[i]) is None

    def pump(self, impatient: bool = False) -> int:
        """Replies and steps until nothing more can run; how many steps ran."""
        ran, progress = 0, True
        while progress:
            progress = False
            for agent in self.agents.values():
                reply = agent.pending_reply(impatient=impatient)
                if reply is not None:
                    progress = True
                    self._reply(agent, reply)
                if agent.advance(1, impatient=impatient):
                    progress, ran = True, ran + 1
                    self._publish(agent)
        return ran

    def run(self, until: float, impatient: bool = False) -> None:
        """Advance the world to ``until`` [s], the fleet with it."""
        while self.world.t < until - 1e-9:
            self.world.step()
            self._sense()
            self.pump(impatient)
