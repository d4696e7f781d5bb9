"""One agent's estimator, independent of ROS: the logic of the estimator node.

Inputs arrive at their own rates and stamps; :meth:`AgentEstimator.advance` then runs as many
fixed steps ``h`` of :func:`observer.cascade_step` as the gyro data allows. Time alignment:

- The gyro is integrated sample by sample (:class:`gyro.GyroBuffer`), never held over a step.
- Each own bearing ``b^i_ij`` measured at ``t_b`` is rotated to the step time ``t`` with the
  gyro, ``b(t) = R(t)ᵀ R(t_b) b(t_b)``, so it pairs with ``R̂_i(t)``. (Pairing a 20 ms old
  bearing with the current R̂ leaves a permanent error of order ``|ω| · 20 ms``.)
- What a neighbour sends is the world-frame product ``R̂_j b^j_ji`` formed by j at one instant.
  It is constant once j has converged, so its transport delay costs nothing at steady state.
- What this agent publishes for others, :meth:`world_bearings`, is formed the same way at the
  state time.

Leaders run the same class with ``leader=True``: their pose comes from :meth:`set_known_pose`
and is propagated with the gyro between pose samples.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from . import so3
from .gyro import GyroBuffer
from .observer import CascadeGains, Edges, cascade_step

if TYPE_CHECKING:
    from .scenario import Scenario

Array = NDArray[np.float64]
# Keep this many bearing samples per target: a bearing newer than the gyro data must wait.
_BEARING_HISTORY = 8


@dataclass
class NeighbourState:
    """What this agent knows about neighbour j (one sensing edge i → j)."""

    name: str
    agent_id: int
    k: float
    d_world: Array | None = None  # R̂_j b^j_ij = -R̂_j b^j_ji, world frame
    p_hat: Array | None = None    # p̂_j [m]
    stamp: float | None = None    # j's state time for the values above


@dataclass
class StepInfo:
    """Diagnostics of the last step."""

    t: float = 0.0
    edges_used: int = 0
    sigma: Array = field(default_factory=lambda: np.zeros(3))


class AgentEstimator:
    """The cascaded observer of one agent, fed by time-stamped measurements.

    Args:
        agent_id: this agent's id (how others' bearing messages name it).
        neighbours: ``(name, agent_id, k_ij)`` of each neighbour j ∈ N_i (empty for leaders).
        gains: ``k_R``, ``k_p``.
        step: the observer step ``h`` [s] (1 / estimator frequency).
        R0, p0: initial estimate ``R̂_i(t0)``, ``p̂_i(t0)`` (a leader's true pose).
        t0: the scenario's start time; the first gyro interval starts here.
        leader: leader mode (known pose, no observer).
    """

    def __init__(self, agent_id: int, neighbours: list[tuple[str, int, float]],
                 gains: CascadeGains, step: float, R0: Array, p0: Array, t0: float = 0.0,
                 leader: bool = False, gyro_horizon: float = 2.0) -> None:
        self.agent_id = agent_id
        self.gains = gains
        self.h = float(step)
        self.leader = leader
        self.t0 = float(t0)
        self.k = 0
        self.R_hat = np.array(R0, dtype=float).reshape(1, 3, 3)
        self.p_hat = np.array(p0, dtype=float).reshape(1, 3)
        self.neighbours = [NeighbourState(n, int(i), float(k)) for n, i, k in neighbours]
        self._by_id = {nb.agent_id: nb for nb in self.neighbours}
        self.gyro = GyroBuffer(t0, gyro_horizon)
        self._bearings: dict[int, deque[tuple[float, Array]]] = {}
        self._known_pose: tuple[float, Array, Array] | None = None
        self.last = StepInfo(t=self.t0)

    @property
    def t(self) -> float:
        """State time: the estimate describes the agent at this time."""
        return self.t0 + self.k * self.h

    # ------------------------------------------------------------------------------ inputs
    def add_gyro(self, stamp: float, omega: Array) -> bool:
        """An interval-average gyro sample (see :mod:`gyro`). False if not newer than the last."""
        return self.gyro.add(stamp, omega)

    def add_bearings(self, stamp: float, ids: NDArray[np.integer], bearings: Array) -> None:
        """Own unit bearings ``b^i_ij`` (body frame) to the agents ``ids``, measured at ``stamp``."""
        for agent_id, b in zip(ids, bearings):
            hist = self._bearings.setdefault(int(agent_id), deque(maxlen=_BEARING_HISTORY))
            if hist and stamp <= hist[-1][0]:
                continue  # out of order: keep the newer one
            hist.append((float(stamp), np.array(b, dtype=float)))

    def add_neighbour(self, agent_id: int, stamp: float, p_hat: Array,
                      world_bearings: dict[int, Array]) -> bool:
        """Neighbour j's message: its ``p̂_j`` and its world bearings ``R̂_j b^j_jl`` to the
        agents l it sees. Returns False if j is not a neighbour or does not see this agent."""
        nb = self._by_id.get(agent_id)
        mine = world_bearings.get(self.agent_id)
        if nb is None or mine is None:
            return False
        if nb.stamp is not None and stamp < nb.stamp:
            return False  # older than what we have
        nb.d_world = -np.asarray(mine, dtype=float)  # R̂_j b^j_ij = -R̂_j b^j_ji
        nb.p_hat = np.asarray(p_hat, dtype=float)
        nb.stamp = float(stamp)
        return True

    def set_known_pose(self, stamp: float, R: Array, p: Array) -> None:
        """Leader mode: the true pose at ``stamp`` (e.g. from motion capture or GNSS/INS)."""
        self._known_pose = (float(stamp), np.asarray(R, dtype=float), np.asarray(p, dtype=float))

    # ------------------------------------------------------------------------------ stepping
    def steps_ready(self) -> int:
        """How many steps the gyro data allows now."""
        return max(0, int(np.floor((self.gyro.end - self.t) / self.h + 1e-9)))

    def advance(self, max_steps: int | None = None) -> int:
        """Run every step the gyro data allows (at most ``max_steps``); return how many ran."""
        n = self.steps_ready()
        if max_steps is not None:
            n = min(n, max_steps)
        for _ in range(n):
            self._step()
        return n

    def body_bearing(self, agent_id: int, t: float) -> Array | None:
        """Own bearing to ``agent_id`` rotated to time ``t`` with the gyro, or None."""
        hist = self._bearings.get(agent_id)
        if not hist:
            return None
        for stamp, b in reversed(hist):  # newest sample the gyro can bridge
            if self.gyro.covers(stamp, t):
                return self.gyro.increment(t, stamp) @ b   # R(t)ᵀ R(t_b) b(t_b)
        return None

    def _step(self) -> None:
        t = self.t
        delta_R = self.gyro.increment(t, t + self.h)[None]
        if self.leader:
            self._apply_known_pose(t)
            self.R_hat = so3.reorthonormalize(self.R_hat @ delta_R)
            self.last = StepInfo(t=t)
        else:
            rows = []
            for nb in self.neighbours:
                b = self.body_bearing(nb.agent_id, t)
                if b is not None and nb.d_world is not None:
                    rows.append((b, nb.d_world, nb.p_hat, nb.k))
            if rows:
                b_body, d_world, p_nbr, k = (np.array(c) for c in zip(*rows))
            else:  # nothing to correct with yet: propagate with the gyro alone
                b_body = d_world = p_nbr = np.zeros((0, 3))
                k = np.zeros(0)
            edges = Edges(agent=np.zeros(len(rows), dtype=np.intp), k=k, n_agents=1)
            res = cascade_step(self.R_hat, self.p_hat, delta_R, self.h, edges, b_body, d_world,
                               p_nbr, self.gains)
            self.R_hat, self.p_hat = res.R_hat, res.p_hat
            self.last = StepInfo(t=t, edges_used=len(rows), sigma=res.sigma[0])
        self.k += 1

    def _apply_known_pose(self, t: float) -> None:
        if self._known_pose is None:
            return
        stamp, R, p = self._known_pose
        if self.gyro.covers(stamp, t):
            self.R_hat = (R @ self.gyro.increment(stamp, t))[None]
            self.p_hat = p[None].copy()
            self._known_pose = None

    # ------------------------------------------------------------------------------ outputs
    def world_bearings(self) -> dict[int, Array]:
        """``R̂_i(t) b^i_il(t)`` for every agent l this agent has a bearing to, at the state
        time: the time-consistent product the listeners need."""
        t, out = self.t, {}
        for agent_id in self._bearings:
            b = self.body_bearing(agent_id, t)
            if b is not None:
                out[agent_id] = self.R_hat[0] @ b
        return out


def estimator_for(scenario: Scenario, name: str) -> AgentEstimator:
    """The estimator of agent ``name`` as the scenario defines it (gains, neighbours and their
    ids, initial estimate, rate; leader mode for leaders)."""
    from .scenario import initial_estimates

    i = scenario.index[name]
    R0, p0 = initial_estimates(scenario)
    nbrs = [(n.name, scenario.agent_id(n.name), n.k) for n in scenario.agents[i].neighbours]
    return AgentEstimator(agent_id=scenario.agent_id(name), neighbours=nbrs,
                          gains=CascadeGains(k_R=scenario.k_R, k_p=scenario.k_p),
                          step=scenario.step, R0=R0[i], p0=p0[i],
                          leader=name in scenario.leaders)
