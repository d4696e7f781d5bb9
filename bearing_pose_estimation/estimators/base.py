"""The estimator interface: what a method declares (:class:`Estimator`'s class attributes,
:class:`Channel`, :func:`edge_table`) and its one vectorised :meth:`Estimator.step`, which the
batch simulator calls for the whole fleet and the runtime (:mod:`bearing_pose_estimation.runtime`)
for one agent or several: each method's math exists once. A step's inputs (:class:`StepInputs`)
are keyed by sensor and channel names, so the runtime fills them from the declarations without
knowing any method's quantity."""
from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING, Any, ClassVar, Generic, Literal, TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from ..core import so3
from ..core.errors import ScenarioError

if TYPE_CHECKING:
    from .fleet import Fleet

Array = NDArray[np.float64]
Index = NDArray[np.intp]
Mask = NDArray[np.bool_]


# ----------------------------------------------------------------------------- declarations
class Sensor(Enum):
    """What an agent measures; the value keys its measurements and names its topic."""

    GYRO = 'gyro'                              # body angular rate (interval averages)
    BEARINGS = 'bearings'                      # unit bearings to the agents it sees (body)
    KNOWN_POSE = 'known_pose'                  # its own pose (leaders: mocap, GNSS/INS)
    ODOMETRY = 'odometry'                      # body linear velocity and rate
    RELATIVE_POSITIONS = 'relative_positions'  # body-frame relative positions (RGB-D)
    BEARING_RATES = 'bearing_rates'            # time derivatives of body bearings
    RANGES = 'ranges'                          # distances to the agents it sees


# The sensors that measure other agents: one vector per agent seen, at the sensor's stamp.
POINT_SENSORS = (Sensor.BEARINGS, Sensor.RELATIVE_POSITIONS, Sensor.BEARING_RATES)


class EstimateFrame(Enum):
    """How a method's estimates relate to the world, i.e. how errors are measured."""

    WORLD = 'world'                            # world poses: errors measured directly
    COMMON_YAW_TRANSLATION = 'common_yaw_translation'  # up to one yaw and one translation
    ANCHOR_BODY = 'anchor_body'                # in the anchor's (moving) body frame


@dataclass(frozen=True)
class Roles:
    """The special agents a method needs: ``leaders`` that know their pose, or an ``anchor``."""

    leaders: int = 0
    anchor: bool = False


# Wire kinds (msg_defs maps each to one codec): a value on the sender's pose (its position,
# or its covariance), a per-agent 3-vector of its own message, or one point per listener.
POSE_POSITION = 'pose.position'
POSE_COVARIANCE = 'pose.covariance'
VECTOR = 'vector'
POINTS = 'points'


@dataclass(frozen=True)
class Channel:
    """One quantity that agent j sends the agents that listen to it.

    - ``per='agent'``: one value for all of them (e.g. ``p̂_j``); ``per='edge'``: one per
      listener i (e.g. ``R̂_j b^j_ji``), formed by :meth:`Estimator.outbox` (round 1) or
      :meth:`Estimator.reply` (``round`` 2: from what the sender received in round 1).
    - ``on``: the receiver's edge flag (:func:`edge_table`) it travels on (``'senses'``: from
      the agents it senses, ``'sensed_by'``: from those that sense it; None: every edge);
      ``owner_only``: only the owner of the pair's shared state sends it.
    - ``sensor``: j's own measurement of i, on j's sensor topic, paired like a measurement.
    - ``pairing`` with the step at t: ``'instant'``, the sender's newest instant at or before t
      with every required channel; ``'exact'``, the value of t itself, else the newest earlier
      one carried to t (:meth:`Estimator.carry`) or the edge goes without.
    - ``optional`` (a covariance): never waited for (else :meth:`Estimator.missing`).
    - ``frame``: ``'world'``, ``'body'`` (the sender's) or ``'estimate'``; ``unit``: unit
      vectors (checked on reception); ``bound``: the largest component a receiver accepts;
      ``psd_blocks``: leading packed symmetric 3x3 blocks (xx, yy, zz, xy, xz, yz) that must
      be positive semi-definite.
    - ``topic`` (in the sender's namespace), wire ``kind`` (:data:`POINTS`, :data:`VECTOR`,
      ...) and a point's ``fields``: how it travels (``msg_defs``).
    """

    name: str
    per: Literal['agent', 'edge']
    frame: str
    unit: bool = False
    shape: tuple[int, ...] = (3,)
    doc: str = ''
    sensor: Sensor | None = None
    owner_only: bool = False
    round: int = 1
    optional: bool = False
    on: str | None = None
    pairing: Literal['instant', 'exact'] = 'instant'
    bound: float = math.inf
    psd_blocks: int = 0
    topic: str = ''
    kind: str = POINTS
    fields: tuple[str, ...] = ('x', 'y', 'z')

    def __post_init__(self) -> None:
        if not self.topic:
            object.__setattr__(self, 'topic', self.sensor.value if self.sensor is not None
                               else self.name)


