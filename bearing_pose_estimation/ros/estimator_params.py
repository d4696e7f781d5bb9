"""The estimator node's parameters, declared with their effective values (so ``ros2 param get``
tells the truth), checked, and turned into :class:`Setup`; and live changes.

Parameters: ``scenario_file`` (+ ``agent``, default: the namespace) or the explicit set
(``agent_id``, ``leader``, ``neighbours``, ...); the method's gains are named as in a scenario's
``gains:`` (another method's gain is an error). Gains, input limits and ``neighbour_wait`` can be
set while the node runs: a change is validated (range, the gain's minimum, the method's check
on the scenario) and applies from the next step, or is refused with the reason. The fault
injection (``inject_*``, :mod:`runtime.faults`) turns ``fixed_exchange`` off.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Collection
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter

from .. import estimators
from .. import msg_defs as wire
from ..core import so3
from ..core.errors import ScenarioError
from ..estimators.base import Estimator, gain_fields, parse_gains
from ..runtime.agent import AgentSpec, PeerSpec
from ..runtime.buffers import Exchange, Limits
from ..runtime.faults import LinkFaults
from ..runtime.table import listener_counts
from ..scenario.model import Scenario
from ..scenario.parse import load_scenario
from ..scenario.runtimes import agent_specs, exchange_of
from .node_main import declare, parameter_overrides

# Used only without a scenario file.
EXPLICIT = ('agent_id', 'leader', 'neighbours', 'neighbour_ids', 'neighbour_gains',
            'initial_position', 'initial_orientation')
# The input limits a running node takes (with the gains and neighbour_wait).
LIVE_LIMITS = ('sensor_timeout', 'neighbour_timeout', 'max_rate', 'link_wait',
               'max_clock_lead')


@dataclass
class Setup:
    """What the node's parameters say: the method with its gains, the agent's spec, its
    rates, limits and frames, whom its writers wait for, and the simulation's exchange."""

    agent: str
    scenario: Scenario | None
    method: type[Estimator]
    gains: Any
    spec: AgentSpec
    step: float
    publish_every: int
    limits: Limits
    listeners: dict[str, int]          # own topic -> how many estimators read it
    expects_odometry: bool
    estimate_frame: str
    world_frame: str
    exchange: Exchange | None
    start_time: float                  # t = 0 on the node's clock; negative: the first gyro
    frames: dict[str, str]             # expected frame ids: 'imu', 'points', 'odom'
    diagnostics_period: float
    neighbour_wait: float
    faults: LinkFaults
    publish_tf: bool
    raw: bool


def _gain_parameters() -> dict[str, str]:
    """Every gain of every registered method, with its help and the methods that read it."""
    out: dict[str, tuple[str, list[str]]] = {}
    for method in estimators.methods():
        for f in gain_fields(estimators.get(method).Gains):
            out.setdefault(f.name, (f.metadata['help'], []))[1].append(method)
    return {name: f'{text} ({", ".join(users)})' for name, (text, users) in out.items()}


def validated_gains(base: Any, values: dict[str, float]) -> Any:
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


def _explicit_parameters(node: Node) -> dict[str, Any]:
    """The explicit mode's parameters, declared (:func:`explicit_spec` checks them)."""
    p = partial(declare, node)
    return {'agent_id': p('agent_id', 0, 'explicit mode: this agent\'s id (1-based)'),
            'leader': p('leader', False, 'explicit mode: a leader (known pose, no neighbours)'),
            'neighbours': [n for n in p('neighbours', [''], 'explicit mode: neighbour names') if n],
            'neighbour_ids': p('neighbour_ids', [0], 'explicit mode: neighbour ids'),
            'neighbour_gains': p('neighbour_gains', [0.0], 'explicit mode: k_ij per neighbour'),
            'initial_position': p('initial_position', [0.0, 0.0, 0.0],
                                  'explicit mode: initial p̂ [m]'),
            'initial_orientation': p('initial_orientation', [0.0, 0.0, 0.0, 1.0],
                                     'explicit mode: initial R̂ as a quaternion x, y, z, w')}


