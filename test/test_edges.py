"""Sums over each agent's edges (``Edges.sum_by_agent``): every way of computing them gives the
same numbers, bit for bit, as adding the edges one after the other, so a step's result does not
depend on how many agents share it (a node's batch, the batch simulator's fleet)."""
from __future__ import annotations

import numpy as np
import pytest

from bearing_pose_estimation.estimators import base
from bearing_pose_estimation.estimators.base import Edges


def in_edge_order(agent: np.ndarray, values: np.ndarray, n_agents: int) -> np.ndarray:
    out = np.zeros((n_agents,) + values.shape[1:])
    for e in range(len(agent)):
        out[agent[e]] = out[agent[e]] + values[e]
    return out


@pytest.mark.parametrize('n_edges', [40, base.SPARSE_SUM_EDGES + 300])
@pytest.mark.parametrize('width', [(3,), (36,)])
def test_sums_by_agent_are_the_edges_added_in_order(n_edges, width):
    rng = np.random.default_rng(n_edges)
    n_agents = n_edges // 4
    agent = np.sort(rng.integers(1, n_agents, n_edges))   # agent 0 has no edge
    scale = 10.0 ** rng.integers(-8, 8, n_edges)
    values = rng.standard_normal((n_edges,) + width) * scale[:, None]
    edges = Edges(agent=agent, k=np.ones(n_edges), n_agents=n_agents)
    expected = in_edge_order(agent, values, n_agents)
    for _ in range(2):   # the sparse matrix is built at the first sum, then reused
        np.testing.assert_array_equal(edges.sum_by_agent(values), expected)
    assert (edges._incidence is not None) == (n_edges > base.SPARSE_SUM_EDGES)
    assert not expected[0].any()
    one = Edges(agent=np.zeros(7, dtype=np.intp), k=np.ones(7), n_agents=1)
    np.testing.assert_array_equal(one.sum_by_agent(values[:7]),
                                  in_edge_order(np.zeros(7, dtype=np.intp), values[:7], 1))


def test_complex_values_are_summed_too():
    """A method may sum complex per-edge terms (yaw phasors): no cast to real on the way."""
    edges = Edges(agent=np.array([0, 0, 2]), k=np.ones(3), n_agents=3)
    np.testing.assert_array_equal(edges.sum_by_agent(np.array([1j, 2.0, 3.0 - 1j])),
                                  [2.0 + 1j, 0.0, 3.0 - 1j])
