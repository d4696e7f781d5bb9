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
from .tran import TranGains, TwoNeighbourPairs, tran_step

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


# Causes that are events of the time rules, not bad input (see AgentEstimator), with what
# they mean for the log.
TIME_EVENTS = {'time_jump': 'the clock jumped back: restarted from the initial estimate',
               'gyro_gap': 'gyro gap: the state time restarts after it, keeping the estimate'}


@dataclass(frozen=True)
class Limits:
    """Input checks and timeouts. Inputs outside them are rejected with a named cause, never
    used: no input can put a non-finite value into the estimate."""

    max_rate: float = 35.0          # |ω| above this [rad/s] is absurd (2000 deg/s: gyro range)
    unit_tolerance: float = 1e-3    # a bearing with | ‖b‖ - 1 | above this is not a unit vector
    sensor_timeout: float = 0.5     # own bearings older than this [s] are not used
    neighbour_timeout: float = 0.5  # a neighbour silent for longer [s] is stale: not used
    max_gyro_gap: float = 0.5       # after a longer gyro gap [s] the state time restarts
    jump_back: float = 1.0          # a stamp this much [s] before the newest: clock jumped back
    max_future: float = 1.0         # stamps further ahead [s] than the newest gyro: rejected


@dataclass
class StepInfo:
    """Diagnostics of the last step."""

    t: float = 0.0
    edges_used: int = 0
    stale: tuple[str, ...] = ()     # neighbours not used for being silent too long
    # The innovation: σ_i (world) for the cascade, the torque driving Ω̃_i (body) for Tran et al.
    sigma: Array = field(default_factory=lambda: np.zeros(3))


def _vector_problem(v: Array, tolerance: float) -> str | None:
    """Why ``v`` is not a usable unit vector, or None."""
    if not np.all(np.isfinite(v)):
        return 'non_finite'
    if np.max(np.abs(v)) > 2.0:  # also keeps the norm below from overflowing
        return 'not_unit'
    norm = float(np.linalg.norm(v))
    if norm < 1e-6:
        return 'zero_vector'
    if abs(norm - 1.0) > tolerance:
        return 'not_unit'
    return None


