"""The estimator interface: what every method declares, and its one vectorised step.

A method is a subclass of :class:`Estimator`, registered under the scenario's ``method:`` key
(:mod:`bearing_pose_estimation.estimators`). It declares, as class attributes,

- ``Gains``: a frozen dataclass whose fields are the YAML keys of ``gains:`` and the estimator
  node's parameter names, each with a default, a help text and a range (:func:`gain`);
- ``roles``: the special agents it needs (:class:`Roles`: two leaders today; later one anchor,
  or none);
- ``sensors``: what it consumes (:class:`Sensor`), and ``optional_sensors`` what it uses when
  available (odometry for the feed-forward of the leader-follower methods);
- ``sends``: what each agent sends the agents that listen to it (:class:`Channel`: per agent
  or per sensing edge, with its frame);
- ``frame``: how its estimates are expressed (:class:`EstimateFrame`), so that errors are
  measured after the right alignment (:mod:`bearing_pose_estimation.metrics.results`);

and implements its per-agent state (a :class:`State` dataclass of ``(N, ...)`` arrays, the
class's second type parameter) and its initial value, its graph-assumption check
(:meth:`Estimator.check`, findings that name the agent, the field and the fix) and one
vectorised :meth:`Estimator.step`. The batch simulator calls that step for the whole fleet, the
agent's node logic (:class:`bearing_pose_estimation.estimators.agent.AgentEstimator`) for one
agent: each method's math exists once.

Sensing edges: edge ``e`` is ``i → j``, agent i (row ``edges.agent[e]`` of the state) senses
and listens to its neighbour j. A step consumes, per edge, i's own measurement and what j sent
i (:class:`StepInputs`); what j sends is formed by j itself (:meth:`Estimator.outbox`), from
its own state and measurements at one instant.

Methods whose agents talk both ways over every sensing edge (``links = 'communication'``, De
Carli et al.: the sensed robot needs what senses it) get one edge ``i → j`` per communication
neighbour j of i instead (j senses i, i senses j, or both), with :class:`LinkInputs` saying
which, and the other end's odometry over the step.
"""
from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, ClassVar, Generic, Literal, TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from ..core import so3
from ..core.errors import ScenarioError
from .fleet import Fleet

Array = NDArray[np.float64]
Index = NDArray[np.intp]


# ----------------------------------------------------------------------------- declarations
class Sensor(Enum):
    """What an agent measures about itself and the agents it sees."""

    GYRO = 'gyro'                              # body angular rate (interval averages)
    BEARINGS = 'bearings'                      # unit bearings to the agents it sees (body)
    KNOWN_POSE = 'known_pose'                  # its own pose (leaders: mocap, GNSS/INS)
    ODOMETRY = 'odometry'                      # body linear velocity and rate
    RELATIVE_POSITIONS = 'relative_positions'  # body-frame relative positions (RGB-D)
    BEARING_RATES = 'bearing_rates'            # time derivatives of body bearings
    RANGES = 'ranges'                          # distances to the agents it sees


class EstimateFrame(Enum):
    """How a method's estimates relate to the world, i.e. how errors are measured."""

    WORLD = 'world'                            # world poses: errors measured directly
    COMMON_YAW_TRANSLATION = 'common_yaw_translation'  # up to one yaw and one translation
    ANCHOR_BODY = 'anchor_body'                # in the anchor's (moving) body frame


@dataclass(frozen=True)
class Roles:
    """The special agents a method needs: ``leaders`` agents that know their pose (the
    scenario's ``leaders:``; Boughellaba & Tayebi and Tran et al.: 2), or one ``anchor``."""

    leaders: int = 0
    anchor: bool = False


