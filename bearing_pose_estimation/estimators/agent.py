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
  j at one instant (:meth:`base.Estimator.outbox`), its stamp ``t_s``. For static fleets such
  a value is constant once j has converged, so its transport delay costs nothing at steady
  state. A moving fleet's values change during the delay, so the step pairs them with this
  agent's own bearing measured at ``t_s`` (interpolated between samples, rotated to the step
  time with the gyro) and with ``p̂_i`` moved back to ``t_s`` by its own odometry
  (:attr:`base.StepInputs.p_own`): exact at the true poses for any motion, and the corrections
  are not delayed.
- Odometry (when the method uses it and samples arrive): interval-average twists integrated
  exactly (:class:`core.odometry.OdometryBuffer`) into the displacement over each step; while
  odometry is live the steps wait for it as they wait for the gyro.
- What this agent sends its listeners, :meth:`outbox`, is formed the same way at the state
  time.

Leaders run the same class with ``leader=True``: their pose comes from :meth:`set_known_pose`
and is propagated with the gyro (and odometry) between pose samples.

In simulation (:class:`Exchange`, the estimator node under ``use_sim_time``) the inputs of each
step are fixed by their stamps, not by what has arrived: step ``[t, t + h]`` uses the own
bearings and the known pose measured by ``t + h`` and each neighbour's values of its newest
publish instant not after ``t``, and waits for them. That is what netsim feeds it, so a DDS run
equals netsim's to rounding whatever the machine's load.
"""
from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from ..core.gyro import GyroBuffer
from ..core.odometry import OdometryBuffer
from .base import Channel, Edges, Estimator, Sensor, State, StepInputs

Array = NDArray[np.float64]
# Keep this many bearing samples per target: a bearing newer than the gyro data must wait.
_BEARING_HISTORY = 8
# Keep this many values of each neighbour channel, to pair them at one instant.
_NEIGHBOUR_HISTORY = 8
# What the agent logic can feed a method today; others come with their sensors' models.
SUPPORTED_SENSORS = frozenset({Sensor.GYRO, Sensor.BEARINGS, Sensor.KNOWN_POSE,
                               Sensor.ODOMETRY})


@dataclass
class NeighbourState:
    """What this agent knows about neighbour j (one sensing edge i → j): the latest value of
    each channel j sends, with j's state time for it."""

    name: str
    agent_id: int
    k: float
    values: dict[str, Array] = field(default_factory=dict)
    stamps: dict[str, float] = field(default_factory=dict)
    # The last few values of each channel: j's channels travel in separate messages, and a
    # moving fleet needs them from one instant (:meth:`at_one_instant`).
    history: dict[str, deque[tuple[float, Array]]] = field(default_factory=dict)
    # The newest stamp of each channel heard from j, used or not (``not_seen``: j's message of
    # that instant had nothing for us): what :class:`Exchange` waits for.
    heard: dict[str, float] = field(default_factory=dict)

    def clear(self) -> None:
        self.values.clear()
        self.stamps.clear()
        self.history.clear()
        self.heard.clear()

    def hear(self, name: str, stamp: float) -> None:
        self.heard[name] = max(self.heard.get(name, -np.inf), float(stamp))

    def newest_until(self, name: str, t: float) -> Array | None:
        """The newest value of channel ``name`` stamped at or before ``t``, or None."""
        for stamp, value in reversed(self.history.get(name, ())):
            if stamp <= t + 1e-9:
                return value
        return None

    def at_one_instant(self, channels: list[str],
                       not_after: float) -> tuple[float, dict[str, Array]] | None:
        """The newest stamp, not after ``not_after`` (j may run ahead of us), at which every
        channel has a value, with those values; None if there is none (e.g. a sender that
        publishes its channels at different instants)."""
        first = self.history.get(channels[0])
        if not first:
            return None
        for stamp, value in reversed(first):
            if stamp > not_after + 1e-9:
                continue
            out = {channels[0]: value}
            for name in channels[1:]:
                match = [v for s, v in self.history.get(name, ()) if abs(s - stamp) < 1e-9]
                if not match:
                    break
                out[name] = match[-1]
            else:
                return stamp, out
        return None


