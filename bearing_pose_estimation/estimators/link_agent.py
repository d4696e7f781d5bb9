"""One robot of a ``links = 'communication'`` method (De Carli et al.), independent of ROS: the
logic of its estimator node.

The step ``[t, t+h]`` of such a method needs, besides its own gyro, odometry and relative
positions, each communication neighbour j's odometry over the same step (it predicts
``ⁱp̂_ij`` with ``δ_j``), j's measurement of this robot at t (where j senses it) and j's
channels formed at t (the method's :meth:`base.Estimator.due` ones: De Carli's ``ẑ_j`` and
relative yaws at the consensus ticks, ``p̂_j`` at the position ticks). Every input is paired
at its instant, never extrapolated (the notes' §8, timing pitfalls): relative positions are
interpolated between the samples around t after rotating them to the body frame at t (own:
with the gyro; j's: with j's odometry), odometry is integrated exactly.

So a step waits until every neighbour's inputs for it are here, or known not to come:

- a channel value of j stamped t is lost once j has sent a newer one;
- j is silent (nothing newer than ``t - neighbour_timeout``), or its odometry is that far
  behind: j is left out of the step;
- this robot's own sensors are ``link_wait`` (:class:`agent.Limits`) ahead of the step: it
  stops waiting and takes what is here (a late neighbour delays the estimate by up to that
  much, no more; what comes later than that is lost);
- what is late or lost is replaced, when the method can, by j's newest values carried to t
  with j's odometry (:meth:`base.Estimator.carry`; counted in ``carried``): exact at the
  method's fixed point, so a slow link costs only transient accuracy;
- :meth:`LinkAgentEstimator.advance` with ``impatient=True`` (the node's wall-clock patience,
  for when nothing moves at all: two robots that lost each other's values under a lockstep
  clock) leaves out whatever is still missing.

What is left out is passed to the step as missing (:class:`base.LinkInputs`): the method
decides (De Carli: an edge without j's odometry sits the step out and its relative estimates
restart from the next measurements; without j's channels it leaves the consensus and the
position correction for that tick). Causes are counted in :attr:`LinkAgentEstimator.missing`.
"""
from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..core.odometry import OdometryBuffer
from .agent import AgentEstimator, Limits, TimedAgent, _Prepared
from .agent import _finite_max_norm, _twist_problem, _vector_problem as _unit_problem
from .base import Channel, Edges, Estimator, LinkInputs, State, StepInputs, owns_pair

Array = NDArray[np.float64]
# Samples of relative positions and channel values kept per source: enough for a step that
# waits link_wait (0.25 s: 50 samples at 200 Hz) and then looks back.
_HISTORY = 256
# Relative positions beyond this [m] are absurd (a camera with depth sees metres).
MAX_RANGE_M = 1e4


@dataclass
class Link:
    """What this robot knows of one communication neighbour j."""

    name: str
    agent_id: int
    senses: bool       # this robot measures j
    sensed_by: bool    # j measures this robot
    owns: bool         # this robot keeps the pair's shared state
    odometry: OdometryBuffer
    measured: deque[tuple[float, Array]] = field(default_factory=lambda: deque(maxlen=_HISTORY))
    theirs: deque[tuple[float, Array]] = field(default_factory=lambda: deque(maxlen=_HISTORY))
    history: dict[str, deque[tuple[float, Array]]] = field(default_factory=dict)

    def newest(self) -> float:
        """The newest stamp of anything j sent (channels, its measurement, its odometry)."""
        stamps = [h[-1][0] for h in self.history.values() if h]
        stamps += [self.theirs[-1][0]] if self.theirs else []
        if not self.odometry.empty:
            stamps.append(self.odometry.end)
        return max(stamps, default=-np.inf)

    def value_at(self, channel: str, t: float) -> tuple[Array | None, bool]:
        """``(value, decided)``: j's value of ``channel`` stamped ``t``; or None with
        ``decided`` when it will not come (j already sent a newer one)."""
        hist = self.history.get(channel)
        if not hist:
            return None, False
        for stamp, value in reversed(hist):
            if abs(stamp - t) < 1e-9:
                return value, True
            if stamp < t:
                break   # stamps increase (add_neighbour): the rest are older still
        return None, hist[-1][0] > t + 1e-9