@dataclass(frozen=True)
class Channel:
    """One quantity that agent j sends the agents that listen to it (those with j among their
    neighbours). ``per='agent'``: one value for all of them (e.g. ``p̂_j``); ``per='edge'``: one
    value per listener i (e.g. ``R̂_j b^j_ji``). ``frame`` is the frame the value is expressed
    in; ``unit`` values are unit vectors (validated on reception); ``sensor``: the value is
    j's own measurement of i by that sensor, which travels on j's sensor topic (a node pairs it
    at its instant like its own measurements); ``owner_only``: a per-edge value only the owner
    of the pair's shared state sends (a receiver that owns the pair expects none); ``round``
    2: formed from what the sender received in round 1 of the same step
    (:meth:`Estimator.reply`, two-round methods); ``optional``: see below. The wire encoding of
    each channel name lives in ``msg_defs``."""

    name: str
    per: Literal['agent', 'edge']
    frame: str
    unit: bool = False
    shape: tuple[int, ...] = (3,)
    doc: str = ''
    sensor: Sensor | None = None
    owner_only: bool = False
    round: int = 1
    # A value the step can do without (the covariance): a neighbour missing it is not stale,
    # and the step takes Estimator.missing(name) instead.
    optional: bool = False


# ----------------------------------------------------------------------------- gains
def gain(default: float, help: str, minimum: float = 0.0, zero_allowed: bool = False,
         model: bool = False) -> Any:
    """A field of a method's gains dataclass: ``default``, a one-line ``help`` (shown by the
    node's parameter descriptions) and the exclusive lower bound ``minimum`` (gains are > 0;
    ``zero_allowed``: >= 0, for a term that 0 switches off). ``model``: a parameter of the
    covariance's model (noise, prior), not of the estimate: tables of gains leave it out."""
    return field(default=default, metadata={'help': help, 'minimum': minimum,
                                            'zero_allowed': zero_allowed, 'model': model})


def gain_fields(gains_cls: type) -> tuple[dataclasses.Field, ...]:
    """The gains a method reads, in declaration order."""
    return dataclasses.fields(gains_cls)


def parse_gains(gains_cls: type, values: Mapping[str, Any], where: str = 'gains') -> Any:
    """``gains_cls`` from ``values`` (missing keys take their defaults).

    Raises:
        ScenarioError: an unknown key, or a value that is not a finite number above the
            gain's minimum, naming ``<where>.<gain>`` and the fix.
    """
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
        low = f.metadata['minimum']
        if x < low or (x == low and not f.metadata.get('zero_allowed', False)):
            relation = '>=' if f.metadata.get('zero_allowed', False) else '>'
            raise ScenarioError(f'{here}: must be {relation} {low:g}, got {x:g}. Fix: '
                                f'use a {"non-negative" if relation == ">=" else "positive"} '
                                'value')
        out[f.name] = x
    return gains_cls(**out)


def format_gains(gains: Any) -> str:
    """``k_R=1, k_p=1``: the gains as logs and tables show them (not the covariance's model)."""
    return ', '.join(f'{f.name}={getattr(gains, f.name):g}' for f in gain_fields(type(gains))
                     if not f.metadata.get('model'))


# ----------------------------------------------------------------------------- edges, state
# Above this many edges, sums over each agent's edges use a sparse incidence matrix: once
# built (~100 µs), its product beats np.add.at from about 64 edges on (5 against 5 µs at 64,
# 6 against 30 µs at 512), what the batch simulator's fleets need (Edges.sum_by_agent).
SPARSE_SUM_EDGES = 64


@dataclass(frozen=True, eq=False)
class Edges:
    """Directed sensing edges ``i → j`` (agent i measures j), fixed for a step.

    ``agent[e]`` indexes the state row of the agent that owns edge ``e`` (always 0 in a node);
    ``k[e]`` is ``k_ij``. Sums over each agent's edges use a sparse ``(n_agents, E)`` incidence
    matrix, built once at the first sum, for a fleet's many edges (the batch simulator's, built
    once a run). Compared by identity, so a method may cache what it derives from a fleet's
    edges.
    """

    agent: Index
    k: Array
    n_agents: int
    # The edge's place in its agent's fixed list of neighbours, for methods that keep per-edge
    # state (a node may leave a silent neighbour out of a step); default: its rank.
    slot: Index | None = None
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

    def weighted(self, terms: Array) -> Array:
        """``k_ij · terms[e]`` (``terms`` itself when every ``k_ij = 1``)."""
        return terms if self.unit_k else terms * self.k[:, None]


S = TypeVar('S', bound='State')


