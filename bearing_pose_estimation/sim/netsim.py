"""The distributed system without DDS, in one process and deterministic: one
:class:`runtime.agent.AgentRuntime` per agent (what the estimator node runs), the simulator
node's world (:class:`.world.World`) and the links, read as :mod:`runtime.table` says.

'instant' channels go out at the ``publish_rate``, 'exact' ones after each step that a
neighbour's next step reads, a second round's as soon as its first is in; a step waits at most
``link_wait`` of its own sensors' time. A fault-free run pairs its inputs as a lockstep
simulation does (:class:`runtime.buffers.Exchange`), so a DDS run equals it to rounding. Faults:

- :class:`LinkFaults`: lost and late neighbour messages (:mod:`runtime.faults`);
- :class:`Outage`: an agent is cut off over ``[start, end)``. ``network_only``: a partition,
  no neighbour message in or out while its own sensors keep feeding it. Otherwise no process,
  no input or output; it comes back as it was (``restart=False``: paused, input sent meanwhile
  is lost) or fresh from its initial estimate (``restart=True``). From 0: a late joiner;
- :class:`ClockJump`, :class:`Clocks`: a simulator restart, robots' clocks off or drifting;
- :class:`Garbage`: a fraction of every input comes with a corrupted copy, or is replaced by it
  (``replace=True``): NaN/inf, bad vectors, unknown ids, bad stamps, absurd rates.

:func:`fault_cases` is the one fault list of ``bench/fault_matrix.py`` and the tests."""
from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from ..core.errors import ScenarioError
from ..estimators.base import POINT_SENSORS, Channel, Sensor
from ..metrics.results import PoseErrors, Recording, pose_errors
from ..runtime.agent import AgentRuntime
from ..runtime.buffers import TIME_EVENTS, Limits
from ..runtime.faults import FaultyLink, LinkFaults
from ..runtime.table import ODOM_TOPIC, subscriptions
from ..runtime.together import advance_together
from ..scenario.model import Scenario
from ..scenario.runtimes import agent_specs, exchange_of, runtime_for
from .world import World

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Outage:
    agent: str
    start: float                # run time [s]
    end: float                  # run time [s]
    restart: bool = True        # comes back as a fresh process (True) or as it was (False)
    network_only: bool = False  # a partition: only neighbour messages are cut

    def __post_init__(self) -> None:
        if self.network_only and self.restart:
            raise ValueError('a network partition (network_only) does not restart the process')


@dataclass(frozen=True)
class ClockJump:
    """The simulator restarts (clock, truth, noise) at run time ``at``. A jump back under
    ``Limits.jump_back`` (1 s) is ``out_of_order`` to the estimators until the clock catches up."""

    at: float  # run time [s] at which the simulator's clock goes back to 0


@dataclass(frozen=True)
class Clocks:
    """Each robot's own clock against the simulator's (true) time ``t``: ``local = s_i
    (offset + drift t) + t``, the sign ``s_i`` alternating over the agents in the scenario's
    order (+ first) or, with a ``seed``, drawn per agent. A robot stamps what it measures and
    sends, and steps, on its clock, untold; errors are measured at true times."""

    offset: float = 0.0      # [s]
    drift: float = 0.0       # [s/s]: 1e-4 is 100 ppm
    seed: int | None = None  # None: alternating signs

    def __bool__(self) -> bool:
        return bool(self.offset or self.drift)

    def of(self, names: Sequence[str]) -> dict[str, tuple[float, float]]:
        """Each agent's ``(offset [s], rate)``: ``local = offset + rate · t``."""
        n = len(names)
        signs = (np.where(np.arange(n) % 2 == 0, 1.0, -1.0) if self.seed is None
                 else np.random.default_rng(self.seed).choice([-1.0, 1.0], n))
        return {name: (float(s * self.offset), float(1.0 + s * self.drift))
                for name, s in zip(names, signs)}


@dataclass(frozen=True)
class Garbage:
    fraction: float = 0.0  # probability that an input gets a corrupted copy
    seed: int = 0
    replace: bool = False  # the copy replaces the input (True) or follows it (False)


