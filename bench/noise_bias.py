"""The steady-state error of Boughellaba & Tayebi's observer under noise: bias or spread?

For each noise setting, SEEDS batch runs of config/paper_noisy.yaml (the paper's fleet with
1 deg bearing noise and 0.01 rad/s gyro noise), averaging every follower's error vector
p̂_i - p_i (and log(R̂_i R_iᵀ)) over the last half of the run. Prints, per follower, the mean
over runs and time (the bias), the spread of the per-run means across seeds, and the spread
within a run: a covariance published with the estimate has to account for what this shows.
The last setting turns on the projector compensation (``gains.bias_std``) at the true noise.

    OMP_NUM_THREADS=1 .venv/bin/python bench/noise_bias.py [--seeds 20] [--duration 60]
"""
from __future__ import annotations

import argparse
import dataclasses
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.scenario import load_scenario
from bearing_pose_estimation.sim.batch import BatchSimulator
from bearing_pose_estimation.studies.montecarlo import reseed

SCENARIO = Path(__file__).resolve().parents[1] / 'config' / 'paper_noisy.yaml'


def one_run(args: tuple[int, float, float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(position errors, attitude errors) every 0.1 s of the second half: (t, agents, 3)."""
    seed, bearing_std, gyro_std, bias_std, duration = args
    s = reseed(load_scenario(SCENARIO), seed)
    s = dataclasses.replace(s, noise=dataclasses.replace(s.noise, bearing_std=bearing_std,
                                                         gyro_std=gyro_std),
                            gains=dataclasses.replace(s.gains, bias_std=bias_std))
    b = BatchSimulator(s)
    n = int(round(duration / b.h))
    every = max(1, int(round(0.1 / b.h)))
    dp, dth = [], []
    for k in range(n):
        b.step()
        if k >= n // 2 and k % every == 0:
            dp.append(b.x.p_hat - b.p)
            dth.append([so3.log(Rh @ R.T) for Rh, R in zip(b.x.R_hat, b.R)])
    return np.array(dp), np.array(dth)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--seeds', type=int, default=20)
    ap.add_argument('--duration', type=float, default=60.0)
    ap.add_argument('--jobs', type=int, default=2)
    opts = ap.parse_args()
    base = load_scenario(SCENARIO)
    followers = [k for k, a in enumerate(base.agents) if a.name not in base.leaders]
    b_std, g_std = base.noise.bearing_std, base.noise.gyro_std
    # (bearing noise, gyro noise, the projector compensation's bias_std)
    settings = [(b_std, g_std, 0.0), (b_std / 2, g_std, 0.0), (b_std, 0.0, 0.0),
                (0.0, g_std, 0.0), (b_std, g_std, b_std)]
    with ProcessPoolExecutor(opts.jobs) as pool:
        for bearing_std, gyro_std, bias_std in settings:
            runs = list(pool.map(one_run, [(seed, bearing_std, gyro_std, bias_std,
                                            opts.duration) for seed in range(opts.seeds)]))
            dp = np.stack([r[0] for r in runs])    # runs, t, agents, 3
            dth = np.stack([r[1] for r in runs])
            print(f'\nbearing_std {np.degrees(bearing_std):.2f} deg, gyro_std {gyro_std:g} '
                  f'rad/s, gains.bias_std {np.degrees(bias_std):.2f} deg, {opts.seeds} runs, '
                  f'last {opts.duration / 2:g} s')
            print('agent    position bias [m]         |bias|    seed-to-seed  within-run '
                  '  attitude bias [rad]  attitude rms')
            for k in followers:
                bias = dp[:, :, k].mean(axis=(0, 1))
                across = np.linalg.norm(dp[:, :, k].mean(axis=1).std(axis=0))
                within = np.linalg.norm(dp[:, :, k].std(axis=1).mean(axis=0))
                att = dth[:, :, k]
                text = ' '.join(f'{v:+.4f}' for v in bias)
                print(f'{base.agents[k].name:8s} [{text}] '
                      f'{np.linalg.norm(bias):.4f}    {across:.4f}        {within:.4f}      '
                      f'{np.linalg.norm(att.mean(axis=(0, 1))):.1e}              '
                      f'{np.sqrt((att ** 2).sum(axis=2).mean()):.1e}')


if __name__ == '__main__':
    main()
