"""Scenario files: YAML → validated, typed :class:`Scenario`.

The format is documented in the README ("Scenario format") and by ``config/paper_8_agents.yaml``.
Every error names the file, the field (``agents[3] (agent_4).neighbours[1]``) and the fix.
Structural checks live here; the graph conditions of the paper's Assumption 2 live in
:mod:`bearing_pose_estimation.graph`.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from . import so3
from .motion import AngularVelocity, Component, Sinusoid

METHODS = ('boughellaba_tayebi', 'tran_anderson_ahn')
# Gains each method reads from `gains:` (k_ij: every edge's default weight).
METHOD_GAINS = {'boughellaba_tayebi': {'k_R', 'k_p', 'k_ij'},
                 'tran_anderson_ahn': {'k_omega', 'k_c', 'k_p', 'k_ij'}}
# Agent names become ROS namespaces and frame prefixes (`agent_3/base_link`).
_NAME_RE = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')


class ScenarioError(ValueError):
    """A scenario file is invalid. The message names the file, the field and the fix."""


@dataclass(frozen=True)
class Neighbour:
    name: str
    k: float  # k_ij > 0


@dataclass(frozen=True)
class Agent:
    """One agent. Units SI; frames: ``position`` and ``attitude`` (body → world) in ``world``."""

    name: str
    position: NDArray[np.float64]
    attitude: NDArray[np.float64]
    angular_velocity: AngularVelocity
    neighbours: tuple[Neighbour, ...] = ()
    initial_position: NDArray[np.float64] | None = None   # p̂_i(0), followers only
    initial_attitude: NDArray[np.float64] | None = None   # R̂_i(0), followers only


@dataclass(frozen=True)
class RandomInit:
    """Random initial estimates for followers that give none explicitly.

    ``p̂(0) = p + N(0, position_std² I)``; ``R̂(0) = R exp(θ u)``, u uniform on the sphere,
    θ uniform in ``[0, max_angle_deg]``.
    """

    seed: int = 0
    position_std: float = 1.0
    max_angle_deg: float = 180.0


@dataclass(frozen=True)
class BearingPerturbation:
    """Deterministic bearing perturbation (Tran, Anderson & Ahn 2020): every measured bearing
    is ``rot_X(θ0 sin(2π f t)) b``, the rotation about the body axis ``X`` (the paper: "an
    arbitrary direction, e.g. the principal axes"; default x)."""

    amplitude_deg: float   # θ0, in [0, 90]
    frequency_hz: float    # f > 0
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)   # X, a unit vector (body frame)


@dataclass(frozen=True)
class Noise:
    """Measurement noise, all off by default; applied by :mod:`bearing_pose_estimation.noise`.

    - ``gyro_std`` [rad/s]: white noise on each gyro sample (at ``simulation.imu_rate``),
      per axis; the batch simulator averages it over the samples its step spans.
    - ``gyro_bias`` [rad/s]: constant body-frame gyro bias, the same for every agent, plus
      ``gyro_bias_std`` [rad/s]: each agent's own constant bias, drawn once per axis from
      ``N(0, gyro_bias_std²)``. Measured rate = true + bias + white noise.
    - ``bearing_std`` [rad]: each bearing is turned by a random rotation perpendicular to it,
      whose two angular components each have this standard deviation (so the RMS angle is
      ``√2 · bearing_std``: 1° gives 1.41°).
    - ``bearing_perturbation``: the deterministic ``rot_X(θ0 sin 2πft)`` of each bearing.
    - ``outlier_probability``: chance that a bearing is replaced by a uniformly random unit
      vector.
    - ``seed``: seeds every random draw, so a scenario and seed give the same run.
    """

    gyro_std: float = 0.0
    gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_bias_std: float = 0.0
    bearing_std: float = 0.0
    bearing_perturbation: BearingPerturbation | None = None
    outlier_probability: float = 0.0
    seed: int = 0


