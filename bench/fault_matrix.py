"""Fault matrix: what each network fault costs on the paper's 8-agent scenario.

Runs the distributed estimators without DDS (bearing_pose_estimation.netsim: the same
AgentEstimator as the node, fed like the simulator node feeds it) with one fault per row, and
compares with the fault-free run at the same instants. Deterministic; prints a Markdown table.

    .venv/bin/python bench/fault_matrix.py [--duration 60]

recovery: time after the fault ends until both mean errors are back below their values just
before it began (outages only). cost: how many seconds of convergence the fault lost by the
end, i.e. the end time minus the time at which the fault-free run had the same mean attitude
error.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bearing_pose_estimation.netsim import LinkFaults, Outage, run_network
from bearing_pose_estimation.scenario import load_scenario

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'

# (label, run_network arguments, outage (start, end) or None)
ROWS = [
    ('none (reference)', {}, None),
    ('30 % of neighbour messages lost', dict(links=LinkFaults(drop_rate=0.3, seed=1)), None),
    ('neighbour messages 200 ms late', dict(links=LinkFaults(delay=0.2)), None),
    ('30 % lost and 200 ms late', dict(links=LinkFaults(drop_rate=0.3, delay=0.2, seed=1)), None),
    ('agent_4 cut off 20-25 s (partition)',
     dict(outages=(Outage('agent_4', 20.0, 25.0, restart=False),)), (20.0, 25.0)),
    ('agent_4 killed at 20 s, restarted at 25 s',
     dict(outages=(Outage('agent_4', 20.0, 25.0, restart=True),)), (20.0, 25.0)),
    ('agent_7 joins late, at 10 s', dict(outages=(Outage('agent_7', 0.0, 10.0),)), (0.0, 10.0)),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--duration', type=float, default=60.0)
    args = ap.parse_args()
    scenario = load_scenario(PAPER)
    ref = None
    print('| fault | mean att. error at end [rad] | mean pos. error at end [m] | '
          'recovery after the fault [s] | cost at the end [s] | non-finite estimates |')
    print('|---|---|---|---|---|---|')
    for label, kwargs, outage in ROWS:
        rec = run_network(scenario, args.duration, record_every=0.5, **kwargs)
        att, pos = rec.att_err.mean(axis=1), rec.pos_err.mean(axis=1)
        if ref is None:
            ref = att
        bad = ~np.isfinite(rec.att_err).all(axis=1) | ~np.isfinite(rec.pos_err).all(axis=1)
        recovery = 'n/a'
        if outage is not None:
            k0 = np.searchsorted(rec.t, outage[0])
            back = np.flatnonzero((rec.t >= outage[1]) & (att <= att[k0]) & (pos <= pos[k0]))
            recovery = f'{rec.t[back[0]] - outage[1]:.1f}' if back.size else 'not by the end'
        # First time the reference was as good as this run's end (to the 0.5 s record step).
        k = np.flatnonzero(ref <= att[-1])
        cost = rec.t[-1] - rec.t[k[0]] if k.size else 0.0  # no worse than the reference
        print(f'| {label} | {att[-1]:.2e} | {pos[-1]:.2e} | {recovery} | {cost:.1f} | '
              f'{int(bad.sum())} |', flush=True)


if __name__ == '__main__':
    main()
