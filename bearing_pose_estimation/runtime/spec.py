"""Each agent's :class:`.agent.AgentSpec` from a fleet's description: the method's edges
(:func:`estimators.base.edge_table`, the batch simulator's order), roles and initial estimates."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ..estimators.base import Estimator, edge_table
from .agent import AgentSpec, PeerSpec

Array = NDArray[np.float64]


def fleet_specs(method: type[Estimator], names: Sequence[str], tail: NDArray[np.intp],
                head: NDArray[np.intp], k: Array, R0: Array, p0: Array,
                leaders: Sequence[int] = (), anchor: int | None = None,
                ranged: Sequence[int] = (), pinned: bool = False,
                rate_tau: float | None = None) -> list[AgentSpec]:
    """The specs of the agents ``names`` (index i has the wire id i + 1) whose sensing edges
    are ``tail → head`` with gains ``k``, initial estimates ``R0`` ``(N, 3, 3)``, ``p0``
    ``(N, 3)``, the ``leaders``, the ``anchor`` and the agents it ranges (indices); ``pinned``:
    the anchor holds ``(I, 0)``; ``rate_tau``: bearing rates from the bearings."""
    n = len(names)
    table = edge_table(method, n, tail, head, k, anchor, ranged)
    known = frozenset(range(1, n + 1))
    specs = []
    for i, name in enumerate(names):
        rows = table.of(i)
        peers = tuple(PeerSpec(names[j], j + 1, float(table.k[e]),
                               {f: bool(v[e]) for f, v in table.flags.items()})
                      for e, j in zip(rows.tolist(), table.other[rows].tolist()))
        specs.append(AgentSpec(name=name, agent_id=i + 1, peers=peers, R0=R0[i], p0=p0[i],
                               leader=i in leaders,
                               anchor=None if anchor is None else (names[anchor], anchor + 1),
                               pinned=pinned and i == anchor, known_ids=known,
                               rate_tau=rate_tau))
    return specs