@dataclass(frozen=True)
class FaultCase:
    """One row of the fault matrix: a short key, a label and the faults to inject."""

    key: str
    label: str
    links: LinkFaults = LinkFaults()
    outages: tuple[Outage, ...] = ()
    clock_jump: ClockJump | None = None
    garbage: Garbage = Garbage()
    clocks: Clocks = Clocks()

    @property
    def window(self) -> tuple[float, float] | None:
        """When the fault happens, ``(start, end)`` in run time, or None (the whole run)."""
        if self.clock_jump is not None:
            return self.clock_jump.at, self.clock_jump.at
        if self.outages:
            return min(o.start for o in self.outages), max(o.end for o in self.outages)
        return None


def fault_cases(at: float = 20.0, length: float = 5.0, late_join: float = 10.0,
                garbage: float = 0.1, victim: str = 'agent_4', late: str = 'agent_7',
                delay: float = 0.2) -> list[FaultCase]:
    """The fault matrix, the reference (no fault) first, for the paper's 8-agent scenario (the
    tests shrink the times). ``at``, ``length`` [s]: the outages and the clock jump (``at`` a
    multiple of the step keeps records aligned); ``late_join`` [s]: when ``late`` starts;
    ``victim``: the agent cut off, paused or restarted; ``garbage``: fraction corrupted."""
    end = at + length
    return [
        FaultCase('reference', 'none (reference)'),
        FaultCase('loss', '30 % of neighbour messages lost',
                  links=LinkFaults(drop_rate=0.3, seed=1)),
        FaultCase('delay', f'neighbour messages {1000 * delay:g} ms late',
                  links=LinkFaults(delay=delay)),
        FaultCase('loss_delay', f'30 % lost and {1000 * delay:g} ms late',
                  links=LinkFaults(drop_rate=0.3, delay=delay, seed=1)),
        FaultCase('partition', f'{victim} cut off the network {at:g}-{end:g} s (partition; '
                  'its own sensors keep running)',
                  outages=(Outage(victim, at, end, restart=False, network_only=True),)),
        FaultCase('pause', f'{victim} paused {at:g}-{end:g} s (no input, no output)',
                  outages=(Outage(victim, at, end, restart=False),)),
        FaultCase('restart', f'{victim} killed at {at:g} s, restarted at {end:g} s',
                  outages=(Outage(victim, at, end, restart=True),)),
        FaultCase('late_join', f'{late} joins late, at {late_join:g} s',
                  outages=(Outage(late, 0.0, late_join),)),
        FaultCase('clock_jump', f'simulated clock jumps back to 0 at {at:g} s (simulator '
                  'restart)', clock_jump=ClockJump(at)),
        FaultCase('garbage', f'{100 * garbage:g} % of the inputs followed by a garbage copy '
                  '(NaN/inf, zero-length, non-unit, unknown ids, stale/late/future stamps, '
                  'absurd gyro)', garbage=Garbage(fraction=garbage, seed=1)),
        FaultCase('garbage_replacing', f'the same garbage replacing {100 * garbage:g} % of the '
                  'inputs (the good data is lost)',
                  garbage=Garbage(fraction=garbage, seed=1, replace=True)),
        *clock_cases(),
    ]


def clock_cases(offsets: Sequence[float] = (0.005, 0.05), drift: float = 1e-4
                ) -> list[FaultCase]:
    """The clock rows (:class:`Clocks`): clocks off by ``±offset`` [s] (neighbours then often
    disagree twice as much), and drifting by ``±drift`` [s/s] from t = 0 (0: no such row)."""
    rows = [FaultCase(f'clock_{1000 * o:g}ms', f'clocks off by ±{1000 * o:g} ms (alternating '
                      'over the agents)', clocks=Clocks(offset=o)) for o in offsets]
    return rows + [FaultCase('clock_drift', f'clocks drifting by ±{1e6 * drift:g} ppm from '
                             'agreeing at t = 0', clocks=Clocks(drift=drift))] * bool(drift)


