"""What each agent reads from the others, derived once from its method's declarations: the one
table of netsim, the estimator and simulator nodes and the recorder.

Per edge and topic: the sender's channels on that topic (optional ones first: published in this
order, a value no step waits for usually arrives before one a step waits for), its point sensor
readings of this agent, its odometry; and the anchor's odometry if the method needs it.
"""
from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from ..estimators.base import Channel, Estimator
from .agent import AgentSpec, reads

ODOMETRY: Literal['odometry'] = 'odometry'   # the kind of an odometry subscription
ODOM_TOPIC = 'odom'     # its topic (REP-105's name)


@dataclass(frozen=True)
class Subscription:
    """One topic of agent ``source`` (``source_id``) that an agent reads: ``kind`` ``'channels'``
    (on ``topic``), ``'points'`` (carried by ``channels[0]``), or ``'odometry'``."""

    source: str
    source_id: int
    topic: str
    kind: Literal['channels', 'points', 'odometry']
    channels: tuple[str, ...] = ()


def optional_first(channels: Sequence[Channel]) -> list[Channel]:
    """The optional channels first, the others in their order (module docstring)."""
    return sorted(channels, key=lambda c: not c.optional)


def subscriptions(method: type[Estimator], spec: AgentSpec) -> list[Subscription]:
    """What the agent of ``spec`` reads from the others (module docstring)."""
    out: list[Subscription] = []
    for peer in spec.peers if not spec.leader else ():
        topics: dict[str, tuple[str, ...]] = {}
        for c in optional_first(method.sends):
            if not reads(peer.flags, c):
                continue
            if c.sensor is not None:
                out.append(Subscription(peer.name, peer.agent_id, c.topic, 'points', (c.name,)))
            else:
                topics[c.topic] = topics.get(c.topic, ()) + (c.name,)
        out += [Subscription(peer.name, peer.agent_id, topic, 'channels', names)
                for topic, names in topics.items()]
        if method.peer_odometry == 'links':
            out.append(Subscription(peer.name, peer.agent_id, ODOM_TOPIC, ODOMETRY))
    if (method.peer_odometry == 'anchor' and spec.anchor is not None
            and spec.anchor[1] != spec.agent_id):
        out.append(Subscription(spec.anchor[0], spec.anchor[1], ODOM_TOPIC, ODOMETRY))
    return out


def listener_counts(method: type[Estimator],
                    specs: Sequence[AgentSpec]) -> Counter[tuple[str, str]]:
    """``(agent, topic) → how many other agents' estimators read it``."""
    return Counter((sub.source, sub.topic) for spec in specs
                   for sub in subscriptions(method, spec))
