"""One agent running any registered estimator, independent of ROS: the logic of the estimator
node (netsim runs it too, without DDS).

Inputs arrive at their own rates and stamps; :meth:`AgentEstimator.advance` then runs as many
fixed steps ``h`` of the method's :meth:`base.Estimator.step` (one agent) as the gyro data
allows. Time alignment:

- The gyro is integrated sample by sample (:class:`gyro.GyroBuffer`), never held over a step.
- Each own bearing ``b^i_ij`` measured at ``t_b`` is rotated to the step time ``t`` with the
  gyro, ``b(t) = R(t)ᵀ R(t_b) b(t_b)``, so it pairs with ``R̂_i(t)``. (Pairing a 20 ms old
  bearing with the current R̂ leaves a permanent error of order ``|ω| · 20 ms``.)
- What a neighbour sends (the method's channels, e.g. ``R̂_j b^j_ji`` and ``p̂_j``) is formed by
  j at one instant (:meth:`base.Estimator.outbox`). A value like ``R̂_j b^j_ji`` is constant once
  j has converged, so its transport delay costs nothing at steady state.
- What this agent sends its listeners, :meth:`outbox`, is formed the same way at the state
  time.

Leaders run the same class with ``leader=True``: their pose comes from :meth:`set_known_pose`
and is propagated with the gyro between pose samples.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..core.gyro import GyroBuffer
from .base import Channel, Edges, Estimator, Sensor, State, StepInputs

if TYPE_CHECKING:
    from ..scenario.model import Scenario

Array = NDArray[np.float64]
# Keep this many bearing samples per target: a bearing newer than the gyro data must wait.
_BEARING_HISTORY = 8
# What the agent logic can feed a method today; others come with their sensors' models.
SUPPORTED_SENSORS = frozenset({Sensor.GYRO, Sensor.BEARINGS, Sensor.KNOWN_POSE})


@dataclass
class NeighbourState:
    """What this agent knows about neighbour j (one sensing edge i → j): the latest value of
    each channel j sends, with j's state time for it."""

    name: str
    agent_id: int
    k: float
    values: dict[str, Array] = field(default_factory=dict)
    stamps: dict[str, float] = field(default_factory=dict)

    def clear(self) -> None:
        self.values.clear()
        self.stamps.clear()


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
    # The method's per-agent diagnostics (e.g. 'innovation': σ_i for Boughellaba & Tayebi,
    # the torque driving Ω̃_i for Tran et al.), row 0 of what its step returned.
    diagnostics: dict[str, Array] = field(default_factory=dict)


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
    """One agent's estimator (any registered method), fed by time-stamped measurements.

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
        estimator: the method with its gains (:func:`bearing_pose_estimation.estimators.build`).
        agent_id: this agent's id (how others' bearing messages name it).
        neighbours: ``(name, agent_id, k_ij)`` of each neighbour j ∈ N_i (empty for leaders).
        step: the estimator step ``h`` [s] (1 / estimator frequency).
        R0, p0: initial estimate ``R̂_i(t0)``, ``p̂_i(t0)`` (a leader's true pose).
        t0: the scenario's start time; the first gyro interval starts here.
        leader: leader mode (known pose, no observer).
        known_ids: the ids that exist (bearings to other ids are rejected); None: any.
        limits: input checks and timeouts.
    """

    def __init__(self, estimator: Estimator, agent_id: int,
                 neighbours: list[tuple[str, int, float]], step: float, R0: Array, p0: Array,
                 t0: float = 0.0, leader: bool = False, gyro_horizon: float = 2.0,
                 known_ids: set[int] | None = None, limits: Limits = Limits()) -> None:
        missing = sorted(s.value for s in estimator.sensors - SUPPORTED_SENSORS)
        if missing:
            raise NotImplementedError(f'{estimator.method} needs sensors {", ".join(missing)}, '
                                      'which the agent logic cannot feed yet')
        self.estimator = estimator
        self.agent_id = agent_id
        self.h = float(step)
        self.leader = leader
        self.limits = limits
        self.known_ids = known_ids
        self.origin = float(t0)  # the step grid is origin + n h, across restarts too
        self.t0 = float(t0)
        self.k = 0
        self.R0 = np.array(R0, dtype=float).reshape(3, 3)
        self.p0 = np.array(p0, dtype=float).reshape(3)
        self.x: State = estimator.initial_state(self.R0[None], self.p0[None])
        self.channels: dict[str, Channel] = {c.name: c for c in estimator.sends}
        self.neighbours = [NeighbourState(n, int(i), float(k)) for n, i, k in neighbours]
        self._by_id = {nb.agent_id: nb for nb in self.neighbours}
        self.gyro = GyroBuffer(t0, gyro_horizon)
        self._bearings: dict[int, deque[tuple[float, Array]]] = {}
        self._known_pose: tuple[float, Array, Array] | None = None
        self.last = StepInfo(t=self.t0)
        self.non_finite_steps = 0

    @property
    def gains(self) -> object:
        return self.estimator.gains

    @property
    def R_hat(self) -> Array:
        """``(1, 3, 3)`` attitude estimate at the state time (body → the method's frame)."""
        return self.x.R_hat

    @property
    def p_hat(self) -> Array:
        """``(1, 3)`` position estimate at the state time [m]."""
        return self.x.p_hat

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
            self.x = self.estimator.initial_state(self.R0[None], self.p0[None])
            for nb in self.neighbours:
                nb.clear()
        self.last = StepInfo(t=self.t)

    # ------------------------------------------------------------------------------ inputs
    def add_gyro(self, stamp: float, omega: Array, now: float | None = None) -> str | None:
        """An interval-average gyro sample (see :mod:`core.gyro`). ``now``: the receiver's
        clock, to reject stamps from the future."""
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

    def add_neighbour(self, agent_id: int, stamp: float,
                      values: dict[str, object]) -> str | None:
        """A message from neighbour j with its values of some of the method's channels, all
        valid at j's state time ``stamp``: per-agent channels as arrays, per-edge ones as
        ``{listener id: value}`` (this agent picks its own; ``not_seen`` when j has none for
        it yet). The message is used whole or rejected whole."""
        lim = self.limits
        nb = self._by_id.get(agent_id)
        if nb is None:
            return 'unknown_id'
        mine: dict[str, Array] = {}
        for name, value in values.items():
            channel = self.channels.get(name)
            if channel is None:
                return 'unknown_channel'
            if channel.per == 'edge':
                value = value.get(self.agent_id) if isinstance(value, dict) else None
                if value is None:
                    return 'not_seen'
            v = np.asarray(value, dtype=float)
            if v.shape != channel.shape:
                return 'malformed'
            mine[name] = v
        if not (np.isfinite(stamp) and all(np.all(np.isfinite(v)) for name, v in mine.items()
                                           if not self.channels[name].unit)):
            return 'non_finite'
        for name, v in mine.items():
            if self.channels[name].unit:
                problem = _vector_problem(v, lim.unit_tolerance)
                if problem is not None:
                    return problem
        if stamp > self.gyro.end + lim.max_future:
            return 'future_stamp'
        # Older than what we hold: out of order, unless much older (j restarted its clock).
        for name in mine:
            held = nb.stamps.get(name)
            if held is not None and stamp < held and held - stamp <= lim.jump_back:
                return 'out_of_order'
        nb.values.update(mine)
        nb.stamps.update(dict.fromkeys(mine, float(stamp)))
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
        """Neighbours missing a channel, or whose latest value of one is older than
        ``neighbour_timeout``."""
        limit = t - self.limits.neighbour_timeout
        return [nb.name for nb in self.neighbours
                if any(nb.stamps.get(c, -np.inf) < limit for c in self.channels)]

    def step_inputs(self, t: float, delta_R: Array, stale: list[str]) -> StepInputs:
        """What the step at ``t`` uses: the fresh neighbours to which an own bearing exists."""
        used = []
        for nb in self.neighbours:
            b = self.body_bearing(nb.agent_id, t)
            if b is not None and nb.name not in stale:
                used.append((nb, b))
        received = {name: (np.array([nb.values[name] for nb, _ in used]) if used
                           else np.zeros((0,) + c.shape)) for name, c in self.channels.items()}
        return StepInputs(
            delta_R=delta_R,
            edges=Edges(agent=np.zeros(len(used), dtype=np.intp),
                        k=np.array([nb.k for nb, _ in used]), n_agents=1),
            bearings=np.array([b for _, b in used]) if used else np.zeros((0, 3)),
            received=received)

    def _step(self) -> None:
        t = self.t
        est = self.estimator
        delta_R = self.gyro.increment(t, t + self.h)[None]
        if self.leader:
            self._apply_known_pose(t)
            self.x = est.propagate(self.x, delta_R)
            self.last = StepInfo(t=t)
        else:
            stale = self.stale_neighbours(t)
            inputs = self.step_inputs(t, delta_R, stale)
            x, diagnostics = est.step(self.x, self.h, inputs)
            if x.is_finite():
                self.x = x
            else:  # cannot happen with validated inputs; never let it reach the estimate
                self.non_finite_steps += 1
                self.x = est.propagate(self.x, delta_R)
            self.last = StepInfo(t=t, edges_used=len(inputs.edges), stale=tuple(stale),
                                 diagnostics={k: v[0] for k, v in diagnostics.items()})
        self.k += 1

    def _apply_known_pose(self, t: float) -> None:
        if self._known_pose is None:
            return
        stamp, R, p = self._known_pose
        if self.gyro.covers(stamp, t):
            self.x = self.estimator.with_known_pose(
                self.x, np.zeros(1, dtype=np.intp), (R @ self.gyro.increment(stamp, t))[None],
                p[None])
            self._known_pose = None

    # ------------------------------------------------------------------------------ outputs
    def own_bearings(self, t: float) -> tuple[list[int], Array]:
        """Ids of the agents this agent has a bearing to, and those bearings rotated to ``t``
        ``(M, 3)``."""
        ids, bearings = [], []
        for agent_id in self._bearings:
            b = self.body_bearing(agent_id, t)
            if b is not None:
                ids.append(agent_id)
                bearings.append(b)
        return ids, np.array(bearings).reshape(-1, 3)

    def outbox(self) -> dict[str, object]:
        """What this agent sends its listeners, formed at the state time (the time-consistent
        values they need): per-agent channels as arrays, per-edge ones as
        ``{listener id: value}`` for every agent it has a bearing to."""
        ids, bearings = self.own_bearings(self.t)
        sent = self.estimator.outbox(self.x, np.zeros(len(ids), dtype=np.intp), bearings)
        return {name: dict(zip(ids, sent[name])) if c.per == 'edge' else sent[name][0]
                for name, c in self.channels.items()}

    def conditioning(self) -> Array | None:
        """Eigenvalues of the method's local matrix (:meth:`base.Estimator.conditioning`) from
        the current own bearings, or None (no such matrix, or a bearing to some neighbour is
        missing)."""
        bearings = [self.body_bearing(nb.agent_id, self.t) for nb in self.neighbours]
        if not bearings or any(b is None for b in bearings):
            return None
        matrix = self.estimator.conditioning(np.array(bearings),
                                             np.array([nb.k for nb in self.neighbours]))
        return None if matrix is None else np.linalg.eigvalsh(matrix).astype(np.float64)


def estimator_for(scenario: Scenario, name: str, limits: Limits = Limits(),
                  initial: tuple[Array, Array] | None = None) -> AgentEstimator:
    """The estimator of agent ``name`` as the scenario defines it (method and gains, neighbours
    and their ids, initial estimate, rate; leader mode for leaders). ``initial``: the fleet's
    ``initial_estimates(scenario)``, when the caller builds many estimators (it draws them
    all, so computing it once per fleet saves O(N²) work)."""
    from ..scenario.model import initial_estimates

    i = scenario.index[name]
    R0, p0 = initial if initial is not None else initial_estimates(scenario)
    nbrs = [(n.name, scenario.agent_id(n.name), n.k) for n in scenario.agents[i].neighbours]
    return AgentEstimator(scenario.estimator(), agent_id=scenario.agent_id(name),
                          neighbours=nbrs, step=scenario.step, R0=R0[i], p0=p0[i],
                          leader=name in scenario.leaders,
                          known_ids=set(range(1, len(scenario.agents) + 1)), limits=limits)
