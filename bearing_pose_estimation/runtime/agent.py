"""One agent running any registered estimator, independent of ROS (the estimator node's, netsim's
and an ``estimators`` process's), configured by its method's declarations (:mod:`estimators.base`).

Inputs arrive at their own rates and stamps; each fixed step
``h`` runs as soon as its inputs are in: the own gyro and odometry, integrated sample by sample
(:mod:`core.gyro`, :mod:`core.odometry`; live odometry is waited for as the gyro is); the own
point sensors (``measures``), rotated with the gyro to the body frame of the step's instant (a
20 ms old bearing paired with the current R̂ costs ``|ω| · 20 ms``) and paired by
``own_pairing``; what neighbours send (``sends``), paired as :class:`base.Channel` says (a
sender's measurement of this agent is interpolated like the own, turned with its odometry); a
two-round method's reply (:meth:`AgentRuntime.pending_reply`) once round 1 is in, after which
the step waits for round 2.

Every wait ends when the own sensors are ``link_wait`` ahead (own samples: ``sensor_timeout``),
or at once when ``impatient``; what is missing is counted (``missing``) and masked. A gyro
stamp ``jump_back`` before the newest restarts from the initial estimate (``time_jump``); a gap
over ``max_gyro_gap`` restarts the state time after it, keeping the estimate (``gyro_gap``);
the step grid stays aligned to ``t0``. Leaders take their known pose, carried by the gyro (and
odometry). Every ``add_*`` returns None when the input is used, or why it is rejected.
"""
from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from ..core.bearing_rates import BearingRateFilter
from ..core.gyro import GyroBuffer
from ..core.odometry import OdometryBuffer
from ..estimators.base import (ANCHOR_DELTA_R, ANCHOR_DISPLACEMENT, DELTA_R, DISPLACEMENT, HELD,
                               IS_ANCHOR, P_OWN, PEER_DELTA_R, PEER_DISPLACEMENT, PEER_ODOMETRY,
                               PINNED, POSE_COVARIANCE, Channel, Edges, Estimator, Motion,
                               Sensor, State, StepInputs)
from .buffers import (SAME, Exchange, Limits, Stamped, bounded_problem, complete,
                      finite_max_norm, twist_problem, unit_problem)

Array = NDArray[np.float64]
# A neighbour's covariance that rises this many times across a silence announces a reset (not
# without one: Presenza et al.'s rises a thousandfold in the first steps of a run).
RESET_JUMP = 10.0
# The largest component [unit per sensor] of an own or received point measurement.
POINT_BOUNDS = {Sensor.BEARINGS: 2.0, Sensor.RELATIVE_POSITIONS: 1e4,
                Sensor.BEARING_RATES: 100.0}
# The receiver's flag of an edge on which the sender's flag holds (and back).
MIRROR = {'senses': 'sensed_by', 'sensed_by': 'senses', 'ranges': 'ranged_by',
          'ranged_by': 'ranges'}


@dataclass(frozen=True)
class PeerSpec:
    """One edge of an agent: the other end's name, id, ``k_ij`` and the edge's flags."""

    name: str
    agent_id: int
    k: float = 1.0
    flags: Mapping[str, bool] = field(default_factory=dict)


@dataclass(frozen=True)
class AgentSpec:
    """One agent's place in its fleet: its edges in slot order (:func:`base.edge_table`), its
    initial estimate, its role (``leader``: its pose is known; ``anchor``: the anchor's name
    and id; ``pinned``: it is the anchor and holds ``(I, 0)``), the ids that exist (points of
    others are rejected; None: any) and ``rate_tau``: no bearing-rate sensor, the rates come
    from consecutive bearings through this filter (:mod:`core.bearing_rates`)."""

    name: str
    agent_id: int
    peers: tuple[PeerSpec, ...]
    R0: Array
    p0: Array
    leader: bool = False
    anchor: tuple[str, int] | None = None
    pinned: bool = False
    known_ids: frozenset[int] | None = None
    rate_tau: float | None = None


def reads(flags: Mapping[str, bool], channel: Channel) -> bool:
    """An agent reads ``channel`` on an edge with ``flags`` (its ``on`` flag; an owner-only
    value comes from the owner)."""
    if channel.on is not None and not flags.get(channel.on, False):
        return False
    return not (channel.owner_only and flags.get('owns', False))


def _psd(v: Array, blocks: int) -> bool:
    """The first ``blocks`` packed symmetric 3x3 blocks of ``v`` are positive semi-definite."""
    lam = np.linalg.eigvalsh(so3.sym_unpack(v[:6 * blocks].reshape(blocks, 6)))
    return bool(np.all(lam >= -1e-9 * max(float(np.abs(lam).max()), 1e-300)))


class Peer:
    """One edge's other end: its channels' values and measurements of this agent by name, the
    newest stamp each channel was heard on (with a value for this agent or not), its odometry."""

    __slots__ = ('name', 'agent_id', 'k', 'slot', 'flags', 'values', 'heard', 'odometry',
                 'last', 'known', 'bar', 'silent')

    def __init__(self, spec: PeerSpec, slot: int, odometry: OdometryBuffer | None) -> None:
        self.name, self.agent_id, self.k, self.slot = spec.name, spec.agent_id, spec.k, slot
        self.flags = dict(spec.flags)
        self.values: dict[str, Stamped] = {}
        self.heard: dict[str, float] = {}
        self.odometry = odometry
        self.last = -math.inf   # the newest stamp of a value or measurement it sent
        self.forget()

    def forget(self) -> None:
        """No covariance of it used yet (``known``: its last, relative to the prior), and no
        reset announced (``bar``: what it must be back at; :meth:`AgentRuntime._distrust`)."""
        self.known, self.bar, self.silent = math.nan, math.nan, False

    @property
    def reset(self) -> bool:
        return not math.isnan(self.bar)

    def newest(self) -> float:
        """The newest stamp of anything it sent (channels, measurements, odometry)."""
        if self.odometry is not None and not self.odometry.empty:
            return max(self.last, self.odometry.end)
        return self.last

    def latest(self, name: str) -> Array | None:
        hist = self.values.get(name)
        return hist.samples[-1][1] if hist else None

    def instants(self, names: Sequence[str],
                 not_after: float) -> Iterator[tuple[float, dict[str, Array]]]:
        """Newest first, the stamps not after ``not_after`` at which every channel ``names``
        has a value, with those values."""
        first = self.values.get(names[0]) if names else None
        for stamp, value in reversed(first.samples) if first else ():
            if stamp > not_after + SAME:
                continue
            out = {names[0]: value}
            for name in names[1:]:
                hist = self.values.get(name)
                match = hist.at(stamp)[0] if hist else None
                if match is None:
                    break
                out[name] = match
            else:
                yield stamp, out

    def at_one_instant(self, names: Sequence[str],
                       not_after: float) -> tuple[float, dict[str, Array]] | None:
        """The newest of :meth:`instants`, or None."""
        return next(self.instants(names, not_after), None)


@dataclass
class StepInfo:
    """Diagnostics of the last step: its time, the edges it used, the neighbours left out for
    being silent, whether odometry fed it, and the method's per-agent diagnostics (row 0)."""

    t: float = 0.0
    edges_used: int = 0
    stale: tuple[str, ...] = ()
    odometry: bool = False
    diagnostics: dict[str, Array] = field(default_factory=dict)


@dataclass(frozen=True)
class Prepared:
    """A step up to the method's own (:func:`.together.advance_together` runs that for
    several agents at once): its time, the silent neighbours, its inputs."""

    t: float
    stale: tuple[str, ...]
    inputs: StepInputs


