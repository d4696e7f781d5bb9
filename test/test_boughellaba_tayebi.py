"""The cascaded observer: error dynamics, Lyapunov decrease, equilibria, and convergence of the
discrete scheme to an independent continuous-time solution of (3) and (23)."""
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.estimators.base import Edges
from bearing_pose_estimation.estimators.boughellaba_tayebi import (CascadeGains, cascade_step,
                                                                   innovation)
from bearing_pose_estimation.scenario import load_scenario, parse_scenario
from bearing_pose_estimation.sim.batch import BatchSimulator

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'
RNG = np.random.default_rng(11)


def _paper_sim(**kwargs) -> BatchSimulator:
    return BatchSimulator(load_scenario(PAPER), **kwargs)


def _R_tilde(sim: BatchSimulator) -> np.ndarray:
    return sim.R @ np.swapaxes(sim.R_hat, -1, -2)


def _measure(sim: BatchSimulator) -> tuple[np.ndarray, np.ndarray]:
    """Own bearings b^i_ij and the neighbours' d_ij = R̂_j b^j_ij the next step uses."""
    inputs = sim.inputs()
    return inputs.edge['bearings'], -inputs.edge['world_bearing']


def _b_world(sim: BatchSimulator) -> np.ndarray:
    """The world bearings b_ij of every sensing edge."""
    return sim.truth.world_bearings(sim.edges.agent, sim.edge_nbr)


def test_discrete_attitude_error_is_lie_euler_of_error_dynamics():
    """R̃⁺ = R̃ exp(h k_R [σ]x): the discrete form of dR̃/dt = k_R R̃ [σ]x, whatever ω is."""
    sim = _paper_sim()
    for _ in range(37):  # somewhere in the transient
        sim.step()
    R_tilde = _R_tilde(sim)
    b_own, d_world = _measure(sim)
    sigma, _ = innovation(sim.R_hat, sim.edges, b_own, d_world)
    sim.step()
    expected = R_tilde @ so3.exp(sim.h * sim.scenario.gains.k_R * sigma)
    np.testing.assert_allclose(_R_tilde(sim), expected, atol=1e-13)
    # And the continuous-time identity: (R̃(t+h) - R̃(t))/h → k_R R̃ [σ]x.
    rate = (_R_tilde(sim) - R_tilde) / sim.h
    np.testing.assert_allclose(rate, sim.scenario.gains.k_R * R_tilde @ so3.hat(sigma),
                               atol=sim.h * 2.0)


def test_error_trajectory_does_not_depend_on_the_angular_velocity():
    """The gyro cancels out of the error dynamics: spinning agents and still agents give the
    same errors (to rounding), which is why the true pose is an exact fixed point."""
    spinning = _paper_sim()
    still = BatchSimulator(load_scenario(PAPER))
    still.truth.omega.constant[:] = 0.0
    still.truth.omega.amplitude[:] = 0.0
    for _ in range(500):
        spinning.step()
        still.step()
    np.testing.assert_allclose(_R_tilde(spinning), _R_tilde(still), atol=1e-11)
    np.testing.assert_allclose(spinning.errors()[1], still.errors()[1], atol=1e-11)
    assert np.abs(spinning.R - still.R).max() > 0.5  # they really did rotate differently


def test_true_pose_is_a_fixed_point():
    sim = _paper_sim()
    sim.R_hat, sim.p_hat = sim.R.copy(), sim.p.copy()
    for _ in range(1000):
        sim.step()
    att, pos, _, _ = sim.errors()
    assert att.max() < 1e-12 and pos.max() < 1e-12


def test_position_equilibrium_is_the_true_position():
    """With exact attitudes, p̂ converges to p (Proposition 2: GES), not to anything else."""
    sim = _paper_sim()
    sim.R_hat = sim.R.copy()
    sim.p_hat = sim.p + RNG.normal(scale=3.0, size=sim.p.shape)
    sim.p_hat[sim.leader_idx] = sim.p[sim.leader_idx]
    sim.run(80.0, record_every=80.0)
    assert sim.errors()[1].max() < 1e-6


def _M(sim: BatchSimulator, agent: str) -> np.ndarray:
    i = sim.scenario.index[agent]
    sel = sim.edges.agent == i
    b = _b_world(sim)[sel]
    return np.einsum('e,ea,eb->ab', sim.edges.k[sel], b, b)