def explicit_spec(e: dict[str, Any], agent: str) -> AgentSpec:
    """The spec of the explicit parameters ``e`` (:func:`_explicit_parameters`), checked
    (ScenarioError naming the fix: ids, neighbour lists, gains, initial pose)."""
    names = e['neighbours']
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
    peers = () if e['leader'] else tuple(
        PeerSpec(n, int(i), float(k), {'senses': True, 'sensed_by': True})
        for n, i, k in zip(names, e['neighbour_ids'], e['neighbour_gains']))
    return AgentSpec(name=agent, agent_id=int(e['agent_id']), peers=peers, R0=so3.from_quat(q),
                     p0=p0, leader=bool(e['leader']))


def setup(node: Node) -> Setup:
    """Declare the node's parameters and read what they say (module docstring); ScenarioError
    for a bad value, naming the parameter and the fix."""
    p = partial(declare, node)
    scenario_file = p('scenario_file', '', 'scenario YAML; empty: explicit parameters')
    default_agent = node.get_namespace().strip('/').split('/')[-1]
    agent = p('agent', default_agent, 'agent name (default: namespace)')
    methods = estimators.methods()
    method = p('method', '', f'estimator, {" or ".join(methods)}; empty: the scenario\'s '
               f'(explicit mode: {estimators.DEFAULT_METHOD})')
    d = Limits()
    limits = Limits(
        sensor_timeout=p('sensor_timeout', d.sensor_timeout,
                         'own measurements older than this are not used [s]', 0.0, 1e6,
                         read_only=False),
        neighbour_timeout=p('neighbour_timeout', d.neighbour_timeout,
                            'a neighbour silent for longer is stale and not used [s]',
                            0.0, 1e6, read_only=False),
        max_rate=p('max_rate', d.max_rate, 'gyro rates above this are rejected [rad/s]',
                   0.0, 1e6, read_only=False),
        link_wait=p('link_wait', d.link_wait, 'a step waits for an input until the own '
                    'sensors are this far ahead [s]', 0.0, 1e6, read_only=False),
        max_clock_lead=p('max_clock_lead', d.max_clock_lead, 'a neighbour whose stamps are '
                         'further ahead of this clock is flagged in /diagnostics [s]',
                         0.0, 1e6, read_only=False))
    explicit = _explicit_parameters(node)
    if method and method not in methods:
        raise ScenarioError(f'parameter method: unknown method {method!r}. Fix: one of '
                            f'{", ".join(methods)}, or empty')
    fleet = wire.fleet_of(node.get_namespace())
    scenario: Scenario | None = None
    if scenario_file:
        scenario = load_scenario(scenario_file)
        if agent not in scenario.index:
            raise ScenarioError(f'{scenario_file}: agent {agent!r} is not in the '
                                'scenario. Fix: set the `agent` parameter or the namespace')
        if method and method != scenario.method:
            raise ScenarioError(f'parameter method is {method}, but {scenario_file} uses '
                                f'method {scenario.method}. Fix: remove the parameter (the '
                                'scenario file chooses the method)')
        ignored = sorted(set(EXPLICIT) & set(parameter_overrides(node)))
        if ignored:
            node.get_logger().warning(f'{", ".join(ignored)} ignored: they are for running '
                                      'without a scenario_file, which is set')
        specs = agent_specs(scenario)
        cls = type(scenario.estimator())
        spec = specs[scenario.index[agent]]
        listeners = {topic: n for (source, topic), n in listener_counts(cls, specs).items()
                     if source == agent}
        base_gains, frequency, publish_rate = (scenario.gains, scenario.frequency,
                                               scenario.publish_rate)
        method, anchor, world = scenario.method, scenario.anchor, scenario.world_frame
        fleet = scenario.name
        where, fix = "the scenario's method", 'the scenario file sets the method'
    else:
        method = method or estimators.DEFAULT_METHOD
        cls = estimators.get(method)
        if cls.links == 'communication':
            raise ScenarioError(f'method {method} needs scenario_file: its communication '
                                'links come from the sensing graph. Fix: set scenario_file')
        spec = explicit_spec(explicit, agent)
        listeners = {}   # unknown: the t0 announcement waits for no reader
        base_gains, frequency, publish_rate = cls.Gains(), 100.0, 50.0
        anchor, world, fleet = None, wire.WORLD_FRAME, 'fleet'
        where = 'the method parameter'
        fix = f'or set method: {" / ".join(m for m in methods if m != method)}'
    frequency = p('frequency', frequency, 'estimator rate [Hz] (default: the scenario\'s, 100 '
                  'in explicit mode)', 1e-3, 1e4)
    publish_rate = p('publish_rate', publish_rate, 'estimate and channel rate [Hz] (default: '
                     'the scenario\'s, 50 in explicit mode)', 1e-3, 1e4)
    own = [f.name for f in gain_fields(cls.Gains)]
    _refuse_other_gains(method, own, parameter_overrides(node), where, fix)
    help_of = _gain_parameters()
    gains = validated_gains(base_gains, {
        g: p(g, float(getattr(base_gains, g)), f'{help_of[g]}; can be set live', 0.0, 1e6,
             read_only=False) for g in own})
    world = p('world_frame', world, "the world (fixed) frame's id: of world-pose estimates, "
              "world-frame channels and a leader's known pose (default: the scenario's "
              'world_frame)')
    step = 1.0 / frequency
    publish_every = max(1, int(round(1.0 / (step * publish_rate))))
    # Simulation: inputs fixed by their stamps and waited for (load-independent runs).
    sim_time = bool(node.get_parameter('use_sim_time').value)
    fixed = p('fixed_exchange', sim_time, 'a step uses the own measurements up to its end and '
              'each neighbour\'s values of its publish instant at or before its start, and '
              'waits for them (default: use_sim_time)')
    faults = LinkFaults(
        p('inject_drop_rate', 0.0, 'fault injection: probability of dropping each neighbour '
          'message', 0.0, 1.0),
        p('inject_delay', 0.0, 'fault injection: extra delay of each neighbour message [s]',
          0.0, 60.0),
        p('inject_seed', 0, 'fault injection: random seed', 0, 2**31 - 1))
    exchange = None
    if fixed and faults:
        node.get_logger().info('fixed_exchange off: faults are injected')
    elif fixed:
        exchange = (exchange_of(scenario, publish_every) if scenario is not None
                    else Exchange(publish_every * step))
    body = wire.body_frame(agent)
    return Setup(
        agent=agent, scenario=scenario, method=cls, gains=gains, spec=spec, step=step,
        publish_every=publish_every, limits=limits, listeners=listeners,
        expects_odometry=scenario is not None and scenario.simulates('odometry'),
        estimate_frame=wire.estimate_frame(cls.frame.value, fleet, anchor, world),
        world_frame=world, exchange=exchange,
        start_time=p('start_time', 0.0, 't = 0 of the scenario on this clock [s]; negative: '
                     'the first gyro stamp'),
        frames={'imu': p('imu_frame', body, 'expected Imu frame_id; empty: any'),
                'points': p('bearings_frame', body, 'expected frame_id of the own point '
                            'sensors; empty: any'),
                'odom': p('odom_child_frame', body, 'expected Odometry child_frame_id (the '
                          'twist\'s frame); empty: any')},
        diagnostics_period=p('diagnostics_period', 1.0, '/diagnostics period [s, wall clock]',
                             0.01, 3600.0),
        neighbour_wait=p('neighbour_wait', 0.25, 'wall time [s] a step waits for a '
                         'neighbour\'s input with its own sensors standing still before going '
                         'on without it', 0.0, 60.0, read_only=False),
        faults=faults,
        publish_tf=p('publish_tf', True, 'broadcast the estimate on TF (estimate frame -> '
                     '<agent>/base_link) when tf2_ros is installed; false for a robot whose '
                     'odometry owns base_link'),
        # Messages as serialised bytes: rclpy builds no Python message (BENCHMARKS.md, "Raw CDR").
        raw=bool(p('raw_messages', True, 'take messages as serialised bytes; false: as rclpy '
                   'message objects')))


def live_change(s: Setup, params: list[Parameter]) -> tuple[Any, Limits]:
    """New gains and limits (and ``s.neighbour_wait``) from a live change of ``params`` (rclpy
    checked type, range, writability): valid gains that pass the method's check on the
    scenario; else ScenarioError with the reason."""
    own = {f.name for f in gain_fields(type(s.gains))}
    new_gains = {p.name: float(p.value) for p in params if p.name in own}
    new_limits = {p.name: float(p.value) for p in params if p.name in LIVE_LIMITS}
    gains = validated_gains(s.gains, new_gains) if new_gains else s.gains
    if new_gains and s.scenario is not None:
        errors = estimators.build(s.scenario.method, gains).check(s.scenario.fleet()).errors
        if errors:
            raise ScenarioError(str(errors[0]))
    s.neighbour_wait = next((float(p.value) for p in params if p.name == 'neighbour_wait'),
                            s.neighbour_wait)
    return gains, replace(s.limits, **new_limits)
