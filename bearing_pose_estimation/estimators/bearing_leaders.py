"""The setting Boughellaba & Tayebi and Tran, Anderson & Ahn share: gyros and bearings, two
leaders that know their pose, followers that each see at least two earlier agents.

Sensing is two-way on every edge: follower i measures ``b^i_ij`` and its neighbour j measures
``b^j_ji``; j sends i the world-frame product ``R̂_j b^j_ji`` (formed by j at one instant, so
that attitude and bearing pair in time) and its position estimate ``p̂_j``. Agent i then uses
``d_ij = R̂_j b^j_ij = -R̂_j b^j_ji`` (note the sign).

Assumption 2 of Boughellaba & Tayebi (Tran et al. assume the same graph class): (a) the sensing
graph is acyclic and every follower is reachable from both leaders; (b) leaders have no
neighbours (enforced when parsing); (d) no two agents are collocated, every follower has
``|N_i| >= 2`` neighbours, all earlier in the agent order, with at least two non-collinear
bearings. Each method adds the spectrum condition of its own lemma (:meth:`Estimator.conditioning`).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from ..core import graph, so3
from .base import (Array, Channel, CheckReport, Edges, EstimateFrame, Estimator, Finding, G,
                   Index, Roles, S, Sensor, StepInputs)

if TYPE_CHECKING:
    from ..scenario.model import Scenario

P_HAT = Channel('p_hat', per='agent', frame='world', doc='p̂_j, the position estimate [m]')
WORLD_BEARING = Channel('world_bearing', per='edge', frame='world', unit=True,
                        doc='R̂_j b^j_ji, j\'s bearing to its listener i in the world frame')

# Bearings closer than this to collinear make Σ P_b singular: an error.
COLLINEAR_ERROR_RAD = 1e-6
# Below this angle the position observer is badly conditioned: a warning.
COLLINEAR_WARN_DEG = 5.0
# Eigenvalues closer than this (relative to the largest) count as repeated.
EIGEN_GAP_REL = 1e-6


def bearing_pull(p_hat: Array, edges: Edges, y: Array, p_hat_nbr: Array) -> Array:
    """``Σ_j P_{y_ij} (p̂_i - p̂_j)`` per agent, ``(N, 3)``, with ``P_y e = e - y (y·e)/‖y‖²``:
    the position correction of both observers (``y_ij = R̂_i b^i_ij``, ``(E, 3)``)."""
    e = np.take(p_hat, edges.agent, axis=0) - p_hat_nbr
    return edges.sum_by_agent(e - y * (so3.dot(y, e) / so3.dot(y, y))[:, None])


def repeated(eig: Array) -> bool:
    """Two eigenvalues (ascending) closer than :data:`EIGEN_GAP_REL` of the largest."""
    return bool(np.min(np.diff(eig)) <= EIGEN_GAP_REL * max(eig[-1], 1e-300))


class BearingLeaderEstimator(Estimator[G, S]):
    """Common part of the two leader-follower bearing methods: roles, sensors, messages, the
    graph check. Subclasses give the step and the local matrix of their lemma."""

    roles: ClassVar[Roles] = Roles(leaders=2)
    sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.GYRO, Sensor.BEARINGS,
                                                     Sensor.KNOWN_POSE})
    sends: ClassVar[tuple[Channel, ...]] = (P_HAT, WORLD_BEARING)
    frame: ClassVar[EstimateFrame] = EstimateFrame.WORLD
    conditioning_label: ClassVar[str]      # the local matrix, e.g. 'M_i = Σ_j k_ij b_ij b_ijᵀ'

    def outbox(self, x: S, sender: Index, bearings: Array) -> dict[str, Array]:
        """``R̂_j b^j_jl`` for each sender row j and its own bearing to listener l, and
        ``p̂_j``."""
        R = np.take(x.R_hat, sender, axis=0)
        return {WORLD_BEARING.name: np.einsum('eab,eb->ea', R, bearings),
                P_HAT.name: x.p_hat}

    @staticmethod
    def neighbour_terms(inputs: StepInputs) -> tuple[Array, Array]:
        """``(d_ij = R̂_j b^j_ij (E, 3), p̂_j (E, 3))`` from what the neighbours sent."""
        return -inputs.received[WORLD_BEARING.name], inputs.received[P_HAT.name]

    # ------------------------------------------------------------------ Assumption 2
    def check(self, scenario: Scenario) -> CheckReport:
        report = CheckReport(spectra_of=self.conditioning_label)
        add = report.findings.append
        pos = np.stack([a.position for a in scenario.agents])
        names = [a.name for a in scenario.agents]
        order = scenario.index
        nbrs = {a.name: [n.name for n in a.neighbours] for a in scenario.agents}

        cycle = graph.find_cycle(names, nbrs)
        if cycle:
            add(Finding('error', cycle[0], 'neighbours', 'the sensing graph has a cycle: '
                        + ' -> '.join(cycle) + ' (Assumption 2a)',
                        f'remove {cycle[1]} from the neighbours of {cycle[0]} (or another edge '
                        'of the cycle)'))
        reach = [graph.reachable_from(leader, names, nbrs) for leader in scenario.leaders]
        for a in scenario.followers:
            i = order[a.name]
            if len(a.neighbours) < 2:
                add(Finding('error', a.name, 'neighbours', f'has {len(a.neighbours)} '
                            'neighbour(s), needs at least 2 (Assumption 2d)',
                            'add an earlier agent it can see'))
            if not cycle:
                for n in a.neighbours:
                    if order[n.name] > i:
                        add(Finding('error', a.name, 'neighbours', f'{n.name} comes after '
                                    f'{a.name} in `agents`; neighbours must be earlier '
                                    '(Assumption 2d)',
                                    f'move {n.name} above {a.name} in `agents`'))
            for leader, seen in zip(scenario.leaders, reach):
                if a.name not in seen:
                    add(Finding('error', a.name, 'neighbours', f'not reachable from leader '
                                f'{leader} (Assumption 2a)', f'give {a.name} or one of its '
                                f'ancestors a path from {leader}'))

            idx = [order[n.name] for n in a.neighbours]
            d = pos[idx] - pos[i]
            dist = np.linalg.norm(d, axis=1)
            if len(idx) == 0 or np.any(dist < graph.COLLOCATED_M):
                continue  # already reported
            b = d / dist[:, None]
            if len(idx) >= 2:
                widest = graph.widest_angle(b)
                if widest < COLLINEAR_ERROR_RAD:
                    add(Finding('error', a.name, 'neighbours', 'all bearings to its neighbours '
                                'are collinear, so its position is unobservable '
                                '(Assumption 2d)',
                                'add a neighbour off the line through the current ones'))
                elif np.degrees(widest) < COLLINEAR_WARN_DEG:
                    add(Finding('warning', a.name, 'neighbours', f'bearings are nearly '
                                f'collinear (widest angle {np.degrees(widest):.2f} deg): slow, '
                                'noise-sensitive position estimate',
                                'add a neighbour in another direction'))
            matrix = self.conditioning(b, np.array([n.k for n in a.neighbours]))
            assert matrix is not None  # both methods have one
            eig = np.linalg.eigvalsh(matrix).astype(np.float64)
            report.spectra[a.name] = eig
            problem = self.conditioning_problem(eig)
            if problem is not None:
                add(Finding('warning', a.name, 'neighbours', problem,
                            self.conditioning_fix(eig, a.neighbours[0].name, len(idx))))
        return report

    def conditioning_fix(self, eig: Array, first_neighbour: str, n_neighbours: int) -> str:
        """How to mend the spectrum ``eig`` that :meth:`conditioning_problem` objects to."""
        return (f'use different per-edge gains, e.g. `neighbours: [{{name: {first_neighbour}, '
                'k: 2.0}, ...]`')
