"""What the covariance costs: one agent's step (what the estimator node calls) with the
covariance against the same step's estimate alone, and the same for the batch simulator's
fleet step on the paper's eight agents. Medians of repeated timings, one core.

    OMP_NUM_THREADS=1 .venv/bin/python bench/covariance_cost.py
"""
from __future__ import annotations

import os
import sys
import timeit
from pathlib import Path

os.environ.setdefault('OMP_NUM_THREADS', '1')
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bearing_pose_estimation.estimators.boughellaba_tayebi import cascade_step  # noqa: E402
from bearing_pose_estimation.estimators.tran_anderson_ahn import tran_step  # noqa: E402
from bearing_pose_estimation.scenario import load_scenario  # noqa: E402
from bearing_pose_estimation.sim.batch import BatchSimulator  # noqa: E402


def median_us(fn, number: int = 200, repeat: int = 9) -> float:
    return float(np.median(timeit.repeat(fn, number=number, repeat=repeat)) / number * 1e6)


def main() -> None:
    print('| method | what | with the covariance [µs] | estimate alone [µs] | ratio |')
    print('|---|---|---|---|---|')
    for method in ('boughellaba_tayebi', 'tran_anderson_ahn'):
        s = load_scenario(ROOT / 'config' / 'paper_noisy.yaml').with_method(method)
        sim = BatchSimulator(s)
        for _ in range(50):
            sim.step()
        est, x, inputs = sim.estimator, sim.x, sim.inputs()
        d_world, p_nbr = est.neighbour_terms(inputs)
        g = est.gains
        if method == 'boughellaba_tayebi':
            def alone(x=x, inputs=inputs):
                return cascade_step(x.R_hat, x.p_hat, inputs.delta_R, sim.h, inputs.edges,
                                    inputs.bearings, d_world, p_nbr, g)
        else:
            pairs = est.pairs(inputs.edges)

            def alone(x=x, inputs=inputs):
                return tran_step(x.R_hat, x.Omega_tilde, x.p_hat, inputs.delta_R, sim.h,
                                 inputs.edges, pairs, inputs.bearings, d_world, p_nbr, g)
        fleet = (median_us(lambda: est.step(x, sim.h, inputs)), median_us(alone))
        i = s.index['agent_6']           # three neighbours
        one, x1 = inputs.agent(i), x.rows(slice(i, i + 1))
        d1, p1 = est.neighbour_terms(one)
        if method == 'boughellaba_tayebi':
            def alone1():
                return cascade_step(x1.R_hat, x1.p_hat, one.delta_R, sim.h, one.edges,
                                    one.bearings, d1, p1, g)
        else:
            pairs1 = est.pairs(one.edges)

            def alone1():
                return tran_step(x1.R_hat, x1.Omega_tilde, x1.p_hat, one.delta_R, sim.h,
                                 one.edges, pairs1, one.bearings, d1, p1, g)
        agent = (median_us(lambda: est.step(x1, sim.h, one)), median_us(alone1))
        for what, (a, b) in (('fleet step, 8 agents', fleet), ('one agent, 3 neighbours',
                                                                 agent)):
            print(f'| {method} | {what} | {a:.0f} | {b:.0f} | {a / b:.1f} |')


if __name__ == '__main__':
    main()
