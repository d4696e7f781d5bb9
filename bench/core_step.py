"""Cost of one observer update per agent, by neighbour count, against a straightforward numpy
implementation of the same equations (eq. 3 and 23).

The straightforward version is what one writes first: a Python loop over neighbours with
np.cross / np.outer and scipy's Rotation for the exponential. The package's version is
:func:`estimators.boughellaba_tayebi.cascade_step` with one agent (what the estimator node calls
each step) and the batch simulator's vectorised step over a whole fleet. Medians of repeated
timings, one core.

    OMP_NUM_THREADS=1 .venv/bin/python bench/core_step.py
"""
from __future__ import annotations

import os
import timeit

os.environ.setdefault('OMP_NUM_THREADS', '1')
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from bearing_pose_estimation.core import so3  # noqa: E402
from bearing_pose_estimation.estimators.base import Edges  # noqa: E402
from bearing_pose_estimation.estimators.boughellaba_tayebi import (  # noqa: E402
    CascadeGains, cascade_step)


def straightforward(R_hat, p_hat, delta_R, h, b_body, d_world, p_nbr, k, k_R, k_p):
    """Eq. (3) and (23), one agent, written plainly."""
    sigma = np.zeros(3)
    pull = np.zeros(3)
    for b, d, pj, kij in zip(b_body, d_world, p_nbr, k):
        y = R_hat @ b
        sigma += kij * np.cross(d, y)
        P = np.eye(3) - np.outer(y, y) / (y @ y)
        pull += P @ (p_hat - pj)
    Q = Rotation.from_rotvec(-h * k_R * sigma).as_matrix()
    return Q @ R_hat @ delta_R, Q @ (p_hat - h * k_p * pull)


def median_us(fn, repeat: int = 7, number: int = 2000) -> float:
    return 1e6 * float(np.median(timeit.repeat(fn, repeat=repeat, number=number))) / number


def main() -> None:
    rng = np.random.default_rng(0)
    gains = CascadeGains()
    h = 0.01
    print('| neighbours | straightforward [us] | cascade_step, one agent [us] | ratio |')
    print('|---|---|---|---|')
    for n in (2, 3, 5, 10, 20):
        R = so3.exp(rng.normal(size=3))
        p = rng.normal(size=3)
        dR = so3.exp(0.01 * rng.normal(size=3))
        b = rng.normal(size=(n, 3))
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pj = rng.normal(size=(n, 3))
        k = np.ones(n)
        edges = Edges(agent=np.zeros(n, dtype=np.intp), k=k, n_agents=1)
        a = straightforward(R, p, dR, h, b, d, pj, k, 1.0, 1.0)
        R1, p1, _ = cascade_step(R[None], p[None], dR[None], h, edges, b, d, pj, gains)
        assert np.allclose(a[0], R1[0], atol=1e-12) and np.allclose(a[1], p1[0])
        plain = median_us(lambda: straightforward(R, p, dR, h, b, d, pj, k, 1.0, 1.0))
        ours = median_us(lambda: cascade_step(R[None], p[None], dR[None], h, edges, b, d, pj,
                                              gains))
        print(f'| {n} | {plain:.1f} | {ours:.1f} | {plain / ours:.2f} |', flush=True)


if __name__ == '__main__':
    main()