@dataclass
class State:
    """A method's per-agent state: every field an ``(N, ...)`` array, row i for agent i.
    Every method estimates a pose: ``R_hat`` (body → the method's frame) and ``p_hat`` [m];
    subclasses add their own fields."""

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

    def set_rows(self, idx: Any, other: State) -> None:
        """Overwrite the rows ``idx`` with ``other`` (same type, one row per index)."""
        for f in dataclasses.fields(self):
            getattr(self, f.name)[idx] = getattr(other, f.name)

    def is_finite(self) -> bool:
        values = (getattr(self, f.name) for f in dataclasses.fields(self))
        return all(bool(np.isfinite(v).all()) for v in values
                   if v.dtype.kind in 'fc')   # bool flags are always finite


@dataclass(frozen=True)
class LinkInputs:
    """What a ``links = 'communication'`` method's step knows of each edge ``i → j`` beyond
    the channels, all ``(E, ...)``: whether i ``senses`` j and j senses i (``sensed_by``: j's
    own measurement of i comes as a channel), whether i ``owns`` the pair's shared state; i's
    measurement ``ⁱp_ij`` at the step's start (``relative_positions``, body frame [m]); the other
    end's gyro increment and odometry displacement over the step (``other_delta_R``,
    ``other_displacement``, in j's body frame at the start).

    A node may lack some of it for a step (None: nothing is missing, the batch simulator):
    ``measured``, its own measurement; ``their_measured``, j's; ``present``, j's odometry (the
    edge then sits the step out and restarts its relative estimates from the next
    measurements); ``fresh``, j's channels of this instant."""

    senses: NDArray[np.bool_]
    sensed_by: NDArray[np.bool_]
    owns: NDArray[np.bool_]
    relative_positions: Array
    other_delta_R: Array
    other_displacement: Array
    measured: NDArray[np.bool_] | None = None
    their_measured: NDArray[np.bool_] | None = None
    present: NDArray[np.bool_] | None = None
    fresh: NDArray[np.bool_] | None = None

    def usable(self) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_],
                              NDArray[np.bool_]]:
        """``(y_ok, m_ok, present, fresh)`` ``(E,)``: i senses j and its measurement is here,
        j senses i and j's is here, j's odometry, j's channels of this instant (what is None
        counts as here)."""
        every = np.ones(len(self.senses), dtype=bool)

        def here(v: NDArray[np.bool_] | None) -> NDArray[np.bool_]:
            return every if v is None else v

        return (self.senses & here(self.measured), self.sensed_by & here(self.their_measured),
                here(self.present), here(self.fresh))

    @staticmethod
    def stack(parts: Sequence[LinkInputs]) -> LinkInputs:
        """Several agents' link inputs as one, edges in that order (:meth:`rows` undone)."""
        def cat(name: str) -> Any:
            values = [getattr(p, name) for p in parts]
            if all(v is None for v in values):
                return None
            if any(v is None for v in values):   # a flag known for some only: the others
                values = [np.ones(len(p.senses), dtype=bool) if v is None else v
                          for p, v in zip(parts, values)]   # have it all (None: all here)
            return np.concatenate(values)

        return LinkInputs(**{f.name: cat(f.name) for f in dataclasses.fields(LinkInputs)})

    def rows(self, sel: Index) -> LinkInputs:
        def pick(v: NDArray[np.bool_] | None) -> NDArray[np.bool_] | None:
            return None if v is None else v[sel]

        return LinkInputs(self.senses[sel], self.sensed_by[sel], self.owns[sel],
                          self.relative_positions[sel], self.other_delta_R[sel],
                          self.other_displacement[sel], measured=pick(self.measured),
                          their_measured=pick(self.their_measured), present=pick(self.present),
                          fresh=pick(self.fresh))


