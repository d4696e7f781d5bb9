"""Each agent's runtime as a scenario defines it (:mod:`bearing_pose_estimation.runtime`):
its edges, role and initial estimate, and a simulation's exchange."""
from __future__ import annotations

import numpy as np

from ..core.errors import ScenarioError
from ..runtime.agent import AgentRuntime, AgentSpec
from ..runtime.buffers import Exchange, Limits
from ..runtime.spec import fleet_specs
from .model import Scenario, initial_estimates


def agent_specs(scenario: Scenario) -> list[AgentSpec]:
    """Every agent's spec, in the scenario's order (ScenarioError: not distributable)."""
    problem = scenario.not_distributable()
    if problem:
        raise ScenarioError(f'{scenario.source}: {problem}')
    R0, p0 = initial_estimates(scenario)
    tail, head = scenario.sensing_edges()
    k = np.array([nb.k for a in scenario.agents for nb in a.neighbours], dtype=float)
    spec = scenario.sensors.bearing_rates
    index = scenario.index
    return fleet_specs(type(scenario.estimator()), [a.name for a in scenario.agents], tail, head,
                       k, R0, p0, leaders=[index[name] for name in scenario.leaders],
                       anchor=scenario.anchor_index, ranged=[index[r] for r in scenario.ranged],
                       pinned=scenario.anchor_pinned,
                       rate_tau=spec.tau if spec.from_bearings else None)


def exchange_of(scenario: Scenario, publish_every: int | None = None) -> Exchange:
    """A simulation's exchange: the periods of what a step waits for, the scenario's rates."""
    sim = scenario.simulation
    every = scenario.publish_every if publish_every is None else publish_every
    return Exchange(every * scenario.step, sim.ticks(sim.bearing_rate) * sim.internal_step,
                    sim.ticks(sim.ground_truth_rate) * sim.internal_step)


def runtime_for(scenario: Scenario, spec: AgentSpec, limits: Limits = Limits(),
                exchange: Exchange | None = None, step: float | None = None,
                t0: float = 0.0) -> AgentRuntime:
    """The runtime of the agent of ``spec`` with the scenario's method and gains."""
    return AgentRuntime(scenario.estimator(), spec, scenario.step if step is None else step,
                        t0=t0, limits=limits, exchange=exchange,
                        expects_odometry=scenario.simulates('odometry'))