# ----------------------------------------------------------------------------- gains
def gain(default: float, help: str, minimum: float = 0.0, zero_allowed: bool = False,
         model: bool = False) -> Any:
    """A field of a method's gains: ``default``, a one-line ``help`` (the parameter description),
    exclusive lower bound ``minimum`` (``zero_allowed``: >= 0); ``model``: the covariance's."""
    return field(default=default, metadata={'help': help, 'minimum': minimum,
                                            'zero_allowed': zero_allowed, 'model': model})


def gain_fields(gains_cls: type) -> tuple[dataclasses.Field, ...]:
    """The gains a method reads, in declaration order."""
    return dataclasses.fields(gains_cls)


def parse_gains(gains_cls: type, values: Mapping[str, Any], where: str = 'gains') -> Any:
    """``gains_cls`` from ``values`` (missing keys: defaults); ScenarioError naming
    ``<where>.<gain>`` and the fix for an unknown key or a value below the gain's minimum."""
    known = [f.name for f in gain_fields(gains_cls)]
    for key in values:
        if key not in known:
            raise ScenarioError(f'{where}.{key}: unknown key. Fix: remove it or use one of: '
                                f'{", ".join(sorted(known))}')
    out = {}
    for f in gain_fields(gains_cls):
        value = values.get(f.name, f.default)
        here = f'{where}.{f.name}'
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ScenarioError(f'{here}: expected a number, got {value!r}. Fix: write a plain '
                                'number')
        x = float(value)
        if not math.isfinite(x):
            raise ScenarioError(f'{here}: {value!r} is not finite. Fix: use a finite number')
        low, zero_ok = f.metadata['minimum'], f.metadata.get('zero_allowed', False)
        if x < low or (x == low and not zero_ok):
            raise ScenarioError(f'{here}: must be {">=" if zero_ok else ">"} {low:g}, got '
                                f'{x:g}. Fix: use a {"non-negative" if zero_ok else "positive"} '
                                'value')
        out[f.name] = x
    return gains_cls(**out)


def format_gains(gains: Any) -> str:
    """``k_R=1, k_p=1``: the gains as logs and tables show them (not the covariance's model)."""
    return ', '.join(f'{f.name}={getattr(gains, f.name):g}' for f in gain_fields(type(gains))
                     if not f.metadata.get('model'))


# ----------------------------------------------------------------------------- edges, state
# Above this many edges, sums over each agent's edges use a sparse incidence matrix: built once
# (~100 µs), its product beats np.add.at from about 64 edges on (6 against 30 µs at 512).
SPARSE_SUM_EDGES = 64