@dataclass(frozen=True)
class AnchorInputs:
    """What the step of a method with an anchor (``roles.anchor``) knows of it: per agent,
    ``is_anchor`` ``(N,)`` and the anchor's gyro increment and odometry displacement over the
    step as every robot receives them (``delta_R`` ``(N, 3, 3)``, ``displacement`` ``(N, 3)``,
    in the anchor's body frame at the step's start); per edge ``i → j``, ``ranges`` ``(E,)``:
    i is the anchor and measures j's relative position (j is a ranged robot), ``ranged_by``
    ``(E,)``: j is the anchor and ranges i; ``pinned``: the anchor holds ``(I, 0)``."""

    is_anchor: NDArray[np.bool_]
    delta_R: Array
    displacement: Array
    ranges: NDArray[np.bool_]
    ranged_by: NDArray[np.bool_]
    pinned: bool = False

    @staticmethod
    def stack(parts: Sequence[AnchorInputs]) -> AnchorInputs:
        """Several agents' anchor inputs as one, agents and edges in that order (:meth:`rows`
        undone); they must agree on ``pinned``."""
        if len({p.pinned for p in parts}) > 1:
            raise ValueError('AnchorInputs.stack: pinned differs between the parts')

        def cat(name: str) -> Any:
            return np.concatenate([getattr(p, name) for p in parts])

        return AnchorInputs(cat('is_anchor'), cat('delta_R'), cat('displacement'), cat('ranges'),
                            cat('ranged_by'), pinned=parts[0].pinned)

    def rows(self, i: int, sel: Index) -> AnchorInputs:
        return AnchorInputs(self.is_anchor[i:i + 1], self.delta_R[i:i + 1],
                            self.displacement[i:i + 1], self.ranges[sel], self.ranged_by[sel],
                            self.pinned)