class _Corruptor:
    """Draws which inputs are garbage and how; copies, never in place (messages are shared)."""

    GYRO = ('nan', 'inf', 'absurd_rate', 'late_stamp', 'future_stamp')
    BEARINGS = ('nan', 'inf', 'zero', 'not_unit', 'huge', 'unknown_id', 'own_id',
                'stale_stamp', 'future_stamp')
    # On the message's first per-agent value (e.g. p̂_j) for the first two (else its per-edge
    # value meant for the listener), on that per-edge value (e.g. R̂_j b^j_ji) for the next two.
    NEIGHBOUR = ('nan_value', 'inf_value', 'zero', 'not_unit', 'unknown_sender',
                 'none_for_me', 'future_stamp')

    # Relative positions: the bearings' kinds that a receiver can tell from a measurement
    # (a relative position three times longer is still a plausible one).
    RELATIVE = tuple(k for k in BEARINGS if k != 'not_unit')

    def __init__(self, garbage: Garbage, channels: dict[str, Channel]) -> None:
        self.channels = channels
        self.fraction = garbage.fraction
        self.replace = garbage.replace
        self.rng = np.random.default_rng(garbage.seed)

    def inputs(self, good: tuple, corrupt: tuple | None) -> list[tuple[tuple, bool]]:
        """What arrives, each flagged garbage or not: the input, its copy instead, or both."""
        if corrupt is None:
            return [(good, False)]
        return [(corrupt, True)] if self.replace else [(good, False), (corrupt, True)]

    def _kind(self, kinds: tuple[str, ...]) -> str | None:
        if self.fraction and self.rng.uniform() < self.fraction:
            return kinds[int(self.rng.integers(len(kinds)))]
        return None

    def gyro(self, stamp: float, w: Array) -> tuple[float, Array] | None:
        kind = self._kind(self.GYRO)
        if kind is None:
            return None
        w = w.copy()
        bad = {'nan': (0, np.nan), 'inf': (1, np.inf), 'absurd_rate': (2, 100.0)}  # [rad/s]
        if kind in bad:
            w[bad[kind][0]] = bad[kind][1]
        # Within the 1 s that would read as a clock jump (a legitimate restart, not garbage).
        stamp += {'late_stamp': -0.1, 'future_stamp': 5.0}.get(kind, 0.0)
        return stamp, w

    def bearings(self, own_id: int, stamp: float, ids: NDArray[np.integer],
                 b: Array, kinds: tuple[str, ...] = BEARINGS
                 ) -> tuple[float, NDArray[np.integer], Array] | None:
        kind = self._kind(kinds)
        if kind is None:
            return None
        ids, b = ids.copy(), b.copy()
        if kind in ('nan', 'inf'):
            b[:, 0] = np.nan if kind == 'nan' else -np.inf
        elif kind in ('zero', 'huge'):
            b[:] = 0.0 if kind == 'zero' else 1e300
        elif kind == 'not_unit':
            b *= 3.0
        elif kind in ('unknown_id', 'own_id'):
            ids[:] = 99 if kind == 'unknown_id' else own_id
        stamp += {'stale_stamp': -5.0, 'future_stamp': 5.0}.get(kind, 0.0)
        return stamp, ids, b

    def neighbour(self, listener_id: int, msg: tuple) -> tuple | None:
        sender, stamp, values = msg
        agent_channel = next((n for n in values if self.channels[n].per == 'agent'), None)
        edge_channel = next((n for n in values if self.channels[n].per == 'edge'), None)
        # The kinds a receiver can tell on this message: a zero or stretched value only where
        # it must be a unit vector, none for it only where the message has values per listener.
        unit = edge_channel is not None and self.channels[edge_channel].unit
        kind = self._kind(tuple(k for k in self.NEIGHBOUR
                                if (unit or k not in ('zero', 'not_unit'))
                                and (edge_channel is not None or k != 'none_for_me')))
        if kind is None:
            return None
        values = dict(values)
        edge_shape = self.channels[edge_channel].shape if edge_channel is not None else (3,)
        per_edge = dict(values.get(edge_channel, {})) if edge_channel is not None else {}
        if kind in ('nan_value', 'inf_value'):
            bad = np.nan if kind == 'nan_value' else np.inf
            if agent_channel is not None:
                values[agent_channel] = np.array(values[agent_channel], dtype=float)
                values[agent_channel].ravel()[0 if kind == 'nan_value' else -1] = bad
            else:
                per_edge[listener_id] = np.full(edge_shape, bad)
        elif kind in ('zero', 'not_unit'):
            per_edge[listener_id] = (np.zeros(edge_shape) if kind == 'zero' else
                                     3.0 * per_edge.get(listener_id, np.eye(edge_shape[0])[0]))
        elif kind == 'unknown_sender':
            sender = 99
        elif kind == 'none_for_me':
            per_edge.pop(listener_id, None)
        elif kind == 'future_stamp':
            stamp += 5.0
        if edge_channel is not None:
            values[edge_channel] = per_edge
        return sender, stamp, values

    def known_pose(self, R: Array) -> tuple[Array] | None:
        if self._kind(('nan',)) is None:
            return None
        R = R.copy()
        R[0, 0] = np.nan
        return (R,)