@dataclass(frozen=True, eq=False)
class Edges:
    """Directed sensing edges ``i → j``, fixed for a step: ``agent[e]`` the state row owning edge
    ``e`` (0 in a node), ``k[e]`` ``k_ij``, ``flags``. Compared by identity, so a method may cache
    what it derives (as :meth:`sum_by_agent` its incidence matrix)."""

    agent: Index
    k: Array
    n_agents: int
    # The edge's place in its agent's fixed list of neighbours, for methods that keep per-edge
    # state (a node may leave a silent neighbour out of a step); default: its rank.
    slot: Index | None = None
    flags: Mapping[str, Mask] = field(default_factory=dict)
    _incidence: sparse.csr_matrix | None = field(init=False, repr=False)
    unit_k: bool = field(init=False, repr=False)  # every k_ij = 1: skip the product

    def __post_init__(self) -> None:
        agent = np.asarray(self.agent, dtype=np.intp)
        k = np.asarray(self.k, dtype=float)
        object.__setattr__(self, 'agent', agent)
        object.__setattr__(self, 'k', k)
        n_edges = agent.shape[0]
        if self.slot is None and self.n_agents == 1:   # a node's one agent: in edge order
            object.__setattr__(self, 'slot', np.arange(n_edges, dtype=np.intp))
        elif self.slot is None:   # rank among the agent's edges (they come grouped by agent)
            first = (np.searchsorted(agent, agent) if (agent[1:] >= agent[:-1]).all()
                     else None)
            rank = (np.arange(n_edges) - first if first is not None
                    else np.array([np.count_nonzero(agent[:e] == agent[e])
                                   for e in range(n_edges)]))
            object.__setattr__(self, 'slot', rank.astype(np.intp))
        else:
            object.__setattr__(self, 'slot', np.asarray(self.slot, dtype=np.intp))
        object.__setattr__(self, '_incidence', None)
        object.__setattr__(self, 'unit_k', bool((k == 1.0).all()))

    def __len__(self) -> int:
        return int(self.agent.shape[0])

    def sum_by_agent(self, values: Array) -> Array:
        """``out[i] = Σ_{e: agent[e] = i} values[e]``, shape ``(n_agents, ...)``, summed in
        edge order whichever way (the same numbers, bit for bit)."""
        if self.n_agents == 1:   # the node: a plain sum is cheaper
            return values.sum(axis=0, keepdims=True)
        if len(self) <= SPARSE_SUM_EDGES:
            # Several agents stepped together (StepBatch): these edges serve one step, and
            # building the sparse matrix would cost 20 times the sum.
            out = np.zeros((self.n_agents,) + values.shape[1:],
                           dtype=np.result_type(values.dtype, float))   # complex too
            np.add.at(out, self.agent, values)
            return out
        incidence = self._incidence
        if incidence is None:
            n_edges = len(self)
            incidence = sparse.csr_matrix((np.ones(n_edges), (self.agent, np.arange(n_edges))),
                                          shape=(self.n_agents, n_edges))
            object.__setattr__(self, '_incidence', incidence)
        return np.asarray(incidence @ values)

    def flag(self, name: str) -> Mask:
        """Flag ``name`` of every edge ``(E,)`` (all set when the edges do not have it)."""
        value = self.flags.get(name)
        return np.ones(len(self), dtype=bool) if value is None else value

    @staticmethod
    def stack(parts: Sequence[Edges]) -> Edges:
        """Several agents' edges (with the same flags) as one, in that order."""
        offsets = np.cumsum([0] + [p.n_agents for p in parts[:-1]])
        slots = [p.slot for p in parts]
        assert all(slot is not None for slot in slots)
        return Edges(agent=np.concatenate([p.agent + o for p, o in zip(parts, offsets)]),
                     k=np.concatenate([p.k for p in parts]),
                     n_agents=sum(p.n_agents for p in parts),
                     slot=np.concatenate(slots),   # type: ignore[arg-type]
                     flags={name: np.concatenate([p.flags[name] for p in parts])
                            for name in parts[0].flags})

    def weighted(self, terms: Array) -> Array:
        """``k_ij · terms[e]`` (``terms`` itself when every ``k_ij = 1``)."""
        return terms if self.unit_k else terms * self.k[:, None]


S = TypeVar('S', bound='State')


@dataclass
class State:
    """A method's per-agent state: every field an ``(N, ...)`` array, row i for agent i; the
    pose ``R_hat`` (body → the method's frame), ``p_hat`` [m], and the method's own fields."""

    R_hat: Array   # (N, 3, 3)
    p_hat: Array   # (N, 3) [m]

    def rows(self: S, idx: Any) -> S:
        """The state of the agents ``idx`` (an index array or slice), copied."""
        return type(self)(**{f.name: np.array(getattr(self, f.name)[idx])
                             for f in dataclasses.fields(self)})

    @classmethod
    def stack(cls: type[S], parts: Sequence[S]) -> S:
        """The states of several agents (one or more rows each) as one, in that order."""
        return cls(**{f.name: np.concatenate([getattr(x, f.name) for x in parts])
                      for f in dataclasses.fields(cls)})

    def is_finite(self) -> bool:
        values = (getattr(self, f.name) for f in dataclasses.fields(self))
        return all(bool(np.isfinite(v).all()) for v in values
                   if v.dtype.kind in 'fc')   # bool flags are always finite


