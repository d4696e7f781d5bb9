"""``estimator``: one agent's cascaded observer as a ROS 2 node (run one per agent, in /<agent>).

A thin adapter: it decodes messages (``msg_defs``), feeds :class:`agent.AgentEstimator`, runs
its fixed steps ``h = 1/frequency`` as soon as the gyro data covers them (checked on every gyro
sample and on a timer at ``frequency``) and publishes. Subscribes (relative names, remappable):
``imu`` (sensor_msgs/Imu), ``bearings`` (sensor_msgs/PointCloud2), ``known_pose`` (leaders), and
``/<j>/estimate`` + ``/<j>/world_bearings`` of each neighbour j. Publishes ``estimate``
(geometry_msgs/PoseStamped in ``world``) and ``world_bearings`` (what its listeners need) every
``publish_rate`` period, on exact multiples of it.

Parameters: either ``scenario_file`` (+ ``agent``, default: the namespace) or the explicit set
``agent_id``, ``leader``, ``neighbours``, ``neighbour_ids``, ``neighbour_gains``,
``initial_position``, ``initial_orientation`` (x, y, z, w); plus ``frequency`` [Hz], ``k_R``,
``k_p`` (0 = from the scenario, or 100 Hz / 1.0 in explicit mode) and ``start_time`` [s]
(the scenario's t = 0 on the node's clock; negative: the first gyro sample's stamp).
"""
from __future__ import annotations

import time
from collections import Counter

import numpy as np
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from . import msg_defs as wire
from .agent import AgentEstimator, estimator_for
from .node_main import run_node
from .observer import CascadeGains
from .scenario import ScenarioError, load_scenario


def _describe(text: str) -> ParameterDescriptor:
    return ParameterDescriptor(description=text)