@dataclass
class InputTally:
    """What became of the estimators' inputs, counted as the node counts them: rejections by
    cause, time rules as events; the corrupted inputs (:class:`Garbage`) also on their own."""

    rejected: Counter[str] = field(default_factory=Counter)          # every rejected input
    events: Counter[str] = field(default_factory=Counter)            # time_jump, gyro_gap
    garbage_injected: int = 0             # corrupted inputs (bearings: per point)
    garbage_rejected: Counter[str] = field(default_factory=Counter)  # their causes

    @property
    def garbage_accepted(self) -> int:
        return self.garbage_injected - sum(self.garbage_rejected.values())

    def count(self, causes: Sequence[str | None], garbage: int | bool = 0) -> None:
        """Record the outcome of one input: ``causes`` is what the ``add_*`` call returned,
        ``garbage`` how many of its values (points, for bearings) were corrupted."""
        self.garbage_injected += garbage
        for cause in causes:
            if cause in TIME_EVENTS:
                self.events[cause] += 1
            elif cause is not None:
                self.rejected[cause] += 1
                if garbage:
                    self.garbage_rejected[cause] += 1


@dataclass
class NetRun:
    """A run of :func:`simulate_network`: the errors and what else it measured."""

    recording: Recording
    inputs: InputTally
    non_finite_estimates: int  # estimates with a NaN/inf, checked after every step
    non_finite_steps: int      # steps the estimators discarded as non-finite
    carried: int = 0           # link methods: late or lost neighbour values carried forward
    warm_starts: Counter[str] = field(default_factory=Counter)   # by outcome (AgentRuntime)
    # Per listener, its neighbours' inputs stamped more than Limits.max_clock_lead ahead of
    # its clock (listeners with none left out).
    ahead: dict[str, dict[str, int]] = field(default_factory=dict)
    # Per listener, the resets its neighbours announced (AgentRuntime._distrust).
    resets: dict[str, dict[str, int]] = field(default_factory=dict)