@dataclass(frozen=True)
class Motion:
    """How the receiver, the sender and the anchor moved over ``[t_s, t]`` (gyro increments
    ``R(t_s)ᵀ R(t)``, displacements in the body frame at ``t_s``), for :meth:`Estimator.carry`;
    None where the receiver does not know it."""

    own_delta_R: Array | None = None
    peer_delta_R: Array | None = None
    peer_displacement: Array | None = None
    anchor_delta_R: Array | None = None
    anchor_displacement: Array | None = None


# Keys of StepInputs.agent that every step gets, and the other end's odometry per edge.
DELTA_R = 'delta_R'                  # (N, 3, 3) gyro increments R(t)ᵀ R(t + h) (body)
DISPLACEMENT = 'displacement'        # (N, 3) odometry R(t)ᵀ (p(t+h) - p(t)) [m], if any
ANCHOR_DELTA_R = 'anchor_delta_R'    # (N, 3, 3) the anchor's gyro increment (its body frame)
ANCHOR_DISPLACEMENT = 'anchor_displacement'   # (N, 3) its odometry [m]
IS_ANCHOR = 'is_anchor'              # (N,) the anchor
PINNED = 'pinned'                    # (N,) the anchor, holding (I, 0)
PEER_DELTA_R = 'peer_delta_R'        # (E, 3, 3) the other end's gyro increment over the step
PEER_DISPLACEMENT = 'peer_displacement'   # (E, 3) its odometry, in its frame at t [m]
PEER_ODOMETRY = 'peer_odometry'      # the mask of the two above
P_OWN = 'p_own'                      # (E, 3) the owner's p̂_i at the stamp of what it paired
HELD = 'held'                        # (E, 2) steps the own sample and the value received serve


@dataclass(frozen=True)
class StepInputs:
    """What one step consumes for N agents and their E edges, all at the step's start time t.

    - ``agent[key]`` ``(N, ...)``: the agent keys above (:data:`DISPLACEMENT` where odometry
      runs, the anchor's for methods with one).
    - ``edge[key]`` ``(E, ...)``: each own point sensor's measurement of j by its name
      (``'bearings'``: ``b^i_ij``, body frame at t); each channel j sent (per-agent ones repeated
      on every edge from j); j's motion with ``peer_odometry``; :data:`P_OWN` (``p̂_i`` moved back
      to the stamp of j's values: exact pairing, undelayed corrections) and :data:`HELD`.
    - ``mask[key]`` ``(E,)``: which edges have ``edge[key]`` (no mask: all; off: zeros or the
      method's stand-in)."""

    edges: Edges
    agent: Mapping[str, Array]
    edge: Mapping[str, Array]
    mask: Mapping[str, Mask] = field(default_factory=dict)
    t: float = 0.0                      # the step's start time [s] (multirate methods)

    @property
    def delta_R(self) -> Array:
        return self.agent[DELTA_R]

    @property
    def displacement(self) -> Array | None:
        """``(N, 3)`` odometry displacement over the step [m], or None (no odometry)."""
        return self.agent.get(DISPLACEMENT)

    def here(self, key: str) -> Mask:
        """``(E,)`` which edges have ``edge[key]``."""
        value = self.mask.get(key)
        return np.ones(len(self.edges), dtype=bool) if value is None else value

    @staticmethod
    def stack(parts: Sequence[StepInputs], same_t: bool = True) -> StepInputs:
        """Several agents' inputs (with the same keys, and t with ``same_t``) as one fleet
        step, in that order."""
        first = parts[0]
        if not all(first.stacks_with(p, same_t) for p in parts[1:]):
            raise ValueError('StepInputs.stack: the parts have different keys or times')
        return StepInputs(
            edges=Edges.stack([p.edges for p in parts]), t=first.t,
            agent={k: np.concatenate([p.agent[k] for p in parts]) for k in first.agent},
            edge={k: np.concatenate([p.edge[k] for p in parts]) for k in first.edge},
            mask={k: np.concatenate([p.mask[k] for p in parts]) for k in first.mask})

    def stacks_with(self, other: StepInputs, same_t: bool = True) -> bool:
        """Whether :meth:`stack` takes both."""
        return ((self.t == other.t or not same_t) and self.agent.keys() == other.agent.keys()
                and self.edge.keys() == other.edge.keys()
                and self.mask.keys() == other.mask.keys()
                and self.edges.flags.keys() == other.edges.flags.keys())

    def agent_inputs(self, i: int) -> StepInputs:
        """The inputs of agent ``i`` alone (``n_agents = 1``): what its node would pass."""
        sel = np.flatnonzero(self.edges.agent == i)
        return self.select(sel, np.zeros(sel.size, dtype=np.intp), slice(i, i + 1), 1)

    def select(self, sel: Index, agent: Index, rows: Any, n_agents: int) -> StepInputs:
        """The edges ``sel`` (now owned by the rows ``agent``) of the agents ``rows``."""
        e = self.edges
        assert e.slot is not None
        edges = Edges(agent=agent, k=e.k[sel], n_agents=n_agents, slot=e.slot[sel],
                      flags={name: v[sel] for name, v in e.flags.items()})
        return StepInputs(edges=edges, t=self.t,
                          agent={k: v[rows] for k, v in self.agent.items()},
                          edge={k: v[sel] for k, v in self.edge.items()},
                          mask={k: v[sel] for k, v in self.mask.items()})

    def complete(self, keys: Sequence[str]) -> StepInputs:
        """Only the edges that have every one of ``keys`` (without ``partial_edges``)."""
        if not self.mask:
            return self
        keep = np.ones(len(self.edges), dtype=bool)
        for key in keys:
            if key in self.mask:
                keep &= self.mask[key]
        if keep.all():
            return self
        sel = np.flatnonzero(keep)
        n = self.edges.n_agents
        return dataclasses.replace(self.select(sel, self.edges.agent[sel], slice(None), n),
                                   mask={})