# Causes that are events of the time rules, not bad input (see AgentEstimator), with what
# they mean for the log.
TIME_EVENTS = {'time_jump': 'the clock jumped back: restarted from the initial estimate',
               'gyro_gap': 'gyro gap: the state time restarts after it, keeping the estimate',
               'odometry_gap': 'odometry gap: its integration restarts after it'}


@dataclass(frozen=True)
class Limits:
    """Input checks and timeouts. Inputs outside them are rejected with a named cause, never
    used: no input can put a non-finite value into the estimate."""

    max_rate: float = 35.0          # |ω| above this [rad/s] is absurd (2000 deg/s: gyro range)
    max_speed: float = 100.0        # an odometry speed above this [m/s] is absurd
    unit_tolerance: float = 1e-3    # a bearing with | ‖b‖ - 1 | above this is not a unit vector
    sensor_timeout: float = 0.5     # own bearings older than this [s] are not used
    neighbour_timeout: float = 0.5  # a neighbour silent for longer [s] is stale: not used
    # Link methods and the fixed exchange (Exchange): a step waits for a neighbour's input
    # until its own sensors are this far [s] ahead (the estimate is then late by as much; a
    # longer delay is a lost input).
    link_wait: float = 0.25
    max_gyro_gap: float = 0.5       # after a longer gyro gap [s] the state time restarts
    jump_back: float = 1.0          # a stamp this much [s] before the newest: clock jumped back
    max_future: float = 1.0         # stamps further ahead [s] than the newest gyro: rejected


@dataclass(frozen=True)
class Exchange:
    """The deterministic exchange of a simulation (module docstring): the periods at which the
    awaited inputs come. ``None``: the spacing of the last two samples received."""

    publish_period: float                  # the neighbours' channels [s]
    bearing_period: float | None = None    # the own bearings [s]
    known_pose_period: float | None = None  # a leader's known pose [s]


def _complete(stamps: Sequence[float], period: float | None, end: float) -> bool:
    """The samples measured by ``end`` are in: the next one due (newest stamp + period) is
    later. Unknown with one sample and no period: taken as in."""
    if not stamps:
        return False
    if period is None:
        if len(stamps) < 2:
            return True
        period = stamps[-1] - stamps[-2]
    return stamps[-1] + period > end + 1e-9


@dataclass
class StepInfo:
    """Diagnostics of the last step."""

    t: float = 0.0
    edges_used: int = 0
    stale: tuple[str, ...] = ()     # neighbours not used for being silent too long
    odometry: bool = False          # the step fed the odometry displacement forward
    # The method's per-agent diagnostics (e.g. 'innovation': σ_i for Boughellaba & Tayebi,
    # the torque driving Ω̃_i for Tran et al.), row 0 of what its step returned.
    diagnostics: dict[str, Array] = field(default_factory=dict)


@dataclass(frozen=True)
class _Prepared:
    """A follower's step up to its method's own: its start time, the neighbours left out for
    being silent, and its inputs."""

    t: float
    stale: tuple[str, ...]
    inputs: StepInputs


def _finite_max_norm(v: Array) -> tuple[bool, float, float]:
    """Whether every entry of the small vector ``v`` is finite, then its largest magnitude and
    norm. Python's floats: each message's checks would otherwise pay numpy's per-call
    overhead (a few µs) several times over for three numbers."""
    values = v.ravel().tolist()
    if not all(map(math.isfinite, values)):
        return False, math.nan, math.nan
    return True, max(map(abs, values), default=0.0), math.hypot(*values)


def _vector_problem(v: Array, tolerance: float) -> str | None:
    """Why ``v`` is not a usable unit vector, or None."""
    finite, largest, norm = _finite_max_norm(v)
    if not finite:
        return 'non_finite'
    if largest > 2.0:
        return 'not_unit'
    if norm < 1e-6:
        return 'zero_vector'
    if abs(norm - 1.0) > tolerance:
        return 'not_unit'
    return None