@dataclass(frozen=True)
class StepInputs:
    """What one step consumes for N agents and their E sensing edges, all at the step's start
    time t (own bearings already rotated to t, neighbours' values as they sent them).

    ``received[c]`` holds, for every channel ``c`` the method's ``sends`` declares, what the
    neighbour j of edge ``e`` sent agent i: ``(E, ...)`` (per-agent channels repeated on every
    edge from j).

    Moving fleets add:

    - ``displacement``: ``(N, 3)`` odometry displacement over the step, ``R(t)ᵀ (p(t+h) -
      p(t))`` (body frame at t) [m], integrated from the samples, never velocity × h; None
      without odometry.
    - ``p_own``: ``(E, 3)`` the position estimate of each edge's owner to pair with what it
      received. Over DDS j's values were formed at its stamp ``t_s < t``, and in a moving fleet
      they change meanwhile: agent i pairs them with its own bearing measured at ``t_s``
      (``bearings``, still rotated to the body frame at t) and with ``p̂_i`` moved back to
      ``t_s`` by its own odometry, ``p̂_i(t) - R̂_i(t) R_i(t)ᵀ R_i(t_s) δ_i(t_s → t)``, so that
      the pairing is exact at the true poses whatever the motion, while the corrections
      themselves are not delayed. None: no transport delay (the batch simulator), ``p̂_i``.
    """

    delta_R: Array                 # (N, 3, 3) gyro increments R(t)ᵀ R(t + h) (body)
    edges: Edges
    bearings: Array                # (E, 3) own unit bearings b^i_ij (body frame of i)
    received: Mapping[str, Array]
    displacement: Array | None = None   # (N, 3) odometry δ over the step [m]
    p_own: Array | None = None          # (E, 3) the owner's p̂_i at the received stamp [m]
    links: LinkInputs | None = None     # links = 'communication' methods only
    t: float = 0.0                      # the step's start time [s] (multirate methods)
    bearing_rates: Array | None = None  # (E, 3) own d/dt b^i_ij (body frame) [1/s]
    anchor: AnchorInputs | None = None  # methods with an anchor only
    # (E, 2) steps each own bearing and each neighbour's value serve (>= 1; a node holds
    # samples slower than its steps, and their noise with them): the covariance's bearing
    # noise lasts that long. None: a fresh sample every step (the batch simulator).
    held: Array | None = None

    @staticmethod
    def stack(parts: Sequence[StepInputs]) -> StepInputs:
        """The inputs of several agents' steps as one fleet step, agents and edges in that
        order: :meth:`agent` undone. What a node builds (own bearings, received values,
        displacement, ``p_own``, ``held``, a link method's :class:`LinkInputs`) only; every
        part has the same optional fields."""
        first = parts[0]
        for name in ('links', 'anchor'):
            given = [getattr(p, name) is not None for p in parts]
            if any(given) and not all(given):
                raise ValueError(f'StepInputs.stack: {name} is given for some parts only')

        def cat(name: str) -> Array | None:
            values = [getattr(p, name) for p in parts]
            if all(v is None for v in values):
                return None
            if any(v is None for v in values):
                raise ValueError(f'StepInputs.stack: {name} is given for some parts only')
            return np.concatenate(values)

        sizes = [p.delta_R.shape[0] for p in parts]
        offsets = np.cumsum([0] + sizes[:-1])
        slots = [p.edges.slot for p in parts]
        assert all(slot is not None for slot in slots)
        edges = Edges(agent=np.concatenate([p.edges.agent + o for p, o in zip(parts, offsets)]),
                      k=np.concatenate([p.edges.k for p in parts]), n_agents=sum(sizes),
                      slot=np.concatenate(slots))   # type: ignore[arg-type]
        return StepInputs(delta_R=np.concatenate([p.delta_R for p in parts]), edges=edges,
                          bearings=np.concatenate([p.bearings for p in parts]),
                          received={c: np.concatenate([p.received[c] for p in parts])
                                    for c in first.received},
                          displacement=cat('displacement'), p_own=cat('p_own'),
                          t=first.t, held=cat('held'), bearing_rates=cat('bearing_rates'),
                          links=None if first.links is None else LinkInputs.stack(
                              [p.links for p in parts if p.links is not None]),
                          anchor=None if first.anchor is None else AnchorInputs.stack(
                              [p.anchor for p in parts if p.anchor is not None]))

    def agent(self, i: int) -> StepInputs:
        """The inputs of agent ``i`` alone (``n_agents = 1``): what its node would pass."""
        sel = np.flatnonzero(self.edges.agent == i)
        assert self.edges.slot is not None
        edges = Edges(agent=np.zeros(sel.size, dtype=np.intp), k=self.edges.k[sel], n_agents=1,
                      slot=self.edges.slot[sel])
        return StepInputs(t=self.t, links=None if self.links is None else self.links.rows(sel),
                          delta_R=self.delta_R[i:i + 1], edges=edges,
                          bearings=self.bearings[sel],
                          received={c: v[sel] for c, v in self.received.items()},
                          displacement=(None if self.displacement is None
                                        else self.displacement[i:i + 1]),
                          p_own=None if self.p_own is None else self.p_own[sel],
                          bearing_rates=(None if self.bearing_rates is None
                                         else self.bearing_rates[sel]),
                          anchor=None if self.anchor is None else self.anchor.rows(i, sel),
                          held=None if self.held is None else self.held[sel])


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
    # 'sensing': one edge per sensing edge i → j, j's channels flow to i; 'communication': one
    # per communication neighbour, both ways (StepInputs.links).
    links: ClassVar[Literal['sensing', 'communication']] = 'sensing'
    # Sensing is directed: a robot measures its `neighbours` only (Presenza et al.'s
    # out-neighbours), not its listeners too.
    directed_sensing: ClassVar[bool] = False
    reference_scenario: ClassVar[str]      # the file in config/ with the paper's simulation
    # How far the truth drifts from a fixed point of the step when the fleet moves, over 300
    # steps of the reference scenario [m, rad]: 0 up to rounding for methods that dead-reckon
    # with the exact odometry increments; first-order methods (Presenza et al.'s free robots
    # move with the velocity reconstructed at the step's start) set their own.
    moving_fixed_point_atol: ClassVar[float] = 1e-12

    def __init__(self, gains: G) -> None:
        self.gains = gains

    @classmethod
    def uses(cls, sensor: Sensor) -> bool:
        """The method consumes ``sensor``, always or when available."""
        return sensor in cls.sensors or sensor in cls.optional_sensors

    # --- state
    @abstractmethod
    def initial_state(self, R_hat: Array, p_hat: Array) -> S:
        """The state of N agents whose initial pose estimates are ``R_hat`` ``(N, 3, 3)`` and
        ``p_hat`` ``(N, 3)``."""

    def with_known_pose(self, x: S, rows: Index, R: Array, p: Array) -> S:
        """``x`` with the agents ``rows`` at their known pose ``R``, ``p`` (leaders) and every
        other state of theirs at its initial value."""
        pinned = self.initial_state(R, p)
        x.set_rows(rows, pinned)
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
        """What agents send their listeners, formed from their state and own measurements at
        one instant: per-edge channels ``(M, ...)`` for sender rows ``sender`` ``(M,)`` whose
        own body bearings to the listener are ``bearings`` ``(M, 3)`` (``links =
        'communication'``: their relative positions, zeros where they do not sense it) and
        whose edge to the listener has the place ``slot`` ``(M,)`` in their own list
        (:attr:`Edges.slot`); per-agent channels ``(N, ...)``, one row per agent of ``x``."""

    @abstractmethod
    def step(self, x: S, h: float, inputs: StepInputs,
             reorthonormalize: bool = True) -> tuple[S, dict[str, Array]]:
        """Advance every agent of ``x`` by ``h``; return the new state and per-agent
        diagnostics (``'innovation'``: what drove the correction, ``(N, 3)``).
        ``reorthonormalize``: pull rotations back onto SO(3) (the batch simulator does it every
        few steps only)."""

    # 2: every step exchanges two rounds of messages, what ``outbox`` forms and then what
    # ``reply`` forms from the first round (channels with ``round = 2``).
    rounds: ClassVar[int] = 1

    def reply(self, x: S, h: float, inputs: StepInputs) -> dict[str, Array]:
        """Two-round methods: the round-2 channels, per edge ``(E, ...)``, that each edge's
        agent sends the edge's other end, formed from its state, its own measurements and the
        round-1 values it received (``inputs`` as :meth:`step` gets them, without round 2)."""
        raise NotImplementedError(f'{self.method} exchanges one round of messages')

    def missing(self, channel: str) -> Array:
        """What the step takes for an ``optional`` channel a neighbour has not sent."""
        raise NotImplementedError(f'{self.method} has no optional channel {channel!r}')

    def due(self, channel: str, t: float, h: float) -> bool:
        """The step at ``t`` reads ``channel`` (multirate methods read some only at their
        stage's ticks: a node waits for those alone). Default: every step."""
        return True

    # --- assumptions
    @abstractmethod
    def check(self, fleet: Fleet) -> CheckReport:
        """The method's graph assumptions on ``fleet`` (``Scenario.fleet()``): errors for what
        breaks convergence, warnings for what weakens it, each naming the agent, the field and
        the fix."""

    def conditioning(self, bearings: Array, k: Array) -> Array | None:
        """The local matrix whose spectrum the method's convergence proof needs, from one
        agent's bearings to its neighbours ``(M, 3)`` and their gains ``(M,)`` (any frame: the
        spectrum is rotation invariant); None when the method has none."""
        return None

    def conditioning_problem(self, eig: Array) -> str | None:
        """Why the spectrum ``eig`` (ascending) breaks the method's hypothesis, or None."""
        return None

    def carry(self, values: Mapping[str, Array], own_delta_R: Array, other_delta_R: Array,
              other_displacement: Array) -> dict[str, Array] | None:
        """A neighbour's channel ``values`` formed at ``t_s`` carried to ``t > t_s`` by the
        motion over ``[t_s, t]`` alone (the receiver's gyro increment ``own_delta_R``, the
        sender's ``other_delta_R`` and ``other_displacement`` in its frame at ``t_s``): what
        they would be at t if no correction had happened meanwhile. None: the method cannot
        (its node then leaves a late value out)."""
        return None

    def carry_anchor_frame(self, values: Mapping[str, Array], delta_R_a: Array,
                           delta_a: Array) -> dict[str, Array] | None:
        """Methods with an anchor: a neighbour's ``values`` in the anchor frame at ``t_s``
        carried to ``t > t_s`` by the anchor's motion over ``[t_s, t]`` (``delta_R_a``,
        ``delta_a``, in its frame at ``t_s``): the values the same world quantities have in the
        anchor frame at t. None: the method cannot."""
        return None

    def agent_groups(self, fleet: Fleet) -> dict[str, list[str]]:
        """The method's roles among the estimating robots, ``{role: names}``, for outputs
        that show them apart (Presenza et al.: sensing and free robots). Empty: none."""
        return {}

    def fleet_margins(self, fleet: Fleet, R_hat: Array, p_hat: Array) -> dict[str, float]:
        """Margins of the method's assumptions evaluated on the whole fleet's estimates
        ``(N, 3, 3)``, ``(N, 3)`` (what the monitor, which sees every estimate, reports;
        Presenza et al.: angle rigidity). Empty: none."""
        return {}

    # The names of the per-agent diagnostic 'stage' (an index), for methods that report one.
    stages: ClassVar[tuple[str, ...]] = ()

    # --- what recordings show beyond the pose errors
    edge_error_label: ClassVar[str] = ''   # e.g. 'rel_yaw_err': the column prefix per pair

    def edge_errors(self, x: S, R: Array, edges: Edges, other: Index) -> Array | None:
        """Per edge ``(E,)``, the error of a per-pair state the method keeps, against the true
        attitudes ``R`` (NaN where the edge's agent keeps none; ``other``: each edge's other
        end); None when the method has no such state."""
        return None

    def check_motion(self, fleet: Fleet, times: Array,
                     positions: Array) -> list[Finding]:
        """The method's assumptions that the motion of a moving ``fleet`` breaks, from its
        sampled truth: ``times`` ``(K,)`` [s] from 0 to its duration and ``positions``
        ``(K, N, 3)`` [m] (agents in scenario order; ``positions[0]`` is where :meth:`check`
        looked). Each finding names the time; what :meth:`check` already reports at t = 0 is
        not repeated. Default: none (nothing of the method depends on the geometry)."""
        return []


