"""De Carli et al. (2024), the three stages' math (the fleet-wide reference implementation,
de_carli_reference.py, which the method is checked against tick for tick), against the
properties the corrected notes derive: exact discrete kinematics, convergence to machine
precision under persistent excitation, a consensus step that stays stable where forward Euler
diverges, and the common yaw/translation as an exact solution of the position observer."""
from __future__ import annotations

import numpy as np

from de_carli_reference import (Pairs, dead_reckoning, position_correction, relative_yaw_step,
                                rot_z, yaw_consensus_step)

from bearing_pose_estimation.estimators.de_carli import unit

H = 0.005   # the paper's 200 Hz base tick


def _truth(t: float) -> tuple[np.ndarray, np.ndarray]:
    """Two robots: yaws ψ (2,) and positions p (2, 3). Robot 1 (the sensed one) circles at
    1 m/s: persistent excitation."""
    psi = np.array([0.3 * t + 0.2 * np.sin(t), -0.5 * t])
    p = np.array([[np.cos(0.2 * t), 0.5 * np.sin(0.3 * t), 0.1 * t],
                  [3.0 + np.cos(t), 1.0 + np.sin(t), 0.2 * np.sin(0.5 * t)]])
    return psi, p


def _measure(psi, p, tail, head):
    """ⁱp_ij = R_iᵀ (p_j − p_i) as (complex xy, z)."""
    d = np.einsum('kba,kb->ka', rot_z(psi[tail]), p[head] - p[tail])
    return d[:, 0] + 1j * d[:, 1], d[:, 2]


def _odometry(t0: float, t1: float):
    """Exact (δ complex, δ_z, Δψ) of both robots over [t0, t1], δ in the frame at t0."""
    (psi0, p0), (psi1, p1) = _truth(t0), _truth(t1)
    d = np.einsum('nba,nb->na', rot_z(psi0), p1 - p0)
    return d[:, 0] + 1j * d[:, 1], d[:, 2], psi1 - psi0


def _run(tail, head, z0, seconds):
    """Stage 1 from the true relative positions and a wrong relative yaw; returns the final
    yaw error of the pair, the position error, and the truth."""
    tail, head = np.array(tail), np.array(head)
    pairs = Pairs.of(tail, head)
    psi, p = _truth(0.0)
    P, Pz = _measure(psi, p, tail, head)
    z = np.array([z0], dtype=complex)
    prev = np.zeros(2, dtype=complex)
    for k in range(int(round(seconds / H))):
        t = k * H
        psi, p = _truth(t)
        y, y_z = _measure(psi, p, tail, head)
        delta, delta_z, dpsi = _odometry(t, t + H)
        P, Pz, z, _ = relative_yaw_step(P, Pz, z, pairs, tail, head, y, y_z, delta, delta_z,
                                        dpsi, prev, H, k_pe=20.0, k_psi=600.0)
        prev = np.exp(-1j * dpsi) * delta
    psi, p = _truth(seconds)
    y, y_z = _measure(psi, p, tail, head)
    return abs(z[0] - np.exp(1j * (psi[1] - psi[0]))), np.abs(P - y).max()


def test_the_discrete_kinematics_are_exact():
    """At the true relative position and yaw (no correction), one tick of stage 1 lands on
    the true values at the tick's end, for this arbitrary 3D motion: §7's exact recursion."""
    tail, head = np.array([0, 1]), np.array([1, 0])
    pairs = Pairs.of(tail, head)
    for t in (0.0, 0.7, 3.1):
        psi, p = _truth(t)
        y, y_z = _measure(psi, p, tail, head)
        delta, delta_z, dpsi = _odometry(t, t + 0.05)   # a long tick: still exact
        z = np.array([np.exp(1j * (psi[1] - psi[0]))])
        P, Pz, z1, E = relative_yaw_step(y, y_z, z, pairs, tail, head, y, y_z, delta, delta_z,
                                         dpsi, np.ones(2, complex), 0.05, 20.0, 600.0)
        psi1, p1 = _truth(t + 0.05)
        y1, y1_z = _measure(psi1, p1, tail, head)
        assert np.abs(E).max() == 0.0
        np.testing.assert_allclose(P, y1, atol=1e-14)
        np.testing.assert_allclose(Pz, y1_z, atol=1e-14)
        np.testing.assert_allclose(z1[0], np.exp(1j * (psi1[1] - psi1[0])), atol=1e-14)


def test_stage_1_converges_to_machine_precision_under_excitation():
    """A relative yaw 2 rad off, one-way (robot 0 senses the circling robot 1) and two-way:
    no forcing term in the error recursion, so it converges to rounding (§7), at about
    k_pe/2 = 10 s⁻¹."""
    for tail, head in (([0], [1]), ([0, 1], [1, 0])):
        psi, _ = _truth(0.0)
        wrong = np.exp(1j * (psi[1] - psi[0] + 2.0))
        err_1s, _ = _run(tail, head, wrong, 1.0)
        err, pos_err = _run(tail, head, wrong, 6.0)
        assert 1e-6 < err_1s < 0.5, (tail, err_1s)
        assert err < 1e-12 and pos_err < 1e-12, (tail, err, pos_err)