def _twist_problem(stamp: float, v: Array, omega: Array, limits: Limits) -> str | None:
    """Why an odometry twist (``v`` [m/s], ``omega`` [rad/s] at ``stamp``) is unusable, or
    None: any entry not finite, a rate above ``max_rate``, a speed above ``max_speed``."""
    finite_v, _, speed = _finite_max_norm(v)
    finite_w, _, rate = _finite_max_norm(omega)
    if not (finite_v and finite_w and math.isfinite(stamp)):
        return 'non_finite'
    if rate > limits.max_rate:
        return 'absurd_rate'
    if speed > limits.max_speed:
        return 'absurd_speed'
    return None


class TimedAgent:
    """What every agent's logic shares, whatever its method's measurements: the state, the
    fixed step grid, the gyro and odometry buffers and their time rules (:class:`AgentEstimator`
    documents them), and the stepping loop. Subclasses feed their method's measurements and
    neighbours' messages and build each step's inputs (:meth:`_step`)."""

    def __init__(self, estimator: Estimator, agent_id: int, step: float, R0: Array, p0: Array,
                 t0: float = 0.0, leader: bool = False, gyro_horizon: float = 2.0,
                 known_ids: set[int] | None = None, limits: Limits = Limits()) -> None:
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
        self.gyro = GyroBuffer(t0, gyro_horizon)
        self.uses_odometry = estimator.uses(Sensor.ODOMETRY)
        # A method that needs odometry (not only uses it when available) waits for it from
        # the first step, unless it falls silent (sensor_timeout behind the gyro).
        self.requires_odometry = Sensor.ODOMETRY in estimator.sensors
        self.odometry = OdometryBuffer(t0, gyro_horizon)
        self.odometry_missing_steps = 0   # steps run without odometry while it was expected
        # Neighbour values that could not be paired at one instant (see the subclasses).
        self.unpaired = 0
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
        self.odometry.reset(stamp)
        if reset_estimate:
            self.x = self.estimator.initial_state(self.R0[None], self.p0[None])
        self._clear_inputs(reset_estimate)
        self.last = StepInfo(t=self.t)

    def _clear_inputs(self, reset_estimate: bool) -> None:
        """Forget the measurements held (and, ``reset_estimate``, what neighbours sent)."""

    # ------------------------------------------------------------------------------ inputs
    def add_gyro(self, stamp: float, omega: Array, now: float | None = None) -> str | None:
        """An interval-average gyro sample (see :mod:`core.gyro`). ``now``: the receiver's
        clock, to reject stamps from the future."""
        lim = self.limits
        omega = np.asarray(omega, dtype=float)
        finite, _, norm = _finite_max_norm(omega)
        if not (finite and math.isfinite(stamp)):
            return 'non_finite'
        if norm > lim.max_rate:   # math.hypot does not overflow: no entry-wise check first
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

    def add_odometry(self, stamp: float, v: Array, omega: Array,
                     now: float | None = None) -> str | None:
        """An interval-average odometry twist (body velocity ``v`` [m/s], rate ``omega``
        [rad/s]; see :mod:`core.odometry`). Ignored (``unused``) by methods without odometry.
        After a gap longer than ``max_gyro_gap`` the integration restarts at this sample
        (``odometry_gap``); the steps over the gap run without it."""
        lim = self.limits
        v, omega = np.asarray(v, dtype=float), np.asarray(omega, dtype=float)
        if not self.uses_odometry:
            return 'unused'
        problem = _twist_problem(stamp, v, omega, lim)
        if problem is not None:
            return problem
        if now is not None and stamp > now + lim.max_future:
            return 'future_stamp'
        end = self.odometry.end
        if stamp <= end:
            if self.odometry.empty and stamp >= end - 1e-9:
                return None   # the sample that closed a gap: the restart began at its stamp
            return 'out_of_order'
        if stamp - end > lim.max_gyro_gap:
            self.odometry.reset(stamp)
            return 'odometry_gap'
        self.odometry.add_twist(stamp, v, omega)
        return None

    def odometry_live(self) -> bool:
        """Odometry samples keep up with the gyro (within ``sensor_timeout``): steps wait for
        them and feed them forward. A method that needs odometry counts it live from the start,
        before its first sample."""
        keeps_up = self.odometry.end >= self.gyro.end - self.limits.sensor_timeout
        return self.uses_odometry and keeps_up and (not self.odometry.empty
                                                    or self.requires_odometry)

    def steps_ready(self) -> int:
        """How many steps the gyro data (and live odometry) allows now."""
        end = self.gyro.end
        if self.odometry_live():
            end = min(end, self.odometry.end)
        return max(0, math.floor((end - self.t) / self.h + 1e-9))

    def own_inputs_ready(self) -> bool:
        """Own gyro (and live odometry) cover the next step: only what comes from others
        (an :class:`Exchange`'s inputs, neighbours' values) may be missing."""
        return TimedAgent.steps_ready(self) > 0

    def _step(self) -> None:
        prepared = self._begin_step()
        if prepared is not None:
            self._end_step(prepared, *self.estimator.step(self.x, self.h, prepared.inputs))

    def _begin_step(self) -> _Prepared | None:
        """A step up to the method's own: its inputs, or None when this was the whole step
        (:func:`advance_together` runs the methods' steps of several agents at once)."""
        raise NotImplementedError

    def _end_step(self, prepared: _Prepared, x: State, diagnostics: dict[str, Array]) -> None:
        """The step's end, from the new state ``x`` (one row) the method's step returned."""
        inputs = prepared.inputs
        if x.is_finite():
            self.x = x
        else:  # cannot happen with validated inputs; never let it reach the estimate
            self.non_finite_steps += 1
            self.x = self.estimator.propagate(self.x, inputs.delta_R, inputs.displacement)
        self.last = StepInfo(t=prepared.t, edges_used=len(inputs.edges), stale=prepared.stale,
                             odometry=inputs.displacement is not None,
                             diagnostics={k: v[0] for k, v in diagnostics.items()})
        self.k += 1

    def advance(self, max_steps: int | None = None) -> int:
        """Run every step the gyro data allows (at most ``max_steps``); return how many ran."""
        n = self.steps_ready()
        if max_steps is not None:
            n = min(n, max_steps)
        for _ in range(n):
            self._step()
        return n


