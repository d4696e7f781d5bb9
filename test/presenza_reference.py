"""An independent solution of Presenza et al.'s observer (16)-(19) with the plant (1), for the
tests: truth and observer integrated together in continuous time (scipy's DOP853, rtol 1e-9),
everything built from ``test/data/presenza-2026-scenarios.json`` itself (not from the
scenario files), written in plain loops over robots and angles, as the notes' §4 states it.

State: per robot the world pose ``p_i``, ``R_i`` and the estimate ``q̂_i``, ``Q̂_i`` (rotation
matrices as 9 numbers; the tight tolerance keeps them orthonormal to ~1e-9).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

JSON = json.loads((Path(__file__).parent / 'data' / 'presenza-2026-scenarios.json').read_text())


def S(x):
    return np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])


def Pi(x):
    return np.eye(3) - np.outer(x, x)


def cross(a, b):   # np.cross costs ~10 µs on 3-vectors
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def norm(a):
    return math.sqrt(a @ a)


def profile(spec, t):
    """A velocity of the JSON (a list of 3 lists of terms) at t."""
    out = np.zeros(3)
    for axis, terms in enumerate(spec['components']):
        for term in terms:
            fn = term['fn']
            out[axis] += (term['amp'] if fn == 'const'
                          else term['amp'] * (np.cos if fn == 'cos' else np.sin)(term['w'] * t))
    return out


class Case:
    """One case of the JSON, 0-based robot indices."""

    def __init__(self, name: str, kappa_Q_free: float | None = None) -> None:
        c = JSON['cases'][name]
        self.c = c
        self.n = len(c['robots'])
        self.a = c['anchor'] - 1
        self.b, self.cc = c['ranged_robots']['b'] - 1, c['ranged_robots']['c'] - 1
        self.out = [[j - 1 for j in c['out_neighbours'][str(i + 1)]] for i in range(self.n)]
        self.sensing = [len(o) >= 2 for o in self.out]
        g = c['gains']
        self.kq, self.ks, self.kQ = g['kappa_q'], g['kappa_s'], g['kappa_Q']
        self.kQf = self.kQ if kappa_Q_free is None else kappa_Q_free
        self.vel = [c['velocities'][str(i + 1)] for i in range(self.n)]

    def x0(self) -> np.ndarray:
        c = self.c
        parts = []
        for i in range(self.n):
            w, e = c['initial_truth_world'][str(i + 1)], c['initial_estimates'][str(i + 1)]
            parts += [w['p'], Rotation.from_quat(w['R_quat_xyzw']).as_matrix().ravel(),
                      e['q_hat'], Rotation.from_quat(e['Q_hat_quat_xyzw']).as_matrix().ravel()]
        return np.concatenate([np.asarray(p, float) for p in parts])

    def unpack(self, x):
        x = x.reshape(self.n, 24)
        return (x[:, 0:3], x[:, 3:12].reshape(-1, 3, 3), x[:, 12:15],
                x[:, 15:24].reshape(-1, 3, 3))

    def commands(self, t, Q_hat):
        u, w = [], []
        for i in range(self.n):
            v = profile(self.vel[i]['u'], t)
            u.append(Q_hat[i].T @ v if self.vel[i]['u']['frame'] == 'anchor_via_own_estimate'
                     else v)
            w.append(profile(self.vel[i]['omega'], t))
        return u, w

    def rhs(self, t, x):
        n, a = self.n, self.a
        p, R, qh, Qh = self.unpack(x)
        u, w = self.commands(t, Qh)
        pdot = [R[i] @ u[i] for i in range(n)]
        # Measurements.
        beta, beta_dot = {}, {}
        for i in range(n):
            for j in self.out[i]:
                d = p[j] - p[i]
                r = norm(d)
                b = R[i].T @ d / r
                v = R[i].T @ (pdot[j] - pdot[i]) / r
                beta[i, j] = b
                beta_dot[i, j] = v - b * (b @ v) - cross(w[i], b)
        q_meas = {k: R[a].T @ (p[k] - p[a]) for k in (self.b, self.cc)}
        u_a, w_a = u[a], w[a]
        # ζ (6), angle by angle.
        zeta = [np.zeros(3) for _ in range(n)]
        for i in range(n):
            o = self.out[i]
            for x1 in range(len(o)):
                for x2 in range(x1 + 1, len(o)):
                    j, k = o[x1], o[x2]
                    dj, dk = qh[j] - qh[i], qh[k] - qh[i]
                    rj, rk = norm(dj), norm(dk)
                    uj, uk = dj / rj, dk / rk
                    cjk = uj @ uk
                    e = cjk - beta[i, j] @ beta[i, k]
                    chi_jk = (uk - cjk * uj) / rj      # Π(𝔮_ij) 𝔮_ik / ‖q_ij‖
                    chi_kj = (uj - cjk * uk) / rk
                    zeta[i] -= e * (chi_jk + chi_kj)
                    zeta[j] += e * chi_jk
                    zeta[k] += e * chi_kj
        zeta[a] = zeta[a] + self.ks * qh[a]
        for k in (self.b, self.cc):
            zeta[k] = zeta[k] + self.ks * (qh[k] - q_meas[k])
        # Velocities (10), (11) and innovations (12), (13).
        ups = [None] * n
        for i in range(n):
            if self.sensing[i]:
                ups[i] = Qh[i] @ u[i] - u_a - cross(w_a, qh[i])
        out = np.zeros_like(x).reshape(n, 24)
        for i in range(n):
            if self.sensing[i]:
                Om = sum(cross(beta[i, j], Qh[i].T @ (qh[j] - qh[i])) for j in self.out[i])
                kQ = self.kQ
            else:
                P, acc = np.zeros((3, 3)), np.zeros(3)
                for j in range(n):
                    if self.sensing[j] and i in self.out[j]:
                        bh = Qh[j] @ beta[j, i]
                        P += Pi(bh)
                        acc += (ups[j] - bh * (bh @ ups[j])) + norm(qh[i] - qh[j]) * (
                            Qh[j] @ (beta_dot[j, i] + cross(w[j], beta[j, i]))
                            - cross(w_a, bh))
                ups[i] = np.linalg.solve(P, acc)
                gam = ups[i] + u_a + cross(w_a, qh[i])
                Om = cross(u[i], Qh[i].T @ gam)
                kQ = self.kQf
            out[i, 0:3] = pdot[i]
            out[i, 3:12] = (R[i] @ S(w[i])).ravel()
            out[i, 12:15] = ups[i] - self.kq * zeta[i]
            out[i, 15:24] = (Qh[i] @ S(w[i] - Qh[i].T @ w_a + kQ * Om)).ravel()
        return out.ravel()

    def errors(self, x):
        """Mean position [m] and attitude [rad] errors over all robots, and per robot
        ``(pos (N,), att (N,))`` (notes §11: anchor frame, no alignment)."""
        p, R, qh, Qh = self.unpack(x)
        a = self.a
        pos, att = np.zeros(self.n), np.zeros(self.n)
        for i in range(self.n):
            pos[i] = np.linalg.norm(qh[i] - R[a].T @ (p[i] - p[a]))
            E = (R[a].T @ R[i]).T @ Qh[i]
            A = E - E.T
            att[i] = np.arctan2(np.linalg.norm([A[2, 1], A[0, 2], A[1, 0]]), (np.trace(E) - 1) / 2)
        return pos, att

    def solve(self, duration: float, every: float = 0.01):
        t_eval = np.arange(0.0, duration + 1e-9, every)
        sol = solve_ivp(self.rhs, (0.0, duration), self.x0(), method='DOP853', rtol=1e-9,
                        atol=1e-10, t_eval=t_eval)
        assert sol.success, sol.message
        pos, att = zip(*(self.errors(sol.y[:, k]) for k in range(sol.y.shape[1])))
        return sol.t, np.array(pos), np.array(att)


def euler(case: Case, duration: float, h: float, substeps: int = 8):
    """The paper's update, sampled (the JSON's "runs"): at t_k the observer's right-hand side
    with the commands and exact measurements at t_k, then ``q̂ ← q̂ + h q̂̇``,
    ``Q̂ ← Q̂ exp(h w)``; the truth in between by RK4 substeps (case 2: the command of t_k
    held). Errors every 0.01 s, for the floor this update leaves."""
    x = case.x0()
    steps = int(round(duration / h))
    every = max(1, int(round(0.01 / h)))
    pos, att, t = [], [], []
    for k in range(steps + 1):
        if k % every == 0:
            e = case.errors(x)
            t.append(k * h)
            pos.append(e[0])
            att.append(e[1])
        if k == steps:
            break
        tk = k * h
        f = case.rhs(tk, x).reshape(case.n, 24)
        y = x.reshape(case.n, 24).copy()
        _, _, qh, Qh = case.unpack(x)
        for i in range(case.n):
            y[i, 12:15] += h * f[i, 12:15]
            W = Qh[i].T @ f[i, 15:24].reshape(3, 3)
            y[i, 15:24] = (Qh[i] @ Rotation.from_rotvec(
                h * np.array([W[2, 1], W[0, 2], W[1, 0]])).as_matrix()).ravel()
        held = case.commands(tk, Qh)[0]

        def plant(tau, z):
            zz = z.reshape(case.n, 12)
            u, w = case.commands(tau, Qh)
            out = np.zeros_like(zz)
            for i in range(case.n):
                ui = held[i] if case.vel[i]['u']['frame'] == 'anchor_via_own_estimate' else u[i]
                Ri = zz[i, 3:12].reshape(3, 3)
                out[i, 0:3] = Ri @ ui
                out[i, 3:12] = (Ri @ S(w[i])).ravel()
            return out.ravel()

        z = x.reshape(case.n, 24)[:, :12].ravel()
        dt = h / substeps
        for m in range(substeps):
            tau = tk + m * dt
            k1 = plant(tau, z)
            k2 = plant(tau + dt / 2, z + dt / 2 * k1)
            k3 = plant(tau + dt / 2, z + dt / 2 * k2)
            k4 = plant(tau + dt, z + dt * k3)
            z = z + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        y[:, :12] = z.reshape(case.n, 12)
        x = y.ravel()
    return np.array(t), np.array(pos), np.array(att)
