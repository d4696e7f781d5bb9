"""One robot of a two-round method (Presenza et al., ``rounds = 2``), independent of ROS: the
logic of its estimator node.

The step ``[t, t+h]`` runs in two rounds of messages (:meth:`base.Estimator.reply`):

1. **Round 1** needs this robot's gyro and odometry over the step, its bearings and bearing
   rates of the robots it senses at ``t``, the anchor's odometry over the step (every robot
   moves with the anchor's frame), each sensed robot's ``q̂_j`` at ``t`` (its estimate) and, for
   a ranged robot, the anchor's relative position of it at ``t``. Once they are here,
   :meth:`TwoRoundAgent.pending_reply` forms what this robot sends each robot it senses
   (gradient terms, the Gauss-Newton block, the anchor-frame bearing, the velocity term);
2. **Round 2**: the step then waits for those values of ``t`` from every robot that senses
   this one, and runs.

Timing is :class:`link_agent.LinkAgentEstimator`'s: a value is lost once its sender sent a
newer one, a silent sender (``neighbour_timeout``) is left out, and the wait ends when the own
sensors are ``link_wait`` ahead (or, ``impatient``, at once). What is missing then:

- ``q̂_j`` or a round-2 value: j's newest one (no older than ``neighbour_timeout``) carried
  to t by the anchor's motion (:meth:`base.Estimator.carry_anchor_frame`: the same world
  quantity in the anchor frame at t; counted in ``carried``); with none, the link's terms sit
  the step out (``LinkInputs.fresh``; a round-2 value: zeros, which the method reads as "not
  sent", so the velocity reconstruction and angle terms use the other sensing robots);
- an own bearing or bearing rate: the link's terms sit the step out (``LinkInputs.measured``;
  the robot keeps its role, sensing or free);
- the anchor's odometry: the step is not run until it comes or the anchor goes silent, then
  the anchor is taken as still (the frame's motion is lost for those steps, counted).

Each cause is counted in :attr:`missing`. Optional values (the covariance's, ``pose_cov`` in
round 1 and ``term_cov`` in round 2) are never waited for: j's of ``t``, else its newest
carried to ``t``, else the method's stand-in (:meth:`base.Estimator.missing`), uncounted.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Collection
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from ..core.bearing_rates import BearingRateFilter
from ..core.odometry import OdometryBuffer
from .agent import Limits, _Prepared, _vector_problem
from .base import AnchorInputs, Edges, Estimator, LinkInputs, State, StepInputs
from .link_agent import _HISTORY, Link, LinkAgentEstimator, _bounded_problem, _interpolated

Array = NDArray[np.float64]
# A bearing rate above this [1/s] is absurd (a target crossing the view in 10 ms).
MAX_BEARING_RATE = 100.0


class TwoRoundAgent(LinkAgentEstimator):
    """One robot of a two-round method fed by time-stamped inputs (module docstring).

    Args:
        links: ``(name, agent_id, senses, sensed_by)`` of each communication neighbour (it
            senses j, j senses it, or one of them is the anchor that ranges the other), in the
            batch simulator's order (ids ascending).
        anchor: ``(name, agent_id)`` of the anchor; ``ranges``: the ids this robot ranges (it
            is the anchor); ``ranged``: the anchor ranges this robot; ``pinned``: the anchor
            holds ``(I, 0)``.
        the rest: as :class:`link_agent.LinkAgentEstimator`.
    """

    def __init__(self, estimator: Estimator, agent_id: int,
                 links: list[tuple[str, int, bool, bool]], step: float, R0: Array, p0: Array,
                 anchor: tuple[str, int], ranges: Collection[int] = (),
                 ranged: bool = False, pinned: bool = False, rate_tau: float | None = None,
                 t0: float = 0.0, gyro_horizon: float = 2.0,
                 known_ids: set[int] | None = None, limits: Limits = Limits()) -> None:
        super().__init__(estimator, agent_id, links, step, R0, p0, t0=t0,
                         gyro_horizon=gyro_horizon, known_ids=known_ids, limits=limits)
        self.anchor_name, self.anchor_id = anchor
        self.is_anchor = self.anchor_id == agent_id
        self.pinned = pinned
        self.ranged = ranged
        self.ranges = frozenset(int(j) for j in ranges)
        self._ranges = np.array([lk.agent_id in self.ranges for lk in self.links], dtype=bool)
        self._ranged_by = np.array([ranged and lk.agent_id == self.anchor_id
                                    for lk in self.links], dtype=bool)
        self.anchor_odometry = None if self.is_anchor else OdometryBuffer(t0, gyro_horizon)
        self.rates: dict[int, deque[tuple[float, Array]]] = {
            lk.agent_id: deque(maxlen=_HISTORY) for lk in self.links if lk.senses}
        self._first = [c.name for c in estimator.sends if c.round == 1 and c.sensor is None]
        self._second = [c.name for c in estimator.sends if c.round == 2]
        # Optional values (the covariance) are never waited for: the newest one that came,
        # or the method's stand-in (Estimator.missing).
        self._optional = {c.name for c in estimator.sends if c.optional}
        self._round1: StepInputs | None = None   # of step self._round1_k, replied
        self._round1_k = -1
        self._reply: dict[str, dict[int, Array]] | None = None
        self.anchor_still_steps = 0   # steps run without the anchor's odometry
        # rate_tau: no bearing-rate sensor; the rates come from consecutive bearings through
        # this filter (core.bearing_rates), one row per link.
        self.rate_tau = rate_tau
        self._rate_filter = (None if rate_tau is None
                             else BearingRateFilter(len(self.links), rate_tau))

    # ------------------------------------------------------------------------------ wiring
    def measures_me(self, link: Link) -> bool:
        """j's sensor topic carries a measurement of this robot that the step reads: the
        anchor's relative position of a ranged robot."""
        return bool(self.ranged and link.agent_id == self.anchor_id)

    def odometry_sources(self) -> list[tuple[str, int]]:
        """Whose odometry this robot reads: the anchor's (unless it is the anchor)."""
        return [] if self.is_anchor else [(self.anchor_name, self.anchor_id)]

    def channel_sources(self, channel: str) -> list[Link]:
        """The neighbours whose values of ``channel`` the step reads: ``q̂_j`` of the robots
        it senses, the anchor's range of this robot, round 2 from the robots that sense it."""
        if channel in self._second:
            return [lk for lk in self.links if lk.sensed_by]
        if self.channels[channel].sensor is not None:
            return [lk for lk in self.links if self.measures_me(lk)]
        return [lk for lk in self.links if lk.senses]

    def _clear_inputs(self, reset_estimate: bool) -> None:
        super()._clear_inputs(reset_estimate)
        for hist in getattr(self, 'rates', {}).values():
            hist.clear()
        if getattr(self, 'anchor_odometry', None) is not None and reset_estimate:
            assert self.anchor_odometry is not None
            self.anchor_odometry.reset(self.t0)
        self._round1, self._round1_k, self._reply = None, -1, None
        if getattr(self, '_rate_filter', None) is not None:
            assert self.rate_tau is not None
            self._rate_filter = BearingRateFilter(len(self.links), self.rate_tau)

    # ------------------------------------------------------------------------------ inputs
    def add_bearings(self, stamp: float, ids: NDArray[np.integer], vectors: Array) -> list[str]:
        """Own unit bearings ``β_ij`` (body frame) of the robots ``ids`` at ``stamp``; points of
        robots this one does not sense are ignored. Returns the causes of rejected points."""
        return self._add_own(stamp, ids, vectors, unit=True)

    def add_bearing_rates(self, stamp: float, ids: NDArray[np.integer],
                          vectors: Array) -> list[str]:
        """Own bearing rates ``β̇_ij`` [1/s] (body frame) at ``stamp``."""
        return self._add_own(stamp, ids, vectors, unit=False)

    def add_relative_positions(self, stamp: float, ids: NDArray[np.integer],
                               vectors: Array) -> list[str]:
        """Unused: the anchor's ranges go to the ranged robots, its own step does not read
        them (they read them with :meth:`add_neighbour_measurements`, for the links where
        :meth:`measures_me`)."""
        return []

    def _add_own(self, stamp: float, ids: NDArray[np.integer], vectors: Array,
                 unit: bool) -> list[str]:
        if unit:   # bearings: unit vectors, kept normalised
            return self._add_own_points(
                stamp, ids, vectors, lambda v: _vector_problem(v, self.limits.unit_tolerance),
                lambda link: link.measured, lambda v: v / np.linalg.norm(v))
        return self._add_own_points(stamp, ids, vectors, _rate_problem,
                                    lambda link: self.rates[link.agent_id], np.copy)

    def add_neighbour_odometry(self, agent_id: int, stamp: float, v: Array,
                               omega: Array) -> str | None:
        """The anchor's odometry sample (the only neighbour odometry this method reads)."""
        if agent_id != self.anchor_id or self.anchor_odometry is None:
            return 'unknown_id'
        return self._add_twist(self.anchor_odometry, stamp, v, omega)

    # ------------------------------------------------------------------------------ stepping
    def stale_neighbours(self, t: float) -> list[str]:
        """Neighbours silent for longer than ``neighbour_timeout`` before ``t``, or since the
        start (a link that only ranges sends nothing the other end reads: never stale)."""
        limit = t - self.limits.neighbour_timeout
        # Heard from since the start: a neighbour whose first values are on their way is not
        # stale before neighbour_timeout has passed.
        return [lk.name for lk in self.links
                if (lk.senses or lk.sensed_by or self.measures_me(lk))
                and max(lk.newest(), self.t0) < limit]

    def _anchor_late(self, t: float) -> bool:
        """The anchor's odometry will not cover the step: silent for ``neighbour_timeout``."""
        odo = self.anchor_odometry
        return odo is not None and odo.end < t - self.limits.neighbour_timeout

    def _awaiting_round(self, t: float, first: bool) -> str | None:
        """What round 1 (``first``) or round 2 of the step at ``t`` still waits for, or None."""
        tol = 1e-9
        own_late = self.gyro.end - t > self.limits.sensor_timeout
        behind = self.gyro.end - t > self.limits.link_wait
        stale = set(self.stale_neighbours(t))
        if first:
            odo = self.anchor_odometry
            if (odo is not None and not behind and not odo.covers(t, t + self.h)
                    and not self._anchor_late(t)):
                return 'anchor_odometry'
            for link in self.links:
                if link.senses and not own_late:
                    if not (link.measured and link.measured[-1][0] >= t - tol):
                        return 'own_bearing'
                    rates = self.rates[link.agent_id]
                    if self._rate_filter is None and not (rates and rates[-1][0] >= t - tol):
                        return 'own_bearing_rate'
                if link.name in stale or behind:
                    continue
                if self.measures_me(link) and not (link.theirs and link.theirs[-1][0] >= t - tol):
                    return 'anchor_range'
                if link.senses:
                    for name in self._first:
                        if name not in self._optional and _waiting(link, name, t):
                            return name
            return None
        if behind:
            return None
        for link in self.links:
            if link.sensed_by and link.name not in stale:
                for name in self._second:
                    if name not in self._optional and _waiting(link, name, t):
                        return name
        return None

    def _round1_inputs(self, t: float) -> StepInputs:
        """Round 1's inputs of the step at ``t`` with whatever is here (module docstring for
        what stands in for what is missing)."""
        n, h = len(self.links), self.h
        est = self.estimator
        measured, fresh = self._senses.copy(), self._senses.copy()
        bearings, rates = np.zeros((n, 3)), np.zeros((n, 3))
        received = {c.name: np.zeros((n,) + c.shape) for c in est.sends}
        rotate = (lambda s_, t_: self.gyro.increment(t_, s_))
        estimated = self._estimated_rates(t)
        for e, link in enumerate(self.links):
            if link.senses:
                b, _ = _interpolated(link.measured, t, rotate)
                rate = (estimated[e] if estimated is not None
                        else _interpolated(self.rates[link.agent_id], t, rotate)[0])
                q, _ = link.value_at('q_hat', t)
                if q is None:
                    q = self._newest(link, 'q_hat', t)
                    if q is not None:
                        self.carried += 1
                for what, value in (('own_bearing', b), ('own_bearing_rate', rate),
                                    ('q_hat', q)):
                    if value is None:
                        self.missing[what] += 1
                measured[e], fresh[e] = b is not None and rate is not None, q is not None
                # Without all three the link's angles and attitude terms sit the step out.
                if b is not None and rate is not None and q is not None:
                    bearings[e] = b / np.linalg.norm(b)
                    rates[e], received['q_hat'][e] = rate, q
                for name in self._optional & set(self._first):
                    received[name][e] = self._optional_value(link, name, t)
            if self._ranged_by[e]:
                v, _ = _interpolated(link.theirs, t, lambda s_, t_: np.eye(3))
                if v is None:
                    self.missing['anchor_range'] += 1
                else:
                    received['q_ranged'][e] = v
        delta_R = self.gyro.increment(t, t + h)[None]
        displacement = np.zeros((1, 3))
        if self.odometry.covers(t, t + h):
            displacement = self.odometry.displacement(t, t + h)[None]
        else:
            self.odometry_missing_steps += 1
        if self.is_anchor:
            a_R, a_d = delta_R, displacement
        elif self.anchor_odometry is not None and self.anchor_odometry.covers(t, t + h):
            a_R = self.anchor_odometry.rotation(t, t + h)[None]
            a_d = self.anchor_odometry.displacement(t, t + h)[None]
        else:
            self.anchor_still_steps += 1
            a_R, a_d = np.eye(3)[None], np.zeros((1, 3))
        ranged_by = self._ranged_by.copy()
        if ranged_by.any() and not np.any(received['q_ranged'][ranged_by]):
            ranged_by[:] = False   # the range did not come: no anchor term this step
        anchor = AnchorInputs(is_anchor=np.array([self.is_anchor]), delta_R=a_R,
                              displacement=a_d, ranges=self._ranges, ranged_by=ranged_by,
                              pinned=self.pinned)
        links = LinkInputs(senses=self._senses, sensed_by=self._sensed_by, owns=self._owns,
                           relative_positions=np.zeros((n, 3)),
                           other_delta_R=np.tile(np.eye(3), (n, 1, 1)),
                           other_displacement=np.zeros((n, 3)),
                           measured=measured | ~self._senses, fresh=fresh | ~self._senses)
        return StepInputs(delta_R=delta_R,
                          edges=Edges(agent=np.zeros(n, dtype=np.intp), k=np.ones(n),
                                      n_agents=1, slot=np.arange(n, dtype=np.intp)),
                          bearings=bearings, received=received, displacement=displacement,
                          links=links, t=t, bearing_rates=rates, anchor=anchor)

    def _estimated_rates(self, t: float) -> list[Array | None] | None:
        """Without a bearing-rate sensor: each sensing link's rate at ``t`` from its bearings
        at ``t`` and at the previous step (None before the second one), as the batch simulator
        forms them; None with a sensor."""
        filt = self._rate_filter
        if filt is None:
            return None
        n = len(self.links)
        b = np.zeros((n, 3))
        here = np.zeros(n, dtype=bool)
        rotate = (lambda s_, t_: self.gyro.increment(t_, s_))
        for e, link in enumerate(self.links):
            v = _interpolated(link.measured, t, rotate)[0] if link.senses else None
            if v is not None:
                b[e], here[e] = v / np.linalg.norm(v), True
        dR = np.tile(np.eye(3), (n, 1, 1))
        for row in np.flatnonzero(here & ~np.isnan(filt.t_prev)).tolist():
            if self.gyro.covers(float(filt.t_prev[row]), t):
                dR[row] = self.gyro.increment(float(filt.t_prev[row]), t)
            else:   # the rotation since the previous bearing is unknown: start again
                filt.t_prev[row], filt.started[row] = np.nan, False
        derotated, have = filt.update(t, b, dR, here)
        omega = so3.log_small(self.gyro.increment(t, t + self.h)[None])[0] / self.h
        return [derotated[e] - np.cross(omega, b[e]) if have[e] else None for e in range(n)]

    def _newest(self, link: Link, name: str, t: float) -> Array | None:
        """j's newest value of ``name`` before ``t`` (no older than ``neighbour_timeout``)
        carried to ``t`` by the anchor's motion (:meth:`base.Estimator.carry_anchor_frame`),
        or None."""
        for stamp, value in reversed(link.history.get(name, ())):
            if stamp >= t - 1e-9:
                continue
            odo = self.odometry if self.is_anchor else self.anchor_odometry
            if stamp < t - self.limits.neighbour_timeout or odo is None or not odo.covers(
                    stamp, t):
                return None
            carried = self.estimator.carry_anchor_frame(
                {name: value}, odo.rotation(stamp, t), odo.displacement(stamp, t))
            return None if carried is None else carried[name]
        return None

    def _optional_value(self, link: Link, name: str, t: float) -> Array:
        """An optional value at ``t``: j's of ``t``, else its newest carried to ``t``, else the
        method's stand-in (never waited for, not counted as missing)."""
        v, _ = link.value_at(name, t)
        if v is None:
            v = self._newest(link, name, t)
        return self.estimator.missing(name) if v is None else v

    def pending_reply(self, impatient: bool = False) -> dict[str, dict[int, Array]] | None:
        """Round 2 of the current step, once: ``{channel: {listener id: value}}`` for every
        robot this one senses (zeros where it has nothing to say, so that listeners need not
        wait), when round 1 is complete (``impatient``: with what is here); else None."""
        if self._round1_k == self.k or not self.own_inputs_ready():
            return None
        t = self.t
        awaited = None if impatient else self._awaiting_round(t, first=True)
        if awaited is not None:
            self._wait_for(awaited)
            return None
        inputs = self._round1_inputs(t)
        sent = self.estimator.reply(self.x, self.h, inputs)
        self._round1, self._round1_k = inputs, self.k
        self._reply = {name: {lk.agent_id: sent[name][e] for e, lk in enumerate(self.links)
                              if lk.senses} for name in self._second}
        return self._reply

    def steps_ready(self) -> int:
        """1 when the current step has replied and its round 2 is here (or given up on)."""
        if self._round1_k != self.k:
            return 0
        awaited = None if self.impatient else self._awaiting_round(self.t, first=False)
        if awaited is not None:
            self._wait_for(awaited)
            return 0
        return 1

    def advance(self, max_steps: int | None = None, impatient: bool = False) -> int:
        """Run the current step if both rounds are complete (``impatient``: with what is
        here); return how many ran (0 or 1: each step needs its reply sent first)."""
        self.impatient = impatient
        ran = 0
        if (max_steps is None or max_steps > 0) and self.steps_ready():
            self._step()
            ran = 1
        self.impatient = False
        return ran

    def _begin_step(self) -> _Prepared:
        """The step's inputs: round 1 as replied to, with the second round's values
        (:func:`.agent.advance_together` runs the method's step for several robots at once)."""
        first = self._round1
        assert first is not None and self._round1_k == self.k
        t = self.t
        received = dict(first.received)
        for name in self._second:
            c = self.channels[name]
            values = np.zeros((len(self.links),) + c.shape)
            for e, link in enumerate(self.links):
                if not link.sensed_by:
                    continue
                if name in self._optional:
                    values[e] = self._optional_value(link, name, t)
                    continue
                v, _ = link.value_at(name, t)
                if v is None:   # late or lost: j's newest, carried to t, if any
                    v = self._newest(link, name, t)
                    self.carried += v is not None
                if v is None:
                    self.missing[name] += 1
                else:
                    values[e] = v
            received[name] = values
        self._pending = replace(first, received=received)
        self._pending_k = self.k
        return super()._begin_step()

    def _end_step(self, prepared: _Prepared, x: State, diagnostics: dict[str, Array]) -> None:
        super()._end_step(prepared, x, diagnostics)
        L = prepared.inputs.links
        assert L is not None and L.measured is not None and L.fresh is not None
        self.last = replace(self.last, edges_used=int(np.count_nonzero(
            L.senses & L.measured & L.fresh)))
        self._round1, self._reply = None, None

    # ------------------------------------------------------------------------------ outputs
    def outbox(self) -> dict[str, object]:
        """Round 1 at the state time: ``q_hat`` (on the estimate) and, for a method with a
        covariance, ``pose_cov`` (on the pose). Round 2 goes out through
        :meth:`pending_reply`."""
        out: dict[str, object] = {'q_hat': self.x.p_hat[0].copy()}
        if 'pose_cov' in self.channels:
            out['pose_cov'] = getattr(self.x, 'P')[0].copy()
        return out


def _rate_problem(v: Array) -> str | None:
    """Why ``v`` is not a usable bearing rate, or None."""
    return _bounded_problem(v, MAX_BEARING_RATE)


def _waiting(link: Link, name: str, t: float) -> bool:
    """j's value of ``name`` at ``t`` may still come (not here, nothing newer either)."""
    value, decided = link.value_at(name, t)
    return value is None and not decided
