"""``estimator``: one agent's estimator as a ROS 2 node (run one per agent, in /<agent>), with
the scenario's ``method`` (any registered one: ``bearing_pose_estimation.estimators``).

A thin adapter: it decodes messages (``msg_defs``), feeds
:class:`estimators.agent.AgentEstimator`, runs its fixed steps ``h = 1/frequency`` as soon as
the inputs cover them (checked on every input that can complete a step: no timer) and
publishes. Subscribes (relative names, remappable): ``imu`` (sensor_msgs/Imu), ``bearings``
(sensor_msgs/PointCloud2), ``known_pose`` (leaders), ``odom`` (nav_msgs/Odometry, for methods
that use odometry: the feed-forward of moving agents), and, for each neighbour j, the topics of
the channels the method sends, one subscription per topic (``msg_defs.CHANNELS``; both
leader-follower methods: ``/<j>/pose``, its p̂_j with its covariance, and
``/<j>/world_bearings``). Publishes ``estimate`` (geometry_msgs/PoseStamped in ``world``),
``pose`` (the same with its covariance, geometry_msgs/PoseWithCovarianceStamped: what the
neighbours and robot_localization read) and
its other channels (``world_bearings``: what its listeners need) every ``publish_rate``
period, on exact multiples of it, and its health on ``/diagnostics``. When the agent moves
(odometry is live), the world bearings of an instant wait for the own bearings measured at it
(listeners pair values of one instant, ``msg_defs/README.md``), and are skipped if the next
step comes first.

Methods whose robots talk over communication links (De Carli et al.) run
:class:`estimators.link_agent.LinkAgentEstimator` instead: the node subscribes to its own
``relative_positions`` (not ``bearings``), and, for each communication neighbour j, to j's
``odom``, j's ``relative_positions`` where j senses this robot, and j's channel topics
(``yaw_estimate``, ``relative_yaws``, ``pose``); it publishes its estimate in
``<fleet>/estimation`` at ``publish_rate`` and its channels when a neighbour's next step reads
them; steps run as soon as every input of their instant is in (``link_wait``, ``neighbour_wait``
bound the wait). These need ``scenario_file`` (the links come from the sensing graph).

Methods with two rounds of messages per step (Presenza et al.) run
:class:`estimators.two_round_agent.TwoRoundAgent`: the node subscribes to its own
``bearings`` and ``bearing_rates`` (unless the scenario estimates the rates from the bearings),
the ``pose`` of each robot it senses, the anchor's ``odom`` and, for a ranged robot, the
anchor's ``relative_positions`` (``ros.wiring``); once a step's first round is in it publishes
its second (``angle_gradient``, ``angle_hessian``, ``anchor_bearing``, ``velocity_term``, to
the robots it senses), then steps once the second round of the robots that sense it is in.
Its estimate is in the anchor's body frame, ``<anchor>/base_link``.

In a simulation (``fixed_exchange``, default: ``use_sim_time``) a leader-follower step does not
use whatever has arrived: step ``[t, t + h]`` waits for the own bearings (a leader's known
pose, simulated odometry) measured by ``t + h`` and for each neighbour's values of its publish
instant at or before ``t`` (:class:`estimators.agent.Exchange`): what netsim feeds the same
logic, so a run equals netsim's to rounding however loaded the machine is. An input that does
not come is waited out once the own sensors are ``link_wait`` ahead (``incomplete_steps`` in
the diagnostics). Off on real robots (nothing waits) and under injected faults.

Bad input is rejected, counted by cause, warned about (throttled) and reported in the
diagnostics; it never stops the node and never reaches the estimate.

Parameters: either ``scenario_file`` (+ ``agent``, default: the namespace) or the explicit set
``agent_id``, ``leader``, ``neighbours``, ``neighbour_ids``, ``neighbour_gains``,
``initial_position``, ``initial_orientation`` (x, y, z, w), with ``method`` (empty: the
registry's default, ``boughellaba_tayebi``); ``frequency`` [Hz], ``publish_rate`` [Hz] and the
method's gains, named as in a scenario's ``gains:`` (``k_R``, ``k_p`` for boughellaba_tayebi;
``k_omega``, ``k_c``, ``k_p`` for tran_anderson_ahn; ...; the covariance's noise model and
prior, ``bearing_std``, ``gyro_noise_density``, ..., are gains too), each declared with its
effective value (the scenario's, or 100 Hz / 50 Hz / the method's defaults in explicit mode), so
``ros2 param get`` tells the truth; a gain of another method is an error.
``start_time`` [s] (the scenario's t = 0 on the node's clock; negative: the first gyro stamp);
the input limits ``sensor_timeout``, ``neighbour_timeout``, ``max_rate``, ``link_wait`` [s of
the own sensors' time] and ``neighbour_wait`` [s of wall time]. The gains and these limits can
be set while the node runs (``ros2 param set``): a change is validated (range, the gain's
minimum, and the method's check on the scenario) and applies from the next step, or is
refused with the reason; every other parameter is read-only. The expected frames
``imu_frame``, ``bearings_frame``, ``odom_child_frame`` (empty: accept any);
``diagnostics_period`` [s, wall clock]; ``fixed_exchange`` (above); and the fault
injection for tests and studies: ``inject_drop_rate`` (probability of dropping each neighbour
message), ``inject_delay`` [s] (extra delay of each neighbour message), ``inject_seed``.
Integers are accepted for numbers; a wrong type or range stops the node with a one-line error,
and unknown keys in a parameter file are warned about (see :func:`node_main.declare`).
"""
from __future__ import annotations

import dataclasses
import heapq
import re
import time
from collections import Counter
from collections.abc import Callable, Collection
from dataclasses import replace
from typing import Any
from functools import partial

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from .. import estimators
from .. import msg_defs as wire
from ..msg_defs import cdr, rviz
from ..core import so3
from ..core.errors import ScenarioError
from ..estimators.agent import TIME_EVENTS, AgentEstimator, Exchange, Limits
from ..estimators.base import (Array, Channel, Estimator, Sensor, format_gains, gain_fields,
                               parse_gains)
from ..estimators.link_agent import LinkAgentEstimator
from ..estimators.two_round_agent import TwoRoundAgent
from ..scenario.agents import agent_for
from ..scenario.model import Scenario
from ..scenario.parse import load_scenario
from .node_main import declare, parameter_overrides, run_node, warn_unknown_parameters
from .step_batch import StepBatch
from .wiring import link_subscriptions, listener_counts, optional_first

