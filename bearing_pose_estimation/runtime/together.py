"""The steps of several agents in one call of their method's step.

An agent's step is mostly numpy's per-call overhead; eight agents' in one call cost little more
than one (BENCHMARKS.md, "Steps run together"). Rows are independent, so each agent gets
exactly what its own step gives (``test_runtime.py``).
"""
from __future__ import annotations

from collections.abc import Sequence

from ..estimators.base import StepInputs
from .agent import AgentRuntime, Prepared


def advance_together(agents: Sequence[AgentRuntime]) -> list[AgentRuntime]:
    """One step of every agent that has one ready (each as its own ``advance(1)``), those of
    one method with equal gains and inputs that stack in one call of the method's step (of
    one instant, if the method's step reads it). Returns the agents that stepped."""
    stepped = [a for a in agents if a.steps_ready() > 0]
    groups: list[list[tuple[AgentRuntime, Prepared]]] = []
    for a in stepped:
        prepared = a.begin_step()
        if prepared is None:
            continue   # a leader: its whole step
        for group in groups:
            b, other = group[0]
            if (type(b.estimator) is type(a.estimator) and b.estimator.gains == a.estimator.gains
                    and b.h == a.h
                    and other.inputs.stacks_with(prepared.inputs, a.estimator.timed_step)):
                group.append((a, prepared))
                break
        else:
            groups.append([(a, prepared)])
    for group in groups:
        lead = group[0][0]
        if len(group) == 1:
            lead.end_step(group[0][1], *lead.estimator.step(lead.x, lead.h, group[0][1].inputs))
            continue
        x, diagnostics = lead.estimator.step(type(lead.x).stack([a.x for a, _ in group]), lead.h,
                                             StepInputs.stack([p.inputs for _, p in group],
                                                              lead.estimator.timed_step))
        for i, (a, prepared) in enumerate(group):
            a.end_step(prepared, x.rows(slice(i, i + 1)),
                       {k: v[i:i + 1] for k, v in diagnostics.items()})
    return stepped
