"""Consistency of the published covariance: NEES over Monte Carlo runs of the batch simulator.

For each run (seeds ``noise.seed``, +1, ...) and each agent that estimates its pose, the
normalised estimation error squared of the position, ``e_iᵀ P_ee⁻¹ e_i``, and of the
attitude, ``φ_iᵀ P_φφ⁻¹ φ_i``, averaged over the samples after ``--after`` seconds. World-frame
methods: ``e_i = p̂_i − p_i``, ``R̂_i = exp([φ_i]x) R_i`` (3 dof each). De Carli et al. (no
anchor): the errors after the exact alignment (metrics/results.py), ``e_i = p̂_i − R_z(a*) p_i −
t*`` in the estimation frame and the yaw error alone (1 dof: roll and pitch are known). A
consistent covariance gives the number of dof; the 95 % band of the average of ``runs``
independent values is ``chi2(dof runs) / runs``. Per method (``--methods``, default the
scenario's own), per agent and the fleet's mean; methods without a covariance are skipped.

    OMP_NUM_THREADS=1 .venv/bin/python bench/nees.py config/paper_noisy.yaml --runs 20 \
        --methods boughellaba_tayebi,tran_anderson_ahn
    OMP_NUM_THREADS=1 .venv/bin/python bench/nees.py config/de_carli_noisy.yaml --runs 20 \
        --duration 20 --after 10

``--netsim`` runs the nodes' logic instead (sim.netsim: bearings at ``simulation.bearing_rate``
and the neighbours' values at ``publish_rate``, held between samples, as over DDS).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy.stats import chi2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bearing_pose_estimation.core import so3  # noqa: E402
from bearing_pose_estimation.core.motion import rot_z, yaw_of  # noqa: E402
from bearing_pose_estimation.estimators.base import EstimateFrame  # noqa: E402
from bearing_pose_estimation.scenario import load_scenario  # noqa: E402
from bearing_pose_estimation.sim import netsim  # noqa: E402
from bearing_pose_estimation.sim.batch import BatchSimulator  # noqa: E402


def errors(frame: EstimateFrame, sim: BatchSimulator) -> tuple[np.ndarray, np.ndarray, list]:
    """``(e (N, 3), φ (N, 3), rows of P that φ covers)`` of the whole fleet, as the method's
    covariance describes them (module docstring)."""
    x = sim.x
    if frame is EstimateFrame.COMMON_YAW_TRANSLATION:
        a = float(np.angle(np.sum(np.exp(1j * (yaw_of(x.R_hat) - yaw_of(sim.R))))))
        Rz = rot_z(np.array(a))
        p_frame = sim.p @ Rz.T
        e = x.p_hat - p_frame - np.mean(x.p_hat - p_frame, axis=0)
        theta = np.angle(np.exp(1j * (yaw_of(x.R_hat) - yaw_of(sim.R) - a)))
        return e, theta[:, None], [5]
    if frame is EstimateFrame.ANCHOR_BODY:     # q_i = R_aᵀ (p_i − p_a), Q_i = R_aᵀ R_i
        a = sim.scenario.anchor_index
        Ra = sim.R[a]
        q = (sim.p - sim.p[a]) @ Ra
        Q = np.einsum('ba,nbc->nac', Ra, sim.R)
        return x.p_hat - q, so3.log(np.einsum('nab,ncb->nac', x.R_hat, Q)), [3, 4, 5]
    if frame is not EstimateFrame.WORLD:
        raise SystemExit(f'{frame}: no NEES for this estimate frame yet')
    return (x.p_hat - sim.p, so3.log(np.einsum('nab,ncb->nac', x.R_hat, sim.R)), [3, 4, 5])


class _Netsim:
    """The fleet of per-agent estimators (the nodes' logic, ``sim.netsim``) seen as the batch
    simulator is here: ``h``, ``step()``, ``x`` (the fleet's state), ``R``, ``p`` (the truth
    at the agents' state time)."""

    def __init__(self, scenario) -> None:
        self.net = netsim._Network(scenario, netsim.LinkFaults(), (), netsim.Garbage(),
                                   netsim.Limits())
        self.net.start()
        self.h, self.tick, self.scenario = scenario.step, 0, scenario
        self.per_step = int(round(scenario.step / self.net.world.dt))

    def step(self) -> None:
        for _ in range(self.per_step):
            self.tick += 1
            self.net.tick(self.tick * self.net.world.dt)
        agents = [self.net.agents[a.name] for a in self.scenario.agents]
        self.x = dataclasses.replace(agents[0].x, **{
            f.name: np.concatenate([getattr(a.x, f.name) for a in agents])
            for f in dataclasses.fields(agents[0].x)})
        k = {int(round(a.t / self.h)) for a in agents}
        if len(k) != 1 or k.pop() not in self.net.truth:
            raise SystemExit('netsim: the agents are not at one state time')
        self.R, self.p = self.net.truth[int(round(agents[0].t / self.h))]


def nees_run(path: str, method: str, seed: int, duration: float, after: float,
             every: float, gains: dict[str, float],
             network: bool = False) -> dict[str, tuple[float, float]]:
    """``{agent: (position NEES, attitude NEES)}`` of one run, averaged over its samples;
    ``network``: the nodes' logic (netsim) instead of the batch simulator."""
    s = load_scenario(path).with_method(method, **gains)
    s = dataclasses.replace(s, noise=dataclasses.replace(s.noise, seed=seed))
    sim = _Netsim(s) if network else BatchSimulator(s)
    frame = s.estimator().frame
    stride = max(1, int(round(every / sim.h)))
    followers = [s.index[a.name] for a in s.followers]
    sums = np.zeros((len(followers), 2))
    count = 0
    for k in range(int(round(duration / sim.h))):
        sim.step()
        if (k + 1) * sim.h < after - 1e-9 or (k + 1) % stride:
            continue
        e, phi, rows = errors(frame, sim)
        for m, i in enumerate(followers):
            P = sim.x.P[i]
            sums[m] += (e[i] @ np.linalg.solve(P[:3, :3], e[i]),
                        phi[i] @ np.linalg.solve(P[np.ix_(rows, rows)], phi[i]))
        count += 1
    return {s.agents[i].name: tuple(sums[m] / count) for m, i in enumerate(followers)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('scenario')
    ap.add_argument('--runs', type=int, default=20)
    ap.add_argument('--duration', type=float, default=60.0)
    ap.add_argument('--after', type=float, default=30.0, help='converged from here [s]')
    ap.add_argument('--every', type=float, default=0.05, help='sample interval [s]')
    ap.add_argument('--methods', default=None,
                    help="comma-separated registry keys (default: the scenario's method)")
    ap.add_argument('--bias-std', type=float, default=None,
                    help="gains.bias_std (default: the scenario's noise.bearing_std)")
    ap.add_argument('--workers', type=int, default=2)
    ap.add_argument('--netsim', action='store_true',
                    help="the nodes' logic (sim.netsim: bearings and neighbours' values at "
                         "their own rates, as over DDS) instead of the batch simulator")
    args = ap.parse_args(argv)
    s = load_scenario(args.scenario)
    print(f'{args.scenario}: {args.runs} runs of {args.duration:g} s'
          f'{" (netsim)" if args.netsim else ""}, NEES averaged over t >= {args.after:g} s')
    for method in (args.methods or s.method).split(','):
        est = s.with_method(method).estimator()
        state = est.initial_state(np.eye(3)[None], np.zeros((1, 3)))
        if not hasattr(state, 'P'):
            print(f'\n{method}: no covariance (its state has none)')
            continue
        bias = s.noise.bearing_std if args.bias_std is None else args.bias_std
        gains = {'bias_std': bias} if 'bias_std' in {
            f.name for f in dataclasses.fields(s.with_method(method).gains)} else {}
        seeds = [s.noise.seed + r for r in range(args.runs)]
        with ProcessPoolExecutor(args.workers) as pool:
            runs = list(pool.map(nees_run, [args.scenario] * args.runs, [method] * args.runs,
                                 seeds, [args.duration] * args.runs, [args.after] * args.runs,
                                 [args.every] * args.runs, [gains] * args.runs,
                                 [args.netsim] * args.runs))
        att_dof = 1 if est.frame is EstimateFrame.COMMON_YAW_TRANSLATION else 3
        band = [(chi2.ppf(0.025, d * args.runs) / args.runs,
                 chi2.ppf(0.975, d * args.runs) / args.runs) for d in (3, att_dof)]
        print(f'\n95 % band of the {args.runs}-run mean: position (3 dof) '
              f'[{band[0][0]:.2f}, {band[0][1]:.2f}], attitude ({att_dof} dof) '
              f'[{band[1][0]:.2f}, {band[1][1]:.2f}]')
        print(f'\n{method} ({", ".join(f"{k}={v:g}" for k, v in gains.items()) or "as given"})')
        print('| agent | position NEES | attitude NEES |')
        print('|---|---|---|')
        agents = list(runs[0])
        table = np.array([[r[a] for a in agents] for r in runs])   # (runs, agents, 2)
        for m, a in enumerate(agents):
            p, q = table[:, m].mean(axis=0)
            print(f'| {a} | {p:.2f} | {q:.2f} |')
        p, q = table.mean(axis=(0, 1))
        print(f'| fleet mean | {p:.2f} | {q:.2f} |')


if __name__ == '__main__':
    main()
