"""What a run's processes wait for and record, from the one table of subscriptions
(:mod:`runtime.table`): how many estimators read each agent's topics (the simulator starts the
clock once they all match), and the topics worth a bag."""
from __future__ import annotations

from collections import Counter

from .. import msg_defs as wire
from ..runtime.table import listener_counts as table_counts
from ..scenario.model import Scenario
from ..scenario.runtimes import agent_specs


def listener_counts(scenario: Scenario) -> Counter[tuple[str, str]]:
    """``(agent, relative topic) → how many other agents' estimators read it``."""
    return table_counts(type(scenario.estimator()), agent_specs(scenario))


def recorded_topics(scenario: Scenario, fleet: str = '') -> list[tuple[str, type]]:
    """Every topic of a run worth a bag (``run --record``), with its type: per agent its pose
    topics, sensors and channels, and /diagnostics; each has a publisher in every run."""
    method = scenario.estimator()
    channels = {topic: wire.channel_type(chans[0]) for topic, chans in
                wire.by_topic([c for c in method.sends if c.sensor is None]).items()}
    per_agent = ([(wire.ESTIMATE, wire.PoseStamped), (wire.GROUND_TRUTH, wire.PoseStamped),
                  (wire.IMU, wire.Imu), (wire.BEARINGS, wire.PointCloud2)]
                 + [(wire.SENSOR_TOPICS[s], wire.SENSOR_TYPES[s]) for s in wire.SENSOR_TOPICS
                    if scenario.simulates(s)]
                 + list(channels.items()))
    return ([(wire.topic(a.name, name, fleet), msg_type) for a in scenario.agents
             for name, msg_type in per_agent] + [(wire.DIAGNOSTICS, wire.DiagnosticArray)])
