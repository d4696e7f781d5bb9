"""The agent logic of one agent as a scenario defines it: the factories that build the
ROS-free agents of :mod:`estimators.agent`, :mod:`estimators.link_agent` and
:mod:`estimators.two_round_agent` (what the estimator node and netsim run) from a
:class:`.model.Scenario`: the method and its gains, the agent's neighbours or links and their
wire ids, its initial estimate and the step.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..core.errors import ScenarioError
from ..estimators.agent import AgentEstimator, Limits
from ..estimators.link_agent import LinkAgentEstimator
from ..estimators.two_round_agent import TwoRoundAgent
from .model import Scenario, initial_estimates

Array = NDArray[np.float64]


def estimator_for(scenario: Scenario, name: str, limits: Limits = Limits(),
                  initial: tuple[Array, Array] | None = None) -> AgentEstimator:
    """The estimator of agent ``name`` as the scenario defines it (method and gains, neighbours
    and their ids, initial estimate, rate; leader mode for leaders). ``initial``: the fleet's
    ``initial_estimates(scenario)``, when the caller builds many estimators (it draws them
    all, so computing it once per fleet saves O(N²) work)."""
    i = scenario.index[name]
    R0, p0 = initial if initial is not None else initial_estimates(scenario)
    nbrs = [(n.name, scenario.agent_id(n.name), n.k) for n in scenario.agents[i].neighbours]
    return AgentEstimator(scenario.estimator(), agent_id=scenario.agent_id(name),
                          neighbours=nbrs, step=scenario.step, R0=R0[i], p0=p0[i],
                          leader=name in scenario.leaders,
                          known_ids=set(range(1, len(scenario.agents) + 1)), limits=limits)


def link_estimator_for(scenario: Scenario, name: str, limits: Limits = Limits(),
                       initial: tuple[Array, Array] | None = None) -> LinkAgentEstimator:
    """The estimator of robot ``name`` as the scenario defines it (its communication links in
    the batch simulator's order)."""
    i = scenario.index[name]
    R0, p0 = initial if initial is not None else initial_estimates(scenario)
    senses = {nb.name for nb in scenario.agents[i].neighbours}
    sensed_by = set(scenario.listeners(name))
    others = sorted(senses | sensed_by, key=scenario.index.__getitem__)
    links = [(o, scenario.agent_id(o), o in senses, o in sensed_by) for o in others]
    return LinkAgentEstimator(scenario.estimator(), agent_id=scenario.agent_id(name),
                              links=links, step=scenario.step, R0=R0[i], p0=p0[i],
                              known_ids=set(range(1, len(scenario.agents) + 1)), limits=limits)


def two_round_agent_for(scenario: Scenario, name: str, limits: Limits = Limits(),
                        initial: tuple[Array, Array] | None = None) -> TwoRoundAgent:
    """The estimator of robot ``name`` as the scenario defines it: its communication links
    (sensing either way, and the anchor's ranging) in the batch simulator's order."""
    i = scenario.index[name]
    anchor = scenario.anchor
    assert anchor is not None, 'two-round methods have an anchor'
    R0, p0 = initial if initial is not None else initial_estimates(scenario)
    senses = {nb.name for nb in scenario.agents[i].neighbours}
    sensed_by = set(scenario.listeners(name))
    ranging = set(scenario.ranged) if name == anchor else (
        {anchor} if name in scenario.ranged else set())
    others = sorted(senses | sensed_by | ranging, key=scenario.index.__getitem__)
    links = [(o, scenario.agent_id(o), o in senses, o in sensed_by) for o in others]
    ranges = {scenario.agent_id(o) for o in scenario.ranged} if name == anchor else set()
    spec = scenario.sensors.bearing_rates
    return TwoRoundAgent(scenario.estimator(), agent_id=scenario.agent_id(name), links=links,
                         step=scenario.step, R0=R0[i], p0=p0[i],
                         anchor=(anchor, scenario.agent_id(anchor)), ranges=ranges,
                         ranged=name in scenario.ranged, pinned=scenario.anchor_pinned,
                         rate_tau=spec.tau if spec.from_bearings else None,
                         known_ids=set(range(1, len(scenario.agents) + 1)), limits=limits)


def agent_for(scenario: Scenario, name: str, limits: Limits = Limits(),
              initial: tuple[Array, Array] | None = None) -> AgentEstimator | LinkAgentEstimator:
    """The agent logic of ``name`` for the scenario's method:
    :class:`estimators.link_agent.LinkAgentEstimator` for ``links = 'communication'`` methods
    (:class:`estimators.two_round_agent.TwoRoundAgent` for two-round ones),
    :class:`estimators.agent.AgentEstimator` for the others."""
    problem = scenario.not_distributable()
    if problem:
        raise ScenarioError(f'{scenario.source}: {problem}')
    if scenario.estimator().rounds == 2:
        return two_round_agent_for(scenario, name, limits, initial)
    if scenario.estimator().links == 'communication':
        return link_estimator_for(scenario, name, limits, initial)
    return estimator_for(scenario, name, limits, initial)