class _Network:
    """The fleet, its world and links, with one run's faults; :meth:`tick`: one world step."""

    def __init__(self, scenario: Scenario, links: LinkFaults, outages: tuple[Outage, ...],
                 garbage: Garbage, limits: Limits, batched: bool = True,
                 clocks: Clocks = Clocks()) -> None:
        self.scenario, self.outages, self.limits = scenario, outages, limits
        self.batched = batched
        if scenario.formation is not None and scenario.formation.mode == 'paper':
            raise ScenarioError(f'{scenario.source}: formation_control.mode: paper needs the '
                                'estimates inside the truth; netsim\'s world, like the '
                                'simulator node, cannot have them. Fix: mode: exogenous')
        self.specs = {spec.name: spec for spec in agent_specs(scenario)}
        self.world = World(scenario)
        self.link = FaultyLink(links)
        estimator = scenario.estimator()
        self.method = type(estimator)
        self.frame = estimator.frame
        self.channels = {c.name: c for c in self.method.sends}
        self.bad = _Corruptor(garbage, self.channels)
        self.names = [a.name for a in scenario.agents]
        self.clocks = clocks.of(self.names) if clocks else None
        # Fault-free: paired as in lockstep; with faults, as robots do (nothing waits).
        self.exchange = (exchange_of(scenario)
                         if not (links or outages or garbage.fraction or clocks) else None)
        self.agents: dict[str, AgentRuntime] = {n: self._runtime(n) for n in self.names}
        self.subs = {name: subscriptions(self.method, spec) for name, spec in self.specs.items()}
        # Who reads what: (sender, topic) -> readers, from the one table.
        self.readers: dict[tuple[str, str], list[str]] = {}
        for name, subs in self.subs.items():
            for sub in subs:
                self.readers.setdefault((sub.source, sub.topic), []).append(name)
        self.topics: dict[int, dict[str, list[str]]] = {}   # round -> topic -> channels
        for c in self.method.sends:
            if c.sensor is None:
                self.topics.setdefault(c.round, {}).setdefault(c.topic, []).append(c.name)
        # The point sensors someone reads: its own step, or a neighbour from its topic.
        read = {c.sensor for c in self.method.sends if c.sensor is not None}
        self.point_sensors = [s for s in POINT_SENSORS if s in self.method.measures or s in read]
        self.sent_k = dict.fromkeys(self.names, -1)
        self.per_step = int(round(scenario.step / self.world.dt))
        self.per_publish = self.per_step * scenario.publish_every
        self.tally = InputTally()
        self.non_finite = 0
        # The truth at the last second of step instants (step index -> (R, p)): an estimator
        # behind the world is measured at its own state time, as the monitor pairs stamps.
        self.truth: dict[int, tuple[Array, Array]] = {}
        # With clocks: the truth at every internal step of the last second (by world tick),
        # for the true times of the estimators' local state times.
        self.tick_truth: dict[int, tuple[Array, Array]] = {}

    def _runtime(self, name: str) -> AgentRuntime:
        rt = runtime_for(self.scenario, self.specs[name], self.limits, self.exchange,
                         t0=self.local(name, 0.0))
        if self.clocks is not None:   # its clock's reading of the fleet's start: not late
            rt.cold_since = None      # (from its initial estimate, as the fault-free run's)
        return rt

    def local(self, name: str, t: float) -> float:
        """``name``'s clock at the simulator's time ``t``."""
        if self.clocks is None:
            return t
        offset, rate = self.clocks[name]
        return offset + rate * t

    def true_time(self, name: str, local: float) -> float:
        """The simulator's time at which ``name``'s clock reads ``local``."""
        if self.clocks is None:
            return local
        offset, rate = self.clocks[name]
        return (local - offset) / rate

    def truth_at(self, i: int, t: float) -> tuple[Array, Array] | None:
        """Agent ``i``'s true pose at the simulator's time ``t`` (within the last second),
        interpolated between internal steps (geodesic for the attitude)."""
        x = t / self.world.dt
        m = int(np.floor(x + 1e-9))
        w, a, b = x - m, self.tick_truth.get(m), self.tick_truth.get(m + 1)
        if a is None:
            return None
        if w < 1e-9 or b is None:
            return a[0][i], a[1][i]
        R = a[0][i] @ so3.exp(w * so3.log(a[0][i].T @ b[0][i]))
        return R, (1.0 - w) * a[1][i] + w * b[1][i]

    def offline(self, name: str, now: float) -> bool:
        """No neighbour messages in or out (any outage)."""
        return any(o.agent == name and o.start <= now < o.end for o in self.outages)

    def stopped(self, name: str, now: float) -> bool:
        """No process: no input at all (an outage that is not a partition)."""
        return any(o.agent == name and not o.network_only and o.start <= now < o.end
                   for o in self.outages)

    def restart(self, name: str, now: float) -> None:
        """A fresh runtime from the initial estimate, announcing its t0 state as a node does."""
        self.agents[name] = self._runtime(name)
        self.sent_k[name] = -1
        self.publish(name, now, lambda n: True)

    def feed_gyro(self, now: float) -> None:
        world = self.world
        for name, w in zip(self.names, world.imu()):
            if self.stopped(name, now):
                continue
            t = self.local(name, world.t)
            for (stamp, rate), bad in self.bad.inputs((t, w), self.bad.gyro(t, w)):
                self.tally.count([self.agents[name].add_gyro(stamp, rate, now=t)], bad)

    def sense(self, now: float) -> None:
        """Odometry (moving fleets), the point sensors and the leaders' known pose, when due:
        to the agent itself and to whoever reads them from its topics."""
        world, scenario = self.world, self.scenario
        every = world.sensor_every.get('odometry')
        if every is not None and world.due(every) and world.tick > 0:
            for i, (name, v, w) in enumerate(zip(self.names, *world.odometry())):
                if not self.stopped(name, now):
                    t = self.local(name, world.t)
                    self.tally.count([self.agents[name].add_odometry(t, v, w, now=t)], 0)
                    self.send(name, ODOM_TOPIC, now, ('odometry', i + 1, t, v, w))
        for sensor in self.point_sensors:
            every = (world.bearing_every if sensor is Sensor.BEARINGS
                     else world.sensor_every.get(sensor.value))
            if every is None or not world.due(every):
                continue
            kinds = _Corruptor.BEARINGS if sensor is Sensor.BEARINGS else _Corruptor.RELATIVE
            for i, name in enumerate(self.names):
                if self.stopped(name, now):
                    continue
                j, v = (world.bearings(i) if sensor is Sensor.BEARINGS
                        else world.sensed(sensor.value, i))
                good = (self.local(name, world.t), j + 1, v)
                agent = self.agents[name]
                for args, bad in self.bad.inputs(good, self.bad.bearings(i + 1, *good,
                                                                         kinds=kinds)):
                    self.tally.count(agent.add_points(sensor, *args), bad * len(j))
                self.send(name, sensor.value, now, ('points', i + 1, sensor, *good))
        if world.due(world.truth_every):
            for name in scenario.leaders:
                if self.stopped(name, now):
                    continue
                i = scenario.index[name]
                t = self.local(name, world.t)
                for (R,), bad in self.bad.inputs((world.R[i],), self.bad.known_pose(world.R[i])):
                    self.tally.count([self.agents[name].add_known_pose(t, R, world.p[i])], bad)

    def send(self, name: str, topic: str, now: float, msg: tuple) -> None:
        """``msg`` on ``name``'s ``topic`` to every reader, through the link faults."""
        if self.offline(name, now):
            return
        for receiver in self.readers.get((name, topic), ()):
            self.link.send(now, partial(self.receive, receiver, msg))

    def receive(self, to: str, msg: tuple, now: float) -> None:
        if self.offline(to, now) or self.stopped(to, now):
            return
        agent, clock = self.agents[to], self.local(to, self.world.t)
        if msg[0] == 'odometry':
            self.tally.count([agent.add_peer_odometry(*msg[1:], now=clock)], 0)
        elif msg[0] == 'points':
            self.tally.count([agent.add_peer_points(*msg[1:], now=clock)], 0)
        else:
            corrupt = self.bad.neighbour(self.scenario.agent_id(to), msg[1:])
            for args, bad in self.bad.inputs(msg[1:], corrupt):
                self.tally.count([agent.add_message(*args, now=clock)], bad)

    def publish(self, name: str, now: float, which: Callable[[str], bool]) -> None:
        """``name``'s round-1 topics that carry a channel ``which`` picks, with their
        values at its state time (a per-edge one with nothing in it: not sent)."""
        ag = self.agents[name]
        if ag.withholding:
            return
        values: dict[str, object] | None = None
        for topic, names in self.topics.get(1, {}).items():
            if not any(which(n) for n in names):
                continue
            if values is None:
                values = ag.outbox()
            content = {n: values[n] for n in names
                       if not (isinstance(values[n], dict) and not values[n])}
            if content:
                self.send(name, topic, now, ('channels', self.scenario.agent_id(name), ag.t,
                                             content))

    def publish_stepped(self, name: str, now: float) -> None:
        """After a step: the 'exact' channels a neighbour's step reads at the new instant."""
        ag = self.agents[name]
        self.publish(name, now, lambda n: self.channels[n].pairing == 'exact'
                     and ag.sends_now(n, False))

    def reply(self, name: str, now: float, reply: dict[str, dict[int, Array]]) -> None:
        """A second round, on its topics."""
        ag = self.agents[name]
        for r, topics in self.topics.items():
            if r == 1:
                continue
            for topic, names in topics.items():
                content = {n: reply[n] for n in names if n in reply}
                if content:
                    self.send(name, topic, now, ('channels', self.scenario.agent_id(name),
                                                 ag.t, content))

    def step(self, now: float) -> None:
        """Every running agent takes the steps its inputs allow, sending what its neighbours
        wait for, until none can go on; count any non-finite estimate."""
        progress = True
        while progress:
            progress = False
            running = [name for name in self.names if not self.stopped(name, now)]
            for name in running:
                reply = self.agents[name].pending_reply()
                if reply is not None:
                    progress = True
                    self.reply(name, now, reply)
            agents = [self.agents[name] for name in running]
            if self.batched:
                stepped = advance_together(agents)
            else:
                stepped = [ag for ag in agents if ag.advance(1)]
            for ag in stepped:
                progress = True
                if not (np.all(np.isfinite(ag.R_hat)) and np.all(np.isfinite(ag.p_hat))):
                    self.non_finite += 1
                if self.sent_k[ag.name] != ag.k:
                    self.sent_k[ag.name] = ag.k
                    self.publish_stepped(ag.name, now)

    def start(self) -> None:
        self.sense(0.0)
        for name in self.names:
            self.publish(name, 0.0, lambda n: True)
            self.sent_k[name] = 0

    def tick(self, now: float) -> None:
        """One internal step; ``now`` is the run time after it."""
        world = self.world
        world.step()
        if world.due(world.imu_every):
            self.feed_gyro(now)
        self.sense(now)
        self.link.release(now)
        if self.clocks is not None:
            self.tick_truth[world.tick] = (world.R.copy(), world.p.copy())
            self.tick_truth.pop(world.tick - int(round(1.0 / world.dt)), None)
        if world.tick % self.per_step == 0:
            k = world.tick // self.per_step
            self.truth[k] = (world.R.copy(), world.p.copy())
            self.truth.pop(k - int(round(1.0 / self.scenario.step)), None)
            self.step(now)
        if world.tick % self.per_publish == 0:
            for name in self.names:   # 'instant' channels at the publish rate
                if not self.stopped(name, now):
                    self.publish(name, now, lambda n: self.channels[n].pairing == 'instant')
            self.link.release(now)

    def errors(self, followers: list[int]) -> PoseErrors:
        """The followers' pose errors (:func:`metrics.results.pose_errors`), each against the
        truth at its estimator's state time (now, unless it waits for gyro data)."""
        R, p = self.world.R.copy(), self.world.p.copy()
        for i, name in enumerate(self.names):
            if self.clocks is not None:
                pose = self.truth_at(i, self.true_time(name, self.agents[name].t))
                if pose is not None:
                    R[i], p[i] = pose
                continue
            k = int(round(self.agents[name].t / self.scenario.step))
            if k in self.truth:
                R[i], p[i] = self.truth[k][0][i], self.truth[k][1][i]
        R_hat = np.concatenate([self.agents[name].R_hat for name in self.names])
        p_hat = np.concatenate([self.agents[name].p_hat for name in self.names])
        return pose_errors(self.frame, R, p, R_hat, p_hat, followers,
                           anchor=self.scenario.anchor_index)


