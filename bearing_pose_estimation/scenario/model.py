"""The scenario model: typed, validated dataclasses (built by :mod:`.parse` from YAML). Units
are SI; positions and attitudes (body → world) are in the scenario's ``world_frame``."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import estimators
from ..core import so3
from ..core.motion import AngularVelocity, LinearVelocity, YawSpline, in_anchor_frame
from ..estimators.base import Estimator
from ..estimators.fleet import Fleet


@dataclass(frozen=True)
class Neighbour:
    name: str
    k: float  # k_ij > 0


@dataclass(frozen=True)
class Agent:
    """One agent: ``position``, ``attitude`` (body → world) at t = 0; ``velocity`` or None."""

    name: str
    position: NDArray[np.float64]
    attitude: NDArray[np.float64]
    angular_velocity: AngularVelocity
    neighbours: tuple[Neighbour, ...] = ()
    velocity: LinearVelocity | None = None
    initial_position: NDArray[np.float64] | None = None   # p̂_i(0), followers only
    initial_attitude: NDArray[np.float64] | None = None   # R̂_i(0), followers only
    yaw: YawSpline | None = None     # yaw-only attitude R_z(ψ(t)) (replaces angular_velocity)
    formation_position: NDArray[np.float64] | None = None   # p*_i: driven by the controller


@dataclass(frozen=True)
class RandomInit:
    """Random initial estimates for followers that give none: ``p̂(0) = p + N(0, position_std²
    I)``; ``R̂(0) = R exp(θ u)``, u uniform on the sphere, θ uniform in ``[0, max_angle_deg]``."""

    seed: int = 0
    position_std: float = 1.0
    max_angle_deg: float = 180.0


@dataclass(frozen=True)
class BearingPerturbation:
    """Tran, Anderson & Ahn (2020): every bearing is ``rot_X(θ0 sin(2π f t)) b``, about the body
    axis ``X`` (the paper: "an arbitrary direction, e.g. the principal axes")."""

    amplitude_deg: float   # θ0, in [0, 90]
    frequency_hz: float    # f > 0
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)   # X, a unit vector (body frame)


@dataclass(frozen=True)
class Noise:
    """Measurement noise, off by default (:mod:`sim.noise`): ``gyro_std`` [rad/s] per sample and
    axis; ``gyro_bias`` [rad/s] plus each agent's ``N(0, gyro_bias_std²)``; ``bearing_std`` [rad]
    per component perpendicular to each bearing (RMS angle ``√2 · bearing_std``); ``seed``."""

    gyro_std: float = 0.0
    gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_bias_std: float = 0.0
    bearing_std: float = 0.0
    bearing_perturbation: BearingPerturbation | None = None
    outlier_probability: float = 0.0
    seed: int = 0


@dataclass(frozen=True)
class SensorSpec:
    """One simulated moving-robot sensor: its rate [Hz] and the white noise's std on each
    component of a sample: [m] (relative positions, ranges), [1/s] (bearing rates), [m/s]
    (odometry; ``angular_std`` [rad/s] on its rate)."""

    rate: float
    std: float = 0.0
    angular_std: float = 0.0
    # Bearing rates only: estimated from consecutive bearings (core.bearing_rates), filtered
    # with time constant `tau` [s]; 0 (raw) by default: on case 1 the lag costs more than noise.
    from_bearings: bool = False
    tau: float = 0.0


@dataclass(frozen=True)
class Sensors:
    """The sensors beyond gyro and bearings (``sensors:``; :meth:`Scenario.simulates`)."""

    odometry: SensorSpec = SensorSpec(100.0)
    relative_positions: SensorSpec = SensorSpec(50.0)
    bearing_rates: SensorSpec = SensorSpec(50.0)
    ranges: SensorSpec = SensorSpec(50.0)
    listed: frozenset[str] = frozenset()

    NAMES = ('odometry', 'relative_positions', 'bearing_rates', 'ranges')

    def spec(self, name: str) -> SensorSpec:
        return getattr(self, name)


@dataclass(frozen=True)
class FormationControl:
    """The formation controller (:mod:`core.formation`, De Carli et al. (30)-(31)): gain ``k_c``
    [1/s], speed bound ``nu_max`` [m/s], ``mode`` (``paper``: on the estimated yaws, batch
    simulator only), at ``rate`` [Hz], held in the body frame in between."""

    k_c: float = 1.0
    nu_max: float = 1.0
    mode: str = 'exogenous'
    rate: float = 200.0

    MODES = ('exogenous', 'paper')


@dataclass(frozen=True)
class SimulationRates:
    """How the simulator node samples the world: every period a whole number of steps [s]."""

    internal_step: float = 0.001
    imu_rate: float = 200.0          # gyro samples [Hz], interval averages
    bearing_rate: float = 50.0       # bearing measurements [Hz]
    ground_truth_rate: float = 50.0  # true poses [Hz], for the monitor and leaders

    def ticks(self, rate: float) -> int:
        """Internal steps per period of ``rate``."""
        return int(round(1.0 / (rate * self.internal_step)))


def noise_model_gains(noise: Noise, simulation: SimulationRates,
                      sensors: Sensors) -> dict[str, float]:
    """The covariance noise model gains a simulation's ``noise:`` and ``sensors:`` imply (stds
    [rad], [1/s], [m]; densities [rad/√s], [m/√s]: a per-sample std over √rate)."""
    rates = sensors.bearing_rates
    # Differenced from bearings at f = simulation.bearing_rate: σ √2 f per sample (correlated
    # in time, which the covariance does not model; a filter's smoothing is not counted).
    rate_std = (noise.bearing_std * float(np.sqrt(2.0)) * simulation.bearing_rate
                if rates.from_bearings else rates.std)
    return {'bearing_std': noise.bearing_std,
            'bearing_rate_std': rate_std,
            'relative_position_std': sensors.relative_positions.std,
            'gyro_noise_density': noise.gyro_std / float(np.sqrt(simulation.imu_rate)),
            'odometry_noise_density': (sensors.odometry.std
                                       / float(np.sqrt(sensors.odometry.rate)))}


@dataclass(frozen=True)
class Scenario:
    name: str
    agents: tuple[Agent, ...]
    leaders: tuple[str, ...]
    anchor: str | None = None   # the agent whose body frame the estimates use (anchor methods)
    ranged: tuple[str, ...] = ()   # the agents whose relative position the anchor measures
    anchor_pinned: bool = False    # the anchor holds (I, 0) instead of estimating its pose
    # Other methods' roles (as a file writes them), for `bearing-pose compare`: unused here.
    other_roles: dict[str, Any] = field(default_factory=dict, compare=False)
    method: str = estimators.DEFAULT_METHOD   # the registry key (`estimators.methods()`)
    gains: Any = None          # the method's own Gains dataclass; None: its defaults
    description: str = ''
    frequency: float = 100.0   # estimator rate [Hz]; batch step h = 1/frequency
    publish_rate: float = 50.0  # estimators publish estimate + world bearings [Hz]
    duration: float = 60.0     # default run length [s]
    world_frame: str = 'world'
    noise: Noise = Noise()
    random_init: RandomInit | None = None
    simulation: SimulationRates = SimulationRates()
    sensors: Sensors = Sensors()
    formation: FormationControl | None = None
    source: str = '<memory>'
    index: dict[str, int] = field(default_factory=dict, compare=False, repr=False)
    # fleet()'s value, computed on first use (dataclasses.replace starts a new one).
    _fleet: Fleet | None = field(default=None, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        self.index.update({a.name: i for i, a in enumerate(self.agents)})
        gains_cls = estimators.get(self.method).Gains
        if self.gains is None:
            object.__setattr__(self, 'gains', gains_cls())
        elif not isinstance(self.gains, gains_cls):
            raise TypeError(f'{self.method} takes {gains_cls.__module__}.Gains, got '
                            f'{type(self.gains).__module__}.Gains: use Scenario.with_method')

    def estimator(self) -> Estimator:
        """The scenario's method with its gains."""
        return estimators.build(self.method, self.gains)

    def fleet(self) -> Fleet:
        """What the method knows of this fleet (:class:`estimators.fleet.Fleet`), built once."""
        if self._fleet is None:
            R0, p0 = initial_estimates(self)
            positions = np.stack([a.position for a in self.agents])
            attitudes = np.stack([a.attitude for a in self.agents])
            for array in (R0, p0, positions, attitudes):
                array.flags.writeable = False
            fleet = Fleet(
                names=tuple(a.name for a in self.agents),
                neighbours=tuple(tuple((self.index[n.name], n.k) for n in a.neighbours)
                                 for a in self.agents),
                positions=positions, attitudes=attitudes, initial_R=R0, initial_p=p0,
                frequency=self.frequency, leaders=tuple(self.index[n] for n in self.leaders),
                anchor=self.anchor_index, ranged=tuple(self.index[n] for n in self.ranged),
                anchor_pinned=self.anchor_pinned, moves=self.moves,
                angular_velocities=tuple(a.angular_velocity for a in self.agents),
                yaws=tuple(a.yaw for a in self.agents))
            object.__setattr__(self, '_fleet', fleet)
            return fleet
        return self._fleet

    def with_method(self, method: str, **gains: float) -> Scenario:
        """The same scenario (truth, initial estimates, noise) run by ``method``: each gain is
        this scenario's of that name, else the noise model's, else the default; then ``gains``."""
        gains_cls = estimators.get(method).Gains
        mine = dataclasses.asdict(self.gains)
        model = noise_model_gains(self.noise, self.simulation, self.sensors)
        values = {f.name: mine.get(f.name, model.get(f.name, f.default))
                  for f in dataclasses.fields(gains_cls)}
        values.update(gains)
        return dataclasses.replace(self, method=method, gains=gains_cls(**values),
                                   index={})

    @property
    def followers(self) -> tuple[Agent, ...]:
        """The agents that estimate their pose: all but the leaders and a pinned anchor."""
        return tuple(a for a in self.agents if a.name not in self.leaders
                     and not (a.name == self.anchor and self.anchor_pinned))

    @property
    def anchor_index(self) -> int | None:
        return None if self.anchor is None else self.index[self.anchor]

    @property
    def step(self) -> float:
        return 1.0 / self.frequency

    @property
    def publish_every(self) -> int:
        """Estimator steps between two publications."""
        return int(round(self.frequency / self.publish_rate))

    @property
    def moves(self) -> bool:
        """Some agent translates (static positions are the papers' setting)."""
        return (any(a.velocity is not None and not a.velocity.value.is_zero
                    for a in self.agents)
                or (self.formation is not None
                    and any(a.formation_position is not None for a in self.agents)))

    @property
    def yaw_only(self) -> bool:
        """The agents' attitudes are yaw splines (``yaw:``), ``R_i = R_z(ψ_i(t))``."""
        return any(a.yaw is not None for a in self.agents)

    def simulates(self, sensor: str) -> bool:
        """``sensor`` is listed, needed by the method, or odometry of a moving fleet."""
        if sensor == 'bearing_rates' and self.sensors.bearing_rates.from_bearings:
            return False   # estimated by the robots from their bearings: no sensor
        needs = {s.value for s in estimators.get(self.method).sensors}
        return (sensor in self.sensors.listed or sensor in needs
                or (sensor == 'odometry' and self.moves))

    def provides(self, sensor: str) -> bool:
        """The robots have ``sensor``'s values: simulated, or bearing rates from bearings."""
        return self.simulates(sensor) or (sensor == 'bearing_rates'
                                          and self.sensors.bearing_rates.from_bearings)

    def not_distributable(self) -> str | None:
        """Why the nodes (and netsim) cannot run this scenario, with the fix, or None."""
        closed = [a.name for a in self.agents
                  if a.velocity is not None and a.velocity.frame == 'anchor_estimate']
        if closed:
            return (f'{closed[0]}.velocity is anchor_estimate: the command goes through the '
                    'robot\'s attitude estimate, which a simulator node cannot see. Fix: run '
                    'it with `bearing-pose simulate`, or give the velocity in the body frame')
        return None

    def agent(self, name: str) -> Agent:
        return self.agents[self.index[name]]

    def agent_id(self, name: str) -> int:
        """The id on the wire: the 1-based position in ``agents`` (the paper's agent number)."""
        return self.index[name] + 1

    def listeners(self, name: str) -> list[str]:
        """Agents that have ``name`` as a neighbour (they receive what it sends)."""
        return [a.name for a in self.agents if any(n.name == name for n in a.neighbours)]

    def sensing_edges(self) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """``(tail, head)`` of every sensing edge (i measures its neighbour j), in file order."""
        return self.fleet().sensing_edges()

    def sensing_targets(self, name: str) -> list[str]:
        """Agents that ``name`` measures bearings to: its neighbours, and its listeners unless
        the method's sensing is directed (Presenza et al.)."""
        targets = {n.name for n in self.agent(name).neighbours}
        if not estimators.get(self.method).directed_sensing:
            targets |= set(self.listeners(name))
        return sorted(targets, key=self.index.__getitem__)

    def sensor_targets(self, sensor: str, name: str) -> list[str]:
        """Agents that ``name``'s ``sensor`` measures: its :meth:`sensing_targets`, except
        relative positions with an anchor: the anchor's, of its ranged robots only."""
        if sensor == 'relative_positions' and self.anchor is not None:
            return list(self.ranged) if name == self.anchor else []
        return self.sensing_targets(name)