@dataclass(frozen=True)
class WarmStart:
    """:meth:`Estimator.warm_start`'s state (None: refused) and, for /diagnostics, why."""

    x: State | None
    note: str


# ----------------------------------------------------------------------------- findings
@dataclass(frozen=True)
class Finding:
    """One broken (error) or doubtful (warning) assumption, with where and how to fix it."""

    severity: str   # 'error' or 'warning'
    agent: str
    field: str
    problem: str
    fix: str

    def __str__(self) -> str:
        return f'{self.severity}: {self.agent}.{self.field}: {self.problem}. Fix: {self.fix}'


@dataclass
class CheckReport:
    """What :meth:`Estimator.check` found, and the spectra of each agent's local matrix."""

    findings: list[Finding] = field(default_factory=list)
    spectra: dict[str, Array] = field(default_factory=dict)  # ascending eigenvalues per agent
    spectra_of: str = ''    # which matrix, e.g. 'M_i = Σ_j k_ij b_ij b_ijᵀ'
    margins: dict[str, float] = field(default_factory=dict)   # fleet-wide numbers, by name

    @property
    def errors(self) -> list[Finding]:
        return [f for f in self.findings if f.severity == 'error']

    @property
    def warnings(self) -> list[Finding]:
        return [f for f in self.findings if f.severity == 'warning']

    @property
    def ok(self) -> bool:
        return not self.errors

    def format(self, max_spectra: int = 50) -> str:
        lines = [str(f) for f in self.findings]
        if self.spectra:
            lines.append(f'spectra (eigenvalues of {self.spectra_of}):')
            for k, (name, eig) in enumerate(self.spectra.items()):
                if k == max_spectra:
                    lines.append(f'  ... {len(self.spectra) - max_spectra} more')
                    break
                lines.append(f'  {name}: {{{", ".join(f"{e:.4g}" for e in eig)}}}')
        if self.margins:
            lines.append('margins:')
            lines += [f'  {name}: {value:.4g}' for name, value in self.margins.items()]
        return '\n'.join(lines)


# ----------------------------------------------------------------------------- the interface
G = TypeVar('G')