def simulate_network(scenario: Scenario, duration: float, record_every: float = 0.1,
                     links: LinkFaults = LinkFaults(), outages: tuple[Outage, ...] = (),
                     clock_jump: ClockJump | None = None, garbage: Garbage = Garbage(),
                     limits: Limits = Limits(), batched: bool = True,
                     clocks: Clocks = Clocks()) -> NetRun:
    """Run the fleet for ``duration`` s of run time with the given faults; record the followers'
    errors every ``record_every`` (monotonic across a clock jump). ``batched``: one instant's
    steps in one call (:func:`runtime.together.advance_together`): bit for bit the same."""
    net = _Network(scenario, links, outages, garbage, limits, batched, clocks)
    dt = net.world.dt
    per_record = int(round(record_every / dt))
    restart_at: dict[int, list[str]] = {}
    for o in outages:
        if o.restart:
            restart_at.setdefault(int(round(o.end / dt)), []).append(o.agent)
    jump_tick = int(round(clock_jump.at / dt)) if clock_jump is not None else -1
    followers = [scenario.index[a.name] for a in scenario.followers]
    rows, times = [], []
    net.start()
    tick = 0  # the run's own clock, monotonic; world.t is the simulator's, which may jump
    while tick * dt < duration - 1e-9:
        tick += 1
        for name in restart_at.get(tick, ()):
            net.restart(name, tick * dt)
        if tick == jump_tick:  # the simulator restarts: clock, truth and noise back to t = 0
            net.world.reset()  # (instead of a step: world and run ticks stay in phase)
            net.truth.clear()
            net.tick_truth.clear()
        else:
            net.tick(tick * dt)
        if tick % per_record == 0:
            times.append(tick * dt)
            rows.append(net.errors(followers))
    rec = Recording.of(times, [net.names[i] for i in followers], rows)
    return NetRun(rec, net.tally, non_finite_estimates=net.non_finite,
                  non_finite_steps=sum(ag.non_finite_steps for ag in net.agents.values()),
                  carried=sum(ag.carried for ag in net.agents.values()),
                  warm_starts=sum((ag.warm_starts for ag in net.agents.values()), Counter()),
                  ahead={n: dict(ag.ahead) for n, ag in net.agents.items() if ag.ahead},
                  resets={n: dict(ag.resets) for n, ag in net.agents.items() if ag.resets})