class AgentEstimator:
    """The cascaded observer of one agent, fed by time-stamped measurements.

    Every ``add_*`` method returns None when the input is used, or the cause of its rejection
    (``non_finite``, ``absurd_rate``, ``zero_vector``, ``not_unit``, ``unknown_id``,
    ``out_of_order``, ``future_stamp``, ``stale``, ...). Time rules (documented in the README):

    - a gyro stamp more than ``jump_back`` before the newest means the clock jumped back (e.g. a
      simulator restart): the estimator restarts from its initial estimate at the new time
      (cause ``time_jump``);
    - a gap longer than ``max_gyro_gap`` (late start, restart, data outage): the state time
      restarts after the gap, keeping the estimate, which the observer then corrects
      (``gyro_gap``);
    - in both cases the step grid stays aligned to the scenario's ``t0``.

    Args:
        agent_id: this agent's id (how others' bearing messages name it).
        neighbours: ``(name, agent_id, k_ij)`` of each neighbour j ∈ N_i (empty for leaders).
        gains: :class:`observer.CascadeGains` (Boughellaba & Tayebi) or
            :class:`tran.TranGains` (Tran, Anderson & Ahn): the type selects the observer.
        step: the observer step ``h`` [s] (1 / estimator frequency).
        R0, p0: initial estimate ``R̂_i(t0)``, ``p̂_i(t0)`` (a leader's true pose).
        t0: the scenario's start time; the first gyro interval starts here.
        leader: leader mode (known pose, no observer).
        known_ids: the ids that exist (bearings to other ids are rejected); None: any.
        limits: input checks and timeouts.
    """

    def __init__(self, agent_id: int, neighbours: list[tuple[str, int, float]],
                 gains: CascadeGains | TranGains, step: float, R0: Array, p0: Array,
                 t0: float = 0.0, leader: bool = False, gyro_horizon: float = 2.0,
                 known_ids: set[int] | None = None, limits: Limits = Limits()) -> None:
        self.agent_id = agent_id
        self.gains = gains
        self.h = float(step)
        self.leader = leader
        self.limits = limits
        self.known_ids = known_ids
        self.origin = float(t0)  # the step grid is origin + n h, across restarts too
        self.t0 = float(t0)
        self.k = 0
        self.R0 = np.array(R0, dtype=float).reshape(3, 3)
        self.p0 = np.array(p0, dtype=float).reshape(3)
        self.R_hat = self.R0.copy()[None]
        self.p_hat = self.p0.copy()[None]
        self.Omega_tilde = np.zeros((1, 3))  # Tran et al.'s state; unused by the cascade
        self.neighbours = [NeighbourState(n, int(i), float(k)) for n, i, k in neighbours]
        self._by_id = {nb.agent_id: nb for nb in self.neighbours}
        self.gyro = GyroBuffer(t0, gyro_horizon)
        self._bearings: dict[int, deque[tuple[float, Array]]] = {}
        self._known_pose: tuple[float, Array, Array] | None = None
        self.last = StepInfo(t=self.t0)
        self.non_finite_steps = 0

    @property
    def t(self) -> float:
        """State time: the estimate describes the agent at this time."""
        return self.t0 + self.k * self.h

    # ------------------------------------------------------------------------------ time
    def _restart_at(self, stamp: float, reset_estimate: bool) -> None:
        """Restart the state time at the first grid instant at or after ``stamp``."""
        n = np.ceil((stamp - self.origin) / self.h - 1e-9)
        self.t0, self.k = self.origin + n * self.h, 0
        self.gyro.reset(stamp)
        self._bearings.clear()
        if reset_estimate:
            self.R_hat, self.p_hat = self.R0.copy()[None], self.p0.copy()[None]
            self.Omega_tilde = np.zeros((1, 3))
            for nb in self.neighbours:
                nb.d_world = nb.p_hat = nb.stamp = None
        self.last = StepInfo(t=self.t)

    # ------------------------------------------------------------------------------ inputs
    def add_gyro(self, stamp: float, omega: Array, now: float | None = None) -> str | None:
        """An interval-average gyro sample (see :mod:`gyro`). ``now``: the receiver's clock,
        to reject stamps from the future."""
        lim = self.limits
        omega = np.asarray(omega, dtype=float)
        if not (np.all(np.isfinite(omega)) and np.isfinite(stamp)):
            return 'non_finite'
        if np.max(np.abs(omega)) > lim.max_rate or float(np.linalg.norm(omega)) > lim.max_rate:
            return 'absurd_rate'
        if now is not None and stamp > now + lim.max_future:
            return 'future_stamp'
        end = self.gyro.end
        if stamp <= end:
            if stamp < end - lim.jump_back:
                self._restart_at(stamp, reset_estimate=True)
                return 'time_jump'
            return 'out_of_order'
        if stamp - end > lim.max_gyro_gap:
            self._restart_at(stamp, reset_estimate=False)
            return 'gyro_gap'
        self.gyro.add(stamp, omega)
        return None

    def add_bearings(self, stamp: float, ids: NDArray[np.integer],
                     bearings: Array) -> list[str]:
        """Own unit bearings ``b^i_ij`` (body frame) to the agents ``ids``, measured at
        ``stamp``. Returns the causes of the rejected points (empty: all used)."""
        lim = self.limits
        if not np.isfinite(stamp):
            return ['non_finite'] * len(ids)
        if stamp > self.gyro.end + lim.max_future:
            return ['future_stamp'] * len(ids)
        if stamp < self.gyro.start:
            return ['stale'] * len(ids)
        rejected = []
        for agent_id, b in zip(ids, bearings):
            agent_id = int(agent_id)
            b = np.asarray(b, dtype=float)
            problem = _vector_problem(b, lim.unit_tolerance)
            if problem is None and (agent_id == self.agent_id or (
                    self.known_ids is not None and agent_id not in self.known_ids)):
                problem = 'unknown_id'
            hist = self._bearings.setdefault(agent_id, deque(maxlen=_BEARING_HISTORY))
            if problem is None and hist and stamp <= hist[-1][0]:
                problem = 'out_of_order'
            if problem is None:
                hist.append((float(stamp), b / np.linalg.norm(b)))
            else:
                rejected.append(problem)
        return rejected

    def add_neighbour(self, agent_id: int, stamp: float, p_hat: Array,
                      world_bearings: dict[int, Array]) -> str | None:
        """Neighbour j's message: its ``p̂_j`` and its world bearings ``R̂_j b^j_jl`` to the
        agents l it sees. ``not_seen`` means j has no bearing to this agent (yet)."""
        lim = self.limits
        nb = self._by_id.get(agent_id)
        if nb is None:
            return 'unknown_id'
        mine = world_bearings.get(self.agent_id)
        if mine is None:
            return 'not_seen'
        p_hat = np.asarray(p_hat, dtype=float)
        if not (np.all(np.isfinite(p_hat)) and np.isfinite(stamp)):
            return 'non_finite'
        problem = _vector_problem(np.asarray(mine, dtype=float), lim.unit_tolerance)
        if problem is not None:
            return problem
        if stamp > self.gyro.end + lim.max_future:
            return 'future_stamp'
        # Older than what we hold: out of order, unless much older (j restarted its clock).
        if nb.stamp is not None and stamp < nb.stamp and nb.stamp - stamp <= lim.jump_back:
            return 'out_of_order'
        nb.d_world = -np.asarray(mine, dtype=float)  # R̂_j b^j_ij = -R̂_j b^j_ji
        nb.p_hat = p_hat
        nb.stamp = float(stamp)
        return None

    def set_known_pose(self, stamp: float, R: Array, p: Array) -> str | None:
        """Leader mode: the true pose at ``stamp`` (e.g. from motion capture or GNSS/INS)."""
        R, p = np.asarray(R, dtype=float), np.asarray(p, dtype=float)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(p)) and np.isfinite(stamp)):
            return 'non_finite'
        self._known_pose = (float(stamp), R, p)
        return None

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
        """Own bearing to ``agent_id`` rotated to time ``t`` with the gyro, or None (none, or
        older than ``sensor_timeout``)."""
        hist = self._bearings.get(agent_id)
        if not hist:
            return None
        for stamp, b in reversed(hist):  # newest sample the gyro can bridge
            if t - stamp > self.limits.sensor_timeout:
                return None
            if self.gyro.covers(stamp, t):
                return self.gyro.increment(t, stamp) @ b   # R(t)ᵀ R(t_b) b(t_b)
        return None

    def stale_neighbours(self, t: float) -> list[str]:
        """Neighbours whose latest data is older than ``neighbour_timeout`` (or absent)."""
        limit = t - self.limits.neighbour_timeout
        return [nb.name for nb in self.neighbours if nb.stamp is None or nb.stamp < limit]

    def _step(self) -> None:
        t = self.t
        delta_R = self.gyro.increment(t, t + self.h)[None]
        if self.leader:
            self._apply_known_pose(t)
            self.R_hat = so3.reorthonormalize(self.R_hat @ delta_R)
            self.last = StepInfo(t=t)
        else:
            stale = self.stale_neighbours(t)
            rows = []
            for nb in self.neighbours:
                b = self.body_bearing(nb.agent_id, t)
                if b is not None and nb.d_world is not None and nb.name not in stale:
                    rows.append((b, nb.d_world, nb.p_hat, nb.k))
            if rows:
                b_body, d_world, p_nbr, k = (np.array(c) for c in zip(*rows))
            else:  # nothing to correct with: propagate with the gyro alone
                b_body = d_world = p_nbr = np.zeros((0, 3))
                k = np.zeros(0)
            edges = Edges(agent=np.zeros(len(rows), dtype=np.intp), k=k, n_agents=1)
            if isinstance(self.gains, TranGains):
                res = tran_step(self.R_hat, self.Omega_tilde, self.p_hat, delta_R, self.h, edges,
                                TwoNeighbourPairs.of(edges), b_body, d_world, p_nbr, self.gains)
                innovation, Omega = res.torque[0], res.Omega_tilde
            else:
                res = cascade_step(self.R_hat, self.p_hat, delta_R, self.h, edges, b_body,
                                   d_world, p_nbr, self.gains)
                innovation, Omega = res.sigma[0], self.Omega_tilde
            if (np.all(np.isfinite(res.R_hat)) and np.all(np.isfinite(res.p_hat))
                    and np.all(np.isfinite(Omega))):
                self.R_hat, self.p_hat, self.Omega_tilde = res.R_hat, res.p_hat, Omega
            else:  # cannot happen with validated inputs; never let it reach the estimate
                self.non_finite_steps += 1
                self.R_hat = so3.reorthonormalize(self.R_hat @ delta_R)
            self.last = StepInfo(t=t, edges_used=len(rows), stale=tuple(stale),
                                 sigma=innovation)
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