class AgentEstimator(TimedAgent):
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
        if missing or estimator.links != 'sensing':
            raise NotImplementedError(
                f'{estimator.method} needs sensors {", ".join(missing)}, which this agent logic '
                'cannot feed' if missing else f'{estimator.method} talks over communication '
                'links: use estimators.link_agent.LinkAgentEstimator')
        super().__init__(estimator, agent_id, step, R0, p0, t0=t0, leader=leader,
                         gyro_horizon=gyro_horizon, known_ids=known_ids, limits=limits)
        self.neighbours = [NeighbourState(n, int(i), float(k)) for n, i, k in neighbours]
        self._by_id = {nb.agent_id: nb for nb in self.neighbours}
        # Moving: neighbour values that could not be paired at one instant (none of their
        # instants has an own bearing yet: the edge sits the step out; or the sender never
        # sends its channels at one instant, or no odometry covers the delay: used as they
        # are): :attr:`unpaired`.
        self._bearings: dict[int, deque[tuple[float, Array]]] = {}
        self._known_poses: deque[tuple[float, Array, Array]] = deque(maxlen=_BEARING_HISTORY)
        # Simulation: inputs fixed by their stamps, waited for (:class:`Exchange`; None: a
        # step uses what is here).
        self.exchange: Exchange | None = None
        self._bearing_stamps: deque[float] = deque(maxlen=2)   # of the bearing messages
        self._pose_stamps: deque[float] = deque(maxlen=2)
        self.impatient = False
        self._required = {name for name, c in self.channels.items() if not c.optional}
        self._ready_k = 0   # steps before this one had their awaited inputs (steps_ready)
        self.awaited: str | None = None   # what the latest waiting step waited for
        # Steps that went on without an awaited input (lost, or waited out): per what.
        self.incomplete: Counter[str] = Counter()

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
        if not self._bearing_stamps or stamp > self._bearing_stamps[-1]:
            self._bearing_stamps.append(float(stamp))
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
                    if np.isfinite(stamp) and stamp <= self.gyro.end + lim.max_future:
                        nb.hear(name, stamp)   # j's message of this instant: none for us
                    return 'not_seen'
            v = np.asarray(value, dtype=float)
            if v.shape != channel.shape:
                return 'malformed'
            mine[name] = v
        if not (np.isfinite(stamp) and all(np.isfinite(v).all() for name, v in mine.items()
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
        for name, v in mine.items():
            nb.history.setdefault(name, deque(maxlen=_NEIGHBOUR_HISTORY)).append((float(stamp), v))
            nb.hear(name, stamp)
        return None

    def set_known_pose(self, stamp: float, R: Array, p: Array) -> str | None:
        """Leader mode: the true pose at ``stamp`` (e.g. from motion capture or GNSS/INS)."""
        R, p = np.asarray(R, dtype=float), np.asarray(p, dtype=float)
        if not (np.isfinite(R).all() and np.isfinite(p).all() and np.isfinite(stamp)):
            return 'non_finite'
        self._known_poses.append((float(stamp), R, p))
        if not self._pose_stamps or stamp > self._pose_stamps[-1]:
            self._pose_stamps.append(float(stamp))
        return None

    def _clear_inputs(self, reset_estimate: bool) -> None:
        self._bearings.clear()
        self._ready_k = 0   # k restarts
        self._bearing_stamps.clear()
        self._pose_stamps.clear()
        if reset_estimate:
            for nb in self.neighbours:
                nb.clear()

    # ------------------------------------------------------------------------------ stepping
    def steps_ready(self) -> int:
        """How many steps the gyro data (and live odometry) allows now; with an
        :class:`Exchange`, only those whose awaited inputs are in (or waited out: the own
        sensors ``link_wait`` ahead)."""
        n = super().steps_ready()
        if self.exchange is None or self.impatient:
            return n
        contiguous = True   # every step so far had its inputs: _step need not check again
        for s in range(max(0, self._ready_k - self.k), n):
            t = self.t + s * self.h
            awaited = self._awaiting(t)
            if awaited is None:
                if contiguous:
                    self._ready_k = self.k + s + 1
            elif self.gyro.end - t <= self.limits.link_wait:
                self.awaited = awaited
                return s
            else:
                contiguous = False   # waited out: it goes on, counted by _step
        return n

    def advance(self, max_steps: int | None = None, impatient: bool = False) -> int:
        """Run every step the inputs allow (at most ``max_steps``; ``impatient``: one step
        with what is here, if the own sensors allow it); return how many ran."""
        if impatient:
            self.impatient = True
            try:
                return super().advance(1)
            finally:
                self.impatient = False
        return super().advance(max_steps)

    def _awaiting(self, t: float) -> str | None:
        """What step ``[t, t + h]`` still waits for under :class:`Exchange`, or None: the own
        bearings (and a leader's known pose) measured by ``t + h``, and the channels of each
        live neighbour (heard within ``neighbour_timeout``, counting from t0 until it is) from
        its publish instant at or before ``t``."""
        ex = self.exchange
        assert ex is not None
        end = t + self.h
        if not _complete(self._bearing_stamps, ex.bearing_period, end):
            return 'bearings'
        if self.leader:
            return (None if _complete(self._pose_stamps, ex.known_pose_period, end)
                    else 'known_pose')
        # Optional channels too, from a neighbour that sends them (it has been heard on them).
        alive = t - self.limits.neighbour_timeout
        due = t + 1e-9 - ex.publish_period   # a newest stamp at or before this: one is due
        for nb in self.neighbours:
            heard = nb.heard
            if not heard:
                if self.t0 < alive:
                    continue   # silent since t0: not waited for
                if self._required:
                    return nb.name
                continue
            stamps = heard.values()
            if max(stamps) < alive:
                continue   # silent: not waited for
            # A required channel never heard, or one whose newest stamp is due for a newer.
            if min(stamps) <= due or not self._required <= heard.keys():
                return nb.name
        return None

    def body_bearing(self, agent_id: int, t: float, at: float | None = None,
                     until: float = np.inf) -> Array | None:
        """Own bearing to ``agent_id`` rotated to the body frame at ``t`` with the gyro, or
        None (none, or older than ``sensor_timeout``): the newest sample the gyro can bridge
        (static fleets: every sample sees the same world bearing), or, given ``at``, the
        bearing measured at ``at`` (moving fleets): interpolated between the two samples around
        it (rotated to t, then a normalised linear interpolation), the newest held after it.
        ``until``: no sample measured after it (the exchange's fixed inputs)."""
        hist = self._bearings.get(agent_id)
        if not hist:
            return None
        if at is None:
            for stamp, b in reversed(hist):
                if stamp > until + 1e-9:
                    continue
                if t - stamp > self.limits.sensor_timeout:
                    return None
                if self.gyro.covers(stamp, t):
                    return self.gyro.increment(t, stamp) @ b   # R(t)ᵀ R(t_b) b(t_b)
            return None
        later: tuple[float, Array] | None = None
        for stamp, b in reversed(hist):  # newest sample the gyro can bridge
            if t - stamp > self.limits.sensor_timeout:
                return None
            if not self.gyro.covers(stamp, t):
                continue
            b_t = self.gyro.increment(t, stamp) @ b   # R(t)ᵀ R(t_b) b(t_b)
            if stamp > at + 1e-9:
                later = (stamp, b_t)
                continue
            if later is None or stamp >= at - 1e-9:
                return b_t
            w = (at - stamp) / (later[0] - stamp)
            mixed = (1.0 - w) * b_t + w * later[1]
            return mixed / np.linalg.norm(mixed)
        return later[1] if later is not None else None

    def stale_neighbours(self, t: float) -> list[str]:
        """Neighbours missing a channel, or whose latest value of one is older than
        ``neighbour_timeout``."""
        limit = t - self.limits.neighbour_timeout
        return [nb.name for nb in self.neighbours
                if any(nb.stamps.get(name, -np.inf) < limit
                       for name, c in self.channels.items() if not c.optional)]

    def moved_back(self, t: float, t_s: float) -> Array | None:
        """``p̂_i`` moved back from ``t`` to ``t_s <= t`` by the own odometry,
        ``p̂_i(t) - R̂_i(t) R(t)ᵀ R(t_s) δ(t_s → t)`` (:attr:`base.StepInputs.p_own`); None
        without odometry over that span."""
        if not (self.odometry_live() and self.odometry.covers(t_s, t)
                and self.gyro.covers(t_s, t)):
            return None
        delta = self.odometry.displacement(t_s, t)
        return self.x.p_hat[0] - self.x.R_hat[0] @ (self.gyro.increment(t, t_s) @ delta)

    def step_inputs(self, t: float, delta_R: Array, stale: list[str],
                    displacement: Array | None = None) -> StepInputs:
        """What the step at ``t`` uses: the fresh neighbours to which an own bearing exists,
        each paired with the own bearing (and, with odometry, ``p̂_i``) at the stamp of what
        it sent."""
        used, p_own, values = [], [], []
        held: list[tuple[float, float]] = []
        moving = displacement is not None  # static fleets: what was sent does not change
        names = [name for name, c in self.channels.items() if not c.optional]
        for nb in self.neighbours:
            if nb.name in stale:
                continue
            t_s, sent = t, nb.values
            if not moving and self.exchange is not None:   # j's values of its instant ≤ t
                fixed = nb.at_one_instant(names, not_after=t)
                sent = fixed[1] if fixed is not None else sent
                for name in self.channels.keys() - sent.keys():   # optional: newest ≤ t
                    value = nb.newest_until(name, t)
                    if value is not None:
                        sent = {**sent, name: value}
            if moving:  # j's values of one instant, paired with our own at that instant
                own = self._bearings.get(nb.agent_id)
                newest = own[-1][0] if own else t   # our bearing at t_s must be here too
                same = nb.at_one_instant(names, not_after=min(t, newest))
                if same is None:
                    self.unpaired += 1
                    if nb.at_one_instant(names, not_after=np.inf) is not None:
                        continue  # this step without j: exact, unlike values of two instants
                t_s, sent = same if same is not None else (max(nb.stamps.values()), sent)
                t_s = min(t_s, t)
            b = self.body_bearing(nb.agent_id, t, at=t_s if moving else None,
                                  until=self._until(t + self.h))
            if b is not None:
                used.append((nb, b))
                held.append((self._interval(self._bearings.get(nb.agent_id)),
                             self._interval(nb.history.get(names[0]) if names else None)))
                values.append({name: self._value(nb, sent, name) for name in self.channels})
                back = self.moved_back(t, t_s) if t_s < t else None
                if back is None and t_s < t:
                    self.unpaired += 1
                p_own.append(self.x.p_hat[0] if back is None else back)
        received = {name: (np.array([v[name] for v in values]) if used
                           else np.zeros((0,) + c.shape)) for name, c in self.channels.items()}
        return StepInputs(
            delta_R=delta_R,
            edges=Edges(agent=np.zeros(len(used), dtype=np.intp),
                        k=np.array([nb.k for nb, _ in used]), n_agents=1),
            bearings=np.array([b for _, b in used]) if used else np.zeros((0, 3)),
            received=received, displacement=displacement,
            p_own=np.array(p_own) if used and moving else None,
            held=np.array(held).reshape(-1, 2))

    def _interval(self, history: Sequence[tuple[float, object]] | None) -> float:
        """Steps between the last two samples of ``history`` (``(stamp, value)`` pairs), at
        least 1: how many steps the newest serves."""
        if not history or len(history) < 2:
            return 1.0
        return max(1.0, (history[-1][0] - history[-2][0]) / self.h)

    def _value(self, nb: NeighbourState, sent: dict[str, Array], name: str) -> Array:
        """``name`` from what ``nb`` sent at the instant used; an optional channel's newest
        value, or the method's stand-in until one came."""
        if name in sent:
            return sent[name]
        return nb.values[name] if name in nb.values else self.estimator.missing(name)

    def _until(self, t: float) -> float:
        """The newest own measurement a step or message at ``t`` may use."""
        return t if self.exchange is not None else np.inf

    def _begin_step(self) -> _Prepared | None:
        """A step up to the method's own (:func:`advance_together` runs that for several
        agents at once): its inputs, or None for a leader, whose whole step this is."""
        t = self.t
        est = self.estimator
        if self.exchange is not None and self.k >= self._ready_k:
            awaited = self._awaiting(t)
            if awaited is not None:
                self.incomplete[awaited] += 1
        delta_R = self.gyro.increment(t, t + self.h)[None]
        displacement = None
        if self.odometry_live():
            if self.odometry.covers(t, t + self.h):
                displacement = self.odometry.displacement(t, t + self.h)[None]
            else:
                self.odometry_missing_steps += 1
        if self.leader:
            self._apply_known_pose(t)
            self.x = est.propagate(self.x, delta_R, displacement)
            self.last = StepInfo(t=t, odometry=displacement is not None)
            self.k += 1
            return None
        stale = self.stale_neighbours(t)
        return _Prepared(t, tuple(stale), self.step_inputs(t, delta_R, stale, displacement))

    def _apply_known_pose(self, t: float) -> None:
        until = self._until(t + self.h)
        usable = [pose for pose in self._known_poses if pose[0] <= until + 1e-9]
        if not usable:
            return
        stamp, R, p = max(usable, key=lambda pose: pose[0])
        moving = self.odometry_live()
        # A pose from another instant is carried to t by the gyro and, moving, the odometry:
        # wait until both cover the way (a pose ahead of the odometry would be misplaced).
        if self.gyro.covers(stamp, t) and (not moving or self.odometry.covers(stamp, t)):
            R_t = R @ self.gyro.increment(stamp, t)
            if moving:
                p = (p + R @ self.odometry.displacement(stamp, t) if stamp <= t
                     else p - R_t @ self.odometry.displacement(t, stamp))
            self.x = self.estimator.with_known_pose(self.x, np.zeros(1, dtype=np.intp),
                                                    R_t[None], p[None])
            newer = [pose for pose in self._known_poses if pose[0] > stamp]
            self._known_poses.clear()
            self._known_poses.extend(newer)

    # ------------------------------------------------------------------------------ outputs
    def own_bearings(self, t: float) -> tuple[list[int], Array]:
        """Ids of the agents this agent has a bearing to, and those bearings rotated to ``t``
        ``(M, 3)`` (measured at t when the agent moves, :meth:`body_bearing`)."""
        ids, bearings = [], []
        at = t if self.odometry_live() else None
        for agent_id in self._bearings:
            b = self.body_bearing(agent_id, t, at=at, until=self._until(t))
            if b is not None:
                ids.append(agent_id)
                bearings.append(b)
        return ids, np.array(bearings).reshape(-1, 3)

    def bearings_at(self, t: float) -> bool:
        """A bearing measured at ``t`` (or later) has arrived from every agent this agent
        sees: what it sends at ``t`` is then exact for a moving fleet."""
        return all(hist[-1][0] >= t - 1e-9 for hist in self._bearings.values() if hist)

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


T = TypeVar('T', bound=TimedAgent)


def advance_together(agents: Sequence[T]) -> list[T]:
    """One step of every agent that has one ready (each as its own ``advance(1)``), the steps
    of those whose estimators are of one method with equal gains in one call of that
    method's step: a step treats its agents' rows independently, so each agent gets what its
    own step gives, and the call's cost (numpy's, per call) is paid once (BENCHMARKS.md,
    "Steps run together"). For :class:`AgentEstimator`, :class:`.link_agent.LinkAgentEstimator`
    and :class:`.two_round_agent.TwoRoundAgent` (whose step is its second round). Returns the
    agents that stepped."""
    stepped = [a for a in agents if a.steps_ready() > 0]
    groups: list[list[tuple[T, _Prepared]]] = []
    for a in stepped:
        prepared = a._begin_step()
        if prepared is None:
            continue
        for group in groups:
            b, other = group[0]
            if (type(b.estimator) is type(a.estimator) and b.estimator.gains == a.estimator.gains
                    and b.h == a.h and _same_fields(other.inputs, prepared.inputs)):
                group.append((a, prepared))
                break
        else:
            groups.append([(a, prepared)])
    for group in groups:
        lead = group[0][0]
        if len(group) == 1:
            lead._end_step(group[0][1], *lead.estimator.step(lead.x, lead.h, group[0][1].inputs))
            continue
        x, diagnostics = lead.estimator.step(type(lead.x).stack([a.x for a, _ in group]), lead.h,
                                             StepInputs.stack([p.inputs for _, p in group]))
        for i, (a, prepared) in enumerate(group):
            a._end_step(prepared, x.rows(slice(i, i + 1)),
                        {k: v[i:i + 1] for k, v in diagnostics.items()})
    return stepped


def _same_fields(a: StepInputs, b: StepInputs) -> bool:
    """Whether two steps' inputs give the same optional fields (they stack)."""
    return ((a.displacement is None) == (b.displacement is None)
            and (a.p_own is None) == (b.p_own is None) and (a.held is None) == (b.held is None)
            and (a.bearing_rates is None) == (b.bearing_rates is None)
            and (None if a.anchor is None else a.anchor.pinned)
            == (None if b.anchor is None else b.anchor.pinned)
            and a.t == b.t and a.received.keys() == b.received.keys())