def initial_truth(scenario: Scenario) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The true poses at t = 0 in the method's estimate frame, ``(R (N,3,3), p (N,3))``."""
    R0 = np.stack([a.attitude for a in scenario.agents])
    p0 = np.stack([a.position for a in scenario.agents])
    if scenario.anchor is not None:
        return in_anchor_frame(R0, p0, scenario.index[scenario.anchor])
    return R0, p0


def initial_estimates(scenario: Scenario) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(R̂(0) (N,3,3), p̂(0) (N,3))`` in the method's estimate frame: leaders exact, the anchor
    at ``(I, 0)`` unless given, followers explicit or drawn (seeded ``random_init``)."""
    R0, p0 = initial_truth(scenario)
    ri = scenario.random_init
    rng = np.random.default_rng(ri.seed if ri else 0)
    for i, a in enumerate(scenario.agents):
        if a.name in scenario.leaders or (a.name == scenario.anchor
                                          and (a.initial_position is None
                                               or scenario.anchor_pinned)):
            continue
        if a.initial_position is not None:
            p0[i], R0[i] = a.initial_position, a.initial_attitude
        else:
            assert ri is not None  # parse_scenario guarantees it
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            theta = np.radians(ri.max_angle_deg) * rng.uniform()
            R0[i] = R0[i] @ so3.exp(theta * u)
            p0[i] = p0[i] + ri.position_std * rng.normal(size=3)
    return R0, p0