# What takes each of msg_defs' decoders' place when the message comes as bytes.
_RAW_DECODERS: dict[Callable[..., tuple], Callable[[bytes], tuple]] = {
    wire.decode_imu: cdr.decode_imu_raw, wire.decode_vectors: cdr.decode_vectors_raw,
    wire.decode_pose: cdr.decode_pose_raw}


def _decode_odometry(msg: wire.Odometry | bytes,
                     child_frame: str | None) -> tuple[float, Array, Array]:
    if isinstance(msg, bytes):
        return cdr.decode_odometry_raw(msg, child_frame)
    return wire.decode_odometry(msg, child_frame)


# fixed_exchange: wall time [s] a step waits with its own sensors standing still before going
# on without an awaited input. Only a hang breaker: under lockstep nothing it awaits is lost
# for good, and a loaded machine can stall a process for 0.25 s (README, De Carli over DDS).
EXCHANGE_PATIENCE = 10.0
# Wall time [s] between checks for a stalled agent (EstimatorNode.on_watch).
WATCH_PERIOD_S = 1.0
# The end-of-run log's count of those steps (destroy_node), as benchmarks read it: 0 or a dict.
INCOMPLETE_LOG = re.compile(r'steps without an awaited input: (\{[^}]*\}|0)')
# The input limits a running node takes (with the gains and neighbour_wait).
_LIVE_LIMITS = ('sensor_timeout', 'neighbour_timeout', 'max_rate', 'link_wait')

# Used only without a scenario file.
_EXPLICIT = ('agent_id', 'leader', 'neighbours', 'neighbour_ids', 'neighbour_gains',
             'initial_position', 'initial_orientation')


def _gain_parameters() -> dict[str, str]:
    """Every gain of every registered method, with its help and the methods that read it."""
    out: dict[str, tuple[str, list[str]]] = {}
    for method in estimators.methods():
        for f in gain_fields(estimators.get(method).Gains):
            out.setdefault(f.name, (f.metadata['help'], []))[1].append(method)
    return {name: f'{text} ({", ".join(users)})' for name, (text, users) in out.items()}


def _validated_gains(base: Any, values: dict[str, float]) -> Any:
    """``base`` (a method's gains) with ``values``, each finite and above its minimum."""
    return parse_gains(type(base), {**dataclasses.asdict(base), **values}, where='parameter')


def _refuse_other_gains(method: str, own: list[str], given: Collection[str], where: str,
                        fix: str) -> None:
    """A gain parameter of another method is an error, not an unknown key."""
    for gain in given:
        if gain in _gain_parameters() and gain not in own:
            other = next(m for m in estimators.methods()
                         if gain in [f.name for f in gain_fields(estimators.get(m).Gains)])
            raise ScenarioError(f'parameter {gain} is a {other} gain, but {where} is {method}. '
                                f'Fix: remove {gain} ({method} takes {", ".join(own)}); {fix}')