def _interpolated(samples: deque[tuple[float, Array]], t: float,
                  rotate: Callable[[float, float], Array]) -> tuple[Array | None, bool]:
    """``(value, decided)`` of relative-position ``samples`` at ``t``: the sample at t, or the
    two around it rotated to the body frame at t (``rotate(s, t) = R(t)ᵀ R(s)``) and
    interpolated linearly; None with ``decided`` once a sample after t is here and none
    before, or no rotation covers the span."""
    before = after = None
    for stamp, v in reversed(samples):
        if abs(stamp - t) < 1e-9:
            return v, True
        if stamp > t:
            after = (stamp, v)
        else:
            before = (stamp, v)
            break
    if after is None:
        return None, False
    if before is None:
        return None, True
    try:
        a = rotate(before[0], t) @ before[1]
        b = rotate(after[0], t) @ after[1]
    except ValueError:   # no rotation data over the span
        return None, True
    w = (t - before[0]) / (after[0] - before[0])
    return (1.0 - w) * a + w * b, True


def _bounded_problem(v: Array, bound: float) -> str | None:
    """Why ``v`` is not a finite 3-vector with every entry within ``±bound``, or None."""
    if v.shape != (3,):
        return 'non_finite'
    finite, largest, _ = _finite_max_norm(v)
    if not finite:
        return 'non_finite'
    return 'absurd_value' if largest > bound else None


def _rotation_of(odometry: OdometryBuffer) -> Callable[[float, float], Array]:
    """``rotate(s, t) = R(t)ᵀ R(s)`` from a neighbour's odometry (either order)."""
    def rotate(s: float, t: float) -> Array:
        return odometry.rotation(t, s) if s >= t else odometry.rotation(s, t).T
    return rotate


