"""Checks of the paper's Assumption 2 and of Lemma 1's hypothesis, on a parsed scenario.

Assumption 2 (Boughellaba & Tayebi): (a) the sensing graph is acyclic and every follower is
reachable from both leaders; (b) leaders have no neighbours (enforced when parsing);
(d) no two agents are collocated, every follower has ``|N_i| >= 2`` neighbours, all earlier in
the agent order, with at least two non-collinear bearings.

Lemma 1 needs ``M_i = Σ_j k_ij b_ij b_ijᵀ`` to have three distinct eigenvalues; an agent can
check it locally on its body-frame bearings (same spectrum). A violation is a warning: the
paper's own agent 8 has spectrum {0, 1, 1} and still converges. For ``method:
tran_anderson_ahn`` the matrix is Tran et al.'s ``K_i`` (their (9); with exactly two
neighbours it includes ``k_c c cᵀ`` for the third direction ``c = b_ij × b_ik / ‖·‖``), which
must be positive definite (non-coplanar bearings) with distinct eigenvalues (their Lemma 2).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .scenario import Scenario

# Bearings closer than this to collinear make Σ P_b singular: an error.
COLLINEAR_ERROR_RAD = 1e-6
# Below this angle the position observer is badly conditioned: a warning.
COLLINEAR_WARN_DEG = 5.0
COLLOCATED_M = 1e-6
# Eigenvalues closer than this (relative to the largest) count as repeated.
EIGEN_GAP_REL = 1e-6


@dataclass(frozen=True)
class Finding:
    severity: str   # 'error' or 'warning'
    agent: str
    field: str
    problem: str
    fix: str

    def __str__(self) -> str:
        return f'{self.severity}: {self.agent}.{self.field}: {self.problem}. Fix: {self.fix}'


@dataclass
class CheckReport:
    findings: list[Finding] = field(default_factory=list)
    spectra: dict[str, NDArray[np.float64]] = field(default_factory=dict)  # eig(M_i), ascending
    spectra_of: str = 'M_i = Σ_j k_ij b_ij b_ijᵀ'   # Tran et al.: their K_i

    @property
    def errors(self) -> list[Finding]:
        return [f for f in self.findings if f.severity == 'error']

    @property
    def warnings(self) -> list[Finding]:
        return [f for f in self.findings if f.severity == 'warning']

    @property
    def ok(self) -> bool:
        return not self.errors

    def format(self, max_spectra: int = 50) -> str:
        lines = [str(f) for f in self.findings]
        if self.spectra:
            lines.append(f'spectra (eigenvalues of {self.spectra_of}):')
            for k, (name, eig) in enumerate(self.spectra.items()):
                if k == max_spectra:
                    lines.append(f'  ... {len(self.spectra) - max_spectra} more')
                    break
                lines.append(f'  {name}: {{{", ".join(f"{e:.4g}" for e in eig)}}}')
        return '\n'.join(lines)


def _find_cycle(scenario: Scenario) -> list[str] | None:
    """A directed cycle of the 'i listens to j' graph, if any (iterative DFS)."""
    names = [a.name for a in scenario.agents]
    nbrs = {a.name: [n.name for n in a.neighbours] for a in scenario.agents}
    state = dict.fromkeys(names, 0)  # 0 new, 1 on stack, 2 done
    for root in names:
        if state[root]:
            continue
        stack: list[tuple[str, int]] = [(root, 0)]
        path = [root]
        state[root] = 1
        while stack:
            node, k = stack[-1]
            if k < len(nbrs[node]):
                stack[-1] = (node, k + 1)
                nxt = nbrs[node][k]
                if state[nxt] == 1:
                    return path[path.index(nxt):] + [nxt]
                if state[nxt] == 0:
                    state[nxt] = 1
                    stack.append((nxt, 0))
                    path.append(nxt)
            else:
                state[node] = 2
                stack.pop()
                path.pop()
    return None


def _reachable_from(scenario: Scenario, leader: str) -> set[str]:
    listeners: dict[str, list[str]] = {a.name: [] for a in scenario.agents}
    for a in scenario.agents:
        for n in a.neighbours:
            listeners[n.name].append(a.name)
    seen, queue = {leader}, deque([leader])
    while queue:
        for nxt in listeners[queue.popleft()]:
            if nxt not in seen:
                seen.add(nxt)
                queue.append(nxt)
    return seen


def check_scenario(scenario: Scenario) -> CheckReport:
    """All Assumption 2 conditions and the M_i spectra of every follower."""
    report = CheckReport()
    if scenario.method == 'tran_anderson_ahn':
        report.spectra_of = 'K_i = Σ_j k_ij b_ij b_ijᵀ, + k_c c cᵀ with two neighbours'
    add = report.findings.append
    pos = np.stack([a.position for a in scenario.agents])
    order = scenario.index

    for i, j in sorted(cKDTree(pos).query_pairs(COLLOCATED_M)):
        a, b = scenario.agents[i].name, scenario.agents[j].name
        add(Finding('error', b, 'position', f'collocated with {a} (Assumption 2d)',
                    f'move {b} or {a}: bearings between them are undefined'))

    cycle = _find_cycle(scenario)
    if cycle:
        add(Finding('error', cycle[0], 'neighbours', 'the sensing graph has a cycle: '
                    + ' -> '.join(cycle) + ' (Assumption 2a)',
                    f'remove {cycle[1]} from the neighbours of {cycle[0]} (or another edge '
                    'of the cycle)'))

    reach = [_reachable_from(scenario, name) for name in scenario.leaders]
    for a in scenario.followers:
        i = order[a.name]
        if len(a.neighbours) < 2:
            add(Finding('error', a.name, 'neighbours', f'has {len(a.neighbours)} neighbour(s), '
                        'needs at least 2 (Assumption 2d)', 'add an earlier agent it can see'))
        if not cycle:
            for n in a.neighbours:
                if order[n.name] > i:
                    add(Finding('error', a.name, 'neighbours', f'{n.name} comes after '
                                f'{a.name} in `agents`; neighbours must be earlier '
                                '(Assumption 2d)', f'move {n.name} above {a.name} in `agents`'))
        for leader, seen in zip(scenario.leaders, reach):
            if a.name not in seen:
                add(Finding('error', a.name, 'neighbours', f'not reachable from leader {leader} '
                            '(Assumption 2a)', f'give {a.name} or one of its ancestors a path '
                            f'from {leader}'))

        idx = [order[n.name] for n in a.neighbours]
        d = pos[idx] - pos[i]
        dist = np.linalg.norm(d, axis=1)
        if len(idx) == 0 or np.any(dist < COLLOCATED_M):
            continue  # already reported
        b = d / dist[:, None]
        if len(idx) >= 2:
            sines = np.linalg.norm(np.cross(b[:, None, :], b[None, :, :]), axis=-1)
            widest = float(np.arcsin(np.clip(sines.max(), 0.0, 1.0)))
            if widest < COLLINEAR_ERROR_RAD:
                add(Finding('error', a.name, 'neighbours', 'all bearings to its neighbours are '
                            'collinear, so its position is unobservable (Assumption 2d)',
                            'add a neighbour off the line through the current ones'))
            elif np.degrees(widest) < COLLINEAR_WARN_DEG:
                add(Finding('warning', a.name, 'neighbours', f'bearings are nearly collinear '
                            f'(widest angle {np.degrees(widest):.2f} deg): slow, noise-sensitive '
                            'position estimate', 'add a neighbour in another direction'))
        k = np.array([n.k for n in a.neighbours])
        M = np.einsum('e,ea,eb->ab', k, b, b)
        tran = scenario.method == 'tran_anderson_ahn'
        if tran and len(idx) == 2 and np.linalg.norm(np.cross(b[0], b[1])) > 0:
            c = np.cross(b[0], b[1])  # Tran et al.'s third direction for two neighbours
            M += scenario.k_c * np.outer(c, c) / (c @ c)
        eig = np.linalg.eigvalsh(M)
        report.spectra[a.name] = eig
        fix = (f'use different per-edge gains, e.g. `neighbours: [{{name: '
               f'{a.neighbours[0].name}, k: 2.0}}, ...]`')
        eigs = '{' + ', '.join(f'{e:.3g}' for e in eig) + '}'
        if tran and eig[0] <= EIGEN_GAP_REL * max(eig[-1], 1e-300):
            add(Finding('warning', a.name, 'neighbours', f'K_i = Σ k_ij b_ij b_ijᵀ is singular '
                        f'(eigenvalues {eigs}): its bearings are coplanar, so Tran et al.\'s '
                        'attitude observer cannot converge (K_i must be positive definite, (9))',
                        'add a neighbour out of the plane of the current ones'))
        elif np.min(np.diff(eig)) <= EIGEN_GAP_REL * max(eig[-1], 1e-300):
            what, ref = (('K_i = Σ k_ij b_ij b_ijᵀ (+ k_c c cᵀ)', 'Tran et al.\'s Lemma 2')
                         if tran else ('M_i = Σ k_ij b_ij b_ijᵀ', 'Lemma 1\'s'))
            add(Finding('warning', a.name, 'neighbours', f'{what} has repeated eigenvalues '
                        f'{eigs}: {ref} hypothesis fails (convergence is then not guaranteed)',
                        fix + (' or another gains.k_c' if tran and len(idx) == 2 else '')))
    return report
