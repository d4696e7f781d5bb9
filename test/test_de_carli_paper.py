"""De Carli et al. (2024) on the paper's scenario, config/de_carli_8_quadrotors.yaml (the notes'
explicit JSON, copied to ``data/de-carli-2024-scenario.json``). The registered method, multirate
as the notes prescribe (relative yaw 200 Hz, yaw consensus 100 Hz, positions 50 Hz), run by the
batch simulator:

- against an independent tight-tolerance solution of the continuous equations (DOP853, written
  here from the notes in plain loops), in both motion modes: the times to 1e-3 rad (yaw) and
  1e-2 m (position) agree within 10 %, and the cascade order holds;
- tick for tick against the fleet-wide reference implementation (``de_carli_reference.py``);
- with a hovering robot: its unexcited pairs are warned about, left out and reported, and the
  rest converges.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline

from de_carli_reference import (ExcitationMonitor, Pairs, dead_reckoning, position_correction,
                                relative_yaw_step, rot_z, yaw_consensus_step)

from bearing_pose_estimation.estimators.de_carli import unit
from bearing_pose_estimation.scenario import check_scenario, parse_scenario
from bearing_pose_estimation.scenario.parse import read_scenario_data
from bearing_pose_estimation.sim.batch import BatchSimulator

# A copy of the notes' file (every number of the paper's Section IV made explicit).
SCENARIO = Path(__file__).resolve().parent / 'data' / 'de-carli-2024-scenario.json'
CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'de_carli_8_quadrotors.yaml'


def config(mode: str, **gains: float) -> dict:
    """The config file as loaded from YAML, in motion ``mode``, with ``gains`` changed."""
    data = read_scenario_data(CONFIG)
    data['formation_control']['mode'] = mode
    data['gains'].update(gains)
    return data


def batch(data: dict, T: float, every: float = 0.1):
    """The method in the batch simulator: records ``(t, yaw error, position error, mean
    relative-yaw error, mean formation error)`` and the recording."""
    rec = BatchSimulator(parse_scenario(data)).run(T, record_every=every)
    att, pos = rec.mean_errors()
    rel = np.mean([v for k, v in rec.extra.items() if k.startswith('rel_yaw_err')], axis=0)
    form = np.mean([v for k, v in rec.extra.items() if k.startswith('formation_err')], axis=0)
    return np.stack([rec.t, att, pos, rel, form], axis=1), rec


class Paper:
    """The scenario's numbers, its yaw splines and the exogenous formation controller."""

    def __init__(self, hovering: tuple[int, ...] = ()) -> None:
        d = json.loads(SCENARIO.read_text())
        self.hovering = list(hovering)   # robots that never translate (no excitation)
        self.d = d
        self.n = d['n_robots']
        edges = np.array(d['sensing_edges'], dtype=np.intp)
        self.tail, self.head = edges[:, 0], edges[:, 1]
        self.pairs = Pairs.of(self.tail, self.head)
        assert [[int(a), int(b)] for a, b in zip(self.pairs.a, self.pairs.b)] == \
            d['communication_pairs']
        g = d['gains']
        self.k_pe, self.k_psi, self.k_z, self.k_p = g['k_pe'], g['k_psi'], g['k_z'], g['k_p']
        y = d['yaw_trajectory']
        self.yaw = CubicSpline(y['knots_s'], np.array(y['knot_values_rad']).T,
                               bc_type='clamped')
        c = d['controller']
        self.k_c, self.nu_max = c['k_c'], c['nu_max_mps']
        self.p_star = np.array(c['p_star_m'])
        self.p0 = np.array(d['initial_state']['p_m'])
        ie = d['initial_estimates']
        self.p_hat0 = np.array(ie['p_hat_m'])
        self.z_hat0 = np.array(ie['z_hat']) @ np.array([1.0, 1j])
        self.z_pair0 = np.array(ie['z_psi_hat']) @ np.array([1.0, 1j])
        rel = np.array(ie['p_rel_hat_m'])
        self.P0, self.Pz0 = rel[:, 0] + 1j * rel[:, 1], rel[:, 2]

    def world_velocity(self, p: np.ndarray, psi: np.ndarray | None = None,
                       psi_hat: np.ndarray | None = None) -> np.ndarray:
        """Exogenous mode: ``sat(k_c Σ_k E_ik ((p*_a − p*_b) − (p_a − p_b)))``; given the true
        and estimated yaws, the paper's mode: ``R_i sat(k_c R̂_iᵀ Σ_k E_ik (p*_a − p*_b + R̂_a
        ᵃp_ab))``."""
        if psi_hat is not None:
            assert psi is not None
            meas = np.einsum('kba,kb->ka', rot_z(psi[self.tail]), p[self.head] - p[self.tail])
            r = (self.p_star[self.tail] - self.p_star[self.head]
                 + np.einsum('kab,kb->ka', rot_z(psi_hat[self.tail]), meas))
            mu = np.zeros_like(p)
            np.add.at(mu, self.tail, r)
            np.add.at(mu, self.head, -r)
            u = self.k_c * np.einsum('nba,nb->na', rot_z(psi_hat), mu)
            u = u * np.minimum(1.0, self.nu_max / np.maximum(
                np.linalg.norm(u, axis=1, keepdims=True), 1e-300))
            u[self.hovering] = 0.0
            return np.einsum('nab,nb->na', rot_z(psi), u)
        r = (self.p_star[self.tail] - self.p_star[self.head]) - (p[self.tail] - p[self.head])
        mu = np.zeros_like(p)
        np.add.at(mu, self.tail, r)
        np.add.at(mu, self.head, -r)
        u = self.k_c * mu
        norm = np.linalg.norm(u, axis=1, keepdims=True)
        u = u * np.minimum(1.0, self.nu_max / np.maximum(norm, 1e-300))
        u[self.hovering] = 0.0
        return u

    def measure(self, psi: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = np.einsum('kba,kb->ka', rot_z(psi[self.tail]), p[self.head] - p[self.tail])
        return d[:, 0] + 1j * d[:, 1], d[:, 2]


def errors(paper: Paper, psi, p, z_hat, p_hat) -> tuple[float, float]:
    """Mean yaw and position errors after the notes' exact alignment (§6): one common yaw a*
    (circular mean) for both, then the mean translation."""
    a = np.angle(np.sum(unit(z_hat) * np.exp(-1j * psi)))
    e_psi = np.abs(np.angle(np.exp(1j * (np.angle(z_hat) - psi - a))))
    aligned = p @ rot_z(np.array(a)).T
    t = np.mean(p_hat - aligned, axis=0)
    return float(e_psi.mean()), float(np.linalg.norm(p_hat - aligned - t, axis=1).mean())


def rel_yaw_error(paper: Paper, psi, z_pair) -> float:
    return float(np.abs(z_pair - np.exp(1j * (psi[paper.pairs.b] - psi[paper.pairs.a]))).mean())


def discrete(paper: Paper, T: float, h: float = 0.005, every: float = 0.1,
             monitor: bool = False) -> tuple[np.ndarray, ExcitationMonitor]:
    """The reference implementation's multirate observer on a sampled-data plant (the
    exogenous controller evaluated at each 5 ms tick and held in the body frame; yaw exact;
    displacement by 3-point Gauss-Legendre, §7), in the method's order (stage 3's correction
    and stage 2 from the state at the tick's start, then stage 1): the records ``(t, yaw
    error, position error, relative-yaw error)`` and the excitation monitor. ``monitor``:
    stage 2 uses only the pairs excited so far."""
    gl = (0.5 - np.sqrt(0.15), 0.5, 0.5 + np.sqrt(0.15)), (5 / 18, 8 / 18, 5 / 18)
    p, P, Pz = paper.p0.copy(), paper.P0.copy(), paper.Pz0.copy()
    z_pair, z_hat, p_hat = paper.z_pair0.copy(), paper.z_hat0.copy(), paper.p_hat0.copy()
    prev = np.zeros(paper.n, dtype=complex)
    active = np.ones(len(paper.pairs), dtype=bool)
    excitation = ExcitationMonitor(paper.pairs, h)
    rec, per_record = [], int(round(every / h))
    for k in range(int(round(T / h)) + 1):
        t = k * h
        psi = paper.yaw(t)
        if k % per_record == 0:
            rec.append((t, *errors(paper, psi, p, z_hat, p_hat),
                        rel_yaw_error(paper, psi, z_pair)))
        if k == int(round(T / h)):
            break
        y, y_z = paper.measure(psi, p)
        v = np.einsum('nba,nb->na', rot_z(psi), paper.world_velocity(p))   # body, held
        delta = np.zeros((paper.n, 3))
        for node, weight in zip(*gl):
            delta += weight * h * np.einsum('nba,nbc,nc->na', rot_z(psi),
                                            rot_z(paper.yaw(t + node * h)), v)
        dpsi = paper.yaw(t + h) - psi
        if monitor:   # the consensus uses the pairs excited so far
            active = excitation.active
        if k % 4 == 0:   # stage 3 correction at 50 Hz, from the state at t
            p_hat = position_correction(p_hat, np.angle(z_hat), paper.tail, paper.head,
                                        np.stack([y.real, y.imag, y_z], axis=1), 0.02,
                                        paper.k_p)
        if k % 2 == 0:   # stage 2 at 100 Hz
            z_hat = yaw_consensus_step(z_hat, unit(z_pair), paper.pairs, active,
                                       0.01 * paper.k_z)
        psi_hat = np.angle(z_hat)
        dc = delta[:, 0] + 1j * delta[:, 1]
        excitation.add(dc)
        P, Pz, z_pair, _ = relative_yaw_step(P, Pz, z_pair, paper.pairs, paper.tail,
                                             paper.head, y, y_z, dc, delta[:, 2], dpsi, prev,
                                             h, paper.k_pe, paper.k_psi)
        prev = np.exp(-1j * dpsi) * dc
        p_hat = dead_reckoning(p_hat, psi_hat, delta)
        z_hat = np.exp(1j * dpsi) * z_hat
        p = p + np.einsum('nab,nb->na', rot_z(psi), delta)
    return np.array(rec), excitation


def continuous(paper: Paper, T: float, every: float = 0.1, mode: str = 'exogenous'):
    """(7)-(8), (13), (21) and the plant (``mode``: exogenous or the paper's closed loop) in
    continuous time, DOP853, written from the notes' equations in plain loops (no code shared
    with the package)."""
    n, K, M = paper.n, len(paper.tail), len(paper.pairs)
    tail, head = paper.tail, paper.head
    pa, pb = paper.pairs.a, paper.pairs.b
    edge_pair, rev = paper.pairs.edge_pair, paper.pairs.reversed_
    dyaw = paper.yaw.derivative()

    def unpack(x):
        o = 0
        p = x[o:o + 3 * n].real.reshape(n, 3)
        o += 3 * n
        P = x[o:o + K]
        o += K
        Pz = x[o:o + K].real
        o += K
        zp = x[o:o + M]
        o += M
        z = x[o:o + n]
        o += n
        ph = x[o:o + 3 * n].real.reshape(n, 3)
        return p, P, Pz, zp, z, ph

    def rhs(t, x):
        p, P, Pz, zp, z, ph = unpack(x)
        psi, om = paper.yaw(t), dyaw(t)
        u_world = (paper.world_velocity(p, psi, np.angle(z)) if mode == 'paper'
                   else paper.world_velocity(p))
        v = np.array([rot_z(psi[i]).T @ u for i, u in enumerate(u_world)])
        w = v[:, 0] + 1j * v[:, 1]
        dP, dPz, dzp = np.zeros(K, complex), np.zeros(K), 1j * (om[pb] - om[pa]) * zp
        for k in range(K):
            i, j = tail[k], head[k]
            d = rot_z(psi[i]).T @ (p[j] - p[i])
            E, ez = P[k] - (d[0] + 1j * d[1]), Pz[k] - d[2]
            zk = np.conj(zp[edge_pair[k]]) if rev[k] else zp[edge_pair[k]]
            dP[k] = -w[i] - 1j * om[i] * P[k] + w[j] * zk - paper.k_pe * E
            dPz[k] = -v[i, 2] + v[j, 2] - paper.k_pe * ez
            g = w[pa[edge_pair[k]]] * np.conj(E) if rev[k] else np.conj(w[pb[edge_pair[k]]]) * E
            dzp[edge_pair[k]] -= paper.k_psi * g
        dz = 1j * om * z
        for m in range(M):
            a, b = pa[m], pb[m]
            u = zp[m] / abs(zp[m])
            dz[a] += paper.k_z * (np.conj(u) * z[b] - z[a])
            dz[b] += paper.k_z * (u * z[a] - z[b])
        dph = np.array([rot_z(np.angle(z[i])) @ v[i] for i in range(n)])
        for k in range(K):
            i, j = tail[k], head[k]
            meas = rot_z(psi[i]).T @ (p[j] - p[i])
            r = ph[i] - ph[j] + rot_z(np.angle(z[i])) @ meas
            dph[i] -= paper.k_p * r
            dph[j] += paper.k_p * r
        return np.concatenate([u_world.ravel(), dP, dPz, dzp, dz,
                               dph.ravel()]).astype(complex)

    x0 = np.concatenate([paper.p0.ravel(), paper.P0, paper.Pz0, paper.z_pair0, paper.z_hat0,
                         paper.p_hat0.ravel()]).astype(complex)
    times = np.arange(0.0, T + 1e-9, every)
    sol = solve_ivp(rhs, (0.0, T), x0, method='DOP853', t_eval=times, rtol=1e-9, atol=1e-11)
    rec = []
    for t, x in zip(sol.t, sol.y.T):
        p, P, Pz, zp, z, ph = unpack(x)
        psi = paper.yaw(t)
        rec.append((t, *errors(paper, psi, p, z, ph), rel_yaw_error(paper, psi, zp)))
    return np.array(rec)


def settle(rec: np.ndarray, column: int, threshold: float) -> float:
    """The first time after which the error stays below ``threshold``."""
    above = np.flatnonzero(rec[:, column] >= threshold)
    return float(rec[above[-1] + 1, 0]) if above.size else 0.0


# Every pair in the consensus from the start, as in the continuous equations.
ALL_PAIRS = {'pe_threshold': 0.0}


@pytest.fixture(scope='module', params=['exogenous', 'paper'])
def runs(request):
    paper, T, every = Paper(), 7.0, 0.01   # the scenario's output step; settled by then
    disc, _ = batch(config(request.param, **ALL_PAIRS), T, every)
    return request.param, disc, continuous(paper, T, every, mode=request.param)


def test_the_method_matches_the_continuous_equations(runs):
    """Times to 1e-3 rad (yaw) and 1e-2 m (position) within 10 % of the continuous solution,
    in both motion modes."""
    mode, disc, cont = runs
    for column, threshold in ((1, 1e-3), (2, 1e-2)):
        t_d, t_c = settle(disc, column, threshold), settle(cont, column, threshold)
        assert 0.0 < t_c < 7.0
        assert abs(t_d - t_c) <= 0.1 * t_c, (mode, column, t_d, t_c)


def test_the_cascade_order_holds(runs):
    """Relative yaw and yaw, then the position, then the formation (§5), in both runs: to a
    thousandth of their initial mean, relative yaw and yaw settle within 0.15 s of each other
    (the consensus, at k_z λ₂ = 80 s⁻¹, follows stage 1 closely; averaging over the cube's 12
    pairs, the mean yaw error even falls a little earlier than the mean relative-yaw error),
    the position at least 1.5 s after both, and the formation (to 1e-2 m) after the
    position."""
    mode, disc, cont = runs
    rel0 = cont[0, 3]   # the method's pairs start at its first step, from the same values
    for rec in (disc, cont):
        t_rel = settle(rec, 3, 1e-3 * rel0)
        t_yaw, t_pos = (settle(rec, c, 1e-3 * rec[0, c]) for c in (1, 2))
        assert abs(t_rel - t_yaw) <= 0.15, (mode, t_rel, t_yaw)
        assert t_pos >= max(t_rel, t_yaw) + 1.5, (mode, t_rel, t_yaw, t_pos)
    t_form = settle(disc, 4, 1e-2)
    assert settle(disc, 2, 1e-2) < t_form < 7.0, (mode, t_form)


def test_the_method_equals_the_reference_implementation_tick_for_tick():
    """The registered method (per robot and link, pairs in the owner's orientation) and the
    fleet-wide reference (pairs a < b) are the same discretisation: the errors agree to
    rounding at every record of the exogenous run."""
    ours, _ = batch(config('exogenous', **ALL_PAIRS), 3.0)
    ref, _ = discrete(Paper(), 3.0)
    np.testing.assert_allclose(ours[:, 1:3], ref[:, 1:3], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(ours[1:, 3], ref[1:, 3], rtol=1e-6, atol=1e-12)


def hovering(data: dict, name: str = 'robot_7') -> dict:
    """``data`` with robot ``name`` hovering: no formation position, so it never moves."""
    for agent in data['agents']:
        if agent['name'] == name:
            del agent['formation_position']
    return data


def test_a_hovering_robot_s_pairs_are_warned_about_left_out_and_reported():
    """Robot 7 hovers: the pairs that only its motion could excite ({4, 7} and {6, 7}: their
    edges sense robot 7) are warned about by the check, never excited, and left out; the rest
    of the fleet, robot 7 included (through pair {3, 7}, whose edge senses robot 3),
    converges. Kept in, their initial relative yaws bias the common yaw, whose error stops far
    above."""
    data = hovering(config('exogenous'))
    scenario = parse_scenario(data)
    warned = {f.problem.split()[2] for f in check_scenario(scenario).warnings
              if 'never excited' in f.problem}
    assert warned == {'robot_4-robot_7', 'robot_6-robot_7'}
    sim = BatchSimulator(scenario)
    rec = sim.run(5.0)
    x, t = sim.x, sim.table
    links = {'agent': t.agent, 'other': t.other, **t.flags}
    excited = {(int(a), int(b)) for a, b, e in zip(links['agent'], links['other'],
                                                  x.excited[links['agent'], sim.edges.slot])
               if e}
    unexcited = {tuple(sorted(p)) for p in zip(links['agent'].tolist(),
                                               links['other'].tolist())} - {
        tuple(sorted(p)) for p in excited}
    assert unexcited == {(4, 7), (6, 7)}
    att, pos = rec.mean_errors()
    assert att[-1] < 1e-6 and pos[-1] < 1e-2, (att[-1], pos[-1])
    biased = BatchSimulator(parse_scenario(hovering(config('exogenous', **ALL_PAIRS)))).run(5.0)
    assert biased.mean_errors()[0][-1] > 1e-2


def test_a_hovering_robot_s_odometry_noise_never_admits_its_pairs():
    """Robot 7 hovers and every odometry has 0.1 m/s of white noise per component (200 Hz):
    robot 7's noise alone adds 0.02 m²/s per second, so the integral since the start passes
    0.05 m²/s (the fixed threshold the monitor had) after 2.5 s. Its pairs {4, 7} and {6, 7}
    stay out for 5 s (their windows stay below twice the noise's mean), and every other pair
    is in after 0.1 s; the check warns about the same two."""
    data = hovering(config('exogenous'))
    data['sensors']['odometry']['std'] = 0.1
    scenario = parse_scenario(data)
    warned = {f.problem.split()[2] for f in check_scenario(scenario).warnings
              if 'never excited' in f.problem}
    assert warned == {'robot_4-robot_7', 'robot_6-robot_7'}
    sim = BatchSimulator(scenario)
    t = sim.table
    pairs = {tuple(sorted(p)) for p in zip(t.agent.tolist(), t.other.tolist())}

    def out() -> set[tuple[int, int]]:
        excited = sim.x.excited[t.agent, sim.edges.slot]
        return pairs - {tuple(sorted((int(a), int(b))))
                        for a, b, e in zip(t.agent, t.other, excited) if e}

    sim.run(0.1)
    assert out() == {(4, 7), (6, 7)}
    sim.run(4.9)
    assert out() == {(4, 7), (6, 7)}
    assert sim.x.excitation[t.agent, sim.edges.slot][t.other == 7].min() > 0.05
