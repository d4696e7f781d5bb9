"""``simulator``: the world of a scenario over DDS, with a simulated clock.

Publishes each agent's sensors and ground truth from :class:`sim.world.World` (topics:
msg_defs/README.md), each at its own rate, and ``/clock``, which only it publishes. Within one
instant the gyro sample goes out first (it completes the step that ends there), then the other
sensors (the next step uses them).

Start: it waits until every estimator and the monitor are matched (subscriptions to its
topics, and the estimators' own topics to each other) and every estimator has announced its
t0 state (which it does only once its own subscriptions are matched), then starts the clock at
t = 0, so t = 0 is the same for every node and no first sample is lost.

Pacing (``lockstep``, default on): the clock runs at most ``max_lag`` seconds ahead of the
slowest estimator's state, like Gazebo's lockstep (results are load-independent because of
``fixed_exchange``, not of the pacing); ``real_time_factor`` > 0 also caps it to wall time.

A robot whose process died must not stop the fleet's clock (``lockstep_patience``,
``absent_lag``, ``rejoin_after``; why: README.md, the simulator's description).
"""
from __future__ import annotations

import time
from collections import Counter
from collections.abc import Sequence
from functools import partial
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Empty

from .. import msg_defs as wire
from ..msg_defs import cdr
from ..core.errors import ScenarioError
from ..estimators.base import Sensor
from .monitor_node import watched
from .node_main import (declare, run_node, scenario_parameter, wall_timer,
                        warn_unknown_parameters)
from .wiring import listener_counts, recorded_topics
from ..plan.processes import CLOCK_STARTED
from ..sim.world import World

# Sim time advanced per wall-timer callback at most: keeps the node responsive.
_MAX_SIM_PER_TICK = 0.02
# Wall time [s] the lockstep clock waits for the slowest estimators before it stops waiting for
# them, named (a healthy run waits milliseconds; a loaded one a second at most).
LOCKSTEP_PATIENCE_S = 5.0
# Wall time [s] a stalled clock waits before it asks the graph whether the estimators it waits
# for still have their estimate writers, and between two such questions.
GRAPH_CHECK_S = 0.2


