"""Directed-graph and geometry helpers for the methods' assumption checks (no project types:
agents are names, graphs are ``{name: [neighbour names]}``)."""
from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

# Agents closer than this [m] are collocated: bearings between them are undefined.
COLLOCATED_M = 1e-6


def find_cycle(names: Sequence[str], nbrs: Mapping[str, Sequence[str]]) -> list[str] | None:
    """A directed cycle of the 'i listens to j' graph as ``[a, b, ..., a]``, if any (iterative
    DFS in the order of ``names``)."""
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


def reachable_from(source: str, names: Sequence[str],
                   nbrs: Mapping[str, Sequence[str]]) -> set[str]:
    """The agents whose information can come from ``source``: ``source`` and every agent that
    listens to one of them, transitively."""
    listeners: dict[str, list[str]] = {name: [] for name in names}
    for name in names:
        for n in nbrs[name]:
            listeners[n].append(name)
    seen, queue = {source}, deque([source])
    while queue:
        for nxt in listeners[queue.popleft()]:
            if nxt not in seen:
                seen.add(nxt)
                queue.append(nxt)
    return seen


def collocated_pairs(positions: NDArray[np.float64]) -> list[tuple[int, int]]:
    """Index pairs ``(i, j)``, ``i < j``, of positions closer than :data:`COLLOCATED_M`."""
    return sorted(cKDTree(positions).query_pairs(COLLOCATED_M))


def widest_angle(b: NDArray[np.float64]) -> float:
    """The largest angle [rad, in [0, π/2]] between the lines of any two unit vectors ``b``
    ``(M, 3)``: 0 when they are all collinear."""
    sines = np.linalg.norm(np.cross(b[:, None, :], b[None, :, :]), axis=-1)
    return float(np.arcsin(np.clip(sines.max(), 0.0, 1.0)))