class EstimatorNode(Node):
    def __init__(self, batch: StepBatch | None = None, **node_kwargs) -> None:
        """``batch``: the steps of the agents that share this process, run together (the
        ``estimators`` process, :mod:`.step_batch`). ``node_kwargs`` go to rclpy's Node
        (``namespace``, ``context``,
        ``parameter_overrides``, ``cli_args``, ...): several agents can share one process."""
        super().__init__('estimator', **node_kwargs)
        p = partial(declare, self)
        scenario_file = p('scenario_file', '', 'scenario YAML; empty: explicit parameters')
        default_agent = self.get_namespace().strip('/').split('/')[-1]
        # Neighbours' topics are beside this node's: /<fleet>/<j>/... (run --fleet-namespace).
        self.fleet = wire.fleet_of(self.get_namespace())
        self.fleet_prefix = f'{self.fleet}/' if self.fleet else ''   # of /diagnostics names
        self.agent = p('agent', default_agent, 'agent name (default: namespace)')
        methods = estimators.methods()
        method = p('method', '', f'estimator, {" or ".join(methods)}; empty: the scenario\'s '
                   f'(explicit mode: {estimators.DEFAULT_METHOD})')
        self.start_time = p('start_time', 0.0, 't = 0 of the scenario on this clock [s]; '
                            'negative: the first gyro stamp')
        d = Limits()
        limits = Limits(
            sensor_timeout=p('sensor_timeout', d.sensor_timeout,
                             'own bearings older than this are not used [s]', 0.0, 1e6,
                             read_only=False),
            neighbour_timeout=p('neighbour_timeout', d.neighbour_timeout,
                                'a neighbour silent for longer is stale and not used [s]',
                                0.0, 1e6, read_only=False),
            max_rate=p('max_rate', d.max_rate, 'gyro rates above this are rejected [rad/s]',
                       0.0, 1e6, read_only=False),
            link_wait=p('link_wait', d.link_wait, 'methods that talk over communication '
                        'links, and fixed_exchange: a step waits for an input until the own '
                        'sensors are this far ahead [s]', 0.0, 1e6, read_only=False))
        self.imu_frame = p('imu_frame', wire.body_frame(self.agent),
                           'expected Imu frame_id; empty: any')
        self.bearings_frame = p('bearings_frame', wire.body_frame(self.agent),
                                'expected bearings frame_id; empty: any')
        self.odom_child_frame = p('odom_child_frame', wire.body_frame(self.agent),
                                  'expected Odometry child_frame_id (the twist\'s frame); '
                                  'empty: any')
        diagnostics_period = p('diagnostics_period', 1.0, '/diagnostics period [s, wall clock]',
                               0.01, 3600.0)
        self.neighbour_wait = p('neighbour_wait', 0.25, 'methods that talk over communication '
                                'links: wall time [s] a step waits for a neighbour\'s missing '
                                'input before going on without it', 0.0, 60.0,
                                read_only=False)
        self.drop_rate = p('inject_drop_rate', 0.0, 'fault injection: probability of dropping '
                           'each neighbour message', 0.0, 1.0)
        self.delay = p('inject_delay', 0.0, 'fault injection: extra delay of each neighbour '
                       'message [s]', 0.0, 60.0)
        self.rng = np.random.default_rng(p('inject_seed', 0, 'fault injection: random seed',
                                           0, 2**31 - 1))
        # Simulation: each step's inputs fixed by their stamps and waited for (agent.Exchange),
        # so runs do not depend on the machine's load. Off for real robots (nothing waits) and
        # under injected faults (which are themselves random).
        sim_time = bool(self.get_parameter('use_sim_time').value)
        self.fixed_exchange = p('fixed_exchange', sim_time, 'leader-follower methods: a step '
                                'uses the own measurements up to its end and each neighbour\'s '
                                'values of its publish instant at or before its start, and '
                                'waits for them (default: use_sim_time)')
        if self.fixed_exchange and (self.drop_rate or self.delay):
            self.get_logger().info('fixed_exchange off: faults are injected')
            self.fixed_exchange = False
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
        if method and method not in methods:
            raise ScenarioError(f'parameter method: unknown method {method!r}. Fix: one of '
                                f'{", ".join(methods)}, or empty')
        scenario: Scenario | None = None
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
            template = agent_for(scenario, self.agent, limits)
            listeners = {topic: n for (agent, topic), n in listener_counts(scenario).items()
                         if agent == self.agent}
            self.expect_odometry = scenario.simulates('odometry')
            fleet, anchor = scenario.name, scenario.anchor
            publish_rate = scenario.publish_rate
            method = scenario.method
            where, fix = "the scenario's method", 'the scenario file sets the method'
        else:
            method = method or estimators.DEFAULT_METHOD
            if estimators.get(method).links == 'communication':
                raise ScenarioError(f'method {method} needs scenario_file: its communication '
                                    'links come from the sensing graph. Fix: set scenario_file')
            fleet, anchor = 'fleet', None
            listeners = {}   # unknown: the t0 announcement waits for no reader
            self.expect_odometry = False   # used whenever it arrives
            template = self._explicit_estimator(
                explicit, limits, estimators.build(method, estimators.get(method).Gains()))
            publish_rate = 50.0
            where = 'the method parameter'
            fix = f'or set method: {" / ".join(m for m in methods if m != method)}'
        # Every parameter reads its effective value (`ros2 param get` tells the truth): the
        # rates and gains default to the scenario's (explicit mode: 100 Hz, 50 Hz, the
        # method's defaults). The gains and the input limits can be set live (validated).
        frequency = p('frequency', 1.0 / template.h, 'estimator rate [Hz] (default: the '
                      "scenario's, 100 in explicit mode)", 1e-3, 1e4)
        publish_rate = p('publish_rate', publish_rate, 'estimate and world-bearing rate [Hz] '
                         "(default: the scenario's, 50 in explicit mode)", 1e-3, 1e4)
        own = [f.name for f in gain_fields(type(template.gains))]
        _refuse_other_gains(method, own, parameter_overrides(self), where, fix)
        help_of = _gain_parameters()
        gains = _validated_gains(template.gains, {
            g: p(g, float(getattr(template.gains, g)), f'{help_of[g]}; can be set live', 0.0,
                 1e6, read_only=False) for g in own})
        self.scenario = scenario
        self.template = template
        self.gains = gains
        self.method = estimators.get(method)
        self.links = isinstance(template, LinkAgentEstimator)
        world = scenario.world_frame if scenario is not None else wire.WORLD_FRAME
        self.world_frame = p('world_frame', world, "the world (fixed) frame's id: of world-pose "
                             "estimates, world bearings and a leader's known pose (default: the "
                             "scenario's world_frame)")
        self.estimate_frame = wire.estimate_frame(self.method.frame.value, fleet, anchor,
                                                  self.world_frame)
        self.tf = self._tf_broadcaster(p('publish_tf', True, 'broadcast the estimate on TF '
                                         '(estimate frame -> <agent>/base_link) when tf2_ros '
                                         'is installed; false for a robot whose odometry owns '
                                         'base_link'))
        # Messages as their serialised bytes, decoded and encoded with numpy (msg_defs/cdr.py):
        # rclpy then builds no Python message (BENCHMARKS.md, "Raw CDR").
        self.raw = bool(p('raw_messages', True, 'take and publish messages as serialised bytes '
                          '(msg_defs/cdr.py); false: as rclpy message objects'))
        self._encode_pose: Callable[..., Any] = (cdr.encode_pose_raw if self.raw
                                                 else wire.encode_pose)
        self._encode_pose_covariance: Callable[..., Any] = (
            cdr.encode_pose_covariance_raw if self.raw else wire.encode_pose_covariance)
        self.h = 1.0 / frequency
        # Publish on exact multiples of the publish period, so the monitor can pair estimates
        # with ground truth at identical stamps.
        self.publish_every = max(1, int(round(1.0 / (self.h * publish_rate))))
        self.est: AgentEstimator | LinkAgentEstimator | None = None
        if self.start_time >= 0.0:
            self.est = self._make_estimator(self.start_time)
        self.rejected: Counter[str] = Counter()
        self.events: Counter[str] = Counter()
        self._published_k = -1
        self._deferred = -1   # the step whose publication waits for its bearings
        self._wall_first_step: float | None = None
        self._delayed: list[tuple[float, int, Callable[[], None]]] = []  # (release, seq, fn)
        self._seq = 0
        self._diag_steps = (0, time.monotonic())
        # (k, gyro end, wall time) when a step began to wait with its sensors standing still.
        self._stuck: tuple[int, float, float] | None = None

        qos_in, qos_est = wire.SENSOR_QOS, wire.ESTIMATE_QOS
        self.pub_estimate = self.create_publisher(wire.PoseStamped, wire.ESTIMATE,
                                                 wire.ESTIMATE_PUB_QOS)
        # The channels that need a message of their own (the others ride on the pose).
        self.wires = {c.name: wire.channel(c.name) for c in optional_first(self.method.sends)}
        if self.method.rounds == 2:
            # Every step waits for these values, the first ones too: a reader that its writer
            # discovers late still gets them (transient local, as the estimate's writer).
            qos_est = wire.ESTIMATE_RECORD_QOS
        self.pub_channels: dict[str, tuple[Any, Callable[[float, Any, str], Any]]] = {}
        for name, w in self.wires.items():
            encode = cdr.RAW_CHANNELS[name][1] if self.raw else w.encode
            if encode is not None:
                self.pub_channels[name] = (self.create_publisher(w.type, w.topic, qos_est),
                                           encode)
        # The estimate with its covariance, on the publish grid: what the neighbours read.
        self.pub_pose = (self.create_publisher(wire.PoseWithCovarianceStamped, wire.POSE,
                                               wire.ESTIMATE_PUB_QOS)
                         if any(w.topic == wire.POSE for w in self.wires.values()) else None)
        self.pub_diag = self.create_publisher(DiagnosticArray, wire.DIAGNOSTICS, 10)
        # The neighbours' readers of each writer: the t0 state is announced once they are
        # matched, so the simulator's clock starts only when every value sent reaches them
        # (its graph view sees a reader before the reader's writer has matched it).
        writers = {wire.ESTIMATE: self.pub_estimate,
                   **({wire.POSE: self.pub_pose} if self.pub_pose is not None else {}),
                   **{self.wires[name].topic: pub for name, (pub, _) in self.pub_channels.items()}}
        self._readers_wanted = [(writers[topic], n) for topic, n in listeners.items()
                                if topic in writers]
        # The steps wait for the batch (a two-round method's replies do not), which learns
        # from the count of callbacks when the queued messages are handled.
        self.batch = batch
        if self.batch is not None:
            self.batch.join(self)

        def subscribe(msg_type: Any, topic: str, callback: Callable[[Any], None],
                      qos: Any) -> Any:
            if self.batch is not None:
                callback = self.batch.counted(callback)
            return self.create_subscription(msg_type, topic, callback, qos, raw=self.raw)

        subs = [subscribe(wire.Imu, wire.IMU, self.on_imu, qos_in)]
        if self.method.uses(Sensor.BEARINGS):
            subs.append(subscribe(wire.PointCloud2, wire.BEARINGS, self.on_bearings, qos_in))
        if self.method.uses(Sensor.BEARING_RATES) and getattr(template, 'rate_tau',
                                                              None) is None:
            subs.append(subscribe(wire.PointCloud2, wire.BEARING_RATES, self.on_bearing_rates,
                            qos_in))
        if self.method.uses(Sensor.RELATIVE_POSITIONS):
            subs.append(subscribe(wire.PointCloud2, wire.RELATIVE_POSITIONS,
                            self.on_relative_positions, qos_in))
        if self.method.uses(Sensor.ODOMETRY):
            odom = subscribe(wire.Odometry, wire.ODOM, self.on_odometry, qos_in)
            if self.expect_odometry:  # the t0 announcement waits for its publisher too
                subs.append(odom)
        if template.leader:
            # Best effort matches both a reliable publisher (the simulator) and a best-effort
            # one (many mocap and GNSS drivers); a reliable reader would miss the latter. A lost
            # sample costs nothing: the gyro carries the pose to the next one.
            subs.append(subscribe(wire.PoseStamped, wire.KNOWN_POSE, self.on_known_pose, qos_in))
        if isinstance(template, LinkAgentEstimator):
            for sub in link_subscriptions(template):
                if not sub.channels:   # its motion: what this robot senses of it, the anchor
                    subs.append(subscribe(
                        wire.Odometry, wire.topic(sub.agent, wire.ODOM, self.fleet),
                        partial(self._link, self.on_neighbour_odometry, sub.agent_id,
                                sub.agent), qos_in))
                    continue
                w = self.wires[sub.channels[0]]
                sensor = any(self.method_channel(c).sensor for c in sub.channels)
                subs.append(subscribe(
                    w.type, wire.topic(sub.agent, w.topic, self.fleet),
                    partial(self._link, self.on_neighbour, sub.agent_id, sub.channels,
                            sub.agent), qos_in if sensor else qos_est))
        else:
            for nb in template.neighbours:
                for topic, names in wire.channel_topics(self.wires).items():
                    subs.append(subscribe(
                        self.wires[names[0]].type, wire.topic(nb.name, topic, self.fleet),
                        partial(self._link, self.on_neighbour, nb.agent_id, names, nb.name),
                        qos_est))
        self._subs = subs
        # No step timer: every input that can complete a step runs it (run_ready_steps); a
        # timer at the step rate cost each agent ~100 wake-ups a second for nothing.
        # Health on the wall clock: a stopped or finished simulation still reports (and a
        # fast one gets its reports, as a monitor expects them: every period of real time).
        self.diag_timer = self.create_timer(diagnostics_period, self.publish_diagnostics,
                                            clock=Clock(clock_type=ClockType.STEADY_TIME))
        # Until the first gyro sample, announce the t0 state on a wall-clock timer, but only once
        # every subscription has a publisher and every writer its neighbours' readers:
        # best-effort sensor readers drop what arrives before they are matched, and a volatile
        # writer's values never reach a reader it matches later, so the simulator starts the
        # clock only after hearing from everyone.
        self.ready_timer = self.create_timer(
            0.05, self.on_ready_check, clock=Clock(clock_type=ClockType.STEADY_TIME))
        if self.links or self.fixed_exchange:   # a step waiting for a lost input goes on
            # A twentieth of neighbour_wait (0.25 s), or of EXCHANGE_PATIENCE (10 s).
            self.patience_timer = self.create_timer(
                0.05 if self.links else 0.5, self.on_patience,
                clock=Clock(clock_type=ClockType.STEADY_TIME))
        # A stalled agent (its clock ahead of its state, nothing changing for a second) checks
        # its subscriptions for messages the executor has not run (:meth:`on_watch`).
        self._watched: tuple[int, float] | None = None
        self.watch_timer = self.create_timer(WATCH_PERIOD_S, self.on_watch,
                                             clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        role = 'leader' if template.leader else f'{len(template.neighbours)} neighbours'
        faults = (f'; INJECTING drop {self.drop_rate:g}, delay {self.delay:g} s on neighbour '
                  'messages' if self.drop_rate or self.delay else '')
        self.get_logger().info(f'{self.agent} (id {template.agent_id}, {role}) at '
                               f'{1.0 / self.h:g} Hz, {method}: {format_gains(gains)}{faults}')
        warn_unknown_parameters(self)

    # --------------------------------------------------------------------------- set-up
    def method_channel(self, name: str) -> Channel:
        """The method's channel ``name``."""
        return next(c for c in self.method.sends if c.name == name)

    def _explicit_estimator(self, e: dict, limits: Limits,
                            estimator: Estimator) -> AgentEstimator:
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
        return AgentEstimator(estimator, agent_id=e['agent_id'], neighbours=nbrs,
                              step=0.01, leader=e['leader'], R0=so3.from_quat(q), p0=p0,
                              limits=limits)

    def _tf_broadcaster(self, wanted: bool) -> Any:
        """tf2_ros's TransformBroadcaster, when wanted and installed (a full Jazzy install;
        the PyPI wheels have no tf2_ros), else None."""
        if not wanted:
            return None
        try:
            from tf2_ros import TransformBroadcaster
        except ImportError:
            self.get_logger().info('tf2_ros is not installed: no TF broadcast (the estimate '
                                   'topic carries the same pose)')
            return None
        return TransformBroadcaster(self)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """A live change of gains or input limits (rclpy has checked the type, the range and
        that the parameter is not read-only): the gains must be valid and, with a scenario,
        pass the method's check on it (e.g. a position gain whose Euler step would diverge is
        refused). Applied from the next step on, all or nothing."""
        own = {f.name for f in gain_fields(type(self.gains))}
        new_gains = {p.name: float(p.value) for p in params if p.name in own}
        new_limits = {p.name: float(p.value) for p in params if p.name in _LIVE_LIMITS}
        try:
            gains = _validated_gains(self.gains, new_gains) if new_gains else self.gains
            if new_gains and self.scenario is not None:
                errors = estimators.build(self.scenario.method, gains).check(
                    self.scenario.fleet()).errors
                if errors:
                    raise ScenarioError(str(errors[0]))
        except ScenarioError as exc:
            self.get_logger().warning(f'parameter change refused: {exc}')
            return SetParametersResult(successful=False, reason=str(exc))
        if new_gains:
            self.gains = gains
            for agent in (self.template, self.est):
                if agent is not None:
                    agent.estimator = self.method(gains)
        if new_limits:
            limits = replace(self.template.limits, **new_limits)
            for agent in (self.template, self.est):
                if agent is not None:
                    agent.limits = limits
        self.neighbour_wait = next((float(p.value) for p in params if p.name == 'neighbour_wait'),
                                   self.neighbour_wait)
        changed = ', '.join(f'{p.name} = {p.value:g}' for p in params)
        self.get_logger().info(f'parameters set live: {changed}')
        return SetParametersResult(successful=True)

    def _make_estimator(self, t0: float) -> AgentEstimator | LinkAgentEstimator:
        t = self.template
        if isinstance(t, TwoRoundAgent):
            return TwoRoundAgent(self.method(self.gains), agent_id=t.agent_id,
                                 links=[(lk.name, lk.agent_id, lk.senses, lk.sensed_by)
                                        for lk in t.links],
                                 step=self.h, R0=t.R0, p0=t.p0,
                                 anchor=(t.anchor_name, t.anchor_id), ranges=t.ranges,
                                 ranged=t.ranged, pinned=t.pinned, rate_tau=t.rate_tau,
                                 t0=t0,
                                 known_ids=t.known_ids, limits=t.limits)
        if isinstance(t, LinkAgentEstimator):
            return LinkAgentEstimator(self.method(self.gains), agent_id=t.agent_id,
                                      links=[(lk.name, lk.agent_id, lk.senses, lk.sensed_by)
                                             for lk in t.links],
                                      step=self.h, R0=t.R0, p0=t.p0, t0=t0,
                                      known_ids=t.known_ids, limits=t.limits)
        assert isinstance(t, AgentEstimator)
        est = AgentEstimator(self.method(self.gains), agent_id=t.agent_id,
                             neighbours=[(n.name, n.agent_id, n.k) for n in t.neighbours],
                             step=self.h, R0=t.R0, p0=t.p0, t0=t0,
                             leader=t.leader, known_ids=t.known_ids, limits=t.limits)
        if self.fixed_exchange:
            est.exchange = self._exchange()
            # Simulated odometry comes with the first step's gyro (netsim feeds it first):
            # wait for it from that step, not from its first arrival.
            est.requires_odometry |= self.expect_odometry and est.uses_odometry
        return est

    def _exchange(self) -> Exchange:
        """The periods of what a step waits for: the scenario's sensor rates (explicit mode:
        the spacing of the samples received)."""
        period = self.publish_every * self.h
        if self.scenario is None:
            return Exchange(period)
        sim = self.scenario.simulation
        return Exchange(period, sim.ticks(sim.bearing_rate) * sim.internal_step,
                        sim.ticks(sim.ground_truth_rate) * sim.internal_step)

    def _reject(self, cause: str, detail: str, count: int = 1) -> None:
        self.rejected[cause] += count
        self.get_logger().warning(f'rejected {detail}: {cause} ({self.rejected[cause]} so far)',
                                  throttle_duration_sec=5.0)

    def _decoded(self, msg: Any, decode: Callable[[Any], tuple], frame: str, what: str,
                 raw_decode: Callable[[bytes], tuple] | None = None) -> tuple | None:
        """``decode(msg)`` (a message's bytes: ``raw_decode``, by default ``decode``'s
        counterpart in msg_defs/cdr.py), or None after counting the rejection: wrong frame
        (unless ``frame`` is empty) or a malformed message."""
        if not self._frame_ok(msg, frame, what):
            return None
        try:
            if isinstance(msg, bytes):
                decode = raw_decode or _RAW_DECODERS[decode]
            return decode(msg)
        except wire.WireError as exc:
            self._reject('malformed', f'{what} ({exc})')
            return None

    def _frame_ok(self, msg: Any, frame: str, what: str) -> bool:
        """Whether the message's frame id is ``frame`` (anything for an empty ``frame``), after
        counting the rejection if not (or if its bytes have no header)."""
        if not frame:
            return True
        try:
            frame_id = (cdr.read_header(msg).frame_id if isinstance(msg, bytes)
                        else msg.header.frame_id)
        except wire.WireError as exc:
            self._reject('malformed', f'{what} ({exc})')
            return False
        if frame_id != frame:
            self._reject('wrong_frame', f'{what} in frame {frame_id!r}')
            return False
        return True

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
            if self.est.k == 0:
                # Once more now that the clock runs: the simulator started it only after the
                # monitor's readers matched, so this one reaches them (the ones before may not).
                self._publish(world=False, force=True)
        cause = self.est.add_gyro(t, omega, now=self._now())
        if cause in TIME_EVENTS:
            self.events[cause] += 1
            self.get_logger().warning(f'{TIME_EVENTS[cause]} (t = {t:.3f} s)')
            self._published_k = -1
        elif cause is not None:
            return self._reject(cause, f'imu sample at {t:.6f}')
        # Steps run as soon as the gyro covers them (a timer on the clock would fire before
        # the sample of its instant, and a lockstep clock would then wait for this agent).
        self.run_ready_steps()

    def on_relative_positions(self, msg: wire.PointCloud2) -> None:
        decoded = self._decoded(msg, wire.decode_vectors, self.bearings_frame,
                                'relative_positions')
        est = self.est
        if decoded is None or not isinstance(est, LinkAgentEstimator):
            return
        t, ids, vectors = decoded
        for cause, n in Counter(est.add_relative_positions(t, ids, vectors)).items():
            self._reject(cause, f'{n} relative position(s) at {t:.6f}', n)
        self.run_ready_steps()

    def on_bearing_rates(self, msg: wire.PointCloud2) -> None:
        decoded = self._decoded(msg, wire.decode_vectors, self.bearings_frame, 'bearing_rates')
        if decoded is None or not isinstance(self.est, TwoRoundAgent):
            return
        t, ids, vectors = decoded
        for cause, n in Counter(self.est.add_bearing_rates(t, ids, vectors)).items():
            self._reject(cause, f'{n} bearing rate(s) at {t:.6f}', n)
        self.run_ready_steps()

    def on_neighbour_odometry(self, agent_id: int, name: str, msg: wire.Odometry) -> None:
        est = self.est
        try:
            t, v, omega = _decode_odometry(msg, wire.body_frame(name))
        except wire.WireError as exc:
            return self._reject('malformed', f'odom of agent {agent_id} ({exc})')
        if not isinstance(est, LinkAgentEstimator):
            return
        cause = est.add_neighbour_odometry(agent_id, t, v, omega)
        if cause == 'odometry_gap':
            self.events[f'{cause}_{name}'] += 1
        elif cause is not None:
            return self._reject(cause, f'odom of agent {agent_id} at {t:.6f}')
        self.run_ready_steps()

    def on_bearings(self, msg: wire.PointCloud2) -> None:
        decoded = self._decoded(msg, wire.decode_vectors, self.bearings_frame, 'bearings')
        if decoded is None or self.est is None:
            return
        t, ids, vectors = decoded
        if isinstance(self.est, TwoRoundAgent):
            for cause, n in Counter(self.est.add_bearings(t, ids, vectors)).items():
                self._reject(cause, f'{n} bearing(s) at {t:.6f}', n)
            return self.run_ready_steps()
        if not isinstance(self.est, AgentEstimator):
            return
        for cause, n in Counter(self.est.add_bearings(t, ids, vectors)).items():
            self._reject(cause, f'{n} bearing(s) at {t:.6f}', n)
        if self.est.k == 0 and self.est.gyro.end <= self.est.t0:
            self._publish(world=True)  # the t0 world bearings, before the first step
        elif self._deferred == self.est.k and self.est.bearings_at(self.est.t):
            self._publish(world=True)
        if self.est.exchange is not None:
            self.run_ready_steps()   # a step may wait for these bearings

    def on_odometry(self, msg: wire.Odometry) -> None:
        try:
            t, v, omega = _decode_odometry(msg, self.odom_child_frame or None)
        except wire.WireError as exc:
            return self._reject('malformed', f'odom ({exc})')
        if self.est is None:
            return
        cause = self.est.add_odometry(t, v, omega, now=self._now())
        if cause == 'odometry_gap':
            self.events[cause] += 1
        elif cause is not None:
            return self._reject(cause, f'odom sample at {t:.6f}')
        self.run_ready_steps()  # steps wait for live odometry as for the gyro

    def on_known_pose(self, msg: wire.PoseStamped) -> None:
        decoded = self._decoded(msg, wire.decode_pose, self.world_frame, 'known_pose')
        if decoded is not None and isinstance(self.est, AgentEstimator):
            t, R, p = decoded
            cause = self.est.set_known_pose(t, R, p)
            if cause is not None:
                self._reject(cause, 'known_pose')
            elif self.est.exchange is not None:
                self.run_ready_steps()   # a step may wait for this pose

    def _link(self, handler: Callable[..., None], *args: object) -> None:
        """A neighbour message through the (optional) injected loss and delay."""
        if self.drop_rate and self.rng.uniform() < self.drop_rate:
            self.events['injected_drop'] += 1
            return
        if self.delay > 0.0:
            self._seq += 1
            heapq.heappush(self._delayed, ((self._now() or 0.0) + self.delay, self._seq,
                                           lambda: handler(*args)))
            return
        handler(*args)

    def _release_delayed(self) -> None:
        now = self._now() or 0.0
        while self._delayed and self._delayed[0][0] <= now:
            heapq.heappop(self._delayed)[2]()

    def on_neighbour(self, agent_id: int, channels: tuple[str, ...], name: str,
                     msg: object) -> None:
        """Neighbour j's message with its values of ``channels`` (its ``pose``: p̂_j and
        P_j; its ``world_bearings``, ...). A channel whose value is malformed is counted and
        left out; the others are used."""
        w = self.wires[channels[0]]
        what = f'{w.topic} of agent {agent_id}'
        frame = w.frame_of(name, self.estimate_frame, self.world_frame)
        if not self._frame_ok(msg, frame, what):
            return
        values: dict[str, object] = {}
        t = 0.0
        for channel in channels:
            decoded = self._decoded(msg, self.wires[channel].decode, '', what,
                                    cdr.RAW_CHANNELS[channel][0])
            if decoded is not None:
                t, values[channel] = decoded
        if not values or self.est is None:
            return
        if isinstance(self.est, LinkAgentEstimator) and self.method_channel(channels[0]).sensor:
            value = values[channels[0]]
            assert isinstance(value, dict)
            ids = np.fromiter(value.keys(), dtype=np.int64, count=len(value))
            cause = self.est.add_neighbour_measurements(
                agent_id, t, ids, np.array(list(value.values())).reshape(-1, 3))
        else:
            cause = self.est.add_neighbour(agent_id, t, values)
        if cause not in (None, 'not_seen'):  # not_seen: j has no bearing to us yet
            self._reject(cause, f'{what} at {t:.6f}')
        elif self.links or getattr(self.est, 'exchange', None) is not None:
            self.run_ready_steps()   # the waiting step may have what it needs now

    # --------------------------------------------------------------------------- stepping
    def on_ready_check(self) -> None:
        if self.est is None or self.est.k > 0:
            return
        if (all(sub.get_publisher_count() > 0 for sub in self._subs)
                and all(pub.get_subscription_count() >= n for pub, n in self._readers_wanted)):
            self._publish(world=True, force=True)

    def run_ready_steps(self) -> None:
        """Every step the inputs allow now (called by each input that can complete one),
        with what each step publishes; in an ``estimators`` process, the batch's call."""
        if self.est is None:
            return
        if self._delayed:
            self._release_delayed()
        if isinstance(self.est, TwoRoundAgent):
            return self._two_rounds()
        if self.batch is not None:
            return self.batch.request(self)   # run with the other agents' (StepBatch.settle)
        while self.est.steps_ready() > 0:
            if self._wall_first_step is None:
                self._wall_first_step = time.monotonic()
            if self.links:
                self.est.advance(1)
                self._stuck = None
                self._publish_links()
            else:
                self._step_and_publish()

    def _step_and_publish(self, impatient: bool = False) -> bool:
        """A leader-follower method: one step (``impatient``: with what is here), then, on
        the publish grid, the estimate and world bearings. False if no step ran."""
        est = self.est
        assert isinstance(est, AgentEstimator)
        self.before_step()
        if not est.advance(1, impatient=impatient):
            return False
        self.after_step()
        return True

    def before_step(self) -> None:
        """What goes before a step (:class:`.step_batch.StepBatch` runs the step between
        the two)."""
        est = self.est
        if isinstance(est, AgentEstimator) and self._deferred == est.k:
            # Its bearings never came: send no world bearings for this instant rather than
            # ones measured at another (listeners pair values of one instant).
            self.events['world_bearings_skipped'] += 1
            self._deferred = -1

    def after_step(self) -> None:
        """What follows a step: a link method's channels when due; a leader-follower
        method's estimate and world bearings on the publish grid."""
        est = self.est
        if self._wall_first_step is None:
            self._wall_first_step = time.monotonic()
        self._stuck = None
        if isinstance(est, TwoRoundAgent):   # and the next step's reply, if its round 1 is in
            self._publish_links()
            return self._send_reply()
        if not isinstance(est, AgentEstimator):
            return self._publish_links()
        # On the absolute grid origin + n h (k restarts after a time jump or gap).
        if round((est.t - est.origin) / self.h) % self.publish_every == 0:
            # Moving: what listeners pair with their own past must be measured at the stamp;
            # the bearings of this instant may still be on their way (the simulator sends
            # them just after the gyro sample that completed this step): the estimate goes
            # now, the world bearings once they are here.
            wait = est.odometry_live() and not est.bearings_at(est.t)
            self._publish(world=not wait)
            if wait:
                self._deferred = est.k

    def _two_rounds(self, impatient: bool = False) -> None:
        """A two-round method: send the current step's reply once its first round is in,
        run it once the second is (in an ``estimators`` process, with the other agents':
        the batch), repeat while inputs allow. ``impatient``: go on with what is here
        (:meth:`on_patience`)."""
        est = self.est
        assert isinstance(est, TwoRoundAgent)
        while True:
            self._send_reply(impatient)
            if self.batch is not None and not impatient:
                if est.steps_ready():
                    self.batch.request(self)
                return
            if not est.advance(1, impatient=impatient):
                return
            if impatient:
                self.events['impatient_steps'] += 1
                impatient = False
            if self._wall_first_step is None:
                self._wall_first_step = time.monotonic()
            self._stuck = None
            self._publish_links()

    def _send_reply(self, impatient: bool = False) -> None:
        """A two-round method's second round for the current step, once its first is in."""
        est = self.est
        assert isinstance(est, TwoRoundAgent)
        reply = est.pending_reply(impatient=impatient)
        if reply is not None:
            frame = self.estimate_frame
            for name in self.pub_channels:    # in optional_first order
                value = reply.get(name)
                if value:
                    pub, encode = self.pub_channels[name]
                    pub.publish(encode(est.t, value, frame))

    def on_patience(self) -> None:
        """A step that waits for a neighbour's input while nothing moves (its own sensors
        stopped too: a lockstep clock waiting for this agent) for ``neighbour_wait`` of wall
        time goes on without it (e.g. two agents that lost each other's values). A
        leader-follower method's ``fixed_exchange`` waits :data:`EXCHANGE_PATIENCE` instead:
        in a simulation nothing it awaits is lost for good (a later sample tells a lost one),
        so this only breaks a hang. While the own sensors advance, the estimator's own rule
        applies (it waits at most ``link_wait`` of their time)."""
        est = self.est
        if est is None or not est.own_inputs_ready() or (isinstance(est, AgentEstimator) and (
                est.exchange is None or est.steps_ready() > 0)):
            self._stuck = None
            return
        now = time.monotonic()
        if self._stuck is None or self._stuck[:2] != (est.k, est.gyro.end):
            self._stuck = (est.k, est.gyro.end, now)
        elif now - self._stuck[2] >= (self.neighbour_wait if self.links else EXCHANGE_PATIENCE):
            self.get_logger().warning(
                f'the step at t = {est.t:.3f} s waited {now - self._stuck[2]:.3g} s of wall time '
                f'for {est.awaited or "a neighbour"} with its own sensors standing still: going '
                'on without it (counted in event_impatient_steps)', throttle_duration_sec=5.0)
            if isinstance(est, TwoRoundAgent):
                self._stuck = None
                self._two_rounds(impatient=True)
            elif isinstance(est, AgentEstimator):
                if self._step_and_publish(impatient=True):
                    self.events['impatient_steps'] += 1
                self.run_ready_steps()
            elif est.advance(1, impatient=True):
                self.events['impatient_steps'] += 1
                self._stuck = None
                self._publish_links()
                self.run_ready_steps()

    def on_watch(self) -> None:
        """Every :data:`WATCH_PERIOD_S` of wall time: an agent that has not moved (state, gyro)
        since the last check while its clock is more than two steps past its state takes what
        its subscriptions hold and handles it. A message that waited there a second is one the
        executor was not told of (or was about to run); under lockstep the clock would wait
        for this agent forever. Found ones are counted (``taken_while_stalled``) and warned
        about; with none found and the gyro silent too, that is reported (the sender or the
        transport lost the samples)."""
        est, now = self.est, self._now()
        if est is None or now is None:
            return
        moved, self._watched = self._watched != (est.k, est.gyro.end), (est.k, est.gyro.end)
        if moved or now <= est.t + 2.0 * self.h:
            return
        found = 0
        for sub in list(self.subscriptions):
            with sub.handle:
                while (taken := sub.handle.take_message(sub.msg_type, sub.raw)) is not None:
                    found += 1
                    sub.callback(taken[0])
        if found:
            self.events['taken_while_stalled'] += found
            self.get_logger().warning(
                f'stalled at t = {est.t:.3f} s with the clock at {now:.3f} s: took {found} '
                'message(s) waiting in the subscriptions (the executor had not run them)',
                throttle_duration_sec=5.0)
        elif now > est.gyro.end + 2.0 * self.h:
            self.get_logger().warning(
                f'no gyro sample after t = {est.gyro.end:.3f} s while the clock is at '
                f'{now:.3f} s: is the imu publisher alive?', throttle_duration_sec=10.0)

    def _publish_links(self) -> None:
        """After a step of a link method: its channels when a neighbour's next step reads
        them, the estimate on the publish grid."""
        est = self.est
        assert est is not None
        due = {name for name in self.wires if est.estimator.due(name, est.t, self.h)}
        # Channels without a message of their own ride on the pose.
        rides = {name for name, w in self.wires.items() if w.topic == wire.POSE}
        estimate = (round((est.t - est.origin) / self.h) % self.publish_every == 0
                    or bool(due & rides))
        world = bool(due & set(self.pub_channels))
        if estimate or world:
            self._publish(world=world, estimate=estimate)

    def _publish(self, world: bool, force: bool = False, estimate: bool = True) -> None:
        """The estimate (unless already sent for this step or ``force``) and, with ``world``,
        the channels that have messages of their own."""
        est = self.est
        assert est is not None  # called once the estimator exists
        self._deferred = -1
        t = est.t
        if force or (estimate and self._published_k != est.k):
            # The pose first: what the neighbours' steps wait for.
            if self.pub_pose is not None:
                P = getattr(est.x, 'P')[0]   # the pose's block: methods may hold more states
                self.pub_pose.publish(self._encode_pose_covariance(
                    t, self.estimate_frame, est.R_hat[0], est.p_hat[0], P[:6, :6]))
            self.pub_estimate.publish(
                self._encode_pose(t, self.estimate_frame, est.R_hat[0], est.p_hat[0]))
            if self.tf is not None:
                self.tf.sendTransform(rviz.encode_transform(
                    t, self.estimate_frame, wire.body_frame(self.agent), est.R_hat[0],
                    est.p_hat[0]))
            self._published_k = est.k
        if world and self.pub_channels:
            sent = est.outbox()
            for name, (pub, encode) in self.pub_channels.items():
                if name not in sent:
                    continue   # a second round's channel: sent by _two_rounds
                value = sent[name]
                if not isinstance(value, dict) or value:  # nothing measured yet: nothing to say
                    pub.publish(encode(t, value,
                                       self.wires[name].frame_of(self.agent,
                                                                 self.estimate_frame,
                                                                 self.world_frame)))

    # --------------------------------------------------------------------------- health
    def publish_diagnostics(self) -> None:
        """Per-agent health on /diagnostics: rate, rejections by cause, stale neighbours, the
        spectrum of the method's local matrix (M_i, K_i) and its verdict, time events."""
        status = DiagnosticStatus(name=f'{self.fleet_prefix}{self.agent}/estimator',
                                  hardware_id=self.agent)
        values = {'state_time_s': 'n/a'}
        level, problems = DiagnosticStatus.OK, list[str]()
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
                eig = est.conditioning()
                if eig is not None:
                    values['conditioning_eigenvalues'] = ','.join(f'{e:.4g}' for e in eig)
                    problem = est.estimator.conditioning_problem(eig)
                    if problem is not None:
                        level = max(level, DiagnosticStatus.WARN)
                        problems.append(problem)
            if isinstance(est, LinkAgentEstimator):
                self._link_diagnostics(est, values)
            elif est.exchange is not None:   # steps that went on without an awaited input
                values['incomplete_steps'] = str(sum(est.incomplete.values()))
            values['non_finite_steps'] = str(est.non_finite_steps)
            values['gyro_gaps_bridged'] = str(est.gyro.bridged)
            if est.uses_odometry:
                values['odometry_gaps_bridged'] = str(est.odometry.bridged)
                values['odometry_live'] = str(est.odometry_live())
                values['odometry_missing_steps'] = str(est.odometry_missing_steps)
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

    def _link_diagnostics(self, est: LinkAgentEstimator, values: dict[str, str]) -> None:
        """Per neighbour the pair's excitation (so far, and whether now), the method's own
        per-agent values (De Carli: |ẑ_i|, the stage) and the inputs left out of steps."""
        for name, (total, now) in est.excitation().items():
            values[f'excitation_{name}'] = (f'{total:.3g} m2/s, '
                                            + ('excited now' if now else 'not excited now'))
        diag = est.last.diagnostics
        stages = est.estimator.stages
        for key, value in diag.items():
            if key == 'stage' and stages:
                values['stage'] = stages[int(value)]
            elif np.ndim(value) == 0:
                values[key] = f'{float(value):.4g}'
        for what, n in sorted(est.missing.items()):
            values[f'missing_{what}'] = str(n)
        values['carried'] = str(est.carried)   # late or lost values carried forward

    def destroy_node(self) -> None:
        """Log what this estimator achieved: steps, the step rate in wall time, rejections."""
        if self.est is not None and self._wall_first_step is not None:
            wall = max(time.monotonic() - self._wall_first_step, 1e-9)
            self.get_logger().info(
                f'{self.est.k} steps ({self.est.k * self.h:.2f} s of state time) in {wall:.1f} s '
                f'wall: {self.est.k / wall:.1f} steps/s; rejected: {dict(self.rejected) or 0}; '
                f'events: {dict(self.events) or 0}; lost-sample gaps bridged: gyro '
                f'{self.est.gyro.bridged}, odometry {self.est.odometry.bridged}; unpaired '
                f'neighbour values: {self.est.unpaired}'
                + (f'; waited for: {dict(self.est.waits) or 0}; left out: '
                   f'{dict(+self.est.missing) or 0}; carried: {self.est.carried}'
                   if isinstance(self.est, LinkAgentEstimator) else
                   f'; steps without an awaited input: {dict(self.est.incomplete) or 0}'
                   if self.est.exchange is not None else ''))
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    raise SystemExit(run_node(EstimatorNode, 'estimator', args))


if __name__ == '__main__':
    main()