def test_lyapunov_function_of_lemma_1_decreases():
    """V = tr(M_3 (I - R̃_3))/4 is non-increasing for agent 3, whose neighbours are leaders
    (the unforced attitude error dynamics), from a large initial error."""
    sim = _paper_sim()
    i = sim.scenario.index['agent_3']
    sim.R_hat[i] = sim.R[i] @ so3.axis_angle([0.3, -1.0, 0.5], 2.8).T
    M = _M(sim, 'agent_3')
    V = []
    for _ in range(3000):
        V.append(0.25 * np.trace(M @ (np.eye(3) - _R_tilde(sim)[i])))
        sim.step()
    V = np.array(V)
    assert V[0] > 0.1
    assert np.all(np.diff(V) <= 1e-15)
    assert V[-1] < 1e-6 * V[0]


def test_undesired_equilibria_are_pi_rotations_about_eigenvectors_of_M():
    """σ = 0 at R̃ = rot(π, v) for each eigenvector v of M_i: the measure-zero set that makes
    the result 'almost' global."""
    sim = _paper_sim()
    i = sim.scenario.index['agent_3']
    _, vecs = np.linalg.eigh(_M(sim, 'agent_3'))
    for v in vecs.T:
        sim.R_hat[i] = (so3.axis_angle(v, np.pi)).T @ sim.R[i]  # R̃ = R R̂ᵀ = rot(π, v)
        sigma, _ = innovation(sim.R_hat, sim.edges, *_measure(sim))
        assert np.linalg.norm(sigma[i]) < 1e-12
    sim.R_hat[i] = so3.axis_angle([1, 1, 0], 1.0).T @ sim.R[i]
    assert np.linalg.norm(innovation(sim.R_hat, sim.edges, *_measure(sim))[0][i]) > 0.1


def test_per_agent_calls_equal_the_batch_step():
    """The node calls cascade_step for its one agent; that must equal the batch row."""
    sim = _paper_sim()
    for _ in range(20):
        sim.step()
    b_own, d_world = _measure(sim)
    delta_R = so3.exp(RNG.normal(scale=0.01, size=(sim.n, 3)))
    gains = CascadeGains(k_R=1.3, k_p=0.7)
    batch = cascade_step(sim.R_hat, sim.p_hat, delta_R, sim.h, sim.edges, b_own, d_world,
                         sim.p_hat[sim.edge_nbr], gains)
    for i in sim.follower_idx:
        sel = sim.edges.agent == i
        one = cascade_step(sim.R_hat[i:i + 1], sim.p_hat[i:i + 1], delta_R[i:i + 1], sim.h,
                           Edges(agent=np.zeros(sel.sum(), int), k=sim.edges.k[sel], n_agents=1),
                           b_own[sel], d_world[sel], sim.p_hat[sim.edge_nbr[sel]], gains)
        np.testing.assert_allclose(one[0][0], batch[0][i], atol=1e-15)
        np.testing.assert_allclose(one[1][0], batch[1][i], atol=1e-14)


# ------------------------------------------------------------- continuous-time reference
def _paper_omega(t: float) -> np.ndarray:
    """ω_1..ω_8 typed from the paper (Section V), independently of the YAML and motion.py."""
    c, s = np.cos, np.sin
    return np.array([[1, -2, 1], [-c(3 * t), 1, s(2 * t)], [-c(t), 1, s(2 * t)],
                     [-c(2 * t), 1, s(5 * t)], [-c(5 * t), 1, s(9 * t)],
                     [-c(2 * t), s(9 * t), 1], [-c(4 * t), 1, 2], [-2, 1, s(9 * t)]], float)


