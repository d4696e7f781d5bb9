"""Random valid scenarios of any size, reproducible from a seed.

Agents fill a cube ``MIN_SPACING_M`` apart, the leaders near the centre; each follower sees 2-3
of its nearest placed agents (acyclic, reachable from both leaders), one pair at least
``MIN_SPREAD_DEG`` from collinear (at 15 deg the smallest eigenvalue of ``M_i`` is 0.03).

Moving fleets (``speed > 0``): ``v_a(t) = V (cos(w t + φ_a), sin(w t + φ_a), 0.3 cos(0.6 w t +
2 φ_a))``, a circle of radius ``R = V / w`` with a slow vertical oscillation. The phases are a
common one plus one in ``±δ``, so two agents move apart by at most ``2√2 R |φ_a - φ_b| <= 4√2 R
δ``, kept below :data:`MAX_RELATIVE_DRIFT_M`: no close approach, by construction. The phases are
drawn last, so ``speed = 0`` writes exactly the static file of the same seed.
"""
from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..core import graph

MIN_SPACING_M = 0.5
MIN_SPREAD_DEG = 35.0
LEADER_SEPARATION_M = 1.5
_CANDIDATES = 8
# Moving fleets: the most two agents move relative to each other [m], half the room between the
# minimum spacing and a close approach.
MAX_RELATIVE_DRIFT_M = 0.5 * (MIN_SPACING_M - graph.CLOSE_APPROACH_M)


def _positions(n: int, rng: np.random.Generator) -> np.ndarray:
    side = 2.0 * max(n, 8) ** (1.0 / 3.0)  # about one agent per 8 m³
    pts = np.empty((0, 3))
    while len(pts) < n:
        pts = np.vstack([pts, rng.uniform(0.0, side, size=(n - len(pts), 3))])
        close = cKDTree(pts).query_pairs(MIN_SPACING_M, output_type='ndarray')
        if len(close):
            pts = np.delete(pts, np.unique(close[:, 1]), axis=0)
    # Leaders: the agent nearest the centre and the nearest one at least LEADER_SEPARATION_M
    # from it. A tighter core would look collinear from everywhere else.
    first = int(np.argmin(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))
    dist = np.linalg.norm(pts - pts[first], axis=1)
    second = int(np.argmin(np.where(dist >= LEADER_SEPARATION_M, dist, np.inf)))
    mid = 0.5 * (pts[first] + pts[second])
    rest = [int(k) for k in np.argsort(np.linalg.norm(pts - mid, axis=1), kind='stable')
            if k not in (first, second)]
    return pts[[first, second] + rest]


def _valid(p: np.ndarray, i: int, pick: list[int]) -> bool:
    # Reachable from both leaders (0, 1): sees both, or a follower (by induction).
    if not (any(j >= 2 for j in pick) or {0, 1} <= set(pick)):
        return False
    d = p[pick] - p[i]
    b = d / np.linalg.norm(d, axis=1, keepdims=True)
    sines = np.linalg.norm(np.cross(b[:, None, :], b[None, :, :]), axis=-1)
    return bool(sines.max() >= np.sin(np.radians(MIN_SPREAD_DEG)))


def _choose_neighbours(p: np.ndarray, i: int, placed: np.ndarray, tree: cKDTree,
                       rng: np.random.Generator) -> list[int] | None:
    """2-3 placed agents near ``i`` forming a valid neighbour set, or None."""
    _, idx = tree.query(p[i], k=min(len(p), 4 * _CANDIDATES))
    near = [int(j) for j in np.atleast_1d(idx) if placed[j]][:_CANDIDATES]
    if len(near) < 2:  # sparse corner: the nearest placed agents, wherever they are
        cand = np.flatnonzero(placed)
        near = [int(j) for j in cand[np.argsort(np.linalg.norm(p[cand] - p[i], axis=1))]
                ][:_CANDIDATES]
    for _ in range(20):
        m = min(int(rng.integers(2, 4)), len(near))
        pick = sorted(int(j) for j in rng.choice(near, size=m, replace=False))
        if _valid(p, i, pick):
            return pick
    for a_pos, a in enumerate(near):  # the random draws missed: try every pair once
        for b in near[:a_pos]:
            if _valid(p, i, [a, b]):
                return sorted([a, b])
    return None


def _build_graph(p: np.ndarray, rng: np.random.Generator) -> tuple[list[int], dict[int, list[int]]]:
    """Placement order (leaders 0 and 1 first, then outwards) and each follower's neighbours."""
    n = len(p)
    tree = cKDTree(p)
    placed = np.zeros(n, dtype=bool)
    placed[:2] = True
    order, nbrs = [0, 1], {}
    queue = deque(range(2, n))
    deferred = 0
    while queue:
        i = queue.popleft()
        pick = _choose_neighbours(p, i, placed, tree, rng)
        if pick is not None:
            placed[i] = True
            order.append(i)
            nbrs[i] = pick
        elif (deferred := deferred + 1) > 4 * n:
            raise RuntimeError('no valid sensing graph for these positions')
        else:
            queue.append(i)
    return order, nbrs