class AgentRuntime:
    """One agent of any registered method (module docstring): ``step`` is ``h`` [s]; the first
    gyro interval starts at ``t0``; ``exchange``: a simulation's (None: a step takes what is
    here); ``expects_odometry``: odometry (simulated) is waited for from the first step on."""

    def __init__(self, estimator: Estimator, spec: AgentSpec, step: float, t0: float = 0.0,
                 limits: Limits = Limits(), exchange: Exchange | None = None,
                 expects_odometry: bool = False, gyro_horizon: float = 2.0) -> None:
        self.estimator = estimator
        cls = type(estimator)
        self.spec = spec
        self.agent_id, self.name = spec.agent_id, spec.name
        self.h = float(step)
        self.limits = limits
        self.exchange = exchange
        self.leader = spec.leader
        self.known_ids = spec.known_ids
        self.origin = float(t0)   # the step grid is origin + n h, across restarts too
        self.t0 = float(t0)
        self.k = 0
        self.R0 = np.array(spec.R0, dtype=float).reshape(3, 3)
        self.p0 = np.array(spec.p0, dtype=float).reshape(3)
        self.x: State = estimator.initial_state(self.R0[None], self.p0[None])
        self.channels = {c.name: c for c in cls.sends}
        self.rounds = cls.rounds()
        # Own point sensors the step reads (estimated bearing rates are not received).
        self.rate_tau = spec.rate_tau if Sensor.BEARING_RATES in cls.measures else None
        self._own_flag = {s: f for s, f in cls.measures.items()
                          if not (s is Sensor.BEARING_RATES and self.rate_tau is not None)}
        self.own: dict[Sensor, dict[int, Stamped]] = {s: {} for s in self._own_flag}
        self._own_stamps: dict[Sensor, deque[float]] = {s: deque(maxlen=2) for s in self.own}
        gyro_odometry = cls.peer_odometry == 'links'
        self.peers = [Peer(p, e, OdometryBuffer(t0, gyro_horizon) if gyro_odometry else None)
                      for e, p in enumerate(spec.peers)]
        self._by_id = {p.agent_id: p for p in self.peers}
        # The neighbours it reads anything from (the others are never stale).
        self._read_peers = [p for p in self.peers if p.odometry is not None or any(
            reads(p.flags, c) for c in self.channels.values())]
        self._required_names = [c.name for c in cls.sends if not c.optional]
        self._optional_names = [c.name for c in cls.sends if c.optional]
        self._instant = any(c.pairing == 'instant' for c in cls.sends)
        self._instant_required = {c.name for c in cls.sends if c.pairing == 'instant'
                                  and not c.optional and c.sensor is None}
        # Per round, the 'exact' channels and the senders' measurements (paired at t).
        self._exact = {r: [c for c in cls.sends if c.round == r
                           and (c.pairing == 'exact' or c.sensor is not None)]
                       for r in range(1, self.rounds + 1)}
        # What an edge needs to take part in a step, for a method without partial_edges.
        self._complete_keys = [s.value for s in cls.measures] + [
            c.name for c in cls.sends if not c.optional and c.sensor is None]
        # The covariance a sender announces its pose with, and the prior's variances it is
        # measured against (the estimator's stand-in for a covariance never received).
        self._cov = next((c.name for c in cls.sends if c.kind == POSE_COVARIANCE), None)
        self._prior_var = (None if self._cov is None
                           else np.diagonal(estimator.missing(self._cov)).copy())
        flags = {name: np.array([p.flags.get(name, False) for p in self.peers], dtype=bool)
                 for name in sorted({f for p in self.peers for f in p.flags})}
        # Its edges, one per peer: the same object every step (a method may cache what it
        # derives from it).
        self._edges = Edges(agent=np.zeros(len(self.peers), dtype=np.intp),
                            k=np.array([p.k for p in self.peers], dtype=float), n_agents=1,
                            slot=np.arange(len(self.peers), dtype=np.intp), flags=flags)
        self.is_anchor = spec.anchor is not None and spec.anchor[1] == spec.agent_id
        self.anchor_odometry = (OdometryBuffer(t0, gyro_horizon)
                                if cls.peer_odometry == 'anchor' and not self.is_anchor
                                else None)
        self.gyro = GyroBuffer(t0, gyro_horizon)
        self.odometry = OdometryBuffer(t0, gyro_horizon)
        self.uses_odometry = estimator.uses(Sensor.ODOMETRY)
        self.requires_odometry = Sensor.ODOMETRY in cls.sensors or (
            expects_odometry and self.uses_odometry)
        self._rate_filter = (None if self.rate_tau is None
                             else BearingRateFilter(len(self.peers), self.rate_tau))
        self._known_poses: deque[tuple[float, Array, Array]] = deque(maxlen=8)
        self._pose_stamps: deque[float] = deque(maxlen=2)
        # What went wrong, by what: inputs left out of a step; attempts that waited; steps
        # that went on without an awaited input.
        self.missing: Counter[str] = Counter()
        self.waits: Counter[str] = Counter()
        self.incomplete: Counter[str] = Counter()
        self.awaited: str | None = None           # what the latest wait was for
        self.awaited_peer: str | None = None      # and from whom (None: the own sensors)
        self.carried = 0                          # late values carried to the step's instant
        self.unpaired = 0                         # values not paired with their instant
        self.odometry_missing_steps = 0           # steps without the odometry expected
        self.anchor_still_steps = 0               # steps without the anchor's odometry
        self.non_finite_steps = 0                 # steps discarded as non-finite
        self.resets: Counter[str] = Counter()     # per neighbour: the resets it announced
        self.distrusted: Counter[str] = Counter()   # per neighbour: steps left out after one
        # No trustworthy estimate since then (None: it has one): started after the fleet's
        # t = 0 (a late or restarted process, or a robot's real clock), a gyro gap or a clock
        # jump. Until then, or warm_window, each step first tries the method's warm start.
        self.cold_since: float | None = self.t0 if self.t0 > SAME and not self.leader else None
        self.warm_note = ''                       # the latest warm start's outcome
        self.clocked = False                      # a gyro sample has set its time
        self.warm_starts: Counter[str] = Counter()   # accepted, refused, unavailable
        # Per neighbour: how far [s] the stamp of its newest input was ahead of the own clock,
        # and how many of its inputs were more than max_clock_lead ahead.
        self.leads: dict[str, float] = {}
        self.ahead: Counter[str] = Counter()
        self.impatient = False
        self._stuck: tuple[int, float, float] | None = None   # (k, gyro end, wall) waiting
        self._pending: StepInputs | None = None   # the inputs of step _pending_k
        self._pending_k = -1
        self._round1: StepInputs | None = None    # round 1 of step _replied_k, replied to
        self._replied_k = -1
        self.last = StepInfo(t=self.t0)

    # ------------------------------------------------------------------------------ state
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

    def _restart_at(self, stamp: float, reset_estimate: bool) -> None:
        """Restart the state time at the first grid instant at or after ``stamp``."""
        n = np.ceil((stamp - self.origin) / self.h - 1e-9)
        self.t0, self.k = self.origin + n * self.h, 0
        self.gyro.reset(stamp)
        self.odometry.reset(stamp)
        if reset_estimate:
            self.x = self.estimator.initial_state(self.R0[None], self.p0[None])
        self.cold_since = None if self.leader else self.t0   # a leader knows its pose
        for by_target in self.own.values():
            by_target.clear()
        for stamps in self._own_stamps.values():
            stamps.clear()
        self._pose_stamps.clear()
        self._pending, self._pending_k = None, -1
        self._round1, self._replied_k = None, -1
        if self._rate_filter is not None and self.rate_tau is not None:
            self._rate_filter = BearingRateFilter(len(self.peers), self.rate_tau)
        if reset_estimate:
            for peer in self.peers:
                peer.values.clear()
                peer.heard.clear()
                peer.last = -math.inf
                peer.forget()
                if peer.odometry is not None:
                    peer.odometry.reset(self.t0)
            if self.anchor_odometry is not None:
                self.anchor_odometry.reset(self.t0)
        self.last = StepInfo(t=self.t)

    @property
    def _future(self) -> str:
        """Why a stamp ahead of the newest gyro sample is unused: ``early`` before the first one
        (a late-started process: the gyro sets its time), else ``future_stamp``."""
        return 'future_stamp' if self.clocked else 'early'

    # ------------------------------------------------------------------------------ own motion
    def add_gyro(self, stamp: float, omega: Array, now: float | None = None) -> str | None:
        """An interval-average gyro sample (see :mod:`core.gyro`). ``now``: the receiver's
        clock, to reject stamps from the future."""
        lim = self.limits
        omega = np.asarray(omega, dtype=float)
        finite, _, norm = finite_max_norm(omega)
        if not (finite and math.isfinite(stamp)):
            return 'non_finite'
        if norm > lim.max_rate:   # math.hypot does not overflow: no entry-wise check first
            return 'absurd_rate'
        if now is not None and stamp > now + lim.max_future:
            return 'future_stamp'
        self.clocked = True   # its time is the gyro's from now on
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
        [rad/s]; see :mod:`core.odometry`); ``unused`` by methods without odometry. The steps
        over a gap longer than ``max_gyro_gap`` run without it."""
        if not self.uses_odometry:
            return 'unused'
        return self._add_twist(self.odometry, stamp, v, omega, own=True, now=now)

    def _add_twist(self, odometry: OdometryBuffer, stamp: float, v: Array, omega: Array,
                   own: bool, now: float | None = None) -> str | None:
        """A twist into ``odometry``, or why not; after a gap (``odometry_gap``), and for another
        agent's first sample or jumped-back clock, the integration restarts at it (``own``: the
        gyro's time rules decide)."""
        v, omega = np.asarray(v, dtype=float), np.asarray(omega, dtype=float)
        problem = twist_problem(stamp, v, omega, self.limits)
        if problem is not None:
            return problem
        if now is not None and stamp > now + self.limits.max_future:
            return 'future_stamp'
        end = odometry.end
        if stamp <= end:
            if own and odometry.empty and stamp >= end - 1e-9:
                return None   # the sample that closed a gap: the restart began at its stamp
            # Its first sample, stamped before our start (its clock is behind ours), or its
            # clock restarted: integrate from it.
            if not own and (odometry.empty or stamp < end - self.limits.jump_back):
                odometry.reset(stamp)
                return None
            return 'out_of_order'
        if stamp - end > self.limits.max_gyro_gap:
            odometry.reset(stamp)
            return 'odometry_gap'
        odometry.add_twist(stamp, v, omega)
        return None

    def odometry_live(self) -> bool:
        """Odometry keeps up with the gyro (within ``sensor_timeout``; from the start for a method
        that needs it): steps wait for it and feed it forward."""
        keeps_up = self.odometry.end >= self.gyro.end - self.limits.sensor_timeout
        return self.uses_odometry and keeps_up and (not self.odometry.empty
                                                    or self.requires_odometry)

    def own_inputs_ready(self) -> bool:
        """The own gyro (and live odometry) cover the next step: only what comes from others
        may be missing."""
        end = self.gyro.end
        if self.odometry_live():
            end = min(end, self.odometry.end)
        return end - self.t >= self.h - 1e-9 * self.h

    # ------------------------------------------------------------------------------ inputs
    def add_points(self, sensor: Sensor, stamp: float, ids: NDArray[np.integer],
                   vectors: Array) -> list[str]:
        """An own point sensor's message: one vector per agent seen (``ids``), measured at
        ``stamp``, in the body frame. Points of agents the step does not read are ignored
        (unknown ids rejected). Returns the causes of the rejected points."""
        by_target = self.own.get(sensor)
        n = len(ids)
        if by_target is None:
            return []   # the step does not read it (another agent reads it from the topic)
        if not math.isfinite(stamp):
            return ['non_finite'] * n
        if stamp > self.gyro.end + self.limits.max_future:
            return [self._future] * n
        if stamp < self.gyro.start:
            return ['stale'] * n
        stamps = self._own_stamps[sensor]
        if not stamps or stamp > stamps[-1]:
            stamps.append(float(stamp))
        flag = self._own_flag[sensor]
        anyone = flag is None and type(self.estimator).links == 'sensing'
        rejected = []
        for j, v in zip(np.asarray(ids).tolist(), np.asarray(vectors, dtype=float)):
            j = int(j)
            if j == self.agent_id or (self.known_ids is not None and j not in self.known_ids):
                rejected.append('unknown_id')
                continue
            peer = self._by_id.get(j)
            if not anyone and (peer is None or not (flag is None or peer.flags.get(flag))):
                continue   # an agent this step does not read
            problem = (unit_problem(v, self.limits.unit_tolerance) if sensor is Sensor.BEARINGS
                       else bounded_problem(v, POINT_BOUNDS[sensor]))
            hist = by_target.setdefault(j, Stamped())
            if problem is None and hist and stamp <= hist.newest_stamp:
                problem = 'out_of_order'
            if problem is None:
                hist.add(float(stamp), v / np.linalg.norm(v) if sensor is Sensor.BEARINGS
                         else v.copy())
            else:
                rejected.append(problem)
        return rejected

    def add_known_pose(self, stamp: float, R: Array, p: Array) -> str | None:
        """A leader's true pose at ``stamp`` (motion capture, GNSS/INS)."""
        R, p = np.asarray(R, dtype=float), np.asarray(p, dtype=float)
        if not (np.isfinite(R).all() and np.isfinite(p).all() and math.isfinite(stamp)):
            return 'non_finite'
        self._known_poses.append((float(stamp), R, p))
        if not self._pose_stamps or stamp > self._pose_stamps[-1]:
            self._pose_stamps.append(float(stamp))
        return None

    def add_message(self, sender: int, stamp: float, values: Mapping[str, object], *,
                    now: float | None = None) -> str | None:
        """A message of neighbour ``sender`` with its values of some channels at its state
        time ``stamp``: per-agent channels as arrays, per-edge ones as ``{listener id:
        value}`` (this agent takes its own; ``not_seen`` when none of them has one). Used
        whole or rejected whole. ``now``: the own clock, for :meth:`note_lead`."""
        peer = self._by_id.get(sender)
        if peer is None:
            return 'unknown_id'
        mine: dict[str, Array] = {}
        heard = []
        for name, value in values.items():
            c = self.channels.get(name)
            if c is None or c.sensor is not None:   # readings travel on sensor topics
                return 'unknown_channel'
            heard.append(name)
            if c.per == 'edge':
                value = value.get(self.agent_id) if isinstance(value, dict) else None
                if value is None:
                    continue   # nothing for this agent in it
            v = np.asarray(value, dtype=float)
            if v.shape != c.shape:
                return 'malformed'
            mine[name] = v
        lim = self.limits
        in_time = math.isfinite(stamp) and stamp <= self.gyro.end + lim.max_future
        if not mine:
            if in_time:
                for name in heard:   # the sender's message of this instant: none for us
                    peer.heard[name] = max(peer.heard.get(name, -math.inf), float(stamp))
            return 'not_seen'
        if not math.isfinite(stamp):
            return 'non_finite'
        for name, v in mine.items():
            c = self.channels[name]
            problem = bounded_problem(v, c.bound)
            # The owner's zeros: no value of the pair yet (the step takes them as such).
            none_yet = c.owner_only and not peer.flags.get('owns', False) and not v.any()
            if problem is None and c.unit and not none_yet:
                problem = unit_problem(v, lim.unit_tolerance)
            if problem is None and c.psd_blocks and not _psd(v, c.psd_blocks):
                problem = 'not_covariance'
            if problem is not None:
                return problem
        if not in_time:
            return self._future
        for name, v in mine.items():
            hist = peer.values.setdefault(name, Stamped())
            if hist and stamp < hist.newest_stamp - SAME:
                if hist.newest_stamp - stamp > lim.jump_back:
                    hist.samples.clear()   # the sender restarted its clock
                else:
                    return 'out_of_order'
        for name, v in mine.items():
            hist = peer.values[name]
            if not (self.channels[name].owner_only and not v.any()
                    and hist.at(stamp)[0] is not None):   # zeros undo no value
                hist.add(float(stamp), v)
        peer.last = max(peer.last, float(stamp))
        for name in heard:
            peer.heard[name] = max(peer.heard.get(name, -math.inf), float(stamp))
        self.note_lead(peer.name, stamp, now)
        return None

    def add_peer_points(self, sender: int, sensor: Sensor, stamp: float,
                        ids: NDArray[np.integer], vectors: Array, *,
                        now: float | None = None) -> str | None:
        """Neighbour ``sender``'s point sensor message: its point of this agent is kept when a
        channel carries that sensor's readings. ``now``: the own clock (:meth:`note_lead`)."""
        peer = self._by_id.get(sender)
        if peer is None:
            return 'unknown_id'
        carriers = [c for c in self.channels.values()
                    if c.sensor is sensor and reads(peer.flags, c)]
        if not carriers:
            return None   # not read from this sender
        if not math.isfinite(stamp):
            return 'non_finite'
        mine = np.flatnonzero(np.asarray(ids) == self.agent_id)
        if not mine.size:
            return None
        v = np.asarray(vectors, dtype=float)[mine[0]]
        c = carriers[0]
        hist = peer.values.setdefault(c.name, Stamped())
        problem = bounded_problem(v, min(c.bound, POINT_BOUNDS[sensor])) or (
            'out_of_order' if hist and stamp <= hist.newest_stamp else None)
        if problem is not None:
            return problem
        hist.add(float(stamp), v.copy())
        peer.last = max(peer.last, float(stamp))
        self.note_lead(peer.name, stamp, now)
        return None

    def add_peer_odometry(self, sender: int, stamp: float, v: Array,
                          omega: Array, *, now: float | None = None) -> str | None:
        """Another agent's odometry sample, for a method that reads it (its edges' other
        ends', or the anchor's). ``now``: the own clock, for :meth:`note_lead`."""
        odometry, name = None, ''
        if self.anchor_odometry is not None and self.spec.anchor is not None:
            if sender == self.spec.anchor[1]:
                odometry, name = self.anchor_odometry, self.spec.anchor[0]
        elif (peer := self._by_id.get(sender)) is not None:
            odometry, name = peer.odometry, peer.name
        if odometry is None:
            return 'unknown_id'
        cause = self._add_twist(odometry, stamp, v, omega, own=False)
        if cause is None:
            self.note_lead(name, stamp, now)
        return cause

    def note_lead(self, sender: str, stamp: float, now: float | None) -> None:
        """How far ``sender``'s stamp was ahead of the own clock ``now`` (None: unknown), less
        latency; counted in :attr:`ahead` beyond ``max_clock_lead``."""
        if now is None:
            return
        lead = stamp - now
        self.leads[sender] = lead
        if lead > self.limits.max_clock_lead:
            self.ahead[sender] += 1

    # ------------------------------------------------------------------------------ readiness
    def stale_neighbours(self, t: float) -> list[str]:
        """Neighbours read from that were silent for over ``neighbour_timeout`` before ``t``
        (counting from the start, so first values on their way are not stale)."""
        limit = t - self.limits.neighbour_timeout
        if self.t0 >= limit:
            return []
        return [p.name for p in self._read_peers if p.newest() < limit]

    def _awaiting(self, t: float, round_: int) -> str | None:
        """What round ``round_`` of the step at ``t`` waits for, or None when every input is here
        or known not to come; :attr:`awaited_peer`: from whom."""
        self.awaited_peer = None
        h = self.h
        behind = self.gyro.end - t > self.limits.link_wait

        def odometry_due(odo: OdometryBuffer | None) -> bool:   # needed, not silent, not in yet
            return (odo is not None and self.requires_odometry and not odo.covers(t, t + h)
                    and odo.end >= t - self.limits.neighbour_timeout)
        if self.exchange is not None and round_ == 1:
            awaited = self._awaiting_exchange(t)
            if awaited is not None:
                return awaited
        if self.leader:
            return None
        if round_ == 1:
            if not behind and odometry_due(self.anchor_odometry):
                return 'anchor_odometry'
            if (type(self.estimator).own_pairing == 'interpolated'
                    and self.gyro.end - t <= self.limits.sensor_timeout):   # not given up on
                for sensor, by_target in self.own.items():
                    flag = self._own_flag[sensor]
                    for p in self.peers:
                        if flag is None or p.flags.get(flag):
                            hist = by_target.get(p.agent_id)
                            if not (hist and hist.newest_stamp >= t - SAME):
                                return sensor.value
        if behind:
            return None
        stale = set(self.stale_neighbours(t))
        due = [c for c in self.channels.values() if c.round == round_ and not c.optional
               and c.pairing == 'exact' and self.estimator.due(c.name, t, h)]
        sensors = [c for c in due if c.sensor is not None]
        sent = [c for c in due if c.sensor is None]
        for p in self.peers:
            if p.name in stale:
                continue
            self.awaited_peer = p.name
            if round_ == 1 and odometry_due(p.odometry):
                return 'odometry'
            for c in sensors:
                hist = p.values.get(c.name)
                if reads(p.flags, c) and not (hist and hist.newest_stamp >= t - SAME):
                    return c.name
            for c in sent:
                if reads(p.flags, c):
                    hist = p.values.get(c.name)
                    value, decided = hist.at(t) if hist is not None else (None, False)
                    if value is None and not decided:
                        return c.name
        self.awaited_peer = None
        return None

    def _awaiting_exchange(self, t: float) -> str | None:
        """Under a simulation's exchange: the own 'newest'-paired samples measured by ``t +
        h``, a leader's known pose, and each live neighbour's 'instant' channels of its publish
        instant at or before ``t`` (heard within ``neighbour_timeout``, counting from t0 until
        it is)."""
        ex = self.exchange
        assert ex is not None
        end = t + self.h
        if type(self.estimator).own_pairing == 'newest':
            for sensor, stamps in self._own_stamps.items():
                if not complete(stamps, ex.sensor_period, end):
                    return sensor.value
        if self.leader:
            return None if complete(self._pose_stamps, ex.known_pose_period, end) else 'known_pose'
        required = self._instant_required
        if not required:
            return None
        alive = t - self.limits.neighbour_timeout
        due = t + SAME - ex.publish_period   # a newest stamp at or before this: one is due
        for p in self.peers:
            heard = p.heard
            if (max(heard.values()) if heard else self.t0) < alive:
                continue   # silent (since t0): not waited for
            if not heard or min(heard.values()) <= due or not required <= heard.keys():
                self.awaited_peer = p.name
                return p.name
        return None

    def _wait(self, t: float, round_: int) -> bool:
        """Whether round ``round_`` of the step at ``t`` waits (counted by what), or goes on
        (with what is here, ``impatient`` or waited out: counted as incomplete)."""
        awaited = self._awaiting(t, round_)
        if awaited is None:
            return False
        if not self.impatient and self.gyro.end - t <= self.limits.link_wait:
            self.waits[awaited] += 1
            self.awaited = awaited
            return True
        self.incomplete[awaited] += 1
        return False

    def steps_ready(self) -> int:
        """1 when the next step's inputs are here (or known not to come, or waited out);
        else 0."""
        if self._pending is not None and self._pending_k == self.k:
            return 1   # complete inputs stay complete
        if not self.own_inputs_ready():
            return 0
        t = self.t
        if self.rounds > 1 and not self.leader:
            if self._replied_k != self.k or self._wait(t, self.rounds):
                return 0
        elif self._wait(t, 1):
            return 0
        self._pending, self._pending_k = self._gather(t), self.k
        return 1

    def advance(self, max_steps: int | None = None, impatient: bool = False) -> int:
        """Run the steps whose inputs are in (at most ``max_steps``; ``impatient``: the first
        one with what is here); return how many ran."""
        ran = 0
        self.impatient = impatient
        try:
            while max_steps is None or ran < max_steps:
                if not self.steps_ready():   # (two rounds: the caller sends pending_reply)
                    break
                prepared = self.begin_step()
                if prepared is not None:
                    self.end_step(prepared, *self.estimator.step(self.x, self.h, prepared.inputs))
                ran += 1
                self.impatient = False
        finally:
            self.impatient = False
        return ran

    def waited_out(self, wall: float, patience: float) -> float | None:
        """How long [s of wall time] the next step has waited, own inputs in and nothing changing,
        once that reaches ``patience`` (the caller then runs it impatient); else None."""
        if not self.own_inputs_ready() or self.steps_ready() > 0:
            self._stuck = None
            return None
        if self._stuck is None or self._stuck[:2] != (self.k, self.gyro.end):
            self._stuck = (self.k, self.gyro.end, wall)
            return None
        waited = wall - self._stuck[2]
        if waited < patience:
            return None
        self._stuck = None
        return waited

    def pending_reply(self, impatient: bool = False) -> dict[str, dict[int, Array]] | None:
        """Round 2 of the current step, once: ``{channel: {listener id: value}}`` for every
        agent it goes to, when round 1 is in (``impatient``: with what is here); else None."""
        if self.rounds == 1 or self.leader or self._replied_k == self.k:
            return None
        if not self.own_inputs_ready():
            return None
        was, self.impatient = self.impatient, self.impatient or impatient
        try:
            if self._wait(self.t, 1):
                return None
            inputs = self._gather(self.t, rounds=1)
        finally:
            self.impatient = was
        sent = self.estimator.reply(self.x, self.h, inputs)
        self._round1, self._replied_k = inputs, self.k
        return {name: self._addressed(self.channels[name], v) for name, v in sent.items()}

    def _addressed(self, c: Channel, values: Array) -> dict[int, Array]:
        """A per-edge channel's values ``(E, ...)`` for the edges whose other end reads it."""
        flag = 'owns' if c.owner_only else MIRROR.get(c.on) if c.on is not None else None
        return {p.agent_id: values[p.slot] for p in self.peers
                if flag is None or p.flags.get(flag, False)}

    # ------------------------------------------------------------------------------ the step
    def begin_step(self) -> Prepared | None:
        """The step's inputs, gathered by :meth:`steps_ready`, or None for a leader, whose
        whole step this is."""
        inputs = self._pending
        assert inputs is not None and self._pending_k == self.k
        t = self.t
        if self.leader:
            self._apply_known_pose(t)
            self.x = self.estimator.propagate(self.x, inputs.delta_R, inputs.displacement)
            self.last = StepInfo(t=t, odometry=inputs.displacement is not None)
            self._pending = None
            self.k += 1
            return None
        if self.cold_since is not None and self.limits.warm_window > 0:
            self._warm_start(t, self.cold_since, inputs)
        return Prepared(t, tuple(self.stale_neighbours(t)), inputs)

    def _warm_start(self, t: float, since: float, inputs: StepInputs) -> None:
        """The method's warm start from the step's inputs (complete edges, or with their masks
        for ``partial_edges``): taken, or tried again next step until ``warm_window`` has passed
        since ``since`` (then it goes on as it is)."""
        tried = self.estimator.warm_start(self.x, inputs)
        if tried is not None and tried.x is None and t - since < self.limits.warm_window:
            self.warm_note = f'trying since t = {since:.3f} s: {tried.note}'
            return
        outcome = 'unavailable' if tried is None else 'refused' if tried.x is None else 'accepted'
        self.warm_starts[outcome] += 1
        self.warm_note = f'{outcome} at t = {t:.3f} s' + (f': {tried.note}' if tried else '')
        self.cold_since = None
        if tried is not None and tried.x is not None:
            self.x = tried.x

    def end_step(self, prepared: Prepared, x: State, diagnostics: dict[str, Array]) -> None:
        """The step's end, from the new state ``x`` (one row) the method's step returned."""
        inputs = prepared.inputs
        if x.is_finite():
            self.x = x
        else:  # cannot happen with validated inputs; never let it reach the estimate
            self.non_finite_steps += 1
            self.x = self.estimator.propagate(self.x, inputs.delta_R, inputs.displacement)
        self.last = StepInfo(t=prepared.t, edges_used=self._edges_used(inputs),
                             stale=prepared.stale, odometry=inputs.displacement is not None,
                             diagnostics={k: v[0] for k, v in diagnostics.items()})
        self._pending = self._round1 = None
        self.k += 1

    def _edges_used(self, inputs: StepInputs) -> int:
        """The edges whose own inputs the step had: all of them for a method that takes
        complete edges only; else those it senses with its measurements and values here."""
        if not type(self.estimator).partial_edges:
            return len(inputs.edges)
        used = inputs.edges.flag('senses').copy()
        cls = type(self.estimator)
        for key in [s.value for s in cls.measures] + [c.name for c in cls.sends if c.round == 1
                                                      and not c.optional and c.sensor is None]:
            used &= inputs.here(key)
        return int(np.count_nonzero(used))

    # ------------------------------------------------------------------------------ gathering
    def _gather(self, t: float, rounds: int | None = None) -> StepInputs:
        """The inputs of the step at ``t`` (rounds up to ``rounds``, default all) with what is
        here, counting what is missing."""
        rounds = self.rounds if rounds is None else rounds
        if rounds == self.rounds and self.rounds > 1 and self._round1 is not None:
            first = self._round1   # round 1 as replied to, with the later rounds added
            later, later_mask = dict(first.edge), dict(first.mask)
            for r in range(2, rounds + 1):
                self._exact_channels(t, r, later, later_mask)
            self._leave_out(later, later_mask)
            return StepInputs(edges=first.edges, agent=first.agent, edge=later,
                              mask=later_mask, t=t)
        h = self.h
        delta_R = self.gyro.increment(t, t + h)[None]
        agent: dict[str, Array] = {DELTA_R: delta_R}
        cls = type(self.estimator)
        if self.odometry_live():
            if self.odometry.covers(t, t + h):
                agent[DISPLACEMENT] = self.odometry.displacement(t, t + h)[None]
            else:
                self.odometry_missing_steps += 1
        if cls.roles.anchor:
            self._anchor_motion(t, agent)
        edges = self._edges
        if self.leader:
            return StepInputs(edges=edges, agent=agent, edge={}, t=t)
        edge: dict[str, Array] = {}
        mask: dict[str, NDArray[np.bool_]] = {}
        if self._instant:
            self._instant_channels(t, agent.get(DISPLACEMENT) is not None, edge, mask)
        else:
            self._own_interpolated(t, edge, mask)
        if cls.peer_odometry == 'links':
            self._peer_motion(t, edge, mask)
        for r in range(1, rounds + 1):
            self._exact_channels(t, r, edge, mask)
        if rounds == 1:
            self._distrust(t, edge, mask)
        inputs = StepInputs(edges=edges, agent=agent, edge=edge, mask=mask, t=t)
        if not cls.partial_edges:
            inputs = inputs.complete(self._complete_keys)
        return inputs

    def _distrust(self, t: float, edge: dict[str, Array],
                  mask: dict[str, NDArray[np.bool_]]) -> None:
        """Leave out what a neighbour sends once it announces a reset: back from a silence
        (``neighbour_timeout``) with a covariance, in units of the prior's, :data:`RESET_JUMP`
        times what it was before and above ``reset_trust`` (a restart, unless its warm start
        made it nearly as sure as before). It is taken back once within RESET_JUMP of this agent's own covariance when
        it announced it: a listener that knows its pose to 1e-4 rad waits for its neighbour
        to know its own to about 3e-4, not 0.1."""
        name, prior = self._cov, self._prior_var
        if name is None or prior is None or name not in edge:
            return
        known, limit = prior > 0, t - self.limits.neighbour_timeout
        for p in self._read_peers:   # (on what it sent, never the stand-in for none yet)
            if p.newest() < limit:
                p.silent = True   # judged at its first value after
                continue
            if not p.values.get(name) or (name in mask and not mask[name][p.slot]):
                continue
            u = float(np.mean(np.diagonal(edge[name][p.slot])[known] / prior[known]))
            if p.reset and u <= p.bar:
                p.bar = math.nan
            elif p.silent and u > self.limits.reset_trust and u > RESET_JUMP * p.known:
                own = np.diagonal(self.covariance())[:len(prior)][known] / prior[known]
                p.bar = max(RESET_JUMP * float(np.mean(own)), 1e-300)
                self.resets[p.name] += 1
            p.silent = False
            p.known = u
            if p.reset:
                self.distrusted[p.name] += 1
        self._leave_out(edge, mask)

    def _leave_out(self, edge: dict[str, Array], mask: dict[str, NDArray[np.bool_]]) -> None:
        """Mask the values of the neighbours that announced a reset (:meth:`_distrust`)."""
        for p in self._read_peers:
            if p.reset:
                for key in self.channels:
                    if key in edge:
                        m = mask.setdefault(key, np.ones(len(self.peers), dtype=bool))
                        m[p.slot] = False

    def _anchor_motion(self, t: float, agent: dict[str, Array]) -> None:
        """The anchor's motion over the step as this agent knows it, and the anchor's flags;
        without the anchor's odometry, taken as still (counted)."""
        h = self.h
        displacement = agent.get(DISPLACEMENT, np.zeros((1, 3)))
        if self.is_anchor:
            a_R, a_d = agent[DELTA_R], displacement
        elif self.anchor_odometry is not None and self.anchor_odometry.covers(t, t + h):
            a_R = self.anchor_odometry.rotation(t, t + h)[None]
            a_d = self.anchor_odometry.displacement(t, t + h)[None]
        else:
            self.anchor_still_steps += 1
            a_R, a_d = np.eye(3)[None], np.zeros((1, 3))
        agent.update({ANCHOR_DELTA_R: a_R, ANCHOR_DISPLACEMENT: a_d,
                      IS_ANCHOR: np.array([self.is_anchor]),
                      PINNED: np.array([self.is_anchor and self.spec.pinned])})

    def _own_interpolated(self, t: float, edge: dict[str, Array],
                          mask: dict[str, NDArray[np.bool_]]) -> None:
        """Each own point sensor's measurement of each edge it measures at ``t``, between
        the samples around t; estimated bearing rates from the bearings."""
        n = len(self.peers)
        for sensor, by_target in self.own.items():
            flag = self._own_flag[sensor]
            values, here = np.zeros((n, 3)), np.zeros(n, dtype=bool)
            for p in self.peers:
                hist = by_target.get(p.agent_id)
                if hist is None or not (flag is None or p.flags.get(flag)):
                    continue
                v, _ = hist.interpolate(t, lambda s_, t_: self.gyro.increment(t_, s_))
                if v is None:
                    self.missing[sensor.value] += 1
                    continue
                values[p.slot] = v / np.linalg.norm(v) if sensor is Sensor.BEARINGS else v
                here[p.slot] = True
            edge[sensor.value], mask[sensor.value] = values, here
        if self._rate_filter is not None:
            self._estimated_rates(t, edge, mask)

    def _estimated_rates(self, t: float, edge: dict[str, Array],
                         mask: dict[str, NDArray[np.bool_]]) -> None:
        """Without a bearing-rate sensor: each edge's rate at ``t`` from its bearings at ``t``
        and at the previous step, as the batch simulator forms them."""
        filt = self._rate_filter
        assert filt is not None
        b, here = edge[Sensor.BEARINGS.value], mask[Sensor.BEARINGS.value]
        n = len(self.peers)
        dR = np.tile(np.eye(3), (n, 1, 1))
        for row in np.flatnonzero(here & ~np.isnan(filt.t_prev)).tolist():
            if self.gyro.covers(float(filt.t_prev[row]), t):
                dR[row] = self.gyro.increment(float(filt.t_prev[row]), t)
            else:   # the rotation since the previous bearing is unknown: start again
                filt.t_prev[row], filt.started[row] = np.nan, False
        derotated, have = filt.update(t, b, dR, here)
        omega = so3.log_small(self.gyro.increment(t, t + self.h)[None])[0] / self.h
        edge[Sensor.BEARING_RATES.value] = np.where(have[:, None],
                                                    derotated - np.cross(omega, b), 0.0)
        mask[Sensor.BEARING_RATES.value] = have

    def _peer_motion(self, t: float, edge: dict[str, Array],
                     mask: dict[str, NDArray[np.bool_]]) -> None:
        """Each edge's other end's motion over the step, from its odometry."""
        n, h = len(self.peers), self.h
        rot, disp = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
        here = np.zeros(n, dtype=bool)
        for p in self.peers:
            odo = p.odometry
            if odo is not None and odo.covers(t, t + h):
                rot[p.slot], disp[p.slot] = odo.rotation(t, t + h), odo.displacement(t, t + h)
                here[p.slot] = True
            else:
                self.missing[PEER_ODOMETRY] += 1
        edge[PEER_DELTA_R], edge[PEER_DISPLACEMENT], mask[PEER_ODOMETRY] = rot, disp, here

    def _peer_rotation(self, peer: Peer) -> Callable[[float, float], Array]:
        """``rotate(s, t) = R(t)ᵀ R(s)`` of a sender's measurement: its odometry's, or none
        (a method that does not read it: the value is taken as it is)."""
        odo = peer.odometry
        if odo is None:
            return lambda s, t: np.eye(3)

        def rotate(s: float, t: float) -> Array:
            return odo.rotation(t, s) if s >= t else odo.rotation(s, t).T
        return rotate

    def _exact_channels(self, t: float, round_: int, edge: dict[str, Array],
                        mask: dict[str, NDArray[np.bool_]]) -> None:
        """Round ``round_``'s 'exact' channels and the senders' measurements of this agent,
        per edge: the value of ``t`` (interpolated for measurements), else the sender's
        newest earlier one carried to t, else left out; optional ones never wait; channels not
        read at t are their newest value."""
        est, n = self.estimator, len(self.peers)
        partial = type(est).partial_edges
        chans = self._exact[round_]
        if not chans:
            return
        for c in chans:
            edge[c.name] = np.zeros((n,) + c.shape)
            mask[c.name] = np.zeros(n, dtype=bool)
        due = {c.name for c in chans if not c.optional and c.sensor is None
               and est.due(c.name, t, self.h)}
        for p in self.peers:
            core = [c.name for c in chans if c.name in due and not c.owner_only
                    and reads(p.flags, c)]
            found = {name: v for name in core
                     if name in p.values and (v := p.values[name].at(t)[0]) is not None}
            if core and len(found) < len(core):
                carried = self._carry(p, core, t)   # late or lost: carried to t
                if carried is not None:
                    found, self.carried = carried, self.carried + 1
                else:
                    for name in core:
                        if name not in found:
                            self.missing[name] += 1
            for c in chans:
                if not reads(p.flags, c):   # not expected on the edge: here, as none is missing
                    mask[c.name][p.slot] = partial
                    continue
                hist = p.values.get(c.name)
                if c.sensor is not None:
                    v, _ = (hist.interpolate(t, self._peer_rotation(p)) if hist
                            else (None, False))
                    if v is None:
                        self.missing[c.name] += 1
                elif c.name in found:
                    v = found[c.name]
                elif c.optional:
                    v = self._optional(p, c, t)
                elif c.name not in due:
                    v = p.latest(c.name)   # not read now: the newest
                else:   # owner-only: its own value, or carried, or none
                    v = hist.at(t)[0] if hist else None
                    if v is None:
                        v = (self._carry(p, [c.name], t) or {}).get(c.name)
                        if v is None:
                            self.missing[c.name] += 1
                if v is not None:
                    edge[c.name][p.slot], mask[c.name][p.slot] = v, True

    def _optional(self, peer: Peer, c: Channel, t: float) -> Array:
        """An optional value at ``t``: the sender's of t, else its newest earlier one carried
        to t (or as it is), else the method's stand-in; never waited for, not counted."""
        hist = peer.values.get(c.name)
        if hist:
            v = hist.at(t)[0]
            if v is None:
                v = (self._carry(peer, [c.name], t) or {}).get(c.name)
            if v is None and (newest := hist.newest(t)) is not None:
                v = newest[1]
            if v is not None:
                return v
        return self.estimator.missing(c.name)

    def _carry(self, peer: Peer, names: Sequence[str], t: float) -> dict[str, Array] | None:
        """The sender's channels ``names`` at ``t`` from its newest instant ``t_s < t`` that
        has them all, no older than ``neighbour_timeout``, carried over ``[t_s, t]`` by the
        method (:meth:`Estimator.carry`) with what this agent knows of the motion; None when
        nothing can be carried."""
        for stamp, values in peer.instants(names, not_after=t):
            if stamp >= t - SAME:
                continue
            if stamp < t - self.limits.neighbour_timeout:
                return None   # too old: its estimator is silent (its sensors may not be)
            out = self.estimator.carry(values, self._motion(peer, stamp, t))
            return None if out is None or out.keys() < set(names) else out
        return None

    def _motion(self, peer: Peer, s: float, t: float) -> Motion:
        """What this agent knows of the motion over ``[s, t]``."""
        own = self.gyro.increment(s, t) if self.gyro.covers(s, t) else None
        odo = peer.odometry
        peer_R = peer_d = anchor_R = anchor_d = None
        if odo is not None and odo.covers(s, t):
            peer_R, peer_d = odo.rotation(s, t), odo.displacement(s, t)
        anchor = self.odometry if self.is_anchor else self.anchor_odometry
        if type(self.estimator).roles.anchor and anchor is not None and anchor.covers(s, t):
            anchor_R, anchor_d = anchor.rotation(s, t), anchor.displacement(s, t)
        return Motion(own, peer_R, peer_d, anchor_R, anchor_d)

    # 'instant' pairing (:class:`base.Channel`): the leader-follower methods' exchange.
    def _instant_channels(self, t: float, moving: bool, edge: dict[str, Array],
                          mask: dict[str, NDArray[np.bool_]]) -> None:
        """Each neighbour's 'instant' channels of its newest instant at or before ``t``, with the
        own measurement paired; a neighbour without them all sits the step out (masked)."""
        names = self._required_names
        sensors = list(self.own)
        until = self._until(t + self.h)
        exchange = self.exchange is not None
        rows: list[tuple[Peer, list[Array], dict[str, Array], float]] = []
        limit = t - self.limits.neighbour_timeout
        for p in self.peers:
            if any(name not in p.values or p.values[name].newest_stamp < limit for name in names):
                continue   # silent: a required channel never sent, or not since neighbour_timeout
            latest = {name: hist.samples[-1][1] for name, hist in p.values.items() if hist}
            t_s, sent = t, latest
            if not moving and exchange:   # its values of its instant ≤ t
                fixed = p.at_one_instant(names, not_after=t)
                if fixed is None:
                    self.unpaired += 1   # its instant left the history: its newest, counted
                else:
                    sent = {**latest, **fixed[1]}
                    for name in self._optional_names:
                        if (hist := p.values.get(name)) and (newest := hist.newest(t)):
                            sent[name] = newest[1]
            elif moving:   # its values of one instant, paired with the own at that instant
                own = self.own[sensors[0]].get(p.agent_id) if sensors else None
                newest_own = own.newest_stamp if own else t
                same = p.at_one_instant(names, not_after=min(t, newest_own))
                if same is None:
                    self.unpaired += 1
                    if p.at_one_instant(names, not_after=math.inf) is not None:
                        continue   # this step without it: exact, unlike values of two instants
                    t_s = max((p.values[name].newest_stamp for name in latest), default=t)
                else:
                    t_s, sent = same[0], {**latest, **same[1]}
                t_s = min(t_s, t)
            measured = [self.body_measurement(s, p.agent_id, t, at=t_s if moving else None,
                                              until=until) for s in sensors]
            if any(v is None for v in measured):
                continue
            rows.append((p, measured, sent, t_s))   # type: ignore[arg-type]
        n = len(self.peers)
        used = [p.slot for p, _, _, _ in rows]
        for k, s in enumerate(sensors):
            edge[s.value] = self._column([m[k] for _, m, _, _ in rows], used, (3,))
        for c in self.channels.values():
            edge[c.name] = self._column([sent[c.name] if c.name in sent
                                         else self.estimator.missing(c.name)
                                         for _, _, sent, _ in rows], used, c.shape)
        first = names[0] if names else None
        edge[HELD] = self._column([np.array([
            self.own[sensors[0]][p.agent_id].interval(self.h) if sensors else 1.0,
            p.values[first].interval(self.h) if first else 1.0]) for p, _, _, _ in rows],
            used, (2,), fill=1.0)
        if moving:
            backs = []
            for _, _, _, t_s in rows:
                back = self.moved_back(t, t_s) if t_s < t else None
                if back is None and t_s < t:
                    self.unpaired += 1
                backs.append(self.x.p_hat[0] if back is None else back)
            edge[P_OWN] = self._column(backs, used, (3,))
        if len(rows) < n:   # (every neighbour there: nothing to mask)
            here = np.zeros(n, dtype=bool)
            here[used] = True
            for key in [s.value for s in sensors] + list(self.channels):
                mask[key] = here

    def _column(self, values: list[Array], rows: list[int], shape: tuple[int, ...],
                fill: float = 0.0) -> Array:
        """``values`` of the edges ``rows`` as one ``(E, *shape)`` array, ``fill`` elsewhere."""
        if len(rows) == len(self.peers):
            return np.array(values, dtype=float).reshape((len(rows),) + shape)
        out = np.full((len(self.peers),) + shape, fill)
        if rows:
            out[rows] = values
        return out

    def _until(self, t: float) -> float:
        """The newest own measurement a step or message at ``t`` may use (a simulation's
        exchange fixes it; a robot uses anything)."""
        return t if self.exchange is not None else math.inf

    def body_measurement(self, sensor: Sensor, agent_id: int, t: float,
                         at: float | None = None, until: float = math.inf) -> Array | None:
        """The own ``sensor``'s measurement of ``agent_id`` rotated to the body frame at
        ``t`` with the gyro, or None (none, or older than ``sensor_timeout``): the newest
        sample the gyro can bridge (a static fleet: every sample sees the same world vector),
        or, given ``at``, the one measured at ``at`` (moving): interpolated between the two
        samples around it (rotated to t, then a normalised linear interpolation), the newest
        held after it. ``until``: no sample measured after it."""
        hist = self.own.get(sensor, {}).get(agent_id)
        if not hist:
            return None
        timeout = self.limits.sensor_timeout
        if at is None:
            for stamp, b in reversed(hist.samples):
                if stamp > until + SAME:
                    continue
                if t - stamp > timeout:
                    return None
                if self.gyro.covers(stamp, t):
                    return self.gyro.increment(t, stamp) @ b   # R(t)ᵀ R(t_b) b(t_b)
            return None
        later: tuple[float, Array] | None = None
        for stamp, b in reversed(hist.samples):   # the newest sample the gyro can bridge
            if t - stamp > timeout:
                return None
            if not self.gyro.covers(stamp, t):
                continue
            b_t = self.gyro.increment(t, stamp) @ b
            if stamp > at + SAME:
                later = (stamp, b_t)
                continue
            if later is None or stamp >= at - SAME:
                return b_t
            w = (at - stamp) / (later[0] - stamp)
            mixed = (1.0 - w) * b_t + w * later[1]
            return mixed / np.linalg.norm(mixed)
        return later[1] if later is not None else None

    def moved_back(self, t: float, t_s: float) -> Array | None:
        """``p̂_i`` moved back from ``t`` to ``t_s <= t`` by the own odometry,
        ``p̂_i(t) - R̂_i(t) R(t)ᵀ R(t_s) δ(t_s → t)`` (:data:`base.P_OWN`); None without odometry
        over that span."""
        if not (self.odometry_live() and self.odometry.covers(t_s, t)
                and self.gyro.covers(t_s, t)):
            return None
        delta = self.odometry.displacement(t_s, t)
        return self.x.p_hat[0] - self.x.R_hat[0] @ (self.gyro.increment(t, t_s) @ delta)

    def _apply_known_pose(self, t: float) -> None:
        """A leader's newest known pose up to the step's end, carried to ``t`` by the gyro
        and, moving, the odometry (waited for until both cover the way)."""
        until = self._until(t + self.h)
        usable = [pose for pose in self._known_poses if pose[0] <= until + SAME]
        if not usable:
            return
        stamp, R, p = max(usable, key=lambda pose: pose[0])
        moving = self.odometry_live()
        if self.gyro.covers(stamp, t) and (not moving or self.odometry.covers(stamp, t)):
            R_t = R @ self.gyro.increment(stamp, t)
            if moving:
                p = (p + R @ self.odometry.displacement(stamp, t) if stamp <= t
                     else p - R_t @ self.odometry.displacement(t, stamp))
            # A copy: with_known_pose writes in place, and values netsim sent share arrays.
            self.x = self.estimator.with_known_pose(self.x.rows(slice(None)), np.zeros(1, int),
                                                    R_t[None], p[None])
            newer = [pose for pose in self._known_poses if pose[0] > stamp]
            self._known_poses.clear()
            self._known_poses.extend(newer)

    # ------------------------------------------------------------------------------ outputs
    def measured_at(self, t: float) -> bool:
        """A sample measured at ``t`` (or later) has arrived from every agent this agent
        measures: what it sends at ``t`` is then exact for a moving fleet."""
        return all(hist.newest_stamp >= t - SAME for by_target in self.own.values()
                   for hist in by_target.values() if hist)

    @property
    def withholding(self) -> bool:
        """Whether it publishes nothing (estimate, channels): cold, until its warm start is
        decided. A cold estimate costs its listeners more than its silence (issue 29: a
        restarted agent_4's first values took agent_5 from 8e-5 to 0.16-0.61 rad), and a
        silent neighbour is left out of their steps, not waited for."""
        return self.cold_since is not None and self.limits.warm_window > 0

    def outbox(self) -> dict[str, object]:
        """What this agent sends in round 1, formed at the state time: per-agent channels as
        arrays, per-edge ones as ``{listener id: value}`` (measurements: on the sensor topics)."""
        cls = type(self.estimator)
        t = self.t
        ids: list[int] | None = None   # the listeners of the per-edge channels (None: the edges')
        if cls.links == 'sensing':   # to every agent it measures, from that measurement
            sensor = cls.partner_sensor
            ids, vectors = [], []
            at = t if self.odometry_live() else None
            for agent_id in (self.own.get(sensor, {}) if sensor is not None else {}):
                v = self.body_measurement(sensor, agent_id, t, at=at,  # type: ignore[arg-type]
                                          until=self._until(t))
                if v is not None:
                    ids.append(agent_id)
                    vectors.append(v)
            sent = self.estimator.outbox(self.x, np.zeros(len(ids), dtype=np.intp),
                                         np.array(vectors).reshape(-1, 3))
        else:
            n = len(self.peers)
            sent = self.estimator.outbox(self.x, np.zeros(n, dtype=np.intp), np.zeros((n, 3)),
                                         slot=np.arange(n, dtype=np.intp))
        return {c.name: sent[c.name][0] if c.per != 'edge'
                else self._addressed(c, sent[c.name]) if ids is None
                else dict(zip(ids, sent[c.name]))
                for c in cls.sends if c.round == 1 and c.sensor is None}

    def sends_now(self, name: str, publish_grid: bool) -> bool:
        """Channel ``name`` goes out after this step: 'exact' when a listener's step reads it at
        this instant, 'instant' on the publish grid."""
        if self.channels[name].pairing == 'exact':
            return self.estimator.due(name, self.t, self.h)
        return publish_grid

    def covariance(self) -> Array:
        """``(6, 6)`` the pose covariance (position, then rotation); zeros for a method that
        keeps none."""
        P = self.estimator.covariance(self.x)
        return np.zeros((6, 6)) if P is None else P[0]

    def conditioning(self) -> Array | None:
        """Eigenvalues of the method's local matrix (:meth:`Estimator.conditioning`) from the
        current own measurements, or None (no such matrix, or a measurement is missing)."""
        sensor = type(self.estimator).partner_sensor
        if sensor is None or not self.peers:
            return None
        vectors = [self.body_measurement(sensor, p.agent_id, self.t) for p in self.peers]
        if any(v is None for v in vectors):
            return None
        matrix = self.estimator.conditioning(np.array(vectors),
                                             np.array([p.k for p in self.peers]))
        return None if matrix is None else np.linalg.eigvalsh(matrix).astype(np.float64)
