"""``check_scenario``: what every method needs (no two agents collocated: bearings between them
are undefined), then the method's own graph assumptions (:meth:`Estimator.check`: Assumption 2
and M_i for Boughellaba & Tayebi, K_i for Tran et al., ...)."""
from __future__ import annotations

import numpy as np

from ..core import graph
from ..estimators.base import CheckReport, Finding
from .model import Scenario


def check_scenario(scenario: Scenario) -> CheckReport:
    """Every finding on ``scenario`` for its method, collocated agents first."""
    pos = np.stack([a.position for a in scenario.agents])
    collocated = []
    for i, j in graph.collocated_pairs(pos):
        a, b = scenario.agents[i].name, scenario.agents[j].name
        collocated.append(Finding('error', b, 'position', f'collocated with {a}',
                                  f'move {b} or {a}: bearings between them are undefined'))
    report = scenario.estimator().check(scenario)
    report.findings[:0] = collocated
    return report