@dataclass(frozen=True)
class SimulationRates:
    """How the simulator node samples the world. Truth is integrated with ``internal_step``
    [s]; every sensor period must be a whole number of internal steps."""

    internal_step: float = 0.001
    imu_rate: float = 200.0          # gyro samples [Hz], interval averages
    bearing_rate: float = 50.0       # bearing measurements [Hz]
    ground_truth_rate: float = 50.0  # true poses [Hz], for the monitor and leaders

    def ticks(self, rate: float) -> int:
        """Internal steps per period of ``rate``."""
        return int(round(1.0 / (rate * self.internal_step)))


@dataclass(frozen=True)
class Scenario:
    name: str
    agents: tuple[Agent, ...]
    leaders: tuple[str, ...]
    method: str = 'boughellaba_tayebi'
    description: str = ''
    k_R: float = 1.0
    k_p: float = 1.0
    k_omega: float = 2.0       # Tran et al.: damping of the gyro-correction state Ω̃
    k_c: float = 1.0           # Tran et al.: the extra direction of two-neighbour followers
    frequency: float = 100.0   # estimator rate [Hz]; batch step h = 1/frequency
    publish_rate: float = 50.0  # estimators publish estimate + world bearings [Hz]
    duration: float = 60.0     # default run length [s]
    world_frame: str = 'world'
    noise: Noise = Noise()
    random_init: RandomInit | None = None
    simulation: SimulationRates = SimulationRates()
    source: str = '<memory>'
    index: dict[str, int] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        self.index.update({a.name: i for i, a in enumerate(self.agents)})

    @property
    def followers(self) -> tuple[Agent, ...]:
        return tuple(a for a in self.agents if a.name not in self.leaders)

    @property
    def step(self) -> float:
        return 1.0 / self.frequency

    @property
    def publish_every(self) -> int:
        """Estimator steps between two publications."""
        return int(round(self.frequency / self.publish_rate))

    def agent(self, name: str) -> Agent:
        return self.agents[self.index[name]]

    def agent_id(self, name: str) -> int:
        """The id on the wire: the 1-based position in ``agents`` (the paper's agent number)."""
        return self.index[name] + 1

    def listeners(self, name: str) -> list[str]:
        """Agents that have ``name`` as a neighbour (they need its world bearings)."""
        return [a.name for a in self.agents if any(n.name == name for n in a.neighbours)]

    def sensing_targets(self, name: str) -> list[str]:
        """Agents that ``name`` measures bearings to: its neighbours and its listeners
        (sensing is two-way on every edge)."""
        targets = {n.name for n in self.agent(name).neighbours} | set(self.listeners(name))
        return sorted(targets, key=self.index.__getitem__)