def _cube():
    """The cube graph of the paper's scenario: 8 robots, 12 edges, λ(L) = {0, 2, 2, 2, 4, 4,
    4, 6}."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)])
    edges = [(i, j) for i in range(8) for j in range(i + 1, 8)
             if np.abs(corners[i] - corners[j]).sum() == 1]
    tail, head = np.array(edges).T
    return corners * 2.0, tail.astype(np.intp), head.astype(np.intp)


def test_the_jacobi_consensus_is_stable_where_forward_euler_diverges():
    """Exact relative yaws, c = h₂ k_z = 0.4 (100 Hz, k_z = 40) on the cube (λ_max = 6): the
    Jacobi step reaches ẑ = α z; forward Euler multiplies the top mode by 1 − 0.4·6 = −1.4
    per step (§7)."""
    _, tail, head = _cube()
    pairs = Pairs.of(tail, head)
    rng = np.random.default_rng(3)
    psi = rng.uniform(-np.pi, np.pi, 8)
    z_true = np.exp(1j * psi)
    u = np.exp(1j * (psi[pairs.b] - psi[pairs.a]))
    active = np.ones(len(pairs), dtype=bool)
    z0 = np.exp(1j * rng.uniform(-np.pi, np.pi, 8))
    z = z0.copy()
    for _ in range(200):
        z = yaw_consensus_step(z, u, pairs, active, 0.4)
    alpha = z / z_true
    np.testing.assert_allclose(alpha, alpha[0], atol=1e-12)   # one common offset
    assert abs(alpha[0]) > 0.1
    z_e = z0.copy()
    for _ in range(60):
        z_e = z_e + 0.4 * np.array([sum(np.conj(u[m]) * z_e[pairs.b[m]] - z_e[i]
                                        for m in np.flatnonzero(pairs.a == i))
                                    + sum(u[m] * z_e[pairs.a[m]] - z_e[i]
                                          for m in np.flatnonzero(pairs.b == i))
                                    for i in range(8)])
    assert np.abs(z_e).max() > 1e6   # forward Euler diverges
    np.testing.assert_allclose(yaw_consensus_step(0.7j * z_true, u, pairs, active, 0.4),
                               0.7j * z_true, atol=1e-15)   # α z is a fixed point


def test_the_common_yaw_and_translation_solve_the_position_observer():
    """ψ̂ = ψ + a and p̂ = R_z(a) p + p̄ make every residual zero (an exact solution of (21)),
    and from anywhere the disagreement decays at k_p λ₂(L̄) = 2 s⁻¹ (§4): 10 s of 50 Hz
    corrections leave less than 1e-7 of it."""
    p, tail, head = _cube()
    psi = np.linspace(0.0, 2.0, 8)
    measured = np.einsum('kba,kb->ka', rot_z(psi[tail]), p[head] - p[tail])
    a, p_bar = 0.9, np.array([0.3, -1.0, 2.0])
    aligned = p @ rot_z(np.array(a)).T + p_bar
    np.testing.assert_allclose(position_correction(aligned, psi + a, tail, head, measured,
                                                   0.02, 1.0), aligned, atol=1e-14)
    p_hat = p + np.random.default_rng(1).normal(size=p.shape)

    def disagreement(q):
        e = q - p
        return np.abs(e - e.mean(axis=0)).max()

    start = disagreement(p_hat)
    for _ in range(500):
        p_hat = position_correction(p_hat, psi, tail, head, measured, 0.02, 1.0)
    assert disagreement(p_hat) < 1e-7 * start
    np.testing.assert_allclose(dead_reckoning(aligned, psi + a, np.ones((8, 3))) - aligned,
                               np.einsum('nab,b->na', rot_z(psi + a), np.ones(3)), atol=1e-15)


def test_unit_guards_a_vanishing_modulus():
    np.testing.assert_allclose(unit(np.array([2j, 0.0, 1e-300])), [1j, 1.0, 1.0])


def test_the_excitation_monitor_admits_a_pair_once_its_motion_is_measurable():
    """Pair {0, 1} (robot 0 senses robot 1, which moves at 0.3 m/s for 1 s, then stops) and
    pair {1, 2} (robot 1 senses robot 2, which hovers). Without noise the first joins the
    consensus at its first tick of motion and stays in; it is no longer "excited now" once its
    window has forgotten the motion (0.09 m²/s (1 - e^{-1}) decays to 1e-6 in 11 s); the
    second never joins."""
    from de_carli_reference import ExcitationMonitor

    pairs = Pairs.of(np.array([0, 1]), np.array([1, 2]))
    monitor = ExcitationMonitor(pairs, H)
    monitor.add(np.array([0.0, 0.3 * H, 0.0], dtype=complex))
    assert list(monitor.active) == [True, False]
    for _ in range(199):
        monitor.add(np.array([0.0, 0.3 * H, 0.0], dtype=complex))
    assert list(monitor.excited_now) == [True, False]
    for k in range(int(12.0 / H)):
        monitor.add(np.zeros(3, dtype=complex))
        if k == int(10.0 / H):
            assert monitor.excited_now[0]
    assert list(monitor.active) == [True, False] and not monitor.excited_now.any()


def test_odometry_noise_alone_never_admits_a_hovering_robot_s_pair():
    """The same pairs with config/de_carli_noisy.yaml's odometry noise (0.02 m/s per
    component at 200 Hz) on every robot, for 100 s: robot 2's noise alone adds 8e-4 m²/s per
    second, so the integral since the start passes 0.05 m²/s (the fixed threshold this monitor
    replaced) after about 63 s, but its window never passes twice the noise's mean, while robot
    1's 0.3 m/s gets the first pair in within 0.05 s."""
    from de_carli_reference import ExcitationMonitor

    sigma = 0.02
    pairs = Pairs.of(np.array([0, 1]), np.array([1, 2]))
    monitor = ExcitationMonitor(pairs, H, noise=sigma * np.sqrt(H))
    rng = np.random.default_rng(0)
    for k in range(int(100.0 / H)):
        noise = sigma * H * (rng.normal(size=3) + 1j * rng.normal(size=3))
        monitor.add(noise + np.array([0.0, 0.3 * H, 0.0]))
        if k == int(0.05 / H):
            assert list(monitor.active) == [True, False]
    assert monitor.total[1] > 0.05
    assert list(monitor.active) == [True, False]