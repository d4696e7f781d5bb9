"""``estimator``: one agent's estimator as a ROS 2 node (one per agent, in /<agent>), any
registered ``method``. A thin adapter around :class:`runtime.agent.AgentRuntime`: it decodes
messages, hands them to the runtime, runs each step as soon as its inputs are in (no timer) and
publishes. Topics, types and frames: msg_defs/README.md; parameters: :mod:`.estimator_params`.

In a simulation (``fixed_exchange``, default: ``use_sim_time``) a step's inputs are fixed by
their stamps and waited for, as netsim feeds the same runtime: a run equals netsim's to rounding
however loaded the machine is. Bad input is rejected and counted by cause; it never stops the
node nor reaches the estimate.
"""
from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from .. import msg_defs as wire
from ..core.errors import ScenarioError
from ..estimators.base import Channel, Sensor, format_gains
from ..msg_defs import cdr, rviz
from ..runtime.agent import AgentRuntime
from ..runtime.buffers import TIME_EVENTS
from ..runtime.faults import FaultyLink
from ..runtime.health import health, summary
from ..runtime.table import ODOMETRY, Subscription, optional_first, subscriptions
from .estimator_params import live_change, setup
from .node_main import (run_node, take_waiting, tf_broadcaster, wall_timer,
                        warn_unknown_parameters)
from .step_batch import StepBatch

# Wall time [s] a step of a fixed exchange waits with its own sensors standing still before
# going on without an awaited input. Only a hang breaker: under lockstep nothing it awaits is
# lost for good, and a loaded machine can stall a process for 0.25 s.
EXCHANGE_PATIENCE = 10.0
# Wall time [s] between checks for a stalled agent (EstimatorNode.on_watch).
WATCH_PERIOD_S = 1.0