class LinkAgentEstimator(TimedAgent):
    """One robot of a ``links = 'communication'`` method fed by time-stamped inputs (module
    docstring); the time rules of its own gyro and odometry are :class:`agent.AgentEstimator`'s.

    Args:
        estimator: the method with its gains.
        agent_id: this robot's id.
        links: ``(name, agent_id, senses, sensed_by)`` of each communication neighbour, in the
            order of the method's link slots (the batch simulator's: ids ascending).
        step, R0, p0, t0, known_ids, limits: as :class:`agent.AgentEstimator`.
    """

    def __init__(self, estimator: Estimator, agent_id: int,
                 links: list[tuple[str, int, bool, bool]], step: float, R0: Array, p0: Array,
                 t0: float = 0.0, gyro_horizon: float = 2.0, known_ids: set[int] | None = None,
                 limits: Limits = Limits()) -> None:
        super().__init__(estimator, agent_id, step, R0, p0, t0=t0, gyro_horizon=gyro_horizon,
                         known_ids=known_ids, limits=limits)
        self.links = [Link(name, int(j), bool(s), bool(b),
                           owns=bool(owns_pair(agent_id, j, s, b)),
                           odometry=OdometryBuffer(t0, gyro_horizon))
                      for name, j, s, b in links]
        self._by_id = {link.agent_id: link for link in self.links}
        self._senses = np.array([lk.senses for lk in self.links], dtype=bool)
        self._sensed_by = np.array([lk.sensed_by for lk in self.links], dtype=bool)
        self._owns = np.array([lk.owns for lk in self.links], dtype=bool)
        self.missing: Counter[str] = Counter()   # inputs left out of a step, by what
        self.waits: Counter[str] = Counter()     # attempts that waited, by what was awaited
        self.awaited: str | None = None          # what the latest of them waited for
        self.carried = 0   # neighbour values of an earlier instant carried to the step's
        self.impatient = False
        self._pending: StepInputs | None = None
        self._pending_k = -1

    @property
    def neighbours(self) -> list[Link]:
        """The communication neighbours (the node subscribes to their topics)."""
        return self.links

    def measures_me(self, link: Link) -> bool:
        """j's sensor topic carries a measurement of this robot that the step reads."""
        return link.sensed_by

    def odometry_sources(self) -> list[tuple[str, int]]:
        """Whose odometry this robot reads (``(name, id)``): every communication neighbour's
        (the prediction of what it senses of j uses j's motion)."""
        return [(lk.name, lk.agent_id) for lk in self.links]

    def channel_sources(self, channel: str) -> list[Link]:
        """The neighbours whose values of ``channel`` this robot reads: every one."""
        return self.links

    def _clear_inputs(self, reset_estimate: bool) -> None:
        self._pending = None
        for link in self.links:
            link.measured.clear()
            if reset_estimate:
                link.theirs.clear()
                link.history.clear()
                link.odometry.reset(self.t0)

    # ------------------------------------------------------------------------------ inputs
    def add_relative_positions(self, stamp: float, ids: NDArray[np.integer],
                               vectors: Array) -> list[str]:
        """Own measurements ``ⁱp_ij`` (body frame [m]) of the robots ``ids`` at ``stamp``;
        points of robots this one does not sense are ignored. Returns the causes of the
        rejected points."""
        return self._add_own_points(stamp, ids, vectors, self._vector_problem,
                                    lambda link: link.measured, np.copy)

    def _add_own_points(self, stamp: float, ids: NDArray[np.integer], vectors: Array,
                        problem_of: Callable[[Array], str | None],
                        history: Callable[[Link], deque[tuple[float, Array]]],
                        kept: Callable[[Array], Array]) -> list[str]:
        """One own sensor message, a vector per sensed robot: each point of a robot this one
        senses is checked (``problem_of``, then its stamp against the newest in its
        ``history(link)``) and kept as ``kept(v)``; others are ignored (unknown ids
        rejected). Returns the causes of the rejected points."""
        if not np.isfinite(stamp):
            return ['non_finite'] * len(ids)
        if stamp > self.gyro.end + self.limits.max_future:
            return ['future_stamp'] * len(ids)
        rejected = []
        for j, v in zip(np.asarray(ids).tolist(), np.asarray(vectors, dtype=float)):
            link = self._by_id.get(int(j))
            if link is None or not link.senses:
                if int(j) == self.agent_id or (self.known_ids is not None
                                               and int(j) not in self.known_ids):
                    rejected.append('unknown_id')
                continue
            hist = history(link)
            problem = problem_of(v)
            if problem is None and hist and stamp <= hist[-1][0]:
                problem = 'out_of_order'
            if problem is None:
                hist.append((float(stamp), kept(v)))
            else:
                rejected.append(problem)
        return rejected

    def add_neighbour_measurements(self, agent_id: int, stamp: float,
                                   ids: NDArray[np.integer], vectors: Array) -> str | None:
        """Neighbour j's relative positions at ``stamp`` (its sensor's message): the point of
        this robot, when the step reads j's measurement of it (:meth:`measures_me`), is
        kept."""
        link = self._by_id.get(agent_id)
        if link is None:
            return 'unknown_id'
        if not self.measures_me(link) or not np.isfinite(stamp):
            return 'non_finite' if self.measures_me(link) else None
        mine = np.flatnonzero(np.asarray(ids) == self.agent_id)
        if not mine.size:
            return None
        v = np.asarray(vectors, dtype=float)[mine[0]]
        problem = self._vector_problem(v)
        if problem is None and link.theirs and stamp <= link.theirs[-1][0]:
            problem = 'out_of_order'
        if problem is not None:
            return problem
        link.theirs.append((float(stamp), v.copy()))
        return None

    def add_neighbour_odometry(self, agent_id: int, stamp: float, v: Array,
                               omega: Array) -> str | None:
        """Neighbour j's odometry sample (interval-average twist, :mod:`core.odometry`)."""
        link = self._by_id.get(agent_id)
        if link is None:
            return 'unknown_id'
        return self._add_twist(link.odometry, stamp, v, omega)

    def _add_twist(self, odometry: OdometryBuffer, stamp: float, v: Array,
                   omega: Array) -> str | None:
        """Another robot's odometry sample into ``odometry``, or why not: non-finite, absurd,
        out of order; its clock restarted or a gap: the integration restarts."""
        v, omega = np.asarray(v, dtype=float), np.asarray(omega, dtype=float)
        problem = _twist_problem(stamp, v, omega, self.limits)
        if problem is not None:
            return problem
        end = odometry.end
        if stamp <= end:
            if stamp < end - self.limits.jump_back:   # j restarted its clock
                odometry.reset(stamp)
                return None
            return 'out_of_order'
        if stamp - end > self.limits.max_gyro_gap:
            odometry.reset(stamp)
            return 'odometry_gap'
        odometry.add_twist(stamp, v, omega)
        return None

    def add_neighbour(self, agent_id: int, stamp: float,
                      values: dict[str, object]) -> str | None:
        """A message of neighbour j with its values of some channels at its state time
        ``stamp`` (per-edge ones as ``{listener id: value}``); used whole or rejected whole."""
        link = self._by_id.get(agent_id)
        if link is None:
            return 'unknown_id'
        mine: dict[str, Array] = {}
        for name, value in values.items():
            channel = self.channels.get(name)
            if channel is None or channel.sensor is not None:   # sensor readings: see above
                return 'unknown_channel'
            if channel.per == 'edge':
                value = value.get(self.agent_id) if isinstance(value, dict) else None
                if value is None:
                    continue   # nothing for us: a pair j does not own
            v = np.asarray(value, dtype=float)
            if v.shape != channel.shape:
                return 'malformed'
            mine[name] = v
        if not mine:
            return 'not_seen'
        if not (np.isfinite(stamp) and all(np.isfinite(v).all() for v in mine.values())):
            return 'non_finite'
        if any(float(np.max(np.abs(v))) > MAX_RANGE_M for v in mine.values()):
            return 'absurd_value'
        for name, v in mine.items():
            # The owner's zeros: no value of the pair yet (the step takes them as such).
            none_yet = self.channels[name].owner_only and not link.owns and not np.any(v)
            if self.channels[name].unit and not none_yet:
                problem = _unit_problem(v, self.limits.unit_tolerance)
                if problem is not None:
                    return problem
        if stamp > self.gyro.end + self.limits.max_future:
            return 'future_stamp'
        for name, v in mine.items():
            hist = link.history.setdefault(name, deque(maxlen=_HISTORY))
            if hist and stamp <= hist[-1][0] - 1e-9:
                if hist[-1][0] - stamp > self.limits.jump_back:
                    hist.clear()   # j restarted its clock
                else:
                    return 'out_of_order'
            if hist and abs(stamp - hist[-1][0]) < 1e-9:
                if np.any(v) or not self.channels[name].owner_only:
                    hist[-1] = (float(stamp), v)   # (an owner's "none yet" undoes no value)
            else:
                hist.append((float(stamp), v))
        return None

    def _vector_problem(self, v: Array) -> str | None:
        return _bounded_problem(v, MAX_RANGE_M)

    # ------------------------------------------------------------------------------ stepping
    def stale_neighbours(self, t: float) -> list[str]:
        """Neighbours silent for longer than ``neighbour_timeout`` before ``t``."""
        limit = t - self.limits.neighbour_timeout
        return [link.name for link in self.links if link.newest() < limit]

    def _awaiting(self, t: float, due: list[str], stale: set[str]) -> str | None:
        """What the step at ``t`` still waits for (the first thing found), or None when
        every input is here or known not to come: a cheap check, run on every arriving
        input, before :meth:`_gather` builds the inputs."""
        h, tol = self.h, 1e-9
        own_late = self.gyro.end - t > self.limits.sensor_timeout
        behind = self.gyro.end - t > self.limits.link_wait
        for link in self.links:
            if link.senses and not own_late and not (link.measured
                                                     and link.measured[-1][0] >= t - tol):
                return 'own_measurement'
            if link.name in stale or behind:
                continue
            odo = link.odometry
            if not odo.covers(t, t + h) and odo.end >= t - self.limits.neighbour_timeout:
                return 'odometry'
            if link.sensed_by and not (link.theirs and link.theirs[-1][0] >= t - tol):
                return 'their_measurement'
            for name in due:
                if link.owns and self.channels[name].owner_only:
                    continue
                hist = link.history.get(name)
                if not (hist and hist[-1][0] >= t - tol):
                    return name
        return None

    def _gather(self, t: float, final: bool) -> StepInputs | None:
        """The inputs of the step at ``t``, or None while some may still come (``final``:
        whatever is missing now is left out)."""
        est, h = self.estimator, self.h
        stale = set(self.stale_neighbours(t))
        # Optional channels (the covariance) are never waited for: the newest value, or
        # the method's stand-in (Estimator.missing).
        due = [c.name for c in est.sends
               if c.sensor is None and not c.optional and est.due(c.name, t, h)]
        if not final:
            awaited = self._awaiting(t, due, stale)
            if awaited is not None:
                self._wait_for(awaited)
                return None
        n = len(self.links)
        y = np.zeros((n, 3))
        theirs = np.zeros((n, 3))
        other_R = np.tile(np.eye(3), (n, 1, 1))
        other_d = np.zeros((n, 3))
        flags = {name: np.zeros(n, dtype=bool)
                 for name in ('measured', 'their_measured', 'present', 'fresh')}
        received = {c.name: np.zeros((n,) + c.shape) for c in est.sends}
        for e, link in enumerate(self.links):   # everything here is decided: take what is
            if link.senses:
                v, _ = _interpolated(link.measured, t,
                                     lambda s_, t_: self.gyro.increment(t_, s_))
                if v is not None:
                    y[e], flags['measured'][e] = v, True
            if link.odometry.covers(t, t + h):
                other_R[e] = link.odometry.rotation(t, t + h)
                other_d[e] = link.odometry.displacement(t, t + h)
                flags['present'][e] = True
            if link.sensed_by:
                v, _ = _interpolated(link.theirs, t, _rotation_of(link.odometry))
                if v is not None:
                    theirs[e], flags['their_measured'][e] = v, True
            wanted = [name for name in due
                      if not (link.owns and self.channels[name].owner_only)]
            values: dict[str, Array | None] = {name: link.value_at(name, t)[0]
                                               for name in wanted}
            # The link is fresh when j's own values are here; an owner-only value that is
            # missing only leaves the pair out of what needs it (zeros).
            core = [name for name in wanted if not self.channels[name].owner_only]
            fresh = all(values[name] is not None for name in core)
            if not fresh:   # late or lost: j's newest values carried to t, if the method can
                carried = self._carried(link, core, t)
                if carried is not None:
                    values.update(carried)
                    fresh = True
                    self.carried += 1
            for name in wanted:
                if values[name] is None and self.channels[name].owner_only:
                    values.update(self._carried(link, [name], t) or {})
            for name, v in values.items():
                if v is not None:
                    received[name][e] = v
            # Values not due this step: the newest (unused by the step, kept finite).
            for c in est.sends:
                if c.name not in due and c.sensor is None and link.history.get(c.name):
                    received[c.name][e] = link.history[c.name][-1][1]
                elif c.optional:
                    received[c.name][e] = est.missing(c.name)
            flags['fresh'][e] = fresh
        for c in est.sends:
            if c.sensor is not None:
                received[c.name] = theirs
        expected = {'measured': self._senses, 'their_measured': self._sensed_by,
                    'present': np.ones(n, bool), 'fresh': np.full(n, bool(due))}
        for name, f in flags.items():
            self.missing[name] += int(np.count_nonzero(expected[name] & ~f))
        delta_R = self.gyro.increment(t, t + h)[None]
        displacement = None
        if self.odometry_live() and self.odometry.covers(t, t + h):
            displacement = self.odometry.displacement(t, t + h)[None]
        elif self.odometry_live():
            self.odometry_missing_steps += 1
        links = LinkInputs(
            senses=self._senses, sensed_by=self._sensed_by, owns=self._owns,
            relative_positions=y, other_delta_R=other_R, other_displacement=other_d, **flags)
        return StepInputs(delta_R=delta_R,
                          edges=Edges(agent=np.zeros(n, dtype=np.intp), k=np.ones(n),
                                      n_agents=1, slot=np.arange(n, dtype=np.intp)),
                          bearings=np.zeros((n, 3)), received=received,
                          displacement=displacement, links=links, t=t)

    def _wait_for(self, awaited: str) -> None:
        self.waits[awaited] += 1
        self.awaited = awaited

    def _carried(self, link: Link, wanted: list[str], t: float) -> dict[str, Array] | None:
        """j's channels ``wanted`` at ``t`` from its newest instant ``t_s < t`` that has them
        all, no older than ``neighbour_timeout``, carried over ``[t_s, t]`` by the method
        (:meth:`base.Estimator.carry`) with j's odometry and this robot's gyro; None when
        nothing can be carried."""
        if not wanted:
            return None
        for stamp, first in reversed(link.history.get(wanted[0], ())):
            if stamp >= t - 1e-9:
                continue
            if stamp < t - self.limits.neighbour_timeout:
                return None   # too old: j's estimator is silent (its sensors may not be)
            values = {wanted[0]: first}
            for name in wanted[1:]:
                v, _ = link.value_at(name, stamp)
                if v is None:
                    break
                values[name] = v
            else:
                if not (link.odometry.covers(stamp, t) and self.gyro.covers(stamp, t)):
                    return None
                return self.estimator.carry(values, self.gyro.increment(stamp, t),
                                            link.odometry.rotation(stamp, t),
                                            link.odometry.displacement(stamp, t))
        return None

    def steps_ready(self) -> int:
        """1 when the next step's inputs are all here (or known not to come), else 0."""
        if self._pending is not None and self._pending_k == self.k:
            return 1   # complete inputs stay complete
        if not self.own_inputs_ready():
            return 0
        self._pending = self._gather(self.t, final=self.impatient)
        self._pending_k = self.k
        return 0 if self._pending is None else 1

    def advance(self, max_steps: int | None = None, impatient: bool = False) -> int:
        """Run the steps whose inputs are complete (``impatient``: the first one with what is
        here now); return how many ran."""
        ran = 0
        self.impatient = impatient
        while max_steps is None or ran < max_steps:
            if not self.steps_ready():
                break
            self._step()
            ran += 1
            self.impatient = False
        self.impatient = False
        return ran

    def _begin_step(self) -> _Prepared:
        """The step's inputs, gathered by :meth:`steps_ready` (:func:`.agent.advance_together`
        runs the method's step for several robots at once)."""
        inputs = self._pending
        assert inputs is not None
        return _Prepared(self.t, tuple(self.stale_neighbours(self.t)), inputs)

    def _end_step(self, prepared: _Prepared, x: State, diagnostics: dict[str, Array]) -> None:
        super()._end_step(prepared, x, diagnostics)   # its edges: one per link (_gather)
        self._pending = None

    # ------------------------------------------------------------------------------ outputs
    def outbox(self) -> dict[str, object]:
        """What this robot sends at the state time: per-agent channels as arrays, per-edge
        ones as ``{listener id: value}`` (the method's values for each link; a channel of a
        sensor's readings is not sent: the neighbours read this robot's sensor topic)."""
        n = len(self.links)
        sent = self.estimator.outbox(self.x, np.zeros(n, dtype=np.intp), np.zeros((n, 3)),
                                     slot=np.arange(n, dtype=np.intp))

        def per_edge(name: str, c: Channel) -> dict[int, Array]:
            # An owner-only value goes to the pairs this robot owns: zeros until it has one
            # (the listener's step then knows not to wait for it).
            return {lk.agent_id: sent[name][e] for e, lk in enumerate(self.links)
                    if not c.owner_only or lk.owns}

        return {name: per_edge(name, c) if c.per == 'edge' else sent[name][0]
                for name, c in self.channels.items() if c.sensor is None}

    def bearings_at(self, t: float) -> bool:
        return True

    def conditioning(self) -> Array | None:
        return None

    def excitation(self) -> dict[str, tuple[float, bool]]:
        """Per neighbour: the pair's excitation so far [m²/s] and whether it is excited now
        (the method's per-link state, when it keeps one)."""
        x = self.x
        total = getattr(x, 'excitation', None)
        recent = getattr(x, 'excitation_recent', None)
        if total is None or recent is None:
            return {}
        threshold = getattr(self.estimator.gains, 'pe_threshold', 0.0)
        return {lk.name: (float(total[0, e]) if e < total.shape[1] else 0.0,
                          bool(e < recent.shape[1] and recent[0, e] >= threshold))
                for e, lk in enumerate(self.links)}