class SimulatorNode(Node):
    def __init__(self, **node_kwargs) -> None:
        """``node_kwargs`` go to rclpy's Node (``context``, ``parameter_overrides``, ...)."""
        super().__init__('simulator', **node_kwargs)
        p = partial(declare, self)
        self.fleet = self.get_namespace().strip('/')   # the fleet namespace: its topics' prefix
        self.scenario = s = scenario_parameter(self)
        self.duration = p('duration', 0.0, 'simulated time [s]; 0: the scenario\'s',
                          0.0, 1e9) or s.duration
        self.lockstep = p('lockstep', True, 'keep the clock at most max_lag ahead of the '
                          'slowest estimator')
        self.max_lag = p('max_lag', 3.0 / s.publish_rate, 'lockstep lead [s]', 0.0, 1e6)
        self.patience = p('lockstep_patience', LOCKSTEP_PATIENCE_S, 'wall time [s] the clock '
                          'waits for estimators whose estimates stopped; 0: for ever', 0.0, 1e6)
        self.absent_lag = p('absent_lag', 0.5, 'lockstep lead [s] while an estimator is not '
                            "waited for: above the estimators' link_wait", 0.0, 1e6)
        self.rejoin_after = p('rejoin_after', 1.0, 'simulated time [s] an absent estimator '
                              'steps before the clock waits for it again', 0.0, 1e6)
        self.rtf = p('real_time_factor', 0.0, 'cap on sim seconds per wall second; 0: none',
                     0.0, 1e6)
        self.wait_for_monitor = p('wait_for_monitor', True,
                                  'start only once the monitor is matched')
        # False: start without each estimator's t0 announcement (fault studies: late joiners,
        # a restarted simulator). Use it with lockstep off, or a silent agent stops the clock.
        self.wait_for_estimators = p('wait_for_estimators', True, 'start only once every '
                                     'estimator announced its t0 state')
        records = p('monitor_records', False, 'the monitor records a bag: the start waits for '
                    "its readers of the simulator's topics too")
        self.start_timeout = p('start_timeout', 120.0, 'give up starting after this [s]', 0.0, 1e6)
        # False: another node owns /clock (a bag replay, Gazebo); the stamps stay sim time.
        self.publish_clock = p('publish_clock', True, 'publish /clock (the simulated time)')

        if s.formation is not None and s.formation.mode == 'paper':
            raise ScenarioError(f'{s.source}: formation_control.mode: paper (the controller uses '
                                'the estimated yaws) needs the estimates inside the truth, '
                                'which a simulator node cannot have. Fix: mode: exogenous (or '
                                'bearing-pose run --formation-mode exogenous)')
        if problem := s.not_distributable():
            raise ScenarioError(f'{s.source}: {problem}')
        self.world = World(s)
        self.monitor_watches = set(watched(s))   # the agents whose truth the monitor reads
        self.recorded = ({topic for topic, _ in recorded_topics(s, self.fleet)}
                         if records and self.wait_for_monitor else set[str]())
        self.names = [a.name for a in s.agents]
        # The topics the estimators exchange, from what the scenario's method sends (a
        # channel of a sensor's readings rides on that sensor's topic: counted there).
        method = s.estimator()
        self.channel_topics = list(dict.fromkeys(c.topic for c in method.sends if c.sensor is None))
        self.uses_bearings = method.uses(Sensor.BEARINGS)
        # Subscriptions each (agent, topic) gets from the other agents' estimators (ros.wiring).
        self.link_subs = listener_counts(s)
        self.pub_imu = self._per_agent(wire.Imu, wire.IMU)
        self.pub_bearings = self._per_agent(wire.PointCloud2, wire.BEARINGS)
        self.pub_truth = self._per_agent(wire.PoseStamped, wire.GROUND_TRUTH)
        self.pub_sensors = {name: self._per_agent(wire.SENSOR_TYPES[name], wire.SENSOR_TOPICS[name])
                            for name in self.world.sensor_every}
        # The sensors each agent's own estimator reads (the others' readers: link_subs).
        self.sensors_read = {name for name in self.pub_sensors if Sensor(name) in method.measures
                             or (name == 'odometry' and method.uses(Sensor.ODOMETRY))}
        self.pub_clock = (self.create_publisher(ClockMsg, wire.fleet_topic(wire.CLOCK, self.fleet),
                                                wire.CLOCK_QOS) if self.publish_clock else None)
        # Estimators' progress: the stamp of each agent's latest estimate (lockstep pacing).
        self.progress = np.full(len(self.names), -np.inf)
        for k, name in enumerate(self.names):
            self.create_subscription(wire.PoseStamped,
                                     wire.topic(name, wire.ESTIMATE, self.fleet),
                                     partial(self._on_estimate, k), wire.ESTIMATE_QOS, raw=True)

        self.monitor_ready = False
        if self.wait_for_monitor:
            self.create_subscription(Empty, wire.fleet_topic(wire.MONITOR_READY, self.fleet),
                                     self._on_monitor_ready, wire.LATCHED_QOS)
        self.state = 'waiting'
        # How far the slowest estimate trailed the clock: µs of sim time -> ticks (few values).
        self.lags: Counter[int] = Counter()
        self.failed = Future()  # completes only if start-up fails; otherwise spin until Ctrl-C
        self.wall_start = time.monotonic()
        self.sim_wall_start = 0.0
        # (slowest estimate time, wall time it was first seen): a stalled lockstep clock.
        self._stall = (-np.inf, 0.0)
        self._graph_checked = 0.0   # wall time of the last look for gone estimate writers
        # The estimators the clock does not wait for, and their estimate time then.
        self.absent = np.zeros(len(self.names), dtype=bool)
        self.left_at = np.full(len(self.names), np.inf)
        self.back_at = np.full(len(self.names), np.inf)
        # /clock once per estimator step: finer ticks only cost every node callbacks.
        self.steps_per_clock = max(1, int(round(s.step / self.world.dt)))
        # Wall clock: the simulator owns sim time. A quarter step (<= 5 ms) keeps /clock smooth;
        # a wake-up costs ~0.3 ms of CPU, so 1 ms took a third of a core (bench/fleet_scale.py).
        self.timer = wall_timer(self, min(0.005, s.step / 4.0), self.on_tick)
        waiting = 'estimators and monitor' if self.wait_for_monitor else 'estimators'
        self.get_logger().info(f'{s.name}: {len(self.names)} agents, {self.duration:g} s'
                               f'{"" if self.publish_clock else ", no /clock"}; '
                               f'waiting for {waiting}')
        warn_unknown_parameters(self)

    def _per_agent(self, msg_type: type, name: str) -> list[Any]:
        return [self.create_publisher(msg_type, wire.topic(a, name, self.fleet),
                                      wire.SIM_PUB_QOS) for a in self.names]

    def _on_monitor_ready(self, _msg: Empty) -> None:
        self.monitor_ready = True

    def _on_estimate(self, k: int, msg: bytes) -> None:
        try:
            t = cdr.read_header(msg).t
        except wire.WireError:
            return   # the estimator's own message: its stamp is what counts here
        self.progress[k] = max(self.progress[k], t)

    # --------------------------------------------------------------------------- start
    def _unmatched(self) -> list[str]:
        """Topics whose expected peers are not matched yet."""
        s, missing = self.scenario, []
        followers = {a.name for a in s.followers}   # the monitor reads their estimates

        def short(pub: Any, readers: int) -> None:
            # Matched by this writer, not only in the graph: a volatile writer sends nothing to an
            # unmatched reader, and under lockstep a missed first sample stops the clock for good.
            if pub.get_subscription_count() < readers + (pub.topic_name in self.recorded):
                missing.append(pub.topic_name)

        for k, name in enumerate(self.names):
            monitored = int(self.wait_for_monitor and name in followers)
            short(self.pub_imu[k], 1)
            short(self.pub_bearings[k], int(self.uses_bearings))
            for sensor, pubs in self.pub_sensors.items():
                # The agent's own estimator, and link neighbours that read it (odometry, a
                # sensor whose readings are a channel).
                short(pubs[k], 1 + self.link_subs[(name, wire.SENSOR_TOPICS[sensor])]
                      if sensor in self.sensors_read else 0)
            short(self.pub_truth[k], int(self.wait_for_monitor and name in self.monitor_watches)
                  + int(name in s.leaders))
            # Every listener subscribes to each channel topic of the agent (link methods: the
            # neighbours that read it); the simulator and the monitor to its estimate as well.
            wanted = {topic: self.link_subs[(name, topic)] for topic in self.channel_topics}
            wanted[wire.ESTIMATE] = wanted.get(wire.ESTIMATE, 0) + 1 + monitored
            for topic, count in wanted.items():
                if self.count_subscribers(wire.topic(name, topic, self.fleet)) < count:
                    missing.append(wire.topic(name, topic, self.fleet))
            if self.count_publishers(wire.topic(name, wire.ESTIMATE, self.fleet)) < 1:
                missing.append(wire.topic(name, wire.ESTIMATE, self.fleet) + ' (publisher)')
        if self.wait_for_monitor and not self.monitor_ready:
            missing.append(wire.fleet_topic(wire.MONITOR_READY, self.fleet))
        return missing

    def _start(self) -> None:
        self.state = 'running'
        self.sim_wall_start = time.monotonic()
        self.get_logger().info(f'all matched after {self.sim_wall_start - self.wall_start:.2f} s;'
                               f' {CLOCK_STARTED}')
        self._publish(clock=True)

    # --------------------------------------------------------------------------- running
    def on_tick(self) -> None:
        if self.state == 'waiting':
            missing = self._unmatched()
            silent = [n for n, t in zip(self.names, self.progress)
                      if t < 0.0 and self.wait_for_estimators]
            if not missing and not silent:
                self._start()
            elif time.monotonic() - self.wall_start > self.start_timeout:
                self.get_logger().error(
                    f'not ready after {self.start_timeout:g} s: unmatched '
                    f'{", ".join(missing[:10]) or "none"}; no t0 estimate from '
                    f'{", ".join(silent[:10]) or "none"}')
                self.state = 'failed'
                self.failed.set_result(False)
            return
        if self.state != 'running':
            return
        w = self.world
        limit = min(self.duration, w.t + _MAX_SIM_PER_TICK)
        if self.lockstep:
            lead = self.absent_lag if self.absent.any() else self.max_lag
            limit = min(limit, self._slowest() + lead)
        if self.rtf > 0.0:
            limit = min(limit, (time.monotonic() - self.sim_wall_start) * self.rtf)
        while w.t + w.dt <= limit + 1e-9:
            w.step()
            self._publish(clock=w.tick % self.steps_per_clock == 0)
        if self.lockstep and w.t < self.duration - 1e-9:
            self._watch_lockstep()
        behind = w.t - self._slowest()
        if np.isfinite(behind):   # not before every estimator has published (no lockstep)
            self.lags[int(round(behind * 1e6))] += 1
        if w.t >= self.duration - 1e-9:
            self.state = 'done'
            wall = time.monotonic() - self.sim_wall_start
            lag = np.repeat(np.array(list(self.lags) or [0], dtype=float) * 1e-3,
                            list(self.lags.values()) or [1])   # [ms], one per tick
            text = (f'reached t = {w.t:g} s in {wall:.1f} s wall (x{w.t / max(wall, 1e-9):.2f} '
                    f'real time); slowest estimate behind the clock: median '
                    f'{np.median(lag):.1f} ms, max {lag.max():.1f} ms of sim time')
            if self.rtf > 0.0:
                # Paced by the wall clock, an estimate is due every publish period: trailing by
                # more than two is a missed deadline (in pure lockstep, lag is by design).
                late_ms = 2e3 / self.scenario.publish_rate
                missed = float(np.mean(lag > late_ms + 1e-6)) * 100.0
                text += (f'; more than {late_ms:.0f} ms behind (a missed deadline) in '
                         f'{missed:.2f} % of ticks')
            self.get_logger().info(text)

    def _slowest(self) -> float:
        """The newest estimate time of the slowest estimator the clock waits for (with none
        waited for, of the most advanced one: the clock still waits for someone)."""
        waited = self.progress[~self.absent]
        return float(waited.min() if waited.size else self.progress.max())

    def _watch_lockstep(self) -> None:
        """Stop waiting for estimators holding the clock whose estimate writer is gone, or after
        :attr:`patience` (warned); wait again after :attr:`rejoin_after` and caught up."""
        slowest, now = self._slowest(), time.monotonic()
        moved = self.absent & (self.progress > self.left_at) & np.isinf(self.back_at)
        self.back_at[moved] = self.progress[moved]
        back = self.absent & (self.progress >= slowest - 1e-9) & (
            self.progress >= self.back_at + self.rejoin_after - 1e-9)
        for k in np.flatnonzero(back):
            self.absent[k] = False
            self.get_logger().info(
                f'{self.names[k]} is back (estimates from t = {self.back_at[k]:.3f} s) and '
                f'has caught up (t = {self.progress[k]:.3f} s): the clock waits for it again')
        lead = self.absent_lag if self.absent.any() else self.max_lag
        held = self.world.t + self.world.dt > slowest + lead + 1e-9   # not by real time
        if slowest != self._stall[0] or not held:
            self._stall = (slowest, now)
            return
        late = [int(k) for k in np.flatnonzero(~self.absent & (self.progress <= slowest))]
        waited_s = now - self._stall[1]
        if self.patience > 0.0 and waited_s >= self.patience:
            self._absent(late, f'its estimates stopped at t = {slowest:.3f} s {waited_s:.0f} s '
                         'of wall time ago')
        elif waited_s >= LOCKSTEP_PATIENCE_S:   # waiting for ever (patience 0): say on whom
            self.get_logger().warning(
                f'the clock has waited {waited_s:.0f} s at t = {self.world.t:.3f} s for '
                f'{", ".join(self.names[k] for k in late)} (newest estimate at t = '
                f'{slowest:.3f} s): those estimators are not stepping; their logs say why',
                throttle_duration_sec=10.0)
        if waited_s >= GRAPH_CHECK_S and now - self._graph_checked >= GRAPH_CHECK_S:
            self._graph_checked = now
            self._absent([k for k in late if not self.absent[k] and self.count_publishers(
                wire.topic(self.names[k], wire.ESTIMATE, self.fleet)) == 0],
                'its estimate writer is gone (the process stopped)')

    def _absent(self, ks: Sequence[int], why: str) -> None:
        """The clock stops waiting for these estimators (:meth:`_watch_lockstep`)."""
        if not ks:
            return
        for k in ks:
            self.absent[k] = True
            self.left_at[k], self.back_at[k] = self.progress[k], np.inf
            self.get_logger().warning(
                f'the clock stops waiting for {self.names[k]} at t = {self.world.t:.3f} s: '
                f'{why}; it leads the others by {self.absent_lag:g} s until {self.names[k]} '
                'is back (restarted with its command) and has caught up')
        self._stall = (self._slowest(), time.monotonic())

    def _publish(self, clock: bool) -> None:
        w, t = self.world, self.world.t
        if w.due(w.imu_every) and w.tick > 0:  # a sample covers the period ending now
            for i, omega in enumerate(w.imu()):
                self.pub_imu[i].publish(cdr.encode_imu_raw(t, self.names[i], omega))
        if w.due(w.bearing_every):
            for i, name in enumerate(self.names):
                j, b = w.bearings(i)
                self.pub_bearings[i].publish(
                    cdr.encode_vectors_raw(t, wire.body_frame(name), j + 1, b))
        for sensor, pubs in self.pub_sensors.items():
            if w.due(w.sensor_every[sensor]) and (sensor != 'odometry' or w.tick > 0):
                self._publish_sensor(sensor, pubs, t)
        if w.due(w.truth_every):
            for i, pub in enumerate(self.pub_truth):
                pub.publish(cdr.encode_pose_raw(t, self.scenario.world_frame, w.R[i], w.p[i]))
        if clock and self.pub_clock is not None:
            self.pub_clock.publish(cdr.encode_clock_raw(t))

    def _publish_sensor(self, sensor: str, pubs: list, t: float) -> None:
        w, spec = self.world, self.scenario.sensors.spec(sensor)
        if sensor == 'odometry':  # interval averages over the period ending now
            v, omega = w.odometry()
            for i, name in enumerate(self.names):
                pubs[i].publish(cdr.encode_odometry_raw(t, name, v[i], omega[i], w.odom_R[i],
                                                        w.odom_p[i], spec.std, spec.angular_std))
            return
        encode = cdr.encode_scalars_raw if sensor == 'ranges' else cdr.encode_vectors_raw
        for i, name in enumerate(self.names):
            j, values = w.sensed(sensor, i)
            pubs[i].publish(encode(t, wire.body_frame(name), j + 1, values))


def main(args: list[str] | None = None) -> None:
    # Spins until Ctrl-C; exits 1 by itself only if start-up fails.
    raise SystemExit(run_node(SimulatorNode, 'simulator', args, until=lambda node: node.failed))


if __name__ == '__main__':
    main()
