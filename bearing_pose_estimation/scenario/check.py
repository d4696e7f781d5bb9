"""``check_scenario``: no two agents collocated, then the method's own assumptions; a moving
scenario also along its sampled motion (close approaches, :meth:`Estimator.check_motion`)."""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from ..core import graph
from ..estimators.base import CheckReport, Finding, Sensor
from .model import Scenario
from .truth import Truth

Array = NDArray[np.float64]

# A moving scenario's truth is sampled every SAMPLE_STEP_S [s] (between samples, on straight
# lines: graph.close_approaches), or coarser so that samples × agents (~100 MB) stays below:
SAMPLE_STEP_S = 0.05
MAX_AGENT_SAMPLES = 4_000_000


def check_scenario(scenario: Scenario) -> CheckReport:
    """Every finding on ``scenario`` for its method, collocated agents first."""
    pos = np.stack([a.position for a in scenario.agents])
    collocated = []
    for i, j in sorted(cKDTree(pos).query_pairs(graph.COLLOCATED_M)):
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
    """``(times (K,), positions (K, N, 3))`` [s], [m]: the truth about ``step`` apart (coarser for
    huge fleets; at 0.05 s the paper's 9 rad/s move a body-frame agent 2e-5 m off in 60 s)."""
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
    """One finding per pair closer than :data:`graph.CLOSE_APPROACH_M`, at its closest approach:
    an error below :data:`graph.COLLOCATED_M`. Pairs collocated at t = 0 are left out."""
    bearings = scenario.estimator().uses(Sensor.BEARINGS)
    why = ('bearings between them are undefined at collision' if bearings
           else 'robots this close may collide')
    out = []
    for i, j, dist, t in zip(*graph.close_approaches(times, positions, graph.CLOSE_APPROACH_M)):
        if np.linalg.norm(positions[0, j] - positions[0, i]) < graph.COLLOCATED_M:
            continue  # reported as collocated
        a, b = scenario.agents[int(i)].name, scenario.agents[int(j)].name
        driven = scenario.agents[int(j)].formation_position is not None
        where = 'formation_position' if driven else 'velocity'
        fix = (f'change the {"formation positions" if driven else "velocities"} or start '
               f'positions of {a} or {b}')
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