def _reference(T: float, R_hat0: np.ndarray, p_hat0: np.ndarray,
               motion=None) -> tuple[np.ndarray, ...]:
    """Solve (1), (3) and (23) as written in estimators/boughellaba_tayebi.py with a
    tight-tolerance RK solver, agent by agent in plain loops (no code shared with the
    package). ``motion``: ``(p(t), v(t))``, the true positions and world velocities
    ``(8, 3)`` of a moving fleet, whose body velocity ``R_iᵀ v_i`` is fed forward
    (``dp̂_i/dt += R̂_i R_iᵀ v_i``); None: the paper's static cube."""
    p0 = np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0],
                   [0, 0, 2], [2, 0, 2], [2, 2, 2], [0, 2, 2]], float)
    N = {2: [0, 1], 3: [1, 2], 4: [0, 3], 5: [1, 3, 4], 6: [2, 3, 5], 7: [0, 6]}
    k_R = k_p = 1.0

    def hat(x):
        return np.array([[0, -x[2], x[1]], [x[2], 0, -x[0]], [-x[1], x[0], 0]])

    def rhs(t, x):
        p, v = (motion[0](t), motion[1](t)) if motion else (p0, np.zeros((8, 3)))
        R = x[:72].reshape(8, 3, 3)
        Rh = x[72:144].reshape(8, 3, 3).copy()
        ph = x[144:].reshape(8, 3).copy()
        Rh[:2], ph[:2] = R[:2], p[:2]  # leaders know their pose
        w = _paper_omega(t)
        dR, dRh, dph = np.zeros((8, 3, 3)), np.zeros((8, 3, 3)), np.zeros((8, 3))
        for i in range(8):
            dR[i] = R[i] @ hat(w[i])
        for i, nbrs in N.items():
            sigma, pull = np.zeros(3), np.zeros(3)
            for j in nbrs:
                b = (p[j] - p[i]) / np.linalg.norm(p[j] - p[i])
                b_i = R[i].T @ b           # b^i_ij, measured by i
                b_j = R[j].T @ (-b)        # b^j_ji, measured by j
                sigma += np.cross(Rh[j] @ -b_j, Rh[i] @ b_i)
                P = np.eye(3) - np.outer(b_i, b_i)
                pull += Rh[i] @ P @ Rh[i].T @ (ph[i] - ph[j])
            dRh[i] = Rh[i] @ hat(w[i] - k_R * Rh[i].T @ sigma)
            dph[i] = -k_R * hat(sigma) @ ph[i] - k_p * pull + Rh[i] @ R[i].T @ v[i]
        return np.concatenate([dR.ravel(), dRh.ravel(), dph.ravel()])

    x0 = np.concatenate([np.tile(np.eye(3), (8, 1, 1)).ravel(), R_hat0.ravel(), p_hat0.ravel()])
    sol = solve_ivp(rhs, (0.0, T), x0, method='DOP853', rtol=1e-12, atol=1e-12)
    x = sol.y[:, -1]
    return x[72:144].reshape(8, 3, 3), x[144:].reshape(8, 3)


def test_discrete_scheme_converges_to_continuous_solution_at_first_order():
    T = 2.0
    first = _paper_sim()
    R_ref, p_ref = _reference(T, first.R_hat, first.p_hat)
    errs = []
    for h in (0.02, 0.01, 0.005):
        sim = _paper_sim(step=h)
        sim.run(T, record_every=T)
        assert sim.t == pytest.approx(T)
        f = sim.follower_idx
        errs.append(max(np.abs(sim.R_hat[f] - R_ref[f]).max(), np.abs(sim.p_hat[f] - p_ref[f]).max()))
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert errs[-1] < 0.05
    assert np.all((orders > 0.85) & (orders < 1.15)), (errs, orders)


def test_scenario_file_omega_matches_the_paper():
    sim = _paper_sim()
    for t in (0.0, 0.37, 1.9, 12.3):
        np.testing.assert_allclose(sim.truth.omega(t), _paper_omega(t), atol=1e-14)


def test_two_agent_innovation_is_zero_when_estimates_are_exact():
    data = {'name': 'tiny', 'leaders': ['a', 'b'], 'agents': [
        {'name': 'a', 'position': [0, 0, 0]}, {'name': 'b', 'position': [1, 0, 0]},
        {'name': 'c', 'position': [0, 1, 0], 'neighbours': ['a', 'b'],
         'initial_estimate': {'position': [0, 1, 0], 'attitude': 'identity'}}]}
    sim = BatchSimulator(parse_scenario(data))
    sigma, y = innovation(sim.R_hat, sim.edges, *_measure(sim))
    assert np.abs(sigma).max() < 1e-15
    np.testing.assert_allclose(y, _b_world(sim), atol=1e-15)
