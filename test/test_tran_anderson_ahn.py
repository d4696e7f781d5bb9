"""Tran, Anderson & Ahn's observer (estimators/tran_anderson_ahn.py): fixed point, convergence, the position equilibrium
formula, the two-neighbour extra direction, and the node's logic (AgentEstimator) matching the
batch simulator."""
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.sim.netsim import run_network
from bearing_pose_estimation.estimators.base import Edges
from bearing_pose_estimation.scenario import check_scenario
from bearing_pose_estimation.scenario import ScenarioError, load_scenario, parse_scenario
from bearing_pose_estimation.sim.batch import BatchSimulator
from bearing_pose_estimation.estimators.tran_anderson_ahn import TranGains
from bearing_pose_estimation.estimators.tran_anderson_ahn import TwoNeighbourPairs, tran_step

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'


def _paper_tran(**gains) -> dict:
    data = yaml.safe_load(PAPER.read_text())
    data['method'] = 'tran_anderson_ahn'
    data['gains'] = {'k_omega': 2.0, 'k_p': 1.0, 'k_c': 1.0, **gains}
    return data


def test_converges_on_the_paper_scenario():
    """From the paper's initial errors (1.26 rad, 3.81 m mean) to below 1e-7 rad and 1e-4 m
    in 60 s (measured: 3.8e-9 rad, 4.0e-6 m), decreasing all the way."""
    rec = BatchSimulator(parse_scenario(_paper_tran())).run(60.0, record_every=5.0)
    att, pos = rec.att_err.mean(axis=1), rec.pos_err.mean(axis=1)
    assert att[0] > 1.0 and pos[0] > 3.0
    assert att[-1] < 1e-7 and pos[-1] < 1e-4
    assert np.all(np.diff(att[2:]) < 0) and np.all(np.diff(pos[2:]) < 0)


def test_the_truth_is_a_fixed_point_under_rotation():
    sim = BatchSimulator(parse_scenario(_paper_tran()))
    sim.R_hat, sim.p_hat = sim.R.copy(), sim.p.copy()
    for _ in range(500):
        sim.step()
    att, pos, *_ = sim.errors()
    assert att.max() < 1e-12 and pos.max() < 1e-12
    assert np.abs(sim.x.Omega_tilde).max() < 1e-12


def test_position_equilibrium_is_the_projector_average():
    """With exact attitudes, a follower's position settles at
    p_i = (Σ_j P_b_ij)⁻¹ Σ_j P_b_ij p̂_j, whatever its neighbours' (wrong) estimates."""
    rng = np.random.default_rng(5)
    p = rng.normal(size=(4, 3)) * 2.0           # agent 0 follows agents 1, 2, 3
    nbr = np.array([1, 2, 3])
    b = (p[nbr] - p[0]) / np.linalg.norm(p[nbr] - p[0], axis=1, keepdims=True)
    R = so3.exp(rng.normal(size=(4, 3)))
    edges = Edges(agent=np.zeros(3, dtype=np.intp), k=np.ones(3), n_agents=4)
    pairs = TwoNeighbourPairs.of(edges)
    b_body = np.einsum('ba,eb->ea', R[0], b)     # R_0ᵀ b_0j
    d_world = b.copy()                           # exact neighbour attitudes
    p_hat_nbr = p[nbr] + rng.normal(size=(3, 3)) * 0.3
    p_hat = np.vstack([rng.normal(size=3) * 5.0, p_hat_nbr])
    R_hat, Om = R.copy(), np.zeros((4, 3))
    for _ in range(3000):
        res = tran_step(R_hat, Om, p_hat, np.broadcast_to(np.eye(3), (4, 3, 3)), 0.01, edges,
                        pairs, b_body, d_world, p_hat_nbr, TranGains())
        p_hat = np.vstack([res[2][:1], p_hat_nbr])
    P = so3.projector(b)
    expected = np.linalg.solve(P.sum(axis=0), np.einsum('eab,eb->a', P, p_hat_nbr))
    np.testing.assert_allclose(p_hat[0], expected, atol=1e-9)
    assert np.linalg.norm(expected - p[0]) > 0.05  # the check is not the trivial p_i = p_i


def test_two_neighbour_followers_get_the_extra_direction():
    """Agents with exactly two neighbours are paired; the extra term is zero at the truth and
    changes the transient (both gains converge)."""
    scenario = parse_scenario(_paper_tran())
    sim = BatchSimulator(scenario)
    two = {a.name for a in scenario.agents if len(a.neighbours) == 2}
    assert two and {scenario.agents[i].name for i in sim.estimator.pairs(sim.edges).agent} == two
    finals = []
    for k_c in (0.5, 3.0):
        rec = BatchSimulator(parse_scenario(_paper_tran(k_c=k_c))).run(30.0, record_every=10.0)
        finals.append(rec.att_err.mean(axis=1)[-1])
        assert finals[-1] < 1e-3
    assert abs(finals[0] - finals[1]) > 0.05 * min(finals)