def owns_pair(i: Any, j: Any, senses: Any, sensed_by: Any) -> Any:
    """Whether agent i keeps the shared state of its pair with j (§8 of the De Carli notes):
    the sensing agent of a one-way pair, the lower index (or id) of a two-way one. Scalars or
    arrays."""
    return np.where(np.logical_and(senses, sensed_by), np.less(i, j), senses)


def communication_links(tail: Index, head: Index, n: int,
                        also: Sequence[tuple[int, int]] = ()) -> dict[str, NDArray[Any]]:
    """The links of ``links = 'communication'`` methods from the sensing edges ``tail → head``
    of ``n`` agents (and the pairs ``also``, e.g. the anchor's ranged robots, linked without
    sensing): one per communication neighbour j of each agent i, grouped by agent, j
    ascending: ``agent``, ``other``, ``senses`` (i senses j), ``sensed_by`` (j senses i),
    ``owns`` (i keeps the pair's shared state: the sensing agent of a one-way pair, the lower
    index of a two-way one) and ``reverse`` (the index of the link j → i)."""
    sensed = set(zip(np.asarray(tail).tolist(), np.asarray(head).tolist()))
    linked = sensed | {(int(i), int(j)) for i, j in also}
    agent: list[int] = []
    other: list[int] = []
    for i in range(n):
        for j in sorted({b for a, b in linked if a == i} | {a for a, b in linked if b == i}):
            agent.append(i)
            other.append(j)
    agent_a, other_a = np.array(agent, dtype=np.intp), np.array(other, dtype=np.intp)
    senses = np.array([(i, j) in sensed for i, j in zip(agent, other)], dtype=bool)
    sensed_by = np.array([(j, i) in sensed for i, j in zip(agent, other)], dtype=bool)
    where = {(i, j): e for e, (i, j) in enumerate(zip(agent, other))}
    return {'agent': agent_a, 'other': other_a, 'senses': senses, 'sensed_by': sensed_by,
            'owns': owns_pair(agent_a, other_a, senses, sensed_by),
            'reverse': np.array([where[(j, i)] for i, j in zip(agent, other)], dtype=np.intp)}


def route(outbox: Mapping[str, Array], sends: Sequence[Channel],
          sender_of_edge: Index) -> dict[str, Array]:
    """The fleet's outbox as each edge's receiver sees it: per-edge channels are already one
    row per edge (formed with ``sender=sender_of_edge``), per-agent ones are gathered."""
    return {c.name: outbox[c.name] if c.per == 'edge'
            else np.take(outbox[c.name], sender_of_edge, axis=0) for c in sends}
