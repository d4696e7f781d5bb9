"""The distributed system without DDS: per-agent estimators, the simulator node's world, and
the links between agents, in one process and deterministic.

It runs the same :class:`agent.AgentEstimator` the estimator node runs, fed exactly as the
simulator node feeds it (:class:`world.World`: interval-average gyro, bearings, leaders' known
pose). Neighbour messages are exchanged at the estimators' ``publish_rate``. Faults:

- :class:`LinkFaults`: each neighbour message is dropped with ``drop_rate`` and delivered
  ``delay`` seconds late (what the node's ``inject_*`` parameters do);
- :class:`Outage`: an agent's estimator is down over ``[start, end)`` — it neither sends nor
  receives — and comes back either as it was (``restart=False``: a network partition) or as a
  fresh process from its initial estimate (``restart=True``: killed and restarted). An outage
  starting at 0 is a late joiner.

Used to measure fault outcomes precisely (the fault matrix in the README); the DDS tests show
that the nodes behave the same way.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from .agent import AgentEstimator, Limits, estimator_for
from .scenario import Scenario, initial_estimates
from .simulator import Recording, pose_errors
from .world import World


@dataclass(frozen=True)
class LinkFaults:
    drop_rate: float = 0.0  # probability of losing each neighbour message
    delay: float = 0.0      # extra delay of each neighbour message [s]
    seed: int = 0


@dataclass(frozen=True)
class Outage:
    agent: str
    start: float            # [s]
    end: float              # [s]
    restart: bool = True    # comes back as a fresh process (True) or as it was (False)


def run_network(scenario: Scenario, duration: float, record_every: float = 0.1,
                links: LinkFaults = LinkFaults(), outages: tuple[Outage, ...] = (),
                limits: Limits = Limits()) -> Recording:
    """Run the fleet for ``duration`` seconds; errors of the followers every ``record_every``."""
    world = World(scenario)
    rng = np.random.default_rng(links.seed)
    names = [a.name for a in scenario.agents]
    initial = initial_estimates(scenario)  # drawn once for the whole fleet
    agents: dict[str, AgentEstimator] = {n: estimator_for(scenario, n, limits, initial)
                                         for n in names}
    per_step = int(round(scenario.step / world.dt))
    per_publish = per_step * scenario.publish_every
    per_record = int(round(record_every / world.dt))
    in_flight: deque[tuple[float, str, tuple]] = deque()  # (deliver at, to, message)
    followers = [scenario.index[a.name] for a in scenario.followers]
    rows, times = [], []

    def down(name: str, t: float) -> bool:
        return any(o.agent == name and o.start <= t < o.end for o in outages)

    def sense(t: float) -> None:
        if world.due(world.bearing_every):
            for i, name in enumerate(names):
                if not down(name, t):
                    j, b = world.bearings(i)
                    agents[name].add_bearings(t, j + 1, b)
        if world.due(world.truth_every):
            for name in scenario.leaders:
                i = scenario.index[name]
                if not down(name, t):
                    agents[name].set_known_pose(t, world.R[i], world.p[i])

    def publish(t: float) -> None:
        for name in names:
            if down(name, t):
                continue
            ag = agents[name]
            msg = (scenario.agent_id(name), ag.t, ag.p_hat[0].copy(), ag.world_bearings())
            for listener in scenario.listeners(name):
                if links.drop_rate and rng.uniform() < links.drop_rate:
                    continue
                in_flight.append((t + links.delay, listener, msg))

    def deliver(t: float) -> None:
        while in_flight and in_flight[0][0] <= t + 1e-9:
            _, to, msg = in_flight.popleft()
            if not down(to, t):
                agents[to].add_neighbour(*msg)

    sense(0.0)
    publish(0.0)
    deliver(0.0)
    while world.t < duration - 1e-9:
        world.step()
        t = world.t
        for o in outages:  # a restarted process starts from its initial estimate
            if o.restart and abs(t - o.end) < 0.5 * world.dt:
                agents[o.agent] = estimator_for(scenario, o.agent, limits, initial)
        if world.due(world.imu_every):
            for name, w in zip(names, world.imu()):
                if not down(name, t):
                    agents[name].add_gyro(t, w)
        sense(t)
        deliver(t)
        if world.tick % per_step == 0:
            for name in names:
                if not down(name, t):
                    agents[name].advance()
        if world.tick % per_publish == 0:
            publish(t)
            deliver(t)
        if world.tick % per_record == 0:
            R_hat = np.stack([agents[names[i]].R_hat[0] for i in followers])
            p_hat = np.stack([agents[names[i]].p_hat[0] for i in followers])
            times.append(t)
            rows.append(pose_errors(world.R[followers], world.p[followers], R_hat, p_hat))
    cols = [np.array([r[c] for r in rows]) for c in range(4)]
    return Recording(t=np.array(times), followers=[names[i] for i in followers],
                     att_err=cols[0], pos_err=cols[1], att_dist_I=cols[2],
                     pos_err_paper=cols[3])