class EstimatorNode(Node):
    def __init__(self) -> None:
        super().__init__('estimator')
        p = self.declare_parameter
        scenario_file = p('scenario_file', '', _describe('scenario YAML; empty: explicit '
                                                          'parameters')).value
        default_agent = self.get_namespace().strip('/').split('/')[-1]
        self.agent = p('agent', default_agent, _describe('agent name (default: namespace)')).value
        frequency = p('frequency', 0.0, _describe('estimator rate [Hz]; 0: scenario / 100')).value
        publish_rate = p('publish_rate', 0.0, _describe('estimate and world-bearing rate [Hz]; '
                                                        '0: scenario / 50')).value
        k_R = p('k_R', 0.0, _describe('attitude gain; 0: scenario / 1')).value
        k_p = p('k_p', 0.0, _describe('position gain; 0: scenario / 1')).value
        self.start_time = p('start_time', 0.0, _describe('t = 0 of the scenario on this clock [s]; '
                                                        'negative: first gyro stamp')).value
        explicit = {
            'agent_id': p('agent_id', 0).value,
            'leader': p('leader', False).value,
            'neighbours': p('neighbours', ['']).value,
            'neighbour_ids': p('neighbour_ids', [0]).value,
            'neighbour_gains': p('neighbour_gains', [0.0]).value,
            'initial_position': p('initial_position', [0.0, 0.0, 0.0]).value,
            'initial_orientation': p('initial_orientation', [0.0, 0.0, 0.0, 1.0]).value,
        }
        if scenario_file:
            scenario = load_scenario(scenario_file)
            if self.agent not in scenario.index:
                raise ScenarioError(f'{scenario_file}: agent {self.agent!r} is not in the '
                                    'scenario. Fix: set the `agent` parameter or the namespace')
            template = estimator_for(scenario, self.agent)
            publish_rate = publish_rate or scenario.publish_rate
        else:
            template = self._explicit_estimator(explicit)
            publish_rate = publish_rate or 50.0
        gains = CascadeGains(k_R=k_R or template.gains.k_R, k_p=k_p or template.gains.k_p)
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
        self._published_k = -1
        self._wall_first_step: float | None = None

        qos_in, qos_est = wire.SENSOR_QOS, wire.ESTIMATE_QOS
        self.pub_estimate = self.create_publisher(wire.PoseStamped, wire.ESTIMATE, qos_est)
        self.pub_world = self.create_publisher(wire.PointCloud2, wire.WORLD_BEARINGS, qos_est)
        subs = [self.create_subscription(wire.Imu, wire.IMU, self.on_imu, qos_in),
                self.create_subscription(wire.PointCloud2, wire.BEARINGS, self.on_bearings,
                                         qos_in)]
        if template.leader:
            subs.append(self.create_subscription(wire.PoseStamped, wire.KNOWN_POSE,
                                                 self.on_known_pose, qos_est))
        self._nbr_p_hat: dict[int, np.ndarray] = {}
        for nb in template.neighbours:
            subs.append(self.create_subscription(
                wire.PoseStamped, wire.topic(nb.name, wire.ESTIMATE),
                lambda msg, j=nb.agent_id: self.on_neighbour_estimate(j, msg), qos_est))
            subs.append(self.create_subscription(
                wire.PointCloud2, wire.topic(nb.name, wire.WORLD_BEARINGS),
                lambda msg, j=nb.agent_id: self.on_neighbour_bearings(j, msg), qos_est))
        self._subs = subs
        self.timer = self.create_timer(self.h, self.on_timer)
        # Until the first gyro sample, announce the t0 state on a wall-clock timer, but only once
        # every subscription has a publisher: best-effort sensor readers drop what arrives before
        # they are matched, so the simulator starts the clock only after hearing from everyone.
        self.ready_timer = self.create_timer(
            0.05, self.on_ready_check, clock=Clock(clock_type=ClockType.STEADY_TIME))
        role = 'leader' if template.leader else f'{len(template.neighbours)} neighbours'
        self.get_logger().info(f'{self.agent} (id {template.agent_id}, {role}) at '
                               f'{1.0 / self.h:g} Hz, k_R={gains.k_R:g}, k_p={gains.k_p:g}')

    # --------------------------------------------------------------------------- set-up
    def _explicit_estimator(self, e: dict) -> AgentEstimator:
        from scipy.spatial.transform import Rotation

        names = [n for n in e['neighbours'] if n]
        if e['agent_id'] <= 0:
            raise ScenarioError('parameter agent_id must be > 0 without a scenario_file. Fix: '
                                'set agent_id (and neighbours, neighbour_ids) or scenario_file')
        if not e['leader'] and not (len(names) == len(e['neighbour_ids'])
                                    == len(e['neighbour_gains']) >= 2):
            raise ScenarioError('parameters neighbours, neighbour_ids and neighbour_gains need '
                                'the same length >= 2 for a follower. Fix: list each neighbour '
                                'once in all three')
        nbrs = [] if e['leader'] else list(zip(names, e['neighbour_ids'], e['neighbour_gains']))
        return AgentEstimator(agent_id=e['agent_id'], neighbours=nbrs, gains=CascadeGains(),
                              step=0.01, leader=e['leader'],
                              R0=Rotation.from_quat(e['initial_orientation']).as_matrix(),
                              p0=np.array(e['initial_position'], dtype=float))

    def _make_estimator(self, t0: float) -> AgentEstimator:
        t = self.template
        return AgentEstimator(agent_id=t.agent_id,
                              neighbours=[(n.name, n.agent_id, n.k) for n in t.neighbours],
                              gains=self.gains, step=self.h, R0=t.R_hat[0], p0=t.p_hat[0],
                              t0=t0, leader=t.leader)

    def _reject(self, cause: str, detail: str) -> None:
        self.rejected[cause] += 1
        self.get_logger().warning(f'rejected {cause}: {detail} ({self.rejected[cause]} so far)',
                                  throttle_duration_sec=5.0)

    # --------------------------------------------------------------------------- inputs
    def on_imu(self, msg: wire.Imu) -> None:
        try:
            t, omega = wire.decode_imu(msg)
        except wire.WireError as exc:
            return self._reject('imu', str(exc))
        if self.est is None:
            self.est = self._make_estimator(t)
            return
        if not self.ready_timer.is_canceled():
            self.ready_timer.cancel()
        if not self.est.add_gyro(t, omega):
            return self._reject('imu', f'stamp {t:.6f} not newer than {self.est.gyro.end:.6f}')
        # Steps run as soon as the gyro covers them. Waiting for the timer alone can deadlock
        # a lockstep simulation: a clock tick handled before the IMU sample of the same
        # instant fires the timer too early, and the clock then waits for this agent.
        self.on_timer()

    def on_bearings(self, msg: wire.PointCloud2) -> None:
        try:
            t, ids, vectors = wire.decode_vectors(msg)
        except wire.WireError as exc:
            return self._reject('bearings', str(exc))
        if self.est is None:
            return
        self.est.add_bearings(t, ids, vectors)
        if self.est.k == 0 and self.est.gyro.end <= self.est.t0:
            self._publish(world=True)  # the t0 world bearings, before the first step

    def on_known_pose(self, msg: wire.PoseStamped) -> None:
        try:
            t, R, p = wire.decode_pose(msg)
        except wire.WireError as exc:
            return self._reject('known_pose', str(exc))
        if self.est is not None:
            self.est.set_known_pose(t, R, p)

    def on_neighbour_estimate(self, agent_id: int, msg: wire.PoseStamped) -> None:
        try:
            _, _, p = wire.decode_pose(msg)
        except wire.WireError as exc:
            return self._reject('neighbour_estimate', str(exc))
        self._nbr_p_hat[agent_id] = p

    def on_neighbour_bearings(self, agent_id: int, msg: wire.PointCloud2) -> None:
        try:
            t, ids, vectors = wire.decode_vectors(msg)
        except wire.WireError as exc:
            return self._reject('neighbour_bearings', str(exc))
        p_hat = self._nbr_p_hat.get(agent_id)
        if self.est is None or p_hat is None:
            return
        self.est.add_neighbour(agent_id, t, p_hat, dict(zip(ids.tolist(), vectors)))

    # --------------------------------------------------------------------------- stepping
    def on_ready_check(self) -> None:
        if self.est is None or self.est.k > 0:
            return
        if all(sub.get_publisher_count() > 0 for sub in self._subs):
            self._publish(world=True, force=True)

    def on_timer(self) -> None:
        if self.est is None:
            return
        while self.est.steps_ready() > 0:
            if self._wall_first_step is None:
                self._wall_first_step = time.monotonic()
            self.est.advance(1)
            if self.est.k % self.publish_every == 0:
                self._publish(world=True)

    def destroy_node(self) -> None:
        """Log what this estimator achieved: steps, the step rate in wall time, rejections."""
        if self.est is not None and self._wall_first_step is not None:
            wall = max(time.monotonic() - self._wall_first_step, 1e-9)
            self.get_logger().info(
                f'{self.est.k} steps ({self.est.k * self.h:.2f} s of state time) in {wall:.1f} s '
                f'wall: {self.est.k / wall:.1f} steps/s; rejected: {dict(self.rejected) or 0}')
        super().destroy_node()

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


def main(args: list[str] | None = None) -> None:
    raise SystemExit(run_node(EstimatorNode, 'estimator', args))


if __name__ == '__main__':
    main()