class EstimatorNode(Node):
    def __init__(self, batch: StepBatch | None = None, **node_kwargs: Any) -> None:
        """``batch``: the steps of the agents that share this process, run together (the
        ``estimators`` process, :mod:`.step_batch`). ``node_kwargs`` go to rclpy's Node
        (``namespace``, ``context``, ``parameter_overrides``, ``cli_args``, ...)."""
        super().__init__('estimator', **node_kwargs)
        self.fleet = wire.fleet_of(self.get_namespace())   # neighbours' topics: beside ours
        self.fleet_prefix = f'{self.fleet}/' if self.fleet else ''
        self.s = s = setup(self)
        self.agent, self.method, self.frames, self.raw = s.agent, s.method, s.frames, s.raw
        self.link = FaultyLink(s.faults)
        self.tf = tf_broadcaster(self, s.publish_tf)
        self.rt = self._runtime(s.start_time) if s.start_time >= 0.0 else None
        self._sim_time = bool(self.get_parameter('use_sim_time').value)
        self.rejected: Counter[str] = Counter()
        self.events: Counter[str] = Counter()
        self._published_k = -1
        self._deferred = -1   # the step whose channels wait for its own measurements
        self._wall_first_step: float | None = None
        self._diag_steps = (0, time.monotonic())
        self._make_publishers()
        self.batch = batch
        if batch is not None:
            batch.join(self)
        self._make_subscriptions()
        wall_timer(self, s.diagnostics_period, self.publish_diagnostics)
        # The t0 state goes out once every subscription has a publisher and every writer its
        # readers (best effort drops what comes before): the simulator waits to hear everyone.
        self.ready_timer = wall_timer(self, 0.05, self.on_ready_check)
        self.exact = any(c.pairing == 'exact' for c in self.method.sends)
        if self.exact or s.exchange is not None:
            wall_timer(self, 0.05 if self.exact else 0.5, self.on_patience)
        self._watched: tuple[int, float] | None = None
        wall_timer(self, WATCH_PERIOD_S, self.on_watch)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        role = 'leader' if s.spec.leader else f'{len(s.spec.peers)} neighbours'
        inject = (f'; INJECTING drop {s.faults.drop_rate:g}, delay {s.faults.delay:g} s on '
                  'neighbour messages' if s.faults else '')
        self.get_logger().info(f'{self.agent} (id {s.spec.agent_id}, {role}) at '
                               f'{1.0 / s.step:g} Hz, {self.method.method}: '
                               f'{format_gains(s.gains)}{inject}')
        warn_unknown_parameters(self)

    # --------------------------------------------------------------------------- set-up
    def _runtime(self, t0: float) -> AgentRuntime:
        s = self.s
        return AgentRuntime(self.method(s.gains), s.spec, s.step, t0=t0, limits=s.limits,
                            exchange=s.exchange, expects_odometry=s.expects_odometry)

    def _make_publishers(self) -> None:
        """The estimate, the pose with its covariance, each channel topic, /diagnostics."""
        qos = wire.ESTIMATE_RECORD_QOS if self.method.rounds() > 1 else wire.ESTIMATE_QOS
        self.channel_qos = qos   # a later round's values are waited for from the first one
        self.pub_estimate = self.create_publisher(wire.PoseStamped, wire.ESTIMATE,
                                                 wire.ESTIMATE_PUB_QOS)
        own = [c for c in optional_first(self.method.sends) if c.sensor is None]
        self.pose_channels = [c for c in own if c.kind in (wire.POSE_POSITION,
                                                           wire.POSE_COVARIANCE)]
        self.pub_pose = (self.create_publisher(wire.PoseWithCovarianceStamped, wire.POSE,
                                               wire.ESTIMATE_PUB_QOS)
                         if self.pose_channels else None)
        self.topics: dict[str, tuple[Any, list[Channel]]] = {
            topic: (self.create_publisher(wire.channel_type(chans[0]), topic, qos), chans)
            for topic, chans in wire.by_topic(own).items() if topic != wire.POSE}
        self.pub_diag = self.create_publisher(wire.DiagnosticArray, wire.DIAGNOSTICS, 10)
        writers = {wire.ESTIMATE: self.pub_estimate, wire.POSE: self.pub_pose,
                   **{topic: pub for topic, (pub, _) in self.topics.items()}}
        self._readers_wanted = [(writers[topic], n) for topic, n in self.s.listeners.items()
                                if writers.get(topic) is not None]

    def _make_subscriptions(self) -> None:
        """The own sensors, and what the table says this agent reads from the others."""
        def sub(msg_type: Any, topic: str, callback: Callable[[Any], None], qos: Any,
                wait: bool = True) -> None:
            if self.batch is not None:
                callback = self.batch.counted(callback)
            s = self.create_subscription(msg_type, topic, callback, qos, raw=self.raw)
            if wait:   # the t0 announcement waits for its publisher
                self._waits.append(s)

        self._waits: list[Any] = []
        qos = wire.SENSOR_QOS
        sub(wire.Imu, wire.IMU, self.on_imu, qos)
        rates_estimated = self.s.spec.rate_tau is not None
        for sensor in self.method.measures:
            if not (sensor is Sensor.BEARING_RATES and rates_estimated):
                sub(wire.PointCloud2, sensor.value, partial(self.on_points, sensor), qos)
        if self.method.uses(Sensor.ODOMETRY):
            sub(wire.Odometry, wire.ODOM, self.on_odometry, qos, wait=self.s.expects_odometry)
        if self.s.spec.leader:
            # Best effort matches a reliable publisher (the simulator) and a best-effort one
            # (many mocap and GNSS drivers). A lost sample costs nothing: the gyro carries the
            # pose to the next one.
            sub(wire.PoseStamped, wire.KNOWN_POSE, self.on_known_pose, qos)
        chans = {c.name: c for c in self.method.sends}
        for s in subscriptions(self.method, self.s.spec):
            topic = wire.topic(s.source, s.topic, self.fleet)
            if s.kind == ODOMETRY:
                sub(wire.Odometry, topic, partial(self._link, self.on_peer_odometry, s), qos,
                    wait=self.s.expects_odometry)
            elif s.kind == 'points':
                sub(wire.PointCloud2, topic, partial(self._link, self.on_peer_points, s), qos)
            else:
                sub(wire.channel_type(chans[s.channels[0]]), topic,
                    partial(self._link, self.on_channels, s), self.channel_qos)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """A live change of gains or input limits, all or nothing, from the next step on."""
        try:
            gains, limits = live_change(self.s, params)
        except ScenarioError as exc:
            self.get_logger().warning(f'parameter change refused: {exc}')
            return SetParametersResult(successful=False, reason=str(exc))
        self.s.gains, self.s.limits = gains, limits
        if self.rt is not None:
            self.rt.estimator, self.rt.limits = self.method(gains), limits
        self.get_logger().info('parameters set live: '
                               + ', '.join(f'{p.name} = {p.value:g}' for p in params))
        return SetParametersResult(successful=True)

    # --------------------------------------------------------------------------- inputs
    def _reject(self, cause: str, detail: str, count: int = 1) -> None:
        self.rejected[cause] += count
        self.get_logger().warning(f'rejected {detail}: {cause} ({self.rejected[cause]} so far)',
                                  throttle_duration_sec=5.0)

    def _decoded(self, msg: Any, frame: str, what: str,
                 decode: Callable[[bytes], Any] = bytes) -> Any:
        """``decode`` of the bytes if their frame is ``frame`` (empty: any); else None, counted."""
        data = wire.raw(msg)
        try:
            frame_id = cdr.read_header(data).frame_id if frame else frame
            if frame_id != frame:
                self._reject('wrong_frame', f'{what} in frame {frame_id!r}')
                return None
            return decode(data)
        except wire.WireError as exc:
            self._reject('malformed', f'{what} ({exc})')
            return None

    def _now(self) -> float | None:
        """The node's clock [s], or None before a simulated clock ticks (nothing is future)."""
        ns = self.get_clock().now().nanoseconds
        return ns * 1e-9 if ns > 0 else None

    def _lead_now(self) -> float | None:
        """The clock for a neighbour's clock lead: None on the shared simulated clock (its
        one-step ticks and lockstep's lag would read as leads)."""
        return None if self._sim_time else self._now()

    def _counted(self, causes: Sequence[str | None], what: str) -> None:
        if not any(causes):
            return   # every input used (the common case: no Counter)
        for cause, n in Counter(c for c in causes if c is not None).items():
            if cause == 'early':   # before the first gyro sample: not a fault, no WARN
                self.events['early_inputs'] += n
            elif cause in TIME_EVENTS:
                self.events[cause] += n
                self.get_logger().warning(f'{TIME_EVENTS[cause]} ({what})')
                self._published_k = -1
            elif cause not in ('unused', 'not_seen'):
                self._reject(cause, what, n)

    def on_imu(self, msg: Any) -> None:
        decoded = self._decoded(msg, self.frames['imu'], 'imu', cdr.decode_imu_raw)
        if decoded is None:
            return
        t, omega = decoded
        if self.rt is None:
            self.rt = self._runtime(t)
            return
        if not self.ready_timer.is_canceled():
            self.ready_timer.cancel()
            if self.rt.k == 0:
                # Once more: the clock runs only once the monitor's readers matched.
                self._publish(grid=True, force=True)
        self._counted([self.rt.add_gyro(t, omega, now=self._now())], f'imu sample at {t:.6f}')
        self.run_ready_steps()

    def on_points(self, sensor: Sensor, msg: Any) -> None:
        decoded = self._decoded(msg, self.frames['points'], sensor.value,
                                cdr.decode_vectors_raw)
        rt = self.rt
        if decoded is None or rt is None:
            return
        t, ids, vectors = decoded
        self._counted(rt.add_points(sensor, t, ids, vectors), f'{sensor.value} at {t:.6f}')
        if rt.k == 0 and rt.gyro.end <= rt.t0:
            self._publish(grid=True)   # the t0 channels, before the first step
        elif self._deferred == rt.k and rt.measured_at(rt.t):
            self._publish(grid=True, deferred=True)
        self.run_ready_steps()

    def _use(self, decoded: Any, add: Callable[..., str | None], what: str) -> None:
        """A decoded input (its stamp first) to the runtime's ``add``: what it rejects is
        counted, and the steps it completes run."""
        if decoded is not None and self.rt is not None:
            self._counted([add(self.rt, *decoded)], f'{what} at {decoded[0]:.6f}')
            self.run_ready_steps()

    def on_odometry(self, msg: Any) -> None:
        self._use(self._decoded(msg, '', 'odom', lambda b: cdr.decode_odometry_raw(
            b, self.frames['odom'] or None)), lambda rt, *d: rt.add_odometry(
                *d, now=self._now()), 'odom sample')

    def on_known_pose(self, msg: Any) -> None:
        self._use(self._decoded(msg, self.s.world_frame, 'known_pose', cdr.decode_pose_raw),
                  AgentRuntime.add_known_pose, 'known_pose')

    def _link(self, handler: Callable[[Subscription, Any], None], sub: Subscription,
              msg: Any) -> None:
        """A neighbour's message through the (optional) injected loss and delay."""
        if not self.s.faults:
            return handler(sub, msg)
        before = self.link.dropped
        self.link.send(self._now() or 0.0, lambda _: handler(sub, msg))
        if self.link.dropped != before:
            self.events['injected_drop'] += 1

    def on_channels(self, sub: Subscription, msg: Any) -> None:
        """A neighbour's channel topic: one undecodable channel is counted and left out."""
        chans = [c for c in self.method.sends if c.name in sub.channels]
        what = f'{sub.topic} of agent {sub.source_id}'
        frame = wire.channel_frame(chans[0], sub.source, self.s.estimate_frame,
                                   self.s.world_frame)
        data = self._decoded(msg, frame, what)
        if data is None or self.rt is None:
            return
        t, values, problems = wire.decode_channels(data, chans)
        for name, problem in problems.items():
            self._reject('malformed', f'{name} of {what} ({problem})')
        if values:
            self._counted([self.rt.add_message(sub.source_id, t, values, now=self._lead_now())],
                          f'{what} at {t:.6f}')
            self.run_ready_steps()

    def on_peer_points(self, sub: Subscription, msg: Any) -> None:
        what = f'{sub.topic} of {sub.source}'
        sensor = next(c.sensor for c in self.method.sends if c.name == sub.channels[0])
        self._use(self._decoded(msg, wire.body_frame(sub.source), what, cdr.decode_vectors_raw),
                  lambda rt, *d: rt.add_peer_points(sub.source_id, sensor, *d,
                                                    now=self._lead_now()), what)

    def on_peer_odometry(self, sub: Subscription, msg: Any) -> None:
        decoded = self._decoded(msg, '', f'odom of {sub.source}', lambda b: (
            cdr.decode_odometry_raw(b, wire.body_frame(sub.source))))
        if decoded is not None and self.rt is not None:
            cause = self.rt.add_peer_odometry(sub.source_id, *decoded,
                                              now=self._lead_now())
            if cause == 'odometry_gap':
                self.events[f'{cause}_{sub.source}'] += 1
            else:
                self._counted([cause], f'odom of {sub.source}')
            self.run_ready_steps()

    # --------------------------------------------------------------------------- stepping
    def on_ready_check(self) -> None:
        if self.rt is None or self.rt.k > 0:
            return
        if (all(s.get_publisher_count() > 0 for s in self._waits)
                and all(pub.get_subscription_count() >= n for pub, n in self._readers_wanted)):
            self._publish(grid=True, force=True)

    def run_ready_steps(self, impatient: bool = False) -> None:
        """Every step the inputs allow now (in an ``estimators`` process: the batch's call)."""
        rt = self.rt
        if rt is None:
            return
        if self.link.holding:
            self.link.release(self._now() or 0.0)
        while True:
            self._send_reply(impatient)
            if self.batch is not None and not impatient:
                self.batch.request(self)   # its flush asks whether a step is ready
                return
            self.before_step()
            if not rt.advance(1, impatient=impatient):
                return
            if impatient:
                self.events['impatient_steps'] += 1
                impatient = False
            self.after_step()

    def before_step(self) -> None:
        """Skip channels deferred for own measurements that never came (one instant each)."""
        if self.rt is not None and self._deferred == self.rt.k:
            self.events['channels_skipped'] += 1
            self._deferred = -1

    def after_step(self) -> None:
        """What follows a step: what it publishes, and a second round's reply."""
        rt = self.rt
        assert rt is not None
        if self._wall_first_step is None:
            self._wall_first_step = time.monotonic()
        self._publish(grid=round((rt.t - rt.origin) / rt.h) % self.s.publish_every == 0)
        self._send_reply()

    def _send_reply(self, impatient: bool = False) -> None:
        """A later round for the current step, once the first is in."""
        rt = self.rt
        reply = None if rt is None else rt.pending_reply(impatient=impatient)
        if rt is None or reply is None:
            return
        for pub, chans in self.topics.values():
            content = {c.name: reply[c.name] for c in chans if reply.get(c.name)}
            if content:
                pub.publish(wire.encode_channels(rt.t, self.s.estimate_frame, chans, content))

    def on_patience(self) -> None:
        """A step waiting with its own sensors still goes on after ``neighbour_wait`` ('exact')
        or :data:`EXCHANGE_PATIENCE` of wall time; else the runtime's ``link_wait`` rules."""
        rt = self.rt
        waited = None if rt is None else rt.waited_out(
            time.monotonic(), self.s.neighbour_wait if self.exact else EXCHANGE_PATIENCE)
        if rt is not None and waited is not None:
            self.get_logger().warning(
                f'the step at t = {rt.t:.3f} s waited {waited:.3g} s of wall time for '
                f'{rt.awaited or "a neighbour"} with its own sensors standing still: going on '
                'without it (counted in event_impatient_steps)', throttle_duration_sec=5.0)
            self.run_ready_steps(impatient=True)
            self.run_ready_steps()

    def on_watch(self) -> None:
        """Stalled for :data:`WATCH_PERIOD_S` with the clock two steps ahead: take what the
        subscriptions hold unannounced (under lockstep the clock would wait forever)."""
        rt, now = self.rt, self._now()
        if rt is None or now is None:
            return
        moved, self._watched = self._watched != (rt.k, rt.gyro.end), (rt.k, rt.gyro.end)
        if moved or now <= rt.t + 2.0 * rt.h:
            return
        found = take_waiting(self)
        if found:
            self.events['taken_while_stalled'] += found
            self.get_logger().warning(
                f'stalled at t = {rt.t:.3f} s with the clock at {now:.3f} s: took {found} '
                'message(s) waiting in the subscriptions (the executor had not run them)',
                throttle_duration_sec=5.0)
        elif now > rt.gyro.end + 2.0 * rt.h:
            self.get_logger().warning(
                f'no gyro sample after t = {rt.gyro.end:.3f} s while the clock is at '
                f'{now:.3f} s: is the imu publisher alive?', throttle_duration_sec=10.0)

    # --------------------------------------------------------------------------- outputs
    def _publish(self, grid: bool, force: bool = False, deferred: bool = False) -> None:
        """Pose and estimate (on the grid, or when read now) and the channel topics read now;
        ``force``: everything (t0); ``deferred``: channels that waited for own measurements."""
        rt = self.rt
        assert rt is not None
        if rt.withholding:   # cold: no estimate yet rather than a wrong one
            return
        t, frame = rt.t, self.s.estimate_frame
        if not deferred and (force or (self._published_k != rt.k and (grid or any(
                rt.sends_now(c.name, grid) for c in self.pose_channels)))):
            if self.pub_pose is not None:   # first: what the neighbours' steps wait for
                self.pub_pose.publish(cdr.encode_pose_covariance_raw(
                    t, frame, rt.R_hat[0], rt.p_hat[0], rt.covariance()))
            self.pub_estimate.publish(cdr.encode_pose_raw(t, frame, rt.R_hat[0], rt.p_hat[0]))
            if self.tf is not None:
                self.tf.sendTransform(rviz.encode_transform(
                    t, frame, wire.body_frame(self.agent), rt.R_hat[0], rt.p_hat[0]))
            self._published_k = rt.k
        due = {topic: (pub, chans) for topic, (pub, chans) in self.topics.items()
               if any(c.round == 1 and (force or rt.sends_now(c.name, grid)) for c in chans)}
        if not due:
            return
        if (not force and self.method.links == 'sensing' and rt.odometry_live()
                and not rt.measured_at(t)):
            self._deferred = rt.k   # what its listeners pair with their own past: measured
            return                  # at t (the simulator sends it just after the gyro)
        self._deferred = -1
        values = rt.outbox()
        for pub, chans in due.values():
            content = {c.name: values[c.name] for c in chans
                       if not (isinstance(values[c.name], dict) and not values[c.name])}
            if content:   # nothing measured yet: nothing to say
                pub.publish(wire.encode_channels(t, wire.channel_frame(
                    chans[0], self.agent, frame, self.s.world_frame), chans, content))

    def publish_diagnostics(self) -> None:
        """The agent's health on /diagnostics (:func:`runtime.health.health`)."""
        rate = None
        if self.rt is not None:
            (steps, wall), now = self._diag_steps, time.monotonic()
            rate, self._diag_steps = (self.rt.k - steps) / max(now - wall, 1e-9), (self.rt.k, now)
        h = health(self.rt, self.rejected, self.events, rate)
        self.pub_diag.publish(wire.diagnostics(
            f'{self.fleet_prefix}{self.agent}/estimator', self.agent, h.message, h.values,
            self.get_clock().now().to_msg(), h.level))

    def destroy_node(self) -> None:
        """Log what this estimator achieved (:func:`runtime.health.summary`)."""
        if self.rt is not None and self._wall_first_step is not None:
            self.get_logger().info(summary(self.rt, self.rejected, self.events,
                                           time.monotonic() - self._wall_first_step))
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    raise SystemExit(run_node(EstimatorNode, 'estimator', args))


if __name__ == '__main__':
    main()