class Estimator(ABC, Generic[G, S]):
    """One method of the literature. An instance holds its gains; the state is separate, so
    one instance serves every agent of a fleet or one agent in a node."""

    method: ClassVar[str]                  # the scenario's `method:`, the registry key
    title: ClassVar[str]                   # 'Boughellaba & Tayebi', for people
    Gains: ClassVar[type]                  # frozen dataclass of `gain` fields
    roles: ClassVar[Roles]
    sensors: ClassVar[frozenset[Sensor]]
    optional_sensors: ClassVar[frozenset[Sensor]] = frozenset()  # used when available
    sends: ClassVar[tuple[Channel, ...]]
    frame: ClassVar[EstimateFrame]
    edge_gains: ClassVar[bool] = True      # per-edge k_ij (`gains.k_ij`, a neighbour's `k`)
    # One edge per neighbour i → j, j's channels to i; or per communication neighbour, both ways.
    links: ClassVar[Literal['sensing', 'communication']] = 'sensing'
    # A robot measures its `neighbours` only, not its listeners too (Presenza et al.).
    directed_sensing: ClassVar[bool] = False
    # Per own point sensor the step reads: the edge flag of the edges it measures (None: every
    # edge, with 'sensing' links the listeners too: the per-edge channels are formed from it).
    measures: ClassVar[Mapping[Sensor, str | None]] = {}
    # An own point sensor's sample for the step at t: 'newest', bridged to t by the gyro (a
    # moving fleet: the one at the stamp of the neighbour's values); 'interpolated' (waited for).
    own_pairing: ClassVar[Literal['newest', 'interpolated']] = 'newest'
    # Whose odometry the step reads besides the own: 'links', each edge's other end's (PEER_*).
    peer_odometry: ClassVar[Literal['none', 'links', 'anchor']] = 'none'
    # The step takes edges with inputs missing (masks); False: only the complete ones.
    partial_edges: ClassVar[bool] = False
    # The step reads ``inputs.t`` (multirate stages): only steps of one instant share a call.
    timed_step: ClassVar[bool] = False
    # The sensor whose measurement of the listener outbox's per-edge channels are formed from.
    partner_sensor: ClassVar[Sensor | None] = None
    reference_scenario: ClassVar[str]      # the file in config/ with the paper's simulation
    # How far the truth drifts from a fixed point of the step in a moving fleet over 300 steps
    # of the reference scenario [m, rad]: rounding, unless the method is first order in h.
    moving_fixed_point_atol: ClassVar[float] = 1e-12

    def __init__(self, gains: G) -> None:
        self.gains = gains

    @classmethod
    def uses(cls, sensor: Sensor) -> bool:
        """The method consumes ``sensor``, always or when available."""
        return sensor in cls.sensors or sensor in cls.optional_sensors

    @classmethod
    def rounds(cls) -> int:
        """Rounds of messages per step (2: what :meth:`reply` forms from round 1)."""
        return max((c.round for c in cls.sends), default=1)

    # --- state
    @abstractmethod
    def initial_state(self, R_hat: Array, p_hat: Array) -> S:
        """The state of N agents from their initial ``R_hat`` ``(N, 3, 3)``, ``p_hat``."""

    def with_known_pose(self, x: S, rows: Index, R: Array, p: Array) -> S:
        """``x`` with the agents ``rows`` (leaders) at their known pose, the rest initial."""
        pinned = self.initial_state(R, p)
        for f in dataclasses.fields(x):
            getattr(x, f.name)[rows] = getattr(pinned, f.name)
        return x

    def propagate(self, x: S, delta_R: Array, displacement: Array | None = None) -> S:
        """``x`` carried over a step by the gyro (and odometry) alone, no correction:
        ``R̂ ← R̂ ΔR``, ``p̂ ← p̂ + R̂ δ``."""
        out = x.rows(slice(None))
        if displacement is not None:
            out.p_hat = x.p_hat + np.einsum('nab,nb->na', x.R_hat, displacement)
        out.R_hat = so3.reorthonormalize(so3.matmul(x.R_hat, delta_R))
        return out

    # --- messages and the step
    @abstractmethod
    def outbox(self, x: S, sender: Index, bearings: Array,
               slot: Index | None = None) -> dict[str, Array]:
        """Round 1, from the senders' state and own measurements at one instant: per-edge
        channels ``(M, ...)`` of the sender rows ``sender`` ``(M,)``, whose ``partner_sensor``
        measurements of the listener are ``bearings`` ``(M, 3)`` (zeros: none) and whose edge
        to it has the place ``slot`` ``(M,)`` (:attr:`Edges.slot`); per-agent ones ``(N, ...)``."""

    @abstractmethod
    def step(self, x: S, h: float, inputs: StepInputs,
             reorthonormalize: bool = True) -> tuple[S, dict[str, Array]]:
        """Advance every agent of ``x`` by ``h``: the new state and per-agent diagnostics
        (``'innovation'`` ``(N, 3)``: what drove the correction). ``reorthonormalize``: pull
        rotations back onto SO(3) (the batch simulator: every few steps only)."""

    def reply(self, x: S, h: float, inputs: StepInputs) -> dict[str, Array]:
        """Two-round methods: the round-2 channels ``(E, ...)`` each edge's agent sends its other
        end, from its state and the round-1 ``inputs`` (as :meth:`step` gets them)."""
        raise NotImplementedError(f'{self.method} exchanges one round of messages')

    def warm_start(self, x: S, inputs: StepInputs) -> WarmStart | None:
        """A state for one agent with no trustworthy estimate (started late, after a gyro gap
        or a clock jump) from its step's ``inputs`` (as :meth:`step` gets them), or why not;
        None: no warm start (the method's, or this agent's role's)."""
        return None

    def missing(self, channel: str) -> Array:
        """What the step takes for an ``optional`` channel a neighbour has not sent."""
        raise NotImplementedError(f'{self.method} has no optional channel {channel!r}')

    def due(self, channel: str, t: float, h: float) -> bool:
        """The step at ``t`` reads ``channel`` (multirate methods: only at their stage's ticks,
        when a node waits for and sends it)."""
        return True

    def carry(self, values: Mapping[str, Array], motion: Motion) -> dict[str, Array] | None:
        """A sender's channel ``values`` formed at ``t_s`` carried to ``t > t_s`` by the motion
        alone (what they would be at t with no correction meanwhile); None: the method cannot,
        and a late value is used as it is (``'instant'`` pairing) or left out."""
        return None

    # --- assumptions
    @abstractmethod
    def check(self, fleet: Fleet) -> CheckReport:
        """The method's graph assumptions on ``fleet``: errors for what breaks convergence,
        warnings for what weakens it, each naming the agent, the field and the fix."""

    def conditioning(self, bearings: Array, k: Array) -> Array | None:
        """The local matrix whose spectrum the convergence proof needs, from one agent's
        bearings ``(M, 3)`` (any frame) and gains ``(M,)``; None when the method has none."""
        return None

    def conditioning_problem(self, eig: Array) -> str | None:
        """Why the spectrum ``eig`` (ascending) breaks the method's hypothesis, or None."""
        return None

    def agent_groups(self, fleet: Fleet) -> dict[str, list[str]]:
        """``{role: names}`` of the estimating robots, for outputs that show them apart."""
        return {}

    def fleet_margins(self, fleet: Fleet, R_hat: Array, p_hat: Array) -> dict[str, float]:
        """Margins of the method's assumptions on the whole fleet's estimates ``(N, 3, 3)``,
        ``(N, 3)``, which the monitor reports (Presenza et al.: angle rigidity)."""
        return {}

    # The names of the per-agent diagnostic 'stage' (an index), for methods that report one.
    stages: ClassVar[tuple[str, ...]] = ()

    # --- what recordings and diagnostics show beyond the pose errors
    edge_error_label: ClassVar[str] = ''   # e.g. 'rel_yaw_err': the column prefix per pair

    def edge_errors(self, x: S, R: Array, edges: Edges, other: Index) -> Array | None:
        """Per edge ``(E,)``, the error of a per-pair state against the true attitudes ``R``
        (NaN where the edge's agent keeps none); None when the method keeps none."""
        return None

    def neighbour_report(self, x: S, slots: int) -> dict[str, list[str]]:
        """``{label: [text per edge slot]}`` for one agent's health report (De Carli et al.:
        each pair's excitation)."""
        return {}

    def covariance(self, x: S) -> Array | None:
        """``(N, 6, 6)``: each pose's covariance as the estimate's message carries it, or None."""
        P = getattr(x, 'P', None)
        return None if P is None else P[:, :6, :6]

    def check_motion(self, fleet: Fleet, times: Array,
                     positions: Array) -> list[Finding]:
        """The method's assumptions that a moving ``fleet`` breaks along its sampled truth,
        ``times`` ``(K,)`` [s] and ``positions`` ``(K, N, 3)`` [m] (``positions[0]``: what
        :meth:`check` saw, whose findings are not repeated); each finding names the time."""
        return []