def run_network(scenario: Scenario, duration: float, record_every: float = 0.1,
                links: LinkFaults = LinkFaults(), outages: tuple[Outage, ...] = (),
                limits: Limits = Limits()) -> Recording:
    """Run the fleet for ``duration`` seconds; errors of the followers every ``record_every``."""
    return simulate_network(scenario, duration, record_every, links, outages,
                            limits=limits).recording


def run_case(scenario: Scenario, case: FaultCase, duration: float,
             record_every: float = 0.5) -> NetRun:
    """One row of the fault matrix."""
    return simulate_network(scenario, duration, record_every, links=case.links,
                            outages=case.outages, clock_jump=case.clock_jump,
                            garbage=case.garbage, clocks=case.clocks)


# How close to the fault-free run at the same instant counts as caught up (catch_up_time).
CATCH_UP_FACTOR = 1.5


def reconvergence_time(rec: Recording, ref: Recording, fault_end: float) -> float | None:
    """Time after ``fault_end`` until both mean errors of ``rec`` are at or below the fault-free
    run's (``ref``, same record times) at ``fault_end``; None if not by the end."""
    if fault_end > ref.t[-1] + 1e-9:
        return None  # the run ended before the fault did
    att, pos = rec.mean_errors()
    ref_att, ref_pos = ref.mean_errors()
    k = int(np.searchsorted(ref.t, fault_end - 1e-9))
    back = np.flatnonzero((rec.t >= fault_end - 1e-9) & (att <= ref_att[k])
                          & (pos <= ref_pos[k]))
    return round(float(rec.t[back[0]] - fault_end), 9) if back.size else None


