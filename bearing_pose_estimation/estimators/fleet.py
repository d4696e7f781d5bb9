"""What a method knows of a fleet: the small frozen value the estimator interface takes instead
of the whole scenario (``Scenario.fleet()`` builds it), so the methods sit below that layer."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from ..core.motion import AngularVelocity, YawSpline

Array = NDArray[np.float64]
Index = NDArray[np.intp]


@dataclass(frozen=True, eq=False)
class Fleet:
    """A fleet's agents, sensing graph, roles and starting estimates. Agents are indices
    ``0..N-1`` in the scenario's order (names are only for messages). Arrays are read-only (one
    fleet is shared by every caller of its scenario)."""

    names: tuple[str, ...]
    # Per agent i: (j, k_ij) for each j in N_i, in the scenario's order.
    neighbours: tuple[tuple[tuple[int, float], ...], ...]
    positions: Array      # (N, 3) true positions at t = 0 [m], world frame
    attitudes: Array      # (N, 3, 3) true attitudes at t = 0 (body -> world)
    initial_R: Array      # (N, 3, 3) initial estimates in the method's estimate frame
    initial_p: Array      # (N, 3) (scenario.model.initial_estimates)
    frequency: float      # estimator rate [Hz]; the step is h = 1/frequency
    leaders: tuple[int, ...] = ()
    anchor: int | None = None
    ranged: tuple[int, ...] = ()
    anchor_pinned: bool = False
    moves: bool = False   # some agent translates
    # Per agent: its angular velocity and its yaw spline (None: none), how its attitude moves.
    angular_velocities: tuple[AngularVelocity, ...] = ()
    yaws: tuple[YawSpline | None, ...] = ()

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def step(self) -> float:
        """The estimator step h [s]."""
        return 1.0 / self.frequency

    @cached_property
    def index(self) -> dict[str, int]:
        """Agent name -> index."""
        return {name: i for i, name in enumerate(self.names)}

    @staticmethod
    def agent_id(i: int) -> int:
        """The id on the wire of agent ``i``: its 1-based position (the paper's number)."""
        return i + 1

    @property
    def followers(self) -> tuple[int, ...]:
        """The agents that estimate their pose: all but the leaders and a pinned anchor."""
        return tuple(i for i in range(self.n) if i not in self.leaders
                     and not (i == self.anchor and self.anchor_pinned))

    def listeners(self, i: int) -> list[int]:
        """Agents that have ``i`` as a neighbour (they receive what it sends), in order."""
        return [j for j, nbrs in enumerate(self.neighbours) if any(k == i for k, _ in nbrs)]

    def sensing_edges(self) -> tuple[Index, Index]:
        """``(tail, head)`` of every sensing edge (i measures its neighbour j), in order."""
        edges = np.array([(i, j) for i, nbrs in enumerate(self.neighbours) for j, _ in nbrs],
                         dtype=np.intp).reshape(-1, 2)
        return edges[:, 0].copy(), edges[:, 1].copy()
