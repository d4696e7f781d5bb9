"""``estimator``: one agent's observer as a ROS 2 node (run one per agent, in /<agent>): the
cascaded observer of Boughellaba & Tayebi, or Tran, Anderson & Ahn's (the scenario's ``method``).

A thin adapter: it decodes messages (``msg_defs``), feeds :class:`agent.AgentEstimator`, runs
its fixed steps ``h = 1/frequency`` as soon as the gyro data covers them (checked on every gyro
sample and on a timer at ``frequency``) and publishes. Subscribes (relative names, remappable):
``imu`` (sensor_msgs/Imu), ``bearings`` (sensor_msgs/PointCloud2), ``known_pose`` (leaders), and
``/<j>/estimate`` + ``/<j>/world_bearings`` of each neighbour j. Publishes ``estimate``
(geometry_msgs/PoseStamped in ``world``) and ``world_bearings`` (what its listeners need) every
``publish_rate`` period, on exact multiples of it, and its health on ``/diagnostics``.

Bad input is rejected, counted by cause, warned about (throttled) and reported in the
diagnostics; it never stops the node and never reaches the estimate.

Parameters (read-only): either ``scenario_file`` (+ ``agent``, default: the namespace) or the
explicit set ``agent_id``, ``leader``, ``neighbours``, ``neighbour_ids``, ``neighbour_gains``,
``initial_position``, ``initial_orientation`` (x, y, z, w), with ``method``
(``boughellaba_tayebi``, the default, or ``tran_anderson_ahn``); ``frequency`` [Hz],
``publish_rate`` [Hz] and the gains ``k_R``, ``k_p`` (boughellaba_tayebi) or ``k_omega``,
``k_c``, ``k_p`` (tran_anderson_ahn): 0 means the scenario's value, or 100 Hz / 50 Hz / the
method's default gains in explicit mode; a gain of the other method is an error.
``start_time`` [s] (the scenario's t = 0 on the node's clock; negative: the first gyro stamp);
the input limits ``sensor_timeout``, ``neighbour_timeout``, ``max_rate``; the expected frames
``imu_frame``, ``bearings_frame`` (empty: accept any); ``diagnostics_period`` [s]; and the fault
injection for tests and studies: ``inject_drop_rate`` (probability of dropping each neighbour
message), ``inject_delay`` [s] (extra delay of each neighbour message), ``inject_seed``.
Integers are accepted for numbers; a wrong type or range stops the node with a one-line error,
and unknown keys in a parameter file are warned about (see :func:`node_main.declare`).
"""
from __future__ import annotations

import heapq
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import fields, replace
from functools import partial

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from . import msg_defs as wire
from . import so3
from .agent import TIME_EVENTS, AgentEstimator, Limits, estimator_for
from .node_main import declare, parameter_overrides, run_node, warn_unknown_parameters
from .observer import CascadeGains
from .scenario import METHODS, ScenarioError, load_scenario
from .tran import TranGains

# The gains each method takes as parameters (0: the scenario's, or the method's default).
_GAINS = {'boughellaba_tayebi': CascadeGains, 'tran_anderson_ahn': TranGains}
_GAIN_HELP = {'k_R': 'attitude gain (boughellaba_tayebi)', 'k_p': 'position gain',
              'k_omega': 'damping of the gyro correction (tran_anderson_ahn)',
              'k_c': 'third direction of two-neighbour followers (tran_anderson_ahn)'}
# Used only without a scenario file.
_EXPLICIT = ('agent_id', 'leader', 'neighbours', 'neighbour_ids', 'neighbour_gains',
             'initial_position', 'initial_orientation')


def _with_gains(base: CascadeGains | TranGains, given: dict[str, float], where: str,
                fix: str) -> CascadeGains | TranGains:
    """``base`` with the non-zero ``given`` gains; a gain of the other method is an error."""
    method = next(m for m, cls in _GAINS.items() if isinstance(base, cls))
    own = [f.name for f in fields(base)]
    for gain, value in given.items():
        if value and gain not in own:
            other = next(m for m, cls in _GAINS.items()
                         if gain in [f.name for f in fields(cls)])
            raise ScenarioError(f'parameter {gain} is a {other} gain, but {where} is {method}. '
                                f'Fix: remove {gain} ({method} takes {", ".join(own)}); {fix}')
    return replace(base, **{g: v for g, v in given.items() if v})


