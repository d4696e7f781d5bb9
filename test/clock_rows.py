"""What the fault matrix's clock rows (netsim.clock_cases) show in every method's matrix test:
which listeners must flag which neighbours' clocks as ahead, from the clocks and the table of
subscriptions (not from the runtime that counts them)."""
from __future__ import annotations

from bearing_pose_estimation.runtime.buffers import Limits
from bearing_pose_estimation.runtime.table import subscriptions
from bearing_pose_estimation.scenario.model import Scenario
from bearing_pose_estimation.scenario.runtimes import agent_specs
from bearing_pose_estimation.sim.netsim import Clocks


def clocks_ahead(scenario: Scenario, clocks: Clocks,
                 limit: float = Limits().max_clock_lead) -> dict[str, set[str]]:
    """Per listener, the neighbours it reads from whose fixed offset is more than ``limit``
    ahead of its own (listeners with none left out)."""
    offsets = {name: o for name, (o, _) in clocks.of([a.name for a in scenario.agents]).items()}
    method = type(scenario.estimator())
    out = {}
    for spec in agent_specs(scenario):
        ahead = {s.source for s in subscriptions(method, spec)
                 if offsets[s.source] - offsets[spec.name] > limit}
        if ahead:
            out[spec.name] = ahead
    return out


def flagged(ahead: dict[str, dict[str, int]]) -> dict[str, set[str]]:
    """A run's :attr:`netsim.NetRun.ahead` as listener -> the neighbours it flagged."""
    return {listener: set(senders) for listener, senders in ahead.items()}
