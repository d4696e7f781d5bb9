"""Scenario files (README, "Scenario format"): YAML → validated, typed :class:`.model.Scenario`.
Every error names the file, the field (``agents[3] (agent_4).neighbours[1]``) and the fix. The
methods' graph assumptions are their estimators' ``check`` (:func:`.check_scenario`)."""
from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Set as AbstractSet
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from .. import estimators
from ..core import so3
from ..core.errors import ScenarioError
from ..core.motion import Component, LinearVelocity, Sinusoid, VectorProfile, YawSpline, rot_z
from ..estimators.base import Estimator, parse_gains
from .model import (Agent, BearingPerturbation, FormationControl, Neighbour, Noise, RandomInit,
                    Scenario, SensorSpec, Sensors, SimulationRates, noise_model_gains)

# Agent names become ROS namespaces and frame prefixes (`agent_3/base_link`).
_NAME_RE = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
# The default weight of every sensing edge, for methods with per-edge gains.
EDGE_GAIN = 'k_ij'


class _Ctx:
    """Where we are in the file, for error messages."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, where: str, problem: str, fix: str) -> ScenarioError:
        return ScenarioError(f'{self.source}: {where}: {problem}. Fix: {fix}')


def _mapping(ctx: _Ctx, value: Any, where: str, allowed: AbstractSet[str],
             required: AbstractSet[str] = frozenset()) -> dict:
    if not isinstance(value, dict):
        raise ctx.fail(where, f'expected a mapping, got {type(value).__name__}',
                       f'write it as `key: value` lines ({", ".join(sorted(allowed))})')
    unknown = sorted(str(k) for k in value if k not in allowed)
    if unknown:
        raise ctx.fail(f'{where}.{unknown[0]}', 'unknown key',
                       f'remove it or use one of: {", ".join(sorted(allowed))}')
    missing = sorted(required - set(value))
    if missing:
        raise ctx.fail(f'{where}.{missing[0]}', 'missing required field', f'add `{missing[0]}:`')
    return value


def _number(ctx: _Ctx, value: Any, where: str, positive: bool = False,
            non_negative: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ctx.fail(where, f'expected a number, got {value!r}', 'write a plain number')
    x = float(value)
    if not math.isfinite(x):
        raise ctx.fail(where, f'{value!r} is not finite', 'use a finite number')
    if positive and x <= 0.0:
        raise ctx.fail(where, f'must be > 0, got {x:g}', 'use a positive value')
    if non_negative and x < 0.0:
        raise ctx.fail(where, f'must be >= 0, got {x:g}', 'use zero or a positive value')
    return x


def _field(ctx: _Ctx, m: dict, where: str, key: str, default: Any, **kw: bool) -> float:
    """``m[key]`` (or ``default``) as a :func:`_number` named ``where.key``."""
    return _number(ctx, m.get(key, default), f'{where}.{key}', **kw)


def _integer(ctx: _Ctx, value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ctx.fail(where, f'expected an integer, got {value!r}', 'write a whole number')
    return int(value)


def _vector(ctx: _Ctx, value: Any, where: str, n: int = 3) -> NDArray[np.float64]:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ctx.fail(where, f'expected a list of {n} numbers, got {value!r}',
                       f'write it as [{", ".join(["0.0"] * n)}]')
    return np.array([_number(ctx, v, f'{where}[{i}]') for i, v in enumerate(value)])


def _string(ctx: _Ctx, value: Any, where: str) -> str:
    if not isinstance(value, str):
        raise ctx.fail(where, f'expected a string, got {value!r}', 'write a name')
    return value


def _attitude(ctx: _Ctx, value: Any, where: str) -> NDArray[np.float64]:
    """``identity`` | ``{axis: [x,y,z], angle_deg: a}`` | ``{axis, angle: rad}`` |
    ``{quaternion: [x, y, z, w]}`` (REP-103 order)."""
    if value == 'identity':
        return np.eye(3)
    m = _mapping(ctx, value, where, {'axis', 'angle', 'angle_deg', 'quaternion'})
    if 'quaternion' in m:
        if set(m) != {'quaternion'}:
            raise ctx.fail(where, 'quaternion cannot be combined with axis/angle',
                           'give either `quaternion` or `axis` and `angle_deg`')
        q = _vector(ctx, m['quaternion'], f'{where}.quaternion', 4)
        norm = np.linalg.norm(q)
        if abs(norm - 1.0) > 1e-6:
            raise ctx.fail(f'{where}.quaternion', f'norm is {norm:.6g}, not 1',
                           'normalise it (order is x, y, z, w)')
        from scipy.spatial.transform import Rotation
        return Rotation.from_quat(q).as_matrix()
    if 'axis' not in m or ('angle' in m) == ('angle_deg' in m):
        raise ctx.fail(where, 'an axis-angle attitude needs `axis` and exactly one of `angle` '
                       '[rad] or `angle_deg`', 'write e.g. {axis: [1, 0, 0], angle_deg: 18}, '
                       '`identity` or {quaternion: [x, y, z, w]}')
    axis = _vector(ctx, m['axis'], f'{where}.axis')
    if np.linalg.norm(axis) < 1e-12:
        raise ctx.fail(f'{where}.axis', 'axis is zero', 'give a non-zero rotation axis')
    theta = (_number(ctx, m['angle'], f'{where}.angle') if 'angle' in m
             else math.radians(_number(ctx, m['angle_deg'], f'{where}.angle_deg')))
    return so3.axis_angle(axis, theta)


def _term(ctx: _Ctx, value: Any, where: str) -> Sinusoid:
    m = _mapping(ctx, value, where, {'sin', 'cos', 'amplitude', 'phase'})
    if ('sin' in m) == ('cos' in m):
        raise ctx.fail(where, 'a sinusoid term needs exactly one of `sin` or `cos` (its angular '
                       'frequency in rad/s)', 'write e.g. {sin: 9} for sin(9t) or {cos: 3, '
                       'amplitude: -1} for -cos(3t)')
    kind = 'sin' if 'sin' in m else 'cos'
    freq = _number(ctx, m[kind], f'{where}.{kind}')
    amp = _field(ctx, m, where, 'amplitude', 1.0)
    phase = _field(ctx, m, where, 'phase', 0.0)
    return Sinusoid(amplitude=amp, frequency=freq,
                    phase=phase + 0.5 * math.pi if kind == 'cos' else phase)


def _component(ctx: _Ctx, value: Any, where: str) -> Component:
    """A number, a sinusoid term, or a list of those (summed)."""
    items = value if isinstance(value, list) else [value]
    constant, terms = 0.0, []
    for k, item in enumerate(items):
        w = f'{where}[{k}]' if isinstance(value, list) else where
        if isinstance(item, dict):
            terms.append(_term(ctx, item, w))
        else:
            constant += _number(ctx, item, w)
    return Component(constant=constant, terms=tuple(terms))


def _profile(ctx: _Ctx, value: Any, where: str) -> VectorProfile:
    if not isinstance(value, list) or len(value) != 3:
        raise ctx.fail(where, f'expected 3 components [x, y, z], got {value!r}',
                       'write e.g. [1, -2, 1] or [{cos: 3, amplitude: -1}, 1, {sin: 2}]')
    x, y, z = (_component(ctx, v, f'{where}[{i}]') for i, v in enumerate(value))
    return VectorProfile(x=x, y=y, z=z)


def _velocity(ctx: _Ctx, value: Any, where: str) -> LinearVelocity:
    """``{world: [x, y, z]}``, ``{body: [...]}`` or ``{anchor_estimate: [...]}`` [m/s]
    (:class:`core.motion.LinearVelocity`)."""
    m = _mapping(ctx, value, where, {'world', 'body', 'anchor_estimate'})
    if len(m) != 1:
        raise ctx.fail(where, 'give the velocity in exactly one frame, `world`, `body` or '
                       '`anchor_estimate`', 'write e.g. {world: [0.3, 0, {sin: 0.5, amplitude: '
                       '0.1}]} or {body: [1, 0, 0]}')
    (frame, raw), = m.items()
    return LinearVelocity(frame=frame, value=_profile(ctx, raw, f'{where}.{frame}'))


def _anchor(ctx: _Ctx, value: Any) -> tuple[str, tuple[str, ...], bool]:
    """``{agent: agent_1, ranged: [agent_2, agent_3], pinned: false}``: the anchor, the two
    agents whose relative position it measures, and whether it holds ``(I, 0)``."""
    m = _mapping(ctx, value, 'anchor', {'agent', 'ranged', 'pinned'}, {'agent', 'ranged'})
    agent = _string(ctx, m['agent'], 'anchor.agent')
    ranged = m['ranged']
    if (not isinstance(ranged, list) or len(ranged) != 2
            or not all(isinstance(r, str) for r in ranged) or ranged[0] == ranged[1]):
        raise ctx.fail('anchor.ranged', f'expected two distinct agent names, got {ranged!r}',
                       'name the two agents the anchor measures bearing and range to, e.g. '
                       '`ranged: [agent_2, agent_3]`')
    pinned = m.get('pinned', False)
    if not isinstance(pinned, bool):
        raise ctx.fail('anchor.pinned', f'expected true or false, got {pinned!r}',
                       'write `pinned: false` (the anchor estimates its pose) or `true`')
    return agent, (ranged[0], ranged[1]), pinned


def _numbers(ctx: _Ctx, value: Any, where: str, minimum: int) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) < minimum:
        raise ctx.fail(where, f'expected a list of at least {minimum} numbers, got {value!r}',
                       'write it as [0.0, 1.0, ...]')
    return tuple(_number(ctx, v, f'{where}[{i}]') for i, v in enumerate(value))


def _yaw(ctx: _Ctx, value: Any, where: str, knots: tuple[float, ...] | None) -> YawSpline:
    """``{values: [rad, ...], knots: [s, ...]}`` (knots default to the top-level
    ``yaw_knots``): a clamped cubic spline."""
    m = _mapping(ctx, value, where, {'knots', 'values'}, {'values'})
    if 'knots' in m:
        knots = _numbers(ctx, m['knots'], f'{where}.knots', 2)
    elif knots is None:
        raise ctx.fail(f'{where}.knots', 'missing, and there is no top-level `yaw_knots`',
                       'add `knots: [0, 2, 4, ...]` [s] or a top-level `yaw_knots:`')
    if any(b <= a for a, b in zip(knots, knots[1:])):
        raise ctx.fail(f'{where}.knots', 'the knots must increase strictly',
                       'sort them and remove duplicates')
    values = _numbers(ctx, m['values'], f'{where}.values', 2)
    if len(values) != len(knots):
        raise ctx.fail(f'{where}.values', f'{len(values)} values for {len(knots)} knots',
                       'give one yaw [rad] per knot')
    return YawSpline(knots=knots, values=values)


def _formation(ctx: _Ctx, value: Any, dt: float) -> FormationControl:
    m = _mapping(ctx, value, 'formation_control', {'k_c', 'nu_max', 'mode', 'rate'})
    d = FormationControl()
    mode = m.get('mode', d.mode)
    if mode not in FormationControl.MODES:
        raise ctx.fail('formation_control.mode', f'unknown mode {mode!r}',
                       f'use one of: {", ".join(FormationControl.MODES)}')
    formation = FormationControl(mode=mode, **{
        k: _field(ctx, m, 'formation_control', k, getattr(d, k), positive=True)
        for k in ('k_c', 'nu_max', 'rate')})
    _check_period(ctx, formation.rate, dt, 'formation_control.rate')
    return formation


def _neighbours(ctx: _Ctx, value: Any, where: str, default_k: float) -> tuple[Neighbour, ...]:
    if not isinstance(value, list):
        raise ctx.fail(where, f'expected a list, got {value!r}',
                       'write e.g. [agent_1, agent_2] or [{name: agent_1, k: 2.0}, agent_2]')
    out = []
    for k, item in enumerate(value):
        w = f'{where}[{k}]'
        if isinstance(item, dict):
            m = _mapping(ctx, item, w, {'name', 'k'}, {'name'})
            name = _string(ctx, m['name'], f'{w}.name')
            gain = _number(ctx, m.get('k', default_k), f'{w}.k', positive=True)
        else:
            name, gain = _string(ctx, item, w), default_k
        out.append(Neighbour(name=name, k=gain))
    return tuple(out)


def _check_period(ctx: _Ctx, rate: float, dt: float, where: str) -> None:
    ticks = 1.0 / (rate * dt)
    if ticks < 1.0 - 1e-9 or abs(ticks - round(ticks)) > 1e-6:
        raise ctx.fail(where, f'a period of 1/{rate:g} s is not a whole number of internal '
                       f'steps ({dt:g} s)', 'choose a rate that divides 1/internal_step (e.g. '
                       '200, 100, 50 Hz with a 1 ms step)')


def _sensors(ctx: _Ctx, value: Any, dt: float) -> Sensors:
    """``{odometry: {rate: 100, std: 0.01, angular_std: 0.0}, relative_positions: {...},
    bearing_rates: {...}, ranges: {...}}``; ``{}`` lists a sensor with its defaults."""
    m = _mapping(ctx, value, 'sensors', set(Sensors.NAMES))
    specs = {}
    for name, raw in m.items():
        where = f'sensors.{name}'
        keys = ({'rate', 'std'} | ({'angular_std'} if name == 'odometry' else set())
                | ({'from_bearings', 'tau'} if name == 'bearing_rates' else set()))
        raw = _mapping(ctx, {} if raw is None else raw, where, keys)
        rate = _field(ctx, raw, where, 'rate', Sensors().spec(name).rate, positive=True)
        _check_period(ctx, rate, dt, f'{where}.rate')
        from_bearings = raw.get('from_bearings', False)
        if not isinstance(from_bearings, bool):
            raise ctx.fail(f'{where}.from_bearings', f'expected true or false, got '
                           f'{from_bearings!r}', 'write `from_bearings: true` (estimate them '
                           'from consecutive bearings) or remove it (a sensor measures them)')
        if 'tau' in raw and not from_bearings:
            raise ctx.fail(f'{where}.tau', 'tau filters bearing rates estimated from bearings',
                           'add `from_bearings: true`, or remove tau')
        if from_bearings and {'rate', 'std'} & set(raw):
            raise ctx.fail(f'{where}', 'rate and std describe a bearing-rate sensor; with '
                           'from_bearings the rates come from the bearings (their rate and '
                           'noise)', 'remove rate and std')
        specs[name] = SensorSpec(
            rate=rate, std=_field(ctx, raw, where, 'std', 0.0, non_negative=True),
            angular_std=_field(ctx, raw, where, 'angular_std', 0.0, non_negative=True),
            from_bearings=from_bearings, tau=_field(ctx, raw, where, 'tau', SensorSpec.tau,
                                                    non_negative=True))
    return Sensors(**specs, listed=frozenset(m))


def _simulation(ctx: _Ctx, value: Any) -> SimulationRates:
    m = _mapping(ctx, value, 'simulation',
                 {'internal_step', 'imu_rate', 'bearing_rate', 'ground_truth_rate'})
    d = SimulationRates()
    dt = _field(ctx, m, 'simulation', 'internal_step', d.internal_step, positive=True)
    rates = {}
    for key in ('imu_rate', 'bearing_rate', 'ground_truth_rate'):
        rates[key] = _field(ctx, m, 'simulation', key, getattr(d, key), positive=True)
        _check_period(ctx, rates[key], dt, f'simulation.{key}')
    return SimulationRates(internal_step=dt, **rates)


def _noise_model(gains: Any, given: Any, noise: Noise, simulation: SimulationRates,
                 sensors: Sensors) -> Any:
    """A method's covariance noise model not given in ``gains:`` is the simulation's own
    ``noise:`` (:func:`.model.noise_model_gains`): in a simulation the model is the truth."""
    names = {f.name for f in dataclasses.fields(gains)}
    fill = {k: v for k, v in noise_model_gains(noise, simulation, sensors).items()
            if k in names and k not in given}
    return dataclasses.replace(gains, **fill) if fill else gains


def _noise(ctx: _Ctx, value: Any) -> Noise:
    m = _mapping(ctx, value, 'noise', {'gyro_std', 'gyro_bias', 'gyro_bias_std', 'bearing_std',
                                       'bearing_perturbation', 'outlier_probability', 'seed'})
    perturbation = None
    if 'bearing_perturbation' in m:
        where = 'noise.bearing_perturbation'
        bp = _mapping(ctx, m['bearing_perturbation'], where,
                      {'amplitude_deg', 'frequency_hz', 'axis'}, {'amplitude_deg', 'frequency_hz'})
        amplitude = _field(ctx, bp, where, 'amplitude_deg', None)
        if not 0.0 <= amplitude <= 90.0:
            raise ctx.fail(f'{where}.amplitude_deg', f'must be in [0, 90] degrees, got '
                           f'{amplitude:g}', 'use an amplitude θ0 between 0 and 90 degrees')
        frequency = _field(ctx, bp, where, 'frequency_hz', None, positive=True)
        axis = _vector(ctx, bp.get('axis', [1.0, 0.0, 0.0]), f'{where}.axis')
        if np.linalg.norm(axis) < 1e-12:
            raise ctx.fail(f'{where}.axis', 'axis is zero',
                           'give a non-zero body axis, e.g. [1, 0, 0]')
        x, y, z = (float(c) for c in axis / np.linalg.norm(axis))
        perturbation = BearingPerturbation(amplitude_deg=amplitude, frequency_hz=frequency,
                                           axis=(x, y, z))
    p_out = _field(ctx, m, 'noise', 'outlier_probability', 0.0)
    if not 0.0 <= p_out < 1.0:
        raise ctx.fail('noise.outlier_probability', f'must be in [0, 1), got {p_out:g}',
                       'give the probability that a bearing is an outlier, e.g. 0.01')
    bias = _vector(ctx, m.get('gyro_bias', [0.0, 0.0, 0.0]), 'noise.gyro_bias')
    return Noise(
        gyro_std=_field(ctx, m, 'noise', 'gyro_std', 0.0, non_negative=True),
        gyro_bias=(float(bias[0]), float(bias[1]), float(bias[2])),
        gyro_bias_std=_field(ctx, m, 'noise', 'gyro_bias_std', 0.0, non_negative=True),
        bearing_std=_field(ctx, m, 'noise', 'bearing_std', 0.0, non_negative=True),
        bearing_perturbation=perturbation, outlier_probability=p_out,
        seed=_integer(ctx, m.get('seed', 0), 'noise.seed'))


_TOP_KEYS = {'name', 'description', 'method', 'world_frame', 'gains', 'frequency', 'publish_rate',
             'duration', 'noise', 'leaders', 'anchor', 'agents', 'initial_estimates',
             'simulation', 'sensors', 'formation_control', 'yaw_knots', 'other_roles'}
_AGENT_KEYS = {'name', 'position', 'attitude', 'angular_velocity', 'velocity', 'neighbours',
               'initial_estimate', 'yaw', 'formation_position'}


def _other_roles(ctx: _Ctx, value: Any, cls: type[Estimator]) -> dict[str, Any]:
    """The roles the scenario's method does not use, for the methods ``compare`` runs beside it
    (``leaders``: a list of names; ``anchor``: as the top-level one)."""
    m = _mapping(ctx, value, 'other_roles', {'leaders', 'anchor'})
    own = {'leaders': cls.roles.leaders > 0, 'anchor': cls.roles.anchor}
    for key in m:
        if own[key]:
            raise ctx.fail(f'other_roles.{key}', f'{cls.title} uses {key} itself',
                           f'give them at the top level only (`{key}:`)')
    if 'leaders' in m and not (isinstance(m['leaders'], list)
                               and all(isinstance(x, str) for x in m['leaders'])):
        raise ctx.fail('other_roles.leaders', f'expected a list of agent names, got '
                       f'{m["leaders"]!r}', 'write e.g. `leaders: [agent_1, agent_2]`')
    if 'anchor' in m:
        _anchor(ctx, m['anchor'])   # the same checks as the top-level one
    return dict(m)


def parse_scenario(data: Any, source: str = '<memory>') -> Scenario:
    """Validate YAML data (a dict) into a :class:`Scenario` (ScenarioError: the first problem,
    naming the field and the fix)."""
    ctx = _Ctx(source)
    top = _mapping(ctx, data, 'top level', _TOP_KEYS, {'name', 'agents'})
    name = _string(ctx, top['name'], 'name')
    method = top.get('method', estimators.DEFAULT_METHOD)
    if not isinstance(method, str):
        raise ctx.fail('method', f'expected a method\'s name, got {method!r}',
                       f'use one of: {", ".join(estimators.methods())}')
    try:
        cls = estimators.get(method)
    except ScenarioError as exc:
        raise ctx.fail('method', *str(exc).split('. Fix: ', 1)) from None
    gain_names = {f.name for f in dataclasses.fields(cls.Gains)}
    raw_gains = _mapping(ctx, top.get('gains', {}), 'gains',
                         gain_names | ({EDGE_GAIN} if cls.edge_gains else set()))
    try:
        gains = parse_gains(cls.Gains, {k: v for k, v in raw_gains.items() if k in gain_names})
    except ScenarioError as exc:
        raise ScenarioError(f'{source}: {exc}') from None
    k_ij = _number(ctx, raw_gains.get(EDGE_GAIN, 1.0), f'gains.{EDGE_GAIN}', positive=True)
    frequency = _number(ctx, top.get('frequency', 100.0), 'frequency', positive=True)
    publish_rate = _number(ctx, top.get('publish_rate', min(50.0, frequency)), 'publish_rate',
                           positive=True)
    ratio = frequency / publish_rate
    if ratio < 1.0 - 1e-9 or abs(ratio - round(ratio)) > 1e-6:
        raise ctx.fail('publish_rate', f'{publish_rate:g} Hz does not divide the estimator '
                       f'frequency {frequency:g} Hz', 'use frequency / n, e.g. 50 for 100 Hz')
    duration = _number(ctx, top.get('duration', 60.0), 'duration', positive=True)
    world_frame = _string(ctx, top.get('world_frame', 'world'), 'world_frame')

    noise = _noise(ctx, top.get('noise', {}))

    simulation = _simulation(ctx, top.get('simulation', {}))
    sensors = _sensors(ctx, top.get('sensors', {}), simulation.internal_step)
    gains = _noise_model(gains, raw_gains, noise, simulation, sensors)
    formation = (_formation(ctx, top['formation_control'], simulation.internal_step)
                 if 'formation_control' in top else None)
    yaw_knots = (_numbers(ctx, top['yaw_knots'], 'yaw_knots', 2) if 'yaw_knots' in top
                 else None)

    random_init = None
    if 'initial_estimates' in top:
        where = 'initial_estimates.random'
        ie = _mapping(ctx, top['initial_estimates'], 'initial_estimates', {'random'}, {'random'})
        r = _mapping(ctx, ie['random'], where, {'seed', 'position_std', 'max_angle_deg'})
        random_init = RandomInit(
            seed=_integer(ctx, r.get('seed', 0), f'{where}.seed'),
            position_std=_field(ctx, r, where, 'position_std', 1.0, non_negative=True),
            max_angle_deg=_field(ctx, r, where, 'max_angle_deg', 180.0, non_negative=True))
        if random_init.max_angle_deg > 180.0:
            raise ctx.fail(f'{where}.max_angle_deg', 'must be <= 180', 'use an angle in [0, 180] '
                           'degrees')

    n_leaders = cls.roles.leaders
    raw_agents = top['agents']
    if not isinstance(raw_agents, list) or len(raw_agents) < max(3, n_leaders + 1):
        raise ctx.fail('agents', f'expected a list of at least {max(3, n_leaders + 1)} agents'
                       + (f' ({n_leaders} leaders, 1 follower)' if n_leaders else ''),
                       'list the agents under `agents:`, each starting with `- name: ...`')
    leaders = top.get('leaders', [])
    if not n_leaders and leaders:
        raise ctx.fail('leaders', f'{cls.title} has no leaders (no agent knows its pose)',
                       'remove `leaders`')
    if cls.roles.anchor != ('anchor' in top):
        raise (ctx.fail('anchor', f'{cls.title} needs one anchor, the agent whose body frame '
                         'the estimates are expressed in', 'add e.g. `anchor: {agent: agent_1, '
                        'ranged: [agent_2, agent_3]}`')
               if cls.roles.anchor else
               ctx.fail('anchor', f'{cls.title} has no anchor', 'remove `anchor`'))
    anchor, ranged, pinned = (_anchor(ctx, top['anchor']) if cls.roles.anchor
                              else (None, (), False))
    other_roles = _other_roles(ctx, top.get('other_roles', {}), cls)
    if (not isinstance(leaders, list) or len(leaders) != n_leaders
            or not all(isinstance(x, str) for x in leaders) or len(set(leaders)) != n_leaders):
        example = ', '.join(f'agent_{k + 1}' for k in range(n_leaders))
        raise ctx.fail('leaders', f'expected the names of exactly {n_leaders} distinct agents ('
                       f'{cls.title} has {n_leaders} leaders), got {leaders!r}', f'write e.g. '
                       f'`leaders: [{example}]`')

    agents: list[Agent] = []
    seen: dict[str, int] = {}
    for idx, raw in enumerate(raw_agents):
        where = f'agents[{idx}]'
        if isinstance(raw, dict) and isinstance(raw.get('name'), str):
            where += f' ({raw["name"]})'  # name the agent in every error, even a missing field
        m = _mapping(ctx, raw, where, _AGENT_KEYS, {'name', 'position'})
        aname = _string(ctx, m['name'], f'{where}.name')
        if not _NAME_RE.match(aname):
            raise ctx.fail(f'{where}.name', f'{aname!r} is not a valid ROS name',
                           'start with a letter; use only letters, digits and _')
        if aname in seen:
            raise ctx.fail(f'{where}.name', f'duplicate agent name {aname!r} (also agents['
                           f'{seen[aname]}])', 'give every agent a unique name')
        seen[aname] = idx
        where = f'agents[{idx}] ({aname})'
        position = _vector(ctx, m['position'], f'{where}.position')
        attitude = _attitude(ctx, m.get('attitude', 'identity'), f'{where}.attitude')
        omega = _profile(ctx, m.get('angular_velocity', [0, 0, 0]), f'{where}.angular_velocity')
        velocity = (_velocity(ctx, m['velocity'], f'{where}.velocity') if 'velocity' in m
                    else None)
        yaw = None
        if 'yaw' in m:
            for key in ('attitude', 'angular_velocity'):
                if key in m:
                    raise ctx.fail(f'{where}.{key}', 'a yaw spline sets the attitude '
                                   'R_z(ψ(t)) and its rate', f'remove `{key}` or `yaw`')
            yaw = _yaw(ctx, m['yaw'], f'{where}.yaw', yaw_knots)
            attitude = rot_z(np.array(yaw.values[0]))
            if velocity is not None and velocity.frame == 'body':
                raise ctx.fail(f'{where}.velocity', 'a body-frame velocity with a yaw spline '
                               'is not supported', 'give it in the world frame, `{world: '
                               '[...]}`, or use formation_control')
        formation_position = None
        if 'formation_position' in m:
            if formation is None:
                raise ctx.fail(f'{where}.formation_position', 'no `formation_control:` block '
                               'moves the agents to it', 'add a top-level `formation_control: '
                               '{k_c: 1, nu_max: 1}` or remove `formation_position`')
            if velocity is not None:
                raise ctx.fail(f'{where}.velocity', 'the formation controller sets the velocity '
                               'of an agent with a formation_position', 'remove `velocity` or '
                               '`formation_position`')
            formation_position = _vector(ctx, m['formation_position'],
                                         f'{where}.formation_position')
        neighbours: tuple[Neighbour, ...] = ()
        p0 = R0 = None
        if aname in leaders:
            for key in ('neighbours', 'initial_estimate'):
                if key in m:
                    raise ctx.fail(f'{where}.{key}', 'a leader knows its pose and has no '
                                   f'{key.replace("_", " ")} (Assumption 2b)', f'remove `{key}` '
                                   f'from {aname}, or remove {aname} from `leaders`')
        else:
            if 'neighbours' not in m and n_leaders:
                raise ctx.fail(f'{where}.neighbours', 'a follower needs neighbours', 'list at '
                               'least two earlier agents, e.g. `neighbours: [agent_1, agent_2]`')
            neighbours = _neighbours(ctx, m.get('neighbours', []), f'{where}.neighbours', k_ij)
            if 'initial_estimate' in m:
                ie = _mapping(ctx, m['initial_estimate'], f'{where}.initial_estimate',
                              {'position', 'attitude'}, {'position', 'attitude'})
                p0 = _vector(ctx, ie['position'], f'{where}.initial_estimate.position')
                R0 = _attitude(ctx, ie['attitude'], f'{where}.initial_estimate.attitude')
            elif random_init is None and aname != anchor:  # the anchor is the reference
                raise ctx.fail(f'{where}.initial_estimate', 'missing, and there is no '
                               'top-level `initial_estimates: {random: ...}` to draw it from',
                               'add `initial_estimate: {position: [...], attitude: ...}` or '
                               '`initial_estimates: {random: {seed: 0}}` at the top level')
        agents.append(Agent(name=aname, position=position, attitude=attitude,
                            angular_velocity=omega, neighbours=neighbours, velocity=velocity,
                            initial_position=p0, initial_attitude=R0, yaw=yaw,
                            formation_position=formation_position))

    if yaw_knots is not None and not any(a.yaw is not None for a in agents):
        raise ctx.fail('yaw_knots', 'no agent has a `yaw:` spline',
                       'remove `yaw_knots` or give agents `yaw: {values: [...]}`')
    if any(a.yaw is not None for a in agents) and not all(a.yaw is not None for a in agents):
        bare = next(k for k, a in enumerate(agents) if a.yaw is None)
        raise ctx.fail(f'agents[{bare}] ({agents[bare].name}).yaw', 'missing: either every '
                       'agent follows a yaw spline or none does',
                       'give it `yaw: {values: [...]}` (a constant yaw: two equal values)')
    if formation is not None and not any(a.yaw is not None for a in agents):
        raise ctx.fail('formation_control', 'the formation controller steers yaw-only robots',
                       'give every agent a `yaw: {values: [...]}` spline')
    if anchor is not None and anchor not in seen:
        raise ctx.fail('anchor.agent', f'{anchor!r} is not an agent',
                       f'use a name from `agents` ({", ".join(list(seen)[:5])}, ...)')
    for k, rname in enumerate(ranged):
        if rname not in seen or rname == anchor:
            raise ctx.fail(f'anchor.ranged[{k}]', f'{rname!r} is not an agent other than the '
                           'anchor', 'name two other agents from `agents`')
    for idx, a in enumerate(agents):
        if anchor is None and a.velocity is not None and a.velocity.frame == 'anchor_estimate':
            raise ctx.fail(f'agents[{idx}] ({a.name}).velocity.anchor_estimate', 'there is no '
                           'anchor frame', 'give it in the world or body frame')
    for lname in leaders:
        if lname not in seen:
            raise ctx.fail('leaders', f'{lname!r} is not an agent',
                           f'use names from `agents` ({", ".join(list(seen)[:5])}, ...)')
    for idx, a in enumerate(agents):
        names = [nb.name for nb in a.neighbours]
        for k, nb in enumerate(a.neighbours):
            w = f'agents[{idx}] ({a.name}).neighbours[{k}]'
            if nb.name not in seen:
                raise ctx.fail(w, f'{nb.name!r} is not an agent', 'use a name from `agents`')
            if nb.name == a.name:
                raise ctx.fail(w, 'an agent cannot be its own neighbour', 'remove it')
            if names.count(nb.name) > 1:
                raise ctx.fail(w, f'{nb.name!r} is listed twice', 'list each neighbour once')

    named = [(f'other_roles.leaders[{k}]', x)
             for k, x in enumerate(other_roles.get('leaders', ()))]
    if 'anchor' in other_roles:
        named.append(('other_roles.anchor.agent', other_roles['anchor']['agent']))
    for where, agent in named:
        if agent not in seen:
            raise ctx.fail(where, f'{agent!r} is not an agent', 'use a name from `agents`')
    return Scenario(name=name, agents=tuple(agents), leaders=tuple(leaders), anchor=anchor,
                    ranged=ranged, anchor_pinned=pinned, other_roles=other_roles, method=method,
                    gains=gains, description=str(top.get('description', '')),
                    frequency=frequency, publish_rate=publish_rate, duration=duration,
                    world_frame=world_frame, noise=noise, random_init=random_init,
                    simulation=simulation, sensors=sensors, formation=formation, source=source)


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file (ScenarioError if unreadable or invalid)."""
    return parse_scenario(read_scenario_data(path), source=str(path))


def read_scenario_data(path: str | Path) -> Any:
    """A scenario file's YAML content, not yet validated (ScenarioError if unreadable)."""
    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except OSError as exc:
        raise ScenarioError(f'{path}: cannot read the scenario file ({exc.strerror}). '
                            'Fix: check the path') from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        at = f'line {mark.line + 1}, column {mark.column + 1}' if mark else 'somewhere'
        problem = getattr(exc, 'problem', None) or str(exc)
        raise ScenarioError(f'{path}: YAML syntax error at {at}: {problem}. Fix: correct the '
                            'YAML at that position (indentation, colons, brackets)') from exc
    if data is None:
        raise ScenarioError(f'{path}: the file is empty (or only comments). Fix: write a scenario;'
                            ' see config/paper_8_agents.yaml and the README\'s "Scenario format"')
    return data