class EstimatorNode(Node):
    def __init__(self, **node_kwargs) -> None:
        """``node_kwargs`` go to rclpy's Node (``namespace``, ``context``,
        ``parameter_overrides``, ``cli_args``, ...): several agents can share one process."""
        super().__init__('estimator', **node_kwargs)
        p = partial(declare, self)
        scenario_file = p('scenario_file', '', 'scenario YAML; empty: explicit parameters')
        default_agent = self.get_namespace().strip('/').split('/')[-1]
        self.agent = p('agent', default_agent, 'agent name (default: namespace)')
        frequency = p('frequency', 0.0, 'estimator rate [Hz]; 0: scenario / 100', 0.0, 10000.0)
        publish_rate = p('publish_rate', 0.0, 'estimate and world-bearing rate [Hz]; '
                         '0: scenario / 50', 0.0, 10000.0)
        method = p('method', '', f'observer, {" or ".join(METHODS)}; empty: the scenario\'s '
                   '(explicit mode: boughellaba_tayebi)')
        given_gains = {g: p(g, 0.0, f'{text}; 0: scenario / default', 0.0, 1e6)
                       for g, text in _GAIN_HELP.items()}
        self.start_time = p('start_time', 0.0, 't = 0 of the scenario on this clock [s]; '
                            'negative: the first gyro stamp')
        d = Limits()
        limits = Limits(
            sensor_timeout=p('sensor_timeout', d.sensor_timeout,
                             'own bearings older than this are not used [s]', 0.0, 1e6),
            neighbour_timeout=p('neighbour_timeout', d.neighbour_timeout,
                                'a neighbour silent for longer is stale and not used [s]',
                                0.0, 1e6),
            max_rate=p('max_rate', d.max_rate, 'gyro rates above this are rejected [rad/s]',
                       0.0, 1e6))
        self.imu_frame = p('imu_frame', wire.body_frame(self.agent),
                           'expected Imu frame_id; empty: any')
        self.bearings_frame = p('bearings_frame', wire.body_frame(self.agent),
                                'expected bearings frame_id; empty: any')
        diagnostics_period = p('diagnostics_period', 1.0, '/diagnostics period [s]',
                               0.01, 3600.0)
        self.drop_rate = p('inject_drop_rate', 0.0, 'fault injection: probability of dropping '
                           'each neighbour message', 0.0, 1.0)
        self.delay = p('inject_delay', 0.0, 'fault injection: extra delay of each neighbour '
                       'message [s]', 0.0, 60.0)
        self.rng = np.random.default_rng(p('inject_seed', 0, 'fault injection: random seed',
                                           0, 2**31 - 1))
        explicit = {
            'agent_id': p('agent_id', 0, 'explicit mode: this agent\'s id (1-based)'),
            'leader': p('leader', False, 'explicit mode: a leader (known pose, no neighbours)'),
            'neighbours': p('neighbours', [''], 'explicit mode: neighbour names'),
            'neighbour_ids': p('neighbour_ids', [0], 'explicit mode: neighbour ids'),
            'neighbour_gains': p('neighbour_gains', [0.0], 'explicit mode: k_ij per neighbour'),
            'initial_position': p('initial_position', [0.0, 0.0, 0.0],
                                  'explicit mode: initial p̂ [m]'),
            'initial_orientation': p('initial_orientation', [0.0, 0.0, 0.0, 1.0],
                                     'explicit mode: initial R̂ as a quaternion x, y, z, w'),
        }
        if method and method not in METHODS:
            raise ScenarioError(f'parameter method: unknown method {method!r}. Fix: one of '
                                f'{", ".join(METHODS)}, or empty')
        if scenario_file:
            scenario = load_scenario(scenario_file)
            if self.agent not in scenario.index:
                raise ScenarioError(f'{scenario_file}: agent {self.agent!r} is not in the '
                                    'scenario. Fix: set the `agent` parameter or the namespace')
            if method and method != scenario.method:
                raise ScenarioError(f'parameter method is {method}, but {scenario_file} uses '
                                    f'method {scenario.method}. Fix: remove the parameter (the '
                                    'scenario file chooses the method)')
            ignored = sorted(set(_EXPLICIT) & set(parameter_overrides(self)))
            if ignored:
                self.get_logger().warning(f'{", ".join(ignored)} ignored: they are for running '
                                          'without a scenario_file, which is set')
            template = estimator_for(scenario, self.agent, limits)
            publish_rate = publish_rate or scenario.publish_rate
            where, fix = "the scenario's method", 'the scenario file sets the method'
        else:
            method = method or METHODS[0]
            template = self._explicit_estimator(explicit, limits, _GAINS[method]())
            publish_rate = publish_rate or 50.0
            where = 'the method parameter'
            fix = f'or set method: {" / ".join(m for m in METHODS if m != method)}'
        gains = _with_gains(template.gains, given_gains, where, fix)
        self.template = template
        self.gains = gains
        self.h = 1.0 / frequency if frequency > 0 else template.h
        # Publish on exact multiples of the publish period, so the monitor can pair estimates
        # with ground truth at identical stamps.
        self.publish_every = max(1, int(round(1.0 / (self.h * publish_rate))))
        self.est: AgentEstimator | None = None
        if self.start_time >= 0.0:
            self.est = self._make_estimator(self.start_time)
        self.rejected: Counter[str] = Counter()
        self.events: Counter[str] = Counter()
        self._published_k = -1
        self._wall_first_step: float | None = None
        self._delayed: list[tuple[float, int, Callable[[], None]]] = []  # (release, seq, fn)
        self._seq = 0
        self._diag_steps = (0, time.monotonic())

        qos_in, qos_est = wire.SENSOR_QOS, wire.ESTIMATE_QOS
        self.pub_estimate = self.create_publisher(wire.PoseStamped, wire.ESTIMATE, qos_est)
        self.pub_world = self.create_publisher(wire.PointCloud2, wire.WORLD_BEARINGS, qos_est)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        subs = [self.create_subscription(wire.Imu, wire.IMU, self.on_imu, qos_in),
                self.create_subscription(wire.PointCloud2, wire.BEARINGS, self.on_bearings,
                                         qos_in)]
        if template.leader:
            # Best effort matches both a reliable publisher (the simulator) and a best-effort
            # one (many mocap and GNSS drivers); a reliable reader would miss the latter. A lost
            # sample costs nothing: the gyro carries the pose to the next one.
            subs.append(self.create_subscription(wire.PoseStamped, wire.KNOWN_POSE,
                                                 self.on_known_pose, qos_in))
        self._nbr_p_hat: dict[int, np.ndarray] = {}
        for nb in template.neighbours:
            subs.append(self.create_subscription(
                wire.PoseStamped, wire.topic(nb.name, wire.ESTIMATE),
                lambda msg, j=nb.agent_id: self._link(self.on_neighbour_estimate, j, msg),
                qos_est))
            subs.append(self.create_subscription(
                wire.PointCloud2, wire.topic(nb.name, wire.WORLD_BEARINGS),
                lambda msg, j=nb.agent_id: self._link(self.on_neighbour_bearings, j, msg),
                qos_est))
        self._subs = subs
        self.timer = self.create_timer(self.h, self.on_timer)
        self.diag_timer = self.create_timer(diagnostics_period, self.publish_diagnostics)
        # Until the first gyro sample, announce the t0 state on a wall-clock timer, but only once
        # every subscription has a publisher: best-effort sensor readers drop what arrives before
        # they are matched, so the simulator starts the clock only after hearing from everyone.
        self.ready_timer = self.create_timer(
            0.05, self.on_ready_check, clock=Clock(clock_type=ClockType.STEADY_TIME))
        role = 'leader' if template.leader else f'{len(template.neighbours)} neighbours'
        faults = (f'; INJECTING drop {self.drop_rate:g}, delay {self.delay:g} s on neighbour '
                  'messages' if self.drop_rate or self.delay else '')
        self.get_logger().info(f'{self.agent} (id {template.agent_id}, {role}) at '
                               f'{1.0 / self.h:g} Hz, '
                               + ', '.join(f'{k}={v:g}' for k, v in vars(gains).items())
                               + faults)
        warn_unknown_parameters(self)

    # --------------------------------------------------------------------------- set-up
    def _explicit_estimator(self, e: dict, limits: Limits,
                            gains: CascadeGains | TranGains) -> AgentEstimator:
        names = [n for n in e['neighbours'] if n]
        if e['agent_id'] <= 0:
            raise ScenarioError('parameter agent_id must be > 0 without a scenario_file. Fix: '
                                'set agent_id (and neighbours, neighbour_ids) or scenario_file')
        if not e['leader'] and not (len(names) == len(e['neighbour_ids'])
                                    == len(e['neighbour_gains']) >= 2):
            raise ScenarioError('parameters neighbours, neighbour_ids and neighbour_gains need '
                                'the same length >= 2 for a follower. Fix: list each neighbour '
                                'once in all three')
        if any(not (k > 0 and np.isfinite(k)) for k in e['neighbour_gains']) and not e['leader']:
            raise ScenarioError('parameter neighbour_gains: every gain must be > 0. Fix: use '
                                'positive gains (e.g. 1.0)')
        q = np.asarray(e['initial_orientation'], dtype=float)
        p0 = np.asarray(e['initial_position'], dtype=float)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1) > 1e-3:
            raise ScenarioError('parameter initial_orientation must be a unit quaternion '
                                '[x, y, z, w]. Fix: normalise it')
        if p0.shape != (3,) or not np.all(np.isfinite(p0)):
            raise ScenarioError('parameter initial_position must be 3 finite numbers [m]')
        nbrs = [] if e['leader'] else list(zip(names, e['neighbour_ids'], e['neighbour_gains']))
        return AgentEstimator(agent_id=e['agent_id'], neighbours=nbrs, gains=gains,
                              step=0.01, leader=e['leader'], R0=so3.from_quat(q), p0=p0,
                              limits=limits)

    def _make_estimator(self, t0: float) -> AgentEstimator:
        t = self.template
        return AgentEstimator(agent_id=t.agent_id,
                              neighbours=[(n.name, n.agent_id, n.k) for n in t.neighbours],
                              gains=self.gains, step=self.h, R0=t.R0, p0=t.p0, t0=t0,
                              leader=t.leader, known_ids=t.known_ids, limits=t.limits)

    def _reject(self, cause: str, detail: str, count: int = 1) -> None:
        self.rejected[cause] += count
        self.get_logger().warning(f'rejected {detail}: {cause} ({self.rejected[cause]} so far)',
                                  throttle_duration_sec=5.0)

    def _decoded(self, msg: object, decode: Callable, frame: str, what: str) -> tuple | None:
        """``decode(msg)``, or None after counting the rejection: wrong frame (unless ``frame``
        is empty) or a malformed message."""
        if frame and msg.header.frame_id != frame:
            return self._reject('wrong_frame', f'{what} in frame {msg.header.frame_id!r}')
        try:
            return decode(msg)
        except wire.WireError as exc:
            return self._reject('malformed', f'{what} ({exc})')

    def _now(self) -> float | None:
        """The node's clock [s], or None before a simulated clock has ticked (a late joiner's
        first samples must not look like they come from the future)."""
        ns = self.get_clock().now().nanoseconds
        return ns * 1e-9 if ns > 0 else None

    # --------------------------------------------------------------------------- inputs
    def on_imu(self, msg: wire.Imu) -> None:
        decoded = self._decoded(msg, wire.decode_imu, self.imu_frame, 'imu')
        if decoded is None:
            return
        t, omega = decoded
        if self.est is None:
            self.est = self._make_estimator(t)
            return
        if not self.ready_timer.is_canceled():
            self.ready_timer.cancel()
        cause = self.est.add_gyro(t, omega, now=self._now())
        if cause in TIME_EVENTS:
            self.events[cause] += 1
            self.get_logger().warning(f'{TIME_EVENTS[cause]} (t = {t:.3f} s)')
            self._published_k = -1
        elif cause is not None:
            return self._reject(cause, f'imu sample at {t:.6f}')
        # Steps run as soon as the gyro covers them. Waiting for the timer alone can deadlock
        # a lockstep simulation: a clock tick handled before the IMU sample of the same
        # instant fires the timer too early, and the clock then waits for this agent.
        self.on_timer()

    def on_bearings(self, msg: wire.PointCloud2) -> None:
        decoded = self._decoded(msg, wire.decode_vectors, self.bearings_frame, 'bearings')
        if decoded is None or self.est is None:
            return
        t, ids, vectors = decoded
        for cause, n in Counter(self.est.add_bearings(t, ids, vectors)).items():
            self._reject(cause, f'{n} bearing(s) at {t:.6f}', n)
        if self.est.k == 0 and self.est.gyro.end <= self.est.t0:
            self._publish(world=True)  # the t0 world bearings, before the first step

    def on_known_pose(self, msg: wire.PoseStamped) -> None:
        decoded = self._decoded(msg, wire.decode_pose, wire.WORLD_FRAME, 'known_pose')
        if decoded is not None and self.est is not None:
            t, R, p = decoded
            cause = self.est.set_known_pose(t, R, p)
            if cause is not None:
                self._reject(cause, 'known_pose')

    def _link(self, handler: Callable[[int, object], None], agent_id: int, msg: object) -> None:
        """A neighbour message through the (optional) injected loss and delay."""
        if self.drop_rate and self.rng.uniform() < self.drop_rate:
            self.events['injected_drop'] += 1
            return
        if self.delay > 0.0:
            self._seq += 1
            heapq.heappush(self._delayed, ((self._now() or 0.0) + self.delay, self._seq,
                                           lambda: handler(agent_id, msg)))
            return
        handler(agent_id, msg)

    def _release_delayed(self) -> None:
        now = self._now() or 0.0
        while self._delayed and self._delayed[0][0] <= now:
            heapq.heappop(self._delayed)[2]()

    def on_neighbour_estimate(self, agent_id: int, msg: wire.PoseStamped) -> None:
        decoded = self._decoded(msg, wire.decode_pose, wire.WORLD_FRAME,
                                f'estimate of agent {agent_id}')
        if decoded is not None:
            self._nbr_p_hat[agent_id] = decoded[2]

    def on_neighbour_bearings(self, agent_id: int, msg: wire.PointCloud2) -> None:
        decoded = self._decoded(msg, wire.decode_vectors, wire.WORLD_FRAME,
                                f'world_bearings of agent {agent_id}')
        p_hat = self._nbr_p_hat.get(agent_id)
        if decoded is None or self.est is None or p_hat is None:
            return
        t, ids, vectors = decoded
        cause = self.est.add_neighbour(agent_id, t, p_hat, dict(zip(ids.tolist(), vectors)))
        if cause not in (None, 'not_seen'):  # not_seen: j has no bearing to us yet
            self._reject(cause, f'world_bearings of agent {agent_id} at {t:.6f}')

    # --------------------------------------------------------------------------- stepping
    def on_ready_check(self) -> None:
        if self.est is None or self.est.k > 0:
            return
        if all(sub.get_publisher_count() > 0 for sub in self._subs):
            self._publish(world=True, force=True)

    def on_timer(self) -> None:
        if self.est is None:
            return
        if self._delayed:
            self._release_delayed()
        while self.est.steps_ready() > 0:
            if self._wall_first_step is None:
                self._wall_first_step = time.monotonic()
            self.est.advance(1)
            # On the absolute grid origin + n h (k restarts after a time jump or gap).
            if round((self.est.t - self.est.origin) / self.h) % self.publish_every == 0:
                self._publish(world=True)

    def _publish(self, world: bool, force: bool = False) -> None:
        est = self.est
        t = est.t
        if force or self._published_k != est.k:
            self.pub_estimate.publish(
                wire.encode_pose(t, wire.WORLD_FRAME, est.R_hat[0], est.p_hat[0]))
            self._published_k = est.k
        if world:
            wb = est.world_bearings()
            if wb:
                ids = np.fromiter(wb.keys(), dtype=np.uint32, count=len(wb))
                self.pub_world.publish(
                    wire.encode_vectors(t, wire.WORLD_FRAME, ids, np.array(list(wb.values()))))

    # --------------------------------------------------------------------------- health
    def conditioning(self) -> np.ndarray | None:
        """Eigenvalues of ``M_i = Σ k_ij b^i_ij b^i_ijᵀ`` from the current own bearings
        (Lemma 1 wants three distinct ones), or None without bearings to every neighbour."""
        est = self.est
        rows = [(nb.k, est.body_bearing(nb.agent_id, est.t)) for nb in est.neighbours]
        if not rows or any(b is None for _, b in rows):
            return None
        return np.linalg.eigvalsh(sum(k * np.outer(b, b) for k, b in rows))

    def publish_diagnostics(self) -> None:
        """Per-agent health on /diagnostics: rate, rejections by cause, stale neighbours,
        conditioning of M_i, time events."""
        status = DiagnosticStatus(name=f'{self.agent}/estimator', hardware_id=self.agent)
        values = {'state_time_s': 'n/a'}
        level, problems = DiagnosticStatus.OK, []
        if self.est is not None:
            est = self.est
            steps, wall = self._diag_steps
            now = time.monotonic()
            values['state_time_s'] = f'{est.t:.3f}'
            values['steps_per_wall_second'] = f'{(est.k - steps) / max(now - wall, 1e-9):.1f}'
            self._diag_steps = (est.k, now)
            if not est.leader:
                stale = est.stale_neighbours(est.t)
                values['stale_neighbours'] = ','.join(stale)
                values['edges_used'] = str(est.last.edges_used)
                if stale:
                    level, problems = DiagnosticStatus.WARN, problems + ['stale neighbours']
                eig = self.conditioning()
                if eig is not None:
                    values['M_eigenvalues'] = ','.join(f'{e:.4g}' for e in eig)
                    if np.min(np.diff(eig)) <= 1e-6 * max(eig[-1], 1e-300):
                        level = max(level, DiagnosticStatus.WARN)
                        problems.append('M_i has repeated eigenvalues (Lemma 1)')
            values['non_finite_steps'] = str(est.non_finite_steps)
        for cause, n in sorted(self.rejected.items()):
            values[f'rejected_{cause}'] = str(n)
        for cause, n in sorted(self.events.items()):
            values[f'event_{cause}'] = str(n)
        if self.rejected:
            level = max(level, DiagnosticStatus.WARN)
            problems.append(f'{sum(self.rejected.values())} input(s) rejected')
        status.level = level
        status.message = '; '.join(problems) or 'ok'
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)

    def destroy_node(self) -> None:
        """Log what this estimator achieved: steps, the step rate in wall time, rejections."""
        if self.est is not None and self._wall_first_step is not None:
            wall = max(time.monotonic() - self._wall_first_step, 1e-9)
            self.get_logger().info(
                f'{self.est.k} steps ({self.est.k * self.h:.2f} s of state time) in {wall:.1f} s '
                f'wall: {self.est.k / wall:.1f} steps/s; rejected: {dict(self.rejected) or 0}; '
                f'events: {dict(self.events) or 0}')
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    raise SystemExit(run_node(EstimatorNode, 'estimator', args))


if __name__ == '__main__':
    main()