def catch_up_time(rec: Recording, ref: Recording, fault_end: float,
                  factor: float = CATCH_UP_FACTOR) -> float | None:
    """Time after ``fault_end`` from which both mean errors of ``rec`` stay within ``factor``
    times the fault-free run's at the same instant (``ref``): back to the run it would have been,
    not only where it was at the fault's end (a fleet that stays behind gets there). Or None."""
    att, pos = rec.mean_errors()
    ref_att, ref_pos = ref.mean_errors()
    after = rec.t >= fault_end - 1e-9
    within = (att <= factor * ref_att) & (pos <= factor * ref_pos)
    out = np.flatnonzero(after & ~within)
    k = np.flatnonzero(after)
    if not k.size or (out.size and out[-1] == len(rec.t) - 1):
        return None
    first = out[-1] + 1 if out.size else k[0]
    return round(max(float(rec.t[first] - fault_end), 0.0), 9)


def convergence_cost(rec: Recording, ref: Recording) -> float:
    """Seconds of convergence a fault lost by the end: the end time minus the first time the
    fault-free run (``ref``) was as good, for the mean error that lost more (0: no worse)."""
    costs = [0.0]
    for err, ref_err in zip(rec.mean_errors(), ref.mean_errors()):
        k = np.flatnonzero(ref_err <= err[-1])
        if k.size:
            costs.append(float(rec.t[-1] - ref.t[k[0]]))
    return round(max(costs), 9)
