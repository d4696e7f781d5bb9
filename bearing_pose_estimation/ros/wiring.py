"""Which neighbour topics an estimator subscribes to: one answer for the estimator node (that
subscribes, and whose writers wait for those readers before it announces its t0 state) and the
simulator node (that waits for those subscriptions before it starts the clock)."""
from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .. import msg_defs as wire
from ..estimators.agent import AgentEstimator
from ..estimators.base import Channel
from ..estimators.link_agent import LinkAgentEstimator
from ..scenario.agents import agent_for

if TYPE_CHECKING:
    from ..scenario.model import Scenario


@dataclass(frozen=True)
class NeighbourTopic:
    """One subscription of an estimator to neighbour ``agent``'s ``topic`` (relative name):
    the method channels it carries (``channels``; none: the neighbour's odometry)."""

    agent: str
    agent_id: int
    topic: str
    channels: tuple[str, ...]


def optional_first(channels: Sequence[Channel]) -> list[Channel]:
    """The optional channels (the covariance) first, the others in their order: a node
    subscribes and publishes in this order, so that a value no step waits for usually
    arrives before the one its neighbour's step does wait for (the step then has the value of
    its own instant, as the batch simulator does)."""
    return sorted(channels, key=lambda c: not c.optional)


def link_subscriptions(template: AgentEstimator | LinkAgentEstimator) -> list[NeighbourTopic]:
    """A link agent's subscriptions to its neighbours' topics: each channel's from the
    neighbours whose values the step reads (a channel of a sensor's readings: from those
    whose sensor measures this robot), and the odometry of those whose motion it uses. None
    for other agents (their node subscribes to each neighbour's channel topics)."""
    if not isinstance(template, LinkAgentEstimator):
        return []
    wanted: dict[tuple[str, int, str], tuple[str, ...]] = {}
    for c in optional_first(template.estimator.sends):
        topic = wire.channel(c.name).topic
        for nb in template.channel_sources(c.name):
            if c.sensor is None or template.measures_me(nb):
                key = (nb.name, nb.agent_id, topic)
                wanted[key] = wanted.get(key, ()) + (c.name,)
    out = [NeighbourTopic(*key, channels) for key, channels in wanted.items()]
    out += [NeighbourTopic(name, agent_id, wire.ODOM, ())
            for name, agent_id in template.odometry_sources()]
    return out


def listener_counts(scenario: Scenario) -> Counter[tuple[str, str]]:
    """(agent, relative topic) -> how many estimators of the other agents subscribe to it:
    for link methods their :func:`link_subscriptions` (odometry too: the simulator's topic),
    for the others each listener of the agent reads each of its channel topics."""
    method = scenario.estimator()
    if method.links == 'communication':
        return Counter((sub.agent, sub.topic) for agent in scenario.agents
                       for sub in link_subscriptions(agent_for(scenario, agent.name)))
    topics = dict.fromkeys(wire.channel(c.name).topic for c in method.sends if c.sensor is None)
    return Counter({(agent.name, topic): len(scenario.listeners(agent.name))
                    for agent in scenario.agents for topic in topics})


# A recorder's reader: reliable matches the simulator's and the estimators' writers, volatile
# matches both volatile and transient-local ones; deep enough not to drop a burst.
RECORD_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)


def recorded_topics(scenario: Scenario, fleet: str = '') -> list[tuple[str, type]]:
    """Every topic of a run worth a bag (``run --record``), with its type: per agent its
    estimate, ground truth, gyro, bearings, the sensors the scenario simulates and the
    channels its method sends on topics of their own (its ``pose`` with the covariance, for
    methods that have one); and /diagnostics. Each has a publisher
    in every run (the simulator's and every estimator's), so a recorder can wait for them."""
    method = scenario.estimator()
    channels = {w.topic: w.type for w in (wire.channel(c.name) for c in method.sends
                                          if c.sensor is None) if w.topic != wire.ESTIMATE}
    per_agent = ([(wire.ESTIMATE, wire.PoseStamped), (wire.GROUND_TRUTH, wire.PoseStamped),
                  (wire.IMU, wire.Imu), (wire.BEARINGS, wire.PointCloud2)]
                 + [(wire.SENSOR_TOPICS[s], wire.SENSOR_TYPES[s]) for s in wire.SENSOR_TOPICS
                    if scenario.simulates(s)]
                 + list(channels.items()))
    return ([(wire.topic(a.name, name, fleet), msg_type) for a in scenario.agents
             for name, msg_type in per_agent] + [(wire.DIAGNOSTICS, DiagnosticArray)])