def gains_for(scenario: Scenario) -> CascadeGains | TranGains:
    """The scenario's method, as the gains type that selects it."""
    if scenario.method == 'tran_anderson_ahn':
        return TranGains(k_omega=scenario.k_omega, k_p=scenario.k_p, k_c=scenario.k_c)
    return CascadeGains(k_R=scenario.k_R, k_p=scenario.k_p)


def estimator_for(scenario: Scenario, name: str, limits: Limits = Limits(),
                  initial: tuple[Array, Array] | None = None) -> AgentEstimator:
    """The estimator of agent ``name`` as the scenario defines it (gains, neighbours and their
    ids, initial estimate, rate; leader mode for leaders). ``initial``: the fleet's
    ``initial_estimates(scenario)``, when the caller builds many estimators (it draws them
    all, so computing it once per fleet saves O(N²) work)."""
    from .scenario import initial_estimates

    i = scenario.index[name]
    R0, p0 = initial if initial is not None else initial_estimates(scenario)
    nbrs = [(n.name, scenario.agent_id(n.name), n.k) for n in scenario.agents[i].neighbours]
    return AgentEstimator(agent_id=scenario.agent_id(name), neighbours=nbrs,
                          gains=gains_for(scenario),
                          step=scenario.step, R0=R0[i], p0=p0[i],
                          leader=name in scenario.leaders,
                          known_ids=set(range(1, len(scenario.agents) + 1)), limits=limits)