def _omega(rng: np.random.Generator) -> list[Any]:
    comps: list[Any] = []
    for _ in range(3):   # a constant plus one sinusoid each, drawn in this order
        const = round(float(rng.uniform(-1.0, 1.0)), 3)
        kind = 'sin' if rng.uniform() < 0.5 else 'cos'
        comps.append([const, {kind: round(float(rng.uniform(0.5, 5.0)), 3),
                              'amplitude': round(float(rng.uniform(-1.0, 1.0)), 3)}])
    return comps


def _velocities(n: int, speed: float, turn_rate: float,
                rng: np.random.Generator) -> list[dict[str, Any]]:
    """The ``velocity:`` of each of ``n`` agents (module docstring)."""
    radius = speed / turn_rate
    # Phases are rounded to 1e-4 rad: keep the bound with that slack.
    spread = float(np.clip(MAX_RELATIVE_DRIFT_M / (4.0 * np.sqrt(2.0) * radius) - 1e-4,
                           0.0, np.pi))
    phases = float(rng.uniform(0.0, 2.0 * np.pi)) + rng.uniform(-spread, spread, size=n)
    v, w = float(speed), float(turn_rate)
    return [{'world': [{'cos': w, 'amplitude': v, 'phase': phi},
                       {'sin': w, 'amplitude': v, 'phase': phi},
                       {'cos': round(0.6 * w, 12), 'amplitude': round(0.3 * v, 12),
                        'phase': round(2.0 * phi, 4)}]}
            for phi in (round(float(x), 4) for x in phases)]


def generate_scenario(n_agents: int, seed: int = 0, max_angle_deg: float = 90.0,
                      position_std: float = 1.0, speed: float = 0.0,
                      turn_rate: float = 0.5) -> dict[str, Any]:
    """A scenario of ``n_agents`` >= 3 as a YAML-ready dict, drawn from ``seed``: attitude errors
    uniform in ``[0, max_angle_deg]``, position errors ``N(0, position_std²)`` per axis [m]; with
    ``speed`` V > 0 [m/s], a fleet turning at ``turn_rate`` [rad/s] (module docstring)."""
    if n_agents < 3:
        raise ValueError('n_agents must be at least 3 (two leaders and one follower)')
    if not (np.isfinite(speed) and speed >= 0):
        raise ValueError('speed must be a number >= 0 [m/s]')
    if speed > 0 and not (np.isfinite(turn_rate) and turn_rate > 0):
        raise ValueError('turn_rate must be a positive number [rad/s]')
    rng = np.random.default_rng(seed)
    for _ in range(100):  # tiny fleets can come out nearly collinear: draw again
        p = _positions(n_agents, rng)
        try:
            order, nbrs = _build_graph(p, rng)
            break
        except RuntimeError:
            continue
    else:
        raise RuntimeError(f'no valid {n_agents}-agent layout found with seed {seed}')
    rank = {i: k for k, i in enumerate(order)}
    names = [f'agent_{k + 1}' for k in range(n_agents)]
    quats = rng.normal(size=(n_agents, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    agents = []
    for k, i in enumerate(order):
        a: dict[str, Any] = {'name': names[k], 'position': [round(float(x), 4) for x in p[i]],
                             'attitude': {'quaternion': [float(x) for x in quats[k]]},
                             'angular_velocity': _omega(rng)}
        if i in nbrs:
            a['neighbours'] = [names[rank[j]] for j in nbrs[i]]
        agents.append(a)
    name = f'random_{n_agents}_agents_seed_{seed}'
    command = f'bearing-pose generate --agents {n_agents} --seed {seed}'
    if speed > 0:
        name += f'_moving_{speed:g}_m_s'
        command += f' --speed {speed:g} --turn-rate {turn_rate:g}'
        for a, velocity in zip(agents, _velocities(n_agents, speed, turn_rate, rng)):
            a['velocity'] = velocity
    return {'name': name, 'description': f'generated by `{command}`',
            'method': 'boughellaba_tayebi', 'world_frame': 'world',
            'gains': {'k_R': 1.0, 'k_p': 1.0, 'k_ij': 1.0}, 'frequency': 100.0, 'duration': 60.0,
            'noise': {'gyro_std': 0.0, 'bearing_std': 0.0, 'seed': seed},
            'initial_estimates': {'random': {'seed': seed, 'position_std': position_std,
                                             'max_angle_deg': max_angle_deg}},
            'leaders': names[:2], 'agents': agents}
