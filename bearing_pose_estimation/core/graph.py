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
# Moving agents that come closer than this [m] are about to collide: a warning (bearings are
# undefined at collision; a real fleet's bodies would touch first).
CLOSE_APPROACH_M = 0.2


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


def widest_angles(b: NDArray[np.float64]) -> NDArray[np.float64]:
    """The largest angle ``(...)`` [rad, in [0, π/2]] between the lines of any two of the unit
    vectors ``b`` ``(..., M, 3)``, ``M >= 2``: 0 when they are all collinear."""
    first, second = np.triu_indices(b.shape[-2], 1)
    sines = np.linalg.norm(np.cross(b[..., first, :], b[..., second, :]), axis=-1)
    return np.arcsin(np.clip(sines.max(axis=-1), 0.0, 1.0))


def close_approaches(times: NDArray[np.float64], positions: NDArray[np.float64],
                     radius: float) -> tuple[NDArray[np.intp], NDArray[np.intp],
                                             NDArray[np.float64], NDArray[np.float64]]:
    """``(i, j, distance, time)`` of the (earliest) closest approach of every pair ``i < j`` closer
    than ``radius`` [m], sorted, on straight lines between ``positions`` ``(K, N, 3)``; a KD-tree
    per segment finds candidates (``radius`` plus twice the farthest move), then exact minima."""
    k_samples, n = positions.shape[:2]
    empty_i, empty_f = np.zeros(0, dtype=np.intp), np.zeros(0)
    if n < 2 or k_samples == 0:
        return empty_i, empty_i, empty_f, empty_f
    if k_samples == 1:  # one instant: a zero-length segment
        positions = np.concatenate([positions, positions])
        times = np.concatenate([times, times])
    seg_list, pair_list = [], []
    for k in range(len(positions) - 1):
        moved = float(np.linalg.norm(positions[k + 1] - positions[k], axis=1).max())
        pairs = cKDTree(positions[k]).query_pairs(radius + 2.0 * moved + 1e-9,
                                                  output_type='ndarray')
        if len(pairs):
            seg_list.append(np.full(len(pairs), k, dtype=np.intp))
            pair_list.append(pairs)
    if not pair_list:
        return empty_i, empty_i, empty_f, empty_f
    seg = np.concatenate(seg_list)
    pairs = np.concatenate(pair_list).astype(np.intp)
    i, j = pairs[:, 0], pairs[:, 1]
    d0 = positions[seg, j] - positions[seg, i]
    dd = positions[seg + 1, j] - positions[seg + 1, i] - d0
    dd2 = np.einsum('ea,ea->e', dd, dd)
    s = np.divide(-np.einsum('ea,ea->e', d0, dd), dd2, out=np.zeros_like(dd2), where=dd2 > 0)
    s = np.clip(s, 0.0, 1.0)
    dist = np.linalg.norm(d0 + s[:, None] * dd, axis=1)
    when = times[seg] + s * (times[seg + 1] - times[seg])
    key = i * n + j
    order = np.lexsort((when, dist, key))           # per pair: closest, then earliest
    key, i, j, dist, when = key[order], i[order], j[order], dist[order], when[order]
    first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    keep = first[dist[first] < radius]
    return i[keep], j[keep], dist[keep], when[keep]