# ----------------------------------------------------------------------------- parsing helpers
class _Ctx:
    """Where we are in the file, for error messages."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, where: str, problem: str, fix: str) -> ScenarioError:
        return ScenarioError(f'{self.source}: {where}: {problem}. Fix: {fix}')


def _mapping(ctx: _Ctx, value: Any, where: str, allowed: set[str],
             required: set[str] = frozenset()) -> dict:
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
        raise ctx.fail(where, 'an axis-angle attitude needs `axis` and exactly one of '
                       '`angle` [rad] or `angle_deg`',
                       'write e.g. {axis: [1, 0, 0], angle_deg: 18}, `identity` or '
                       '{quaternion: [x, y, z, w]}')
    axis = _vector(ctx, m['axis'], f'{where}.axis')
    if np.linalg.norm(axis) < 1e-12:
        raise ctx.fail(f'{where}.axis', 'axis is zero', 'give a non-zero rotation axis')
    if 'angle' in m:
        theta = _number(ctx, m['angle'], f'{where}.angle')
    else:
        theta = math.radians(_number(ctx, m['angle_deg'], f'{where}.angle_deg'))
    return so3.axis_angle(axis, theta)


def _term(ctx: _Ctx, value: Any, where: str) -> Sinusoid:
    m = _mapping(ctx, value, where, {'sin', 'cos', 'amplitude', 'phase'})
    if ('sin' in m) == ('cos' in m):
        raise ctx.fail(where, 'a sinusoid term needs exactly one of `sin` or `cos` '
                       '(its angular frequency in rad/s)',
                       'write e.g. {sin: 9} for sin(9t) or {cos: 3, amplitude: -1} for -cos(3t)')
    kind = 'sin' if 'sin' in m else 'cos'
    freq = _number(ctx, m[kind], f'{where}.{kind}')
    amp = _number(ctx, m.get('amplitude', 1.0), f'{where}.amplitude')
    phase = _number(ctx, m.get('phase', 0.0), f'{where}.phase')
    if kind == 'cos':
        phase += 0.5 * math.pi
    return Sinusoid(amplitude=amp, frequency=freq, phase=phase)


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


def _angular_velocity(ctx: _Ctx, value: Any, where: str) -> AngularVelocity:
    if not isinstance(value, list) or len(value) != 3:
        raise ctx.fail(where, f'expected 3 components [x, y, z], got {value!r}',
                       'write e.g. [1, -2, 1] or [{cos: 3, amplitude: -1}, 1, {sin: 2}]')
    x, y, z = (_component(ctx, v, f'{where}[{i}]') for i, v in enumerate(value))
    return AngularVelocity(x=x, y=y, z=z)


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


def _simulation(ctx: _Ctx, value: Any) -> SimulationRates:
    m = _mapping(ctx, value, 'simulation',
                 {'internal_step', 'imu_rate', 'bearing_rate', 'ground_truth_rate'})
    d = SimulationRates()
    dt = _number(ctx, m.get('internal_step', d.internal_step), 'simulation.internal_step',
                 positive=True)
    rates = {}
    for key in ('imu_rate', 'bearing_rate', 'ground_truth_rate'):
        rate = _number(ctx, m.get(key, getattr(d, key)), f'simulation.{key}', positive=True)
        ticks = 1.0 / (rate * dt)
        if ticks < 1.0 - 1e-9 or abs(ticks - round(ticks)) > 1e-6:
            raise ctx.fail(f'simulation.{key}', f'a period of 1/{rate:g} s is not a whole number '
                           f'of internal steps ({dt:g} s)',
                           'choose a rate that divides 1/internal_step (e.g. 200, 100, 50 Hz '
                           'with a 1 ms step)')
        rates[key] = rate
    return SimulationRates(internal_step=dt, **rates)


def _noise(ctx: _Ctx, value: Any) -> Noise:
    m = _mapping(ctx, value, 'noise', {'gyro_std', 'gyro_bias', 'gyro_bias_std', 'bearing_std',
                                       'bearing_perturbation', 'outlier_probability', 'seed'})
    perturbation = None
    if 'bearing_perturbation' in m:
        bp = _mapping(ctx, m['bearing_perturbation'], 'noise.bearing_perturbation',
                      {'amplitude_deg', 'frequency_hz', 'axis'}, {'amplitude_deg', 'frequency_hz'})
        where = 'noise.bearing_perturbation.amplitude_deg'
        amplitude = _number(ctx, bp['amplitude_deg'], where)
        if not 0.0 <= amplitude <= 90.0:
            raise ctx.fail(where, f'must be in [0, 90] degrees, got {amplitude:g}',
                           'use an amplitude θ0 between 0 and 90 degrees')
        frequency = _number(ctx, bp['frequency_hz'], 'noise.bearing_perturbation.frequency_hz',
                            positive=True)
        axis = _vector(ctx, bp.get('axis', [1.0, 0.0, 0.0]), 'noise.bearing_perturbation.axis')
        if np.linalg.norm(axis) < 1e-12:
            raise ctx.fail('noise.bearing_perturbation.axis', 'axis is zero',
                           'give a non-zero body axis, e.g. [1, 0, 0]')
        perturbation = BearingPerturbation(amplitude_deg=amplitude, frequency_hz=frequency,
                                           axis=tuple(float(x) for x in
                                                      axis / np.linalg.norm(axis)))
    p_out = _number(ctx, m.get('outlier_probability', 0.0), 'noise.outlier_probability')
    if not 0.0 <= p_out < 1.0:
        raise ctx.fail('noise.outlier_probability', f'must be in [0, 1), got {p_out:g}',
                       'give the probability that a bearing is an outlier, e.g. 0.01')
    bias = _vector(ctx, m.get('gyro_bias', [0.0, 0.0, 0.0]), 'noise.gyro_bias')
    return Noise(
        gyro_std=_number(ctx, m.get('gyro_std', 0.0), 'noise.gyro_std', non_negative=True),
        gyro_bias=(float(bias[0]), float(bias[1]), float(bias[2])),
        gyro_bias_std=_number(ctx, m.get('gyro_bias_std', 0.0), 'noise.gyro_bias_std',
                              non_negative=True),
        bearing_std=_number(ctx, m.get('bearing_std', 0.0), 'noise.bearing_std',
                            non_negative=True),
        bearing_perturbation=perturbation, outlier_probability=p_out,
        seed=_integer(ctx, m.get('seed', 0), 'noise.seed'))


_TOP_KEYS = {'name', 'description', 'method', 'world_frame', 'gains', 'frequency',
             'publish_rate', 'duration',
             'noise', 'leaders', 'agents', 'initial_estimates', 'simulation'}
_AGENT_KEYS = {'name', 'position', 'attitude', 'angular_velocity', 'neighbours',
               'initial_estimate'}


def parse_scenario(data: Any, source: str = '<memory>') -> Scenario:
    """Validate a scenario already loaded from YAML (a dict) and build a :class:`Scenario`.

    Raises:
        ScenarioError: on the first problem, naming the field and the fix.
    """
    ctx = _Ctx(source)
    top = _mapping(ctx, data, 'top level', _TOP_KEYS, {'name', 'leaders', 'agents'})
    name = _string(ctx, top['name'], 'name')
    method = top.get('method', 'boughellaba_tayebi')
    if method not in METHODS:
        raise ctx.fail('method', f'unknown method {method!r}', f'use one of: {", ".join(METHODS)}')

    gains = _mapping(ctx, top.get('gains', {}), 'gains', METHOD_GAINS[method])
    k_R = _number(ctx, gains.get('k_R', 1.0), 'gains.k_R', positive=True)
    k_omega = _number(ctx, gains.get('k_omega', 2.0), 'gains.k_omega', positive=True)
    k_c = _number(ctx, gains.get('k_c', 1.0), 'gains.k_c', positive=True)
    k_p = _number(ctx, gains.get('k_p', 1.0), 'gains.k_p', positive=True)
    k_ij = _number(ctx, gains.get('k_ij', 1.0), 'gains.k_ij', positive=True)
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

    random_init = None
    if 'initial_estimates' in top:
        ie = _mapping(ctx, top['initial_estimates'], 'initial_estimates', {'random'}, {'random'})
        r = _mapping(ctx, ie['random'], 'initial_estimates.random',
                     {'seed', 'position_std', 'max_angle_deg'})
        random_init = RandomInit(
            seed=_integer(ctx, r.get('seed', 0), 'initial_estimates.random.seed'),
            position_std=_number(ctx, r.get('position_std', 1.0),
                                 'initial_estimates.random.position_std', non_negative=True),
            max_angle_deg=_number(ctx, r.get('max_angle_deg', 180.0),
                                  'initial_estimates.random.max_angle_deg', non_negative=True))
        if random_init.max_angle_deg > 180.0:
            raise ctx.fail('initial_estimates.random.max_angle_deg', 'must be <= 180',
                           'use an angle in [0, 180] degrees')

    raw_agents = top['agents']
    if not isinstance(raw_agents, list) or len(raw_agents) < 3:
        raise ctx.fail('agents', 'expected a list of at least 3 agents (2 leaders, 1 follower)',
                       'list the agents under `agents:`, each starting with `- name: ...`')
    leaders = top['leaders']
    if (not isinstance(leaders, list) or len(leaders) != 2
            or not all(isinstance(x, str) for x in leaders) or leaders[0] == leaders[1]):
        raise ctx.fail('leaders', f'expected the names of exactly two distinct agents, got '
                       f'{leaders!r}', 'write e.g. `leaders: [agent_1, agent_2]`')

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
        is_leader = aname in leaders
        position = _vector(ctx, m['position'], f'{where}.position')
        attitude = _attitude(ctx, m.get('attitude', 'identity'), f'{where}.attitude')
        omega = _angular_velocity(ctx, m.get('angular_velocity', [0, 0, 0]),
                                  f'{where}.angular_velocity')
        neighbours: tuple[Neighbour, ...] = ()
        p0 = R0 = None
        if is_leader:
            for key in ('neighbours', 'initial_estimate'):
                if key in m:
                    what = 'neighbours' if key == 'neighbours' else 'initial estimate'
                    raise ctx.fail(f'{where}.{key}', 'a leader knows its pose and has no '
                                   f'{what} (Assumption 2b)',
                                   f'remove `{key}` from {aname}, or remove {aname} from '
                                   '`leaders`')
        else:
            if 'neighbours' not in m:
                raise ctx.fail(f'{where}.neighbours', 'a follower needs neighbours',
                               'list at least two earlier agents, e.g. '
                               '`neighbours: [agent_1, agent_2]`')
            neighbours = _neighbours(ctx, m['neighbours'], f'{where}.neighbours', k_ij)
            if 'initial_estimate' in m:
                ie = _mapping(ctx, m['initial_estimate'], f'{where}.initial_estimate',
                              {'position', 'attitude'}, {'position', 'attitude'})
                p0 = _vector(ctx, ie['position'], f'{where}.initial_estimate.position')
                R0 = _attitude(ctx, ie['attitude'], f'{where}.initial_estimate.attitude')
            elif random_init is None:
                raise ctx.fail(f'{where}.initial_estimate', 'missing, and there is no '
                               'top-level `initial_estimates: {random: ...}` to draw it from',
                               'add `initial_estimate: {position: [...], attitude: ...}` or '
                               '`initial_estimates: {random: {seed: 0}}` at the top level')
        agents.append(Agent(name=aname, position=position, attitude=attitude,
                            angular_velocity=omega, neighbours=neighbours,
                            initial_position=p0, initial_attitude=R0))

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

    return Scenario(name=name, agents=tuple(agents), leaders=tuple(leaders), method=method,
                    description=str(top.get('description', '')), k_R=k_R, k_p=k_p,
                    k_omega=k_omega, k_c=k_c,
                    frequency=frequency, publish_rate=publish_rate, duration=duration,
                    world_frame=world_frame,
                    noise=noise, random_init=random_init, simulation=simulation, source=source)


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file.

    Raises:
        ScenarioError: the file is missing, is not valid YAML, or is not a valid scenario.
    """
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
        raise ScenarioError(f'{path}: YAML syntax error at {at}: {problem}. '
                            'Fix: correct the YAML at that position (indentation, colons, '
                            'brackets)') from exc
    if data is None:
        raise ScenarioError(f'{path}: the file is empty (or only comments). Fix: write a '
                            'scenario; see config/paper_8_agents.yaml and the README\'s '
                            '"Scenario format"')
    return data


def initial_estimates(scenario: Scenario) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(R̂(0) (N,3,3), p̂(0) (N,3))`` for all agents: leaders exact, followers explicit or
    drawn from the scenario's seeded ``initial_estimates.random`` block."""
    n = len(scenario.agents)
    R0 = np.stack([a.attitude for a in scenario.agents])
    p0 = np.stack([a.position for a in scenario.agents])
    ri = scenario.random_init
    rng = np.random.default_rng(ri.seed if ri else 0)
    for i, a in enumerate(scenario.agents):
        if a.name in scenario.leaders:
            continue
        if a.initial_position is not None:
            p0[i], R0[i] = a.initial_position, a.initial_attitude
        else:
            assert ri is not None  # parse_scenario guarantees it
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            theta = np.radians(ri.max_angle_deg) * rng.uniform()
            R0[i] = a.attitude @ so3.exp(theta * u)
            p0[i] = a.position + ri.position_std * rng.normal(size=3)
    assert R0.shape == (n, 3, 3)
    return R0, p0