def test_gains_are_checked_per_method():
    data = _paper_tran(k_R=1.0)
    with pytest.raises(ScenarioError, match=r'gains\.k_R: unknown key.*k_omega'):
        parse_scenario(data)
    data = _paper_tran(k_omega=-1.0)
    with pytest.raises(ScenarioError, match=r'gains\.k_omega'):
        parse_scenario(data)


def test_the_node_logic_matches_the_batch_simulator():
    """The estimator node's logic (AgentEstimator fed like the simulator node feeds it, no DDS:
    netsim) runs the same observer as the batch simulator: mean errors within 2 % at 20 s."""
    scenario = parse_scenario(_paper_tran())
    net = run_network(scenario, 20.0, record_every=5.0)
    batch = BatchSimulator(scenario).run(20.0, record_every=5.0)
    for a, b in ((net.att_err, batch.att_err), (net.pos_err, batch.pos_err)):
        assert abs(a[-1].mean() / b[-1].mean() - 1.0) < 0.02
    assert net.att_err[-1].mean() < 1e-2 * net.att_err[0].mean()


def test_the_node_refuses_k_R_for_this_method(tmp_path, context):
    """A k_R override on a Tran scenario is a configuration error naming the fix."""
    from rclpy.parameter import Parameter

    from bearing_pose_estimation.ros.estimator_node import EstimatorNode

    path = tmp_path / 'tran.yaml'
    path.write_text(yaml.safe_dump(_paper_tran()))
    with pytest.raises(ScenarioError, match='k_R is a boughellaba_tayebi gain.*Fix'):
        EstimatorNode(namespace='/agent_3', context=context, parameter_overrides=[
            Parameter('scenario_file', value=str(path)), Parameter('k_R', value=2.0)])
    node = EstimatorNode(namespace='/agent_3', context=context, parameter_overrides=[
        Parameter('scenario_file', value=str(path)), Parameter('k_p', value=1.5)])
    assert node.gains == TranGains(k_omega=2.0, k_p=1.5, k_c=1.0)
    node.destroy_node()


CUBE = PAPER.parent / 'tran_cube.yaml'


def test_its_checker_uses_K_i_with_the_extra_direction():
    """For this method the spectra are Tran et al.'s K_i: with two neighbours k_c c cᵀ fills
    the third direction, so the paper's agent_8 (bearings to agent_1 and agent_7 orthogonal)
    has K_i = I, a repeated spectrum; a coplanar three-neighbour follower is singular."""
    report = check_scenario(parse_scenario(_paper_tran()))
    np.testing.assert_allclose(report.spectra['agent_8'], [1, 1, 1], atol=1e-12)
    assert [w.agent for w in report.warnings] == ['agent_8']
    assert "Tran et al.'s Lemma 2" in report.warnings[0].problem
    report = check_scenario(parse_scenario(_paper_tran(k_c=0.5)))
    np.testing.assert_allclose(report.spectra['agent_8'], [0.5, 1, 1], atol=1e-12)
    data = _paper_tran()
    # agent_6 moved into the z = 0 plane of its three neighbours: coplanar bearings.
    data['agents'][5]['position'] = [1, 2, 0]
    data['agents'][5]['neighbours'] = ['agent_1', 'agent_3', 'agent_4']
    report = check_scenario(parse_scenario(data))
    assert report.ok
    singular = [w for w in report.warnings if w.agent == 'agent_6']
    assert singular and 'coplanar' in singular[0].problem
    assert report.spectra['agent_6'][0] < 1e-12


def test_the_cube_scenario_is_valid_and_converges():
    """config/tran_cube.yaml (the Tran paper's Section 5, our graph): no check warnings; both
    methods converge from random initial estimates; agents 3, 4, 5 really rotate."""
    cube = load_scenario(CUBE)
    report = check_scenario(cube)
    assert report.ok and not report.warnings, report.format()
    assert sorted(len(a.neighbours) for a in cube.followers) == [2, 2, 2, 3, 3, 3]
    sides = {round(float(np.linalg.norm(a.position - b.position)), 9)
             for a in cube.agents for b in cube.agents if a is not b}
    assert sides == {5.0, round(5 * np.sqrt(2), 9), round(5 * np.sqrt(3), 9)}
    for method in ('tran_anderson_ahn', 'boughellaba_tayebi'):
        sim = BatchSimulator(cube.with_method(method))
        R0 = sim.R.copy()
        rec = sim.run(60.0, record_every=10.0)
        assert rec.att_err[0].mean() > 0.5 and rec.pos_err[0].mean() > 2.0
        assert rec.att_err[-1].max() < 1e-6 and rec.pos_err[-1].max() < 1e-5, method
    turned = np.degrees([so3.angle(R0[i].T @ sim.R[i]) for i in range(8)])
    np.testing.assert_allclose(turned[2:5], np.degrees(0.15 * 60.0) % 360, atol=1e-6)
    np.testing.assert_allclose(turned[[0, 1, 5, 6, 7]], 0.0, atol=1e-9)