# ----------------------------------------------------------------------------- the edges
@dataclass(frozen=True)
class EdgeTable:
    """A fleet's edges for one method (:func:`edge_table`), grouped by agent: edge ``e`` joins
    ``agent[e]`` to ``other[e]`` with gain ``k[e]``; ``flags`` ``(E,)``: ``senses``,
    ``sensed_by``, ``owns`` (the pair's shared state, §8 of the De Carli notes), ``ranges``,
    ``ranged_by``; ``reverse``: the index of the edge ``other → agent`` (-1: none)."""

    agent: Index
    other: Index
    k: Array
    flags: dict[str, Mask]
    reverse: Index

    def edges(self, n: int) -> Edges:
        return Edges(agent=self.agent, k=self.k, n_agents=n, flags=self.flags)

    def of(self, i: int) -> Index:
        """The edges of agent ``i``, in their order (their slots)."""
        return np.flatnonzero(self.agent == i)


def edge_table(method: type[Estimator], n: int, tail: Index, head: Index, k: Array,
               anchor: int | None = None, ranged: Sequence[int] = ()) -> EdgeTable:
    """The edges of ``method`` on ``n`` agents with sensing edges ``tail[e] → head[e]`` (gain
    ``k[e]``), grouped by agent: one per sensing edge (``links = 'sensing'``), or one per
    communication neighbour, ids ascending (the anchor's ranged robots included)."""
    tail, head = np.asarray(tail, dtype=np.intp), np.asarray(head, dtype=np.intp)
    edges = list(zip(tail.tolist(), head.tolist()))
    sensed = set(edges)
    if method.links == 'sensing':
        both = not method.directed_sensing
        flags = {'senses': np.ones(len(tail), bool),
                 'sensed_by': np.array([both or (j, i) in sensed for i, j in edges], bool)}
        where = {(i, j): e for e, (i, j) in enumerate(edges)}
        reverse = np.array([where.get((j, i), -1) for i, j in edges], np.intp)
        return EdgeTable(tail, head, np.asarray(k, dtype=float), flags, reverse)
    pairs = [(anchor, int(r)) for r in ranged] if anchor is not None else []
    linked = sensed | set(pairs)
    links = [(i, j) for i in range(n)
             for j in sorted({b for a, b in linked if a == i} | {a for a, b in linked if b == i})]
    agent = np.array([i for i, _ in links], dtype=np.intp)
    other = np.array([j for _, j in links], dtype=np.intp)
    senses = np.array([(i, j) in sensed for i, j in links], dtype=bool)
    sensed_by = np.array([(j, i) in sensed for i, j in links], dtype=bool)
    where = {(i, j): e for e, (i, j) in enumerate(links)}
    flags = {'senses': senses, 'sensed_by': sensed_by,
             'owns': np.where(senses & sensed_by, agent < other, senses)}
    if method.roles.anchor:
        ranges = set(pairs)
        flags['ranges'] = np.array([(i, j) in ranges for i, j in links], bool)
        flags['ranged_by'] = np.array([(j, i) in ranges for i, j in links], bool)
    return EdgeTable(agent, other, np.ones(len(links)), flags,
                     np.array([where[(j, i)] for i, j in links], dtype=np.intp))


def route(outbox: Mapping[str, Array], sends: Sequence[Channel],
          sender_of_edge: Index) -> dict[str, Array]:
    """The fleet's outbox as each edge's receiver sees it: per-edge channels are already one
    row per edge (formed with ``sender=sender_of_edge``), per-agent ones are gathered."""
    return {c.name: outbox[c.name] if c.per == 'edge'
            else np.take(outbox[c.name], sender_of_edge, axis=0) for c in sends}
