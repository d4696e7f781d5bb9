"""Which neighbour topics a communication-link estimator subscribes to: one answer for the
estimator node (that subscribes) and the simulator node (that waits for those subscriptions
before it starts the clock)."""
from __future__ import annotations

from dataclasses import dataclass

from .. import msg_defs as wire
from ..estimators.agent import AgentEstimator
from ..estimators.link_agent import LinkAgentEstimator


@dataclass(frozen=True)
class NeighbourTopic:
    """One subscription of an estimator to neighbour ``agent``'s ``topic`` (relative name):
    a method channel's (``channel``; None: the neighbour's odometry)."""

    agent: str
    agent_id: int
    topic: str
    channel: str | None


def link_subscriptions(template: AgentEstimator | LinkAgentEstimator) -> list[NeighbourTopic]:
    """A link agent's subscriptions to its neighbours' topics: each channel's from the
    neighbours whose values the step reads (a channel of a sensor's readings: from those
    whose sensor measures this robot), and the odometry of those whose motion it uses. None
    for other agents (their node subscribes to each neighbour's channel topics)."""
    if not isinstance(template, LinkAgentEstimator):
        return []
    out = []
    for c in template.estimator.sends:
        w = wire.channel(c.name)
        for nb in template.channel_sources(c.name):
            if c.sensor is None or template.measures_me(nb):
                out.append(NeighbourTopic(nb.name, nb.agent_id, w.topic, c.name))
    out += [NeighbourTopic(name, agent_id, wire.ODOM, None)
            for name, agent_id in template.odometry_sources()]
    return out
