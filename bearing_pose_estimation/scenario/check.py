"""``check_scenario``: what every method needs (no two agents collocated: bearings between them
are undefined), then the method's own graph assumptions (:meth:`Estimator.check`: Assumption 2
and M_i for Boughellaba & Tayebi, K_i for Tran et al., ...).

A moving scenario (:attr:`Scenario.moves`) is also checked along its motion: the truth is
sampled over ``[0, duration]`` (:func:`sample_truth`), pairs of agents that come closer than
:data:`graph.CLOSE_APPROACH_M` are reported (one finding per pair, at its closest approach; an
error below :data:`graph.COLLOCATED_M`), and so is what the motion breaks of the method's own
assumptions (:meth:`Estimator.check_motion`). Static scenarios are checked at t = 0 only, as
before.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ..core import graph
from ..estimators.base import CheckReport, Finding, Sensor
from .model import Scenario
from .truth import Truth

Array = NDArray[np.float64]

# The truth of a moving scenario is sampled every SAMPLE_STEP_S [s] (close approaches between
# samples are found on the straight lines joining them, :func:`graph.close_approaches`) ...
SAMPLE_STEP_S = 0.05
# ... or coarser, so that (samples × agents) stays below this (about 100 MB of positions).
MAX_AGENT_SAMPLES = 4_000_000


def check_scenario(scenario: Scenario) -> CheckReport:
    """Every finding on ``scenario`` for its method, collocated agents first; for a moving
    scenario, then its close approaches and the method's findings along the motion."""
    pos = np.stack([a.position for a in scenario.agents])
    collocated = []
    for i, j in graph.collocated_pairs(pos):
        a, b = scenario.agents[i].name, scenario.agents[j].name
        collocated.append(Finding('error', b, 'position', f'collocated with {a}',
                                  f'move {b} or {a}: bearings between them are undefined'))
    estimator = scenario.estimator()
    report = estimator.check(scenario.fleet())
    report.findings[:0] = collocated
    if scenario.moves:
        times, positions = sample_truth(scenario)
        report.findings += close_approach_findings(scenario, times, positions)
        report.findings += estimator.check_motion(scenario.fleet(), times, positions)
    return report


def sample_truth(scenario: Scenario, step: float = SAMPLE_STEP_S) -> tuple[Array, Array]:
    """The true positions of every agent at ``times`` ``(K,)``, evenly spaced from 0 to
    ``scenario.duration`` about ``step`` apart (coarser for huge fleets,
    :data:`MAX_AGENT_SAMPLES`): ``(times, positions (K, N, 3))`` [s], [m].

    Integrated by :class:`.truth.Truth`, attitudes included, so body-frame velocities are
    right (at steps of 0.05 s the paper's rates, up to 9 rad/s, move a body-frame agent 2e-5 m
    off in 60 s); with a body-frame velocity the integration step stays at most ``step`` when
    the samples are coarser.
    """
    n = len(scenario.agents)
    coarse = max(step, scenario.duration * n / MAX_AGENT_SAMPLES)
    n_samples = max(1, math.ceil(scenario.duration / coarse - 1e-9))
    h = scenario.duration / n_samples
    body = any(a.velocity is not None and a.velocity.frame != 'world'
               and not a.velocity.value.is_zero for a in scenario.agents)
    sub = max(1, math.ceil(h / step - 1e-9)) if body else 1
    truth = Truth(scenario, h / sub)
    positions = np.empty((n_samples + 1, n, 3))
    positions[0] = truth.p
    for k in range(1, n_samples + 1):
        for _ in range(sub):
            truth.advance()
        positions[k] = truth.p
    return np.arange(n_samples + 1, dtype=np.float64) * h, positions


def close_approach_findings(scenario: Scenario, times: Array,
                            positions: Array) -> list[Finding]:
    """One finding per pair of agents closer than :data:`graph.CLOSE_APPROACH_M` at some time
    (its closest approach): an error when they collide (closer than
    :data:`graph.COLLOCATED_M`), else a warning. Pairs collocated at t = 0 are left to the
    static check."""
    bearings = scenario.estimator().uses(Sensor.BEARINGS)
    why = ('bearings between them are undefined at collision' if bearings
           else 'robots this close may collide')
    out = []
    for i, j, dist, t in zip(*graph.close_approaches(times, positions,
                                                     graph.CLOSE_APPROACH_M)):
        if np.linalg.norm(positions[0, j] - positions[0, i]) < graph.COLLOCATED_M:
            continue  # reported as collocated
        a, b = scenario.agents[int(i)].name, scenario.agents[int(j)].name
        driven = scenario.agents[int(j)].formation_position is not None
        where = 'formation_position' if driven else 'velocity'
        fix = (f'change the formation positions or start positions of {a} or {b}' if driven
               else f'change the velocities or start positions of {a} or {b}')
        if dist < graph.COLLOCATED_M:
            out.append(Finding('error', b, where, f'collides with {a} at t = {t:.2f} s '
                               f'(closest distance {dist:.3g} m): '
                               + ('bearings between them are undefined' if bearings
                                  else 'they collide'), fix))
        else:
            out.append(Finding('warning', b, where, f'comes within {dist:.3f} m of {a} '
                               f'at t = {t:.2f} s (closer than {graph.CLOSE_APPROACH_M:g} m; '
                               f'{why})', fix))
    return out
