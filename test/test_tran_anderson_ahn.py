"""Tran, Anderson & Ahn's observer (estimators/tran_anderson_ahn.py): fixed point, convergence, the
position equilibrium formula, the two-neighbour extra direction, and the node's logic
(AgentEstimator) matching the batch simulator."""
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


@pytest.mark.dds
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
    assert node.s.gains == TranGains(k_omega=2.0, k_p=1.5, k_c=1.0)
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


# ------------------------------------------------------------- continuous-time reference
def _reference(T: float, R_hat0: np.ndarray, p_hat0: np.ndarray, k_omega: float, k_p: float,
               k_c: float, motion=None) -> tuple[np.ndarray, ...]:
    """Tran et al.'s observer in continuous time, as the module docstring writes it, solved
    with a tight-tolerance RK solver, agent by agent in plain loops (no code shared with the
    package): ``dR̂_i/dt = R̂_i [ω_i - Ω̃_i]x``, ``dΩ̃_i/dt = -k_ω Ω̃_i + Σ_j (R̂_iᵀ d_ij) × b^i_ij
    (+ k_c (R̂_iᵀ c) × c^i)``, ``dp̂_i/dt = -k_p Σ_j R̂_i P_{b^i_ij} R̂_iᵀ (p̂_i - p̂_j)``.
    ``motion``: ``(p(t), v(t))``, the true positions and world velocities ``(8, 3)`` of a
    moving fleet, whose body velocity ``R_iᵀ v_i`` is fed forward (``dp̂_i/dt += R̂_i R_iᵀ
    v_i``); None: the paper's static cube."""
    from scipy.integrate import solve_ivp

    from test_boughellaba_tayebi import _paper_omega

    p0 = np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0],
                   [0, 0, 2], [2, 0, 2], [2, 2, 2], [0, 2, 2]], float)
    N = {2: [0, 1], 3: [1, 2], 4: [0, 3], 5: [1, 3, 4], 6: [2, 3, 5], 7: [0, 6]}

    def hat(x):
        return np.array([[0, -x[2], x[1]], [x[2], 0, -x[0]], [-x[1], x[0], 0]])

    def unit(v):
        return v / np.linalg.norm(v)

    def rhs(t, x):
        p, v = (motion[0](t), motion[1](t)) if motion else (p0, np.zeros((8, 3)))
        R = x[:72].reshape(8, 3, 3)
        Rh = x[72:144].reshape(8, 3, 3).copy()
        Om = x[144:168].reshape(8, 3).copy()
        ph = x[168:].reshape(8, 3).copy()
        Rh[:2], Om[:2], ph[:2] = R[:2], 0.0, p[:2]  # leaders know their pose
        w = _paper_omega(t)
        dR, dRh, dOm, dph = (np.zeros((8, 3, 3)), np.zeros((8, 3, 3)), np.zeros((8, 3)),
                             np.zeros((8, 3)))
        for i in range(8):
            dR[i] = R[i] @ hat(w[i])
        for i, nbrs in N.items():
            torque, pull, b_i, d = np.zeros(3), np.zeros(3), [], []
            for j in nbrs:
                b = (p[j] - p[i]) / np.linalg.norm(p[j] - p[i])
                b_i.append(R[i].T @ b)               # b^i_ij, measured by i
                d.append(-(Rh[j] @ (R[j].T @ -b)))   # d_ij = -R̂_j b^j_ji, b^j_ji measured by j
                torque += np.cross(Rh[i].T @ d[-1], b_i[-1])
                P = np.eye(3) - np.outer(b_i[-1], b_i[-1])
                pull += Rh[i] @ P @ Rh[i].T @ (ph[i] - ph[j])
            if len(nbrs) == 2:
                c_i, c = unit(np.cross(b_i[0], b_i[1])), unit(np.cross(d[0], d[1]))
                torque += k_c * np.cross(Rh[i].T @ c, c_i)
            dRh[i] = Rh[i] @ hat(w[i] - Om[i])
            dOm[i] = -k_omega * Om[i] + torque
            dph[i] = -k_p * pull + Rh[i] @ R[i].T @ v[i]
        return np.concatenate([dR.ravel(), dRh.ravel(), dOm.ravel(), dph.ravel()])

    x0 = np.concatenate([np.tile(np.eye(3), (8, 1, 1)).ravel(), R_hat0.ravel(),
                         np.zeros(24), p_hat0.ravel()])
    sol = solve_ivp(rhs, (0.0, T), x0, method='DOP853', rtol=1e-12, atol=1e-12)
    x = sol.y[:, -1]
    return x[72:144].reshape(8, 3, 3), x[144:168].reshape(8, 3), x[168:].reshape(8, 3)


def test_discrete_scheme_converges_to_continuous_solution_at_first_order():
    """The discrete step against an independent solution of the continuous equations on the
    paper scenario: the error halves with the step (first order), and is small at h = 5 ms."""
    T = 2.0
    scenario = parse_scenario(_paper_tran(k_omega=1.5, k_c=0.7))
    first = BatchSimulator(scenario)
    R_ref, Om_ref, p_ref = _reference(T, first.R_hat, first.p_hat, 1.5, 1.0, 0.7)
    errs = []
    for h in (0.02, 0.01, 0.005):
        sim = BatchSimulator(scenario, step=h)
        sim.run(T, record_every=T)
        assert sim.t == pytest.approx(T)
        f = sim.follower_idx
        errs.append(max(np.abs(sim.R_hat[f] - R_ref[f]).max(),
                        np.abs(sim.x.Omega_tilde[f] - Om_ref[f]).max(),
                        np.abs(sim.p_hat[f] - p_ref[f]).max()))
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert errs[-1] < 0.05
    assert np.all((orders > 0.85) & (orders < 1.15)), (errs, orders)


def test_the_node_diagnostics_report_the_checks_K_i():
    """One function (Estimator.conditioning) gives `check`'s spectra and the node's
    /diagnostics: for a two-neighbour follower K_i includes k_c c cᵀ (the node's diagnostics
    once left it out), from the body-frame bearings the agent measures."""
    from bearing_pose_estimation.estimators.base import Sensor
    from bearing_pose_estimation.scenario.runtimes import agent_specs, runtime_for
    from bearing_pose_estimation.sim.world import World

    scenario = load_scenario(CUBE)
    report = check_scenario(scenario)
    world = World(scenario)
    specs = agent_specs(scenario)
    two = [a.name for a in scenario.followers if len(a.neighbours) == 2]
    assert two
    for a in scenario.followers:
        est = runtime_for(scenario, specs[scenario.index[a.name]])
        j, b = world.bearings(scenario.index[a.name])
        assert est.add_points(Sensor.BEARINGS, 0.0, j + 1, b) == []
        np.testing.assert_allclose(est.conditioning(), report.spectra[a.name], atol=1e-12)
    agent = scenario.agent(two[0])  # without the k_c term the spectrum differs
    b = [(scenario.agent(nb.name).position - agent.position) for nb in agent.neighbours]
    M = sum(nb.k * np.outer(v, v) / (v @ v) for v, nb in zip(b, agent.neighbours))
    assert not np.allclose(np.linalg.eigvalsh(M), report.spectra[two[0]], atol=1e-3)
