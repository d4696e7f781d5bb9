"""An agent's health as its node reports it (``/diagnostics``, the end-of-run log line): a
pure function of the runtime's counters and the node's own (rejected inputs, time events)."""
from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass

import numpy as np

from .agent import AgentRuntime

OK, WARN = 0, 1   # diagnostic_msgs/DiagnosticStatus levels
# The end-of-run count of steps that went without an awaited input (0 or a dict; benchmarks).
INCOMPLETE_LOG = re.compile(r'steps without an awaited input: (\{[^}]*\}|0)')


@dataclass(frozen=True)
class Health:
    level: int
    message: str
    values: dict[str, str]


def health(rt: AgentRuntime | None, rejected: Counter[str], events: Counter[str],
           steps_per_second: float | None = None) -> Health:
    """The report: state time, step rate, edges used, silent neighbours, the local matrix's
    spectrum and verdict, the method's own values, each neighbour's clock lead
    (``clock_lead_<name>_s``, ``clock_ahead_<name>``), what steps went without, rejections by
    cause, time events. WARN for silent neighbours, a spectrum the method's proof objects to, a
    clock lead beyond ``max_clock_lead``, or rejections."""
    values = {'state_time_s': 'n/a'}
    level, problems = OK, list[str]()
    if rt is not None:
        values['state_time_s'] = f'{rt.t:.3f}'
        if steps_per_second is not None:
            values['steps_per_wall_second'] = f'{steps_per_second:.1f}'
        if not rt.leader:
            stale = rt.stale_neighbours(rt.t)
            values['stale_neighbours'] = ','.join(stale)
            values['edges_used'] = str(rt.last.edges_used)
            if stale:
                level, problems = WARN, problems + ['stale neighbours']
            eig = rt.conditioning()
            if eig is not None:
                values['conditioning_eigenvalues'] = ','.join(f'{e:.4g}' for e in eig)
                problem = rt.estimator.conditioning_problem(eig)
                if problem is not None:
                    level = max(level, WARN)
                    problems.append(problem)
            for label, texts in rt.estimator.neighbour_report(rt.x, len(rt.peers)).items():
                for peer, text in zip(rt.peers, texts):
                    values[f'{label}_{peer.name}'] = text
            stages = rt.estimator.stages
            for key, value in rt.last.diagnostics.items():
                if key == 'stage' and stages:
                    values['stage'] = stages[int(value)]
                elif np.ndim(value) == 0:
                    values[key] = f'{float(value):.4g}'
            for what, n in sorted((+rt.missing).items()):
                values[f'missing_{what}'] = str(n)
            values['carried'] = str(rt.carried)   # late values carried to their instant
            values['unpaired'] = str(rt.unpaired)   # newest values used for their instant's
            if rt.warm_note:
                values['warm_start'] = rt.warm_note
            for peer in rt.peers:   # neighbours left out after announcing a reset
                if rt.resets[peer.name]:
                    values[f'resets_{peer.name}'] = str(rt.resets[peer.name])
                    values[f'left_out_{peer.name}'] = (f'{rt.distrusted[peer.name]} steps'
                                                       + ' (now)' * peer.reset)
            values['incomplete_steps'] = str(sum(rt.incomplete.values()))
        limit = rt.limits.max_clock_lead
        ahead = {name: lead for name, lead in rt.leads.items() if lead > limit}
        for name, lead in sorted(rt.leads.items()):
            values[f'clock_lead_{name}_s'] = f'{lead:.4f}'
            values[f'clock_ahead_{name}'] = str(rt.ahead[name])
        if ahead:
            level = max(level, WARN)
            problems.append('clock ahead of ours: ' + ', '.join(
                f'{name} by {lead:.3f} s' for name, lead in sorted(ahead.items()))
                + f' (max_clock_lead {limit:g} s)')
        values['non_finite_steps'] = str(rt.non_finite_steps)
        values['gyro_gaps_bridged'] = str(rt.gyro.bridged)
        if rt.uses_odometry:
            values['odometry_gaps_bridged'] = str(rt.odometry.bridged)
            values['odometry_live'] = str(rt.odometry_live())
            values['odometry_missing_steps'] = str(rt.odometry_missing_steps)
    for cause, n in sorted(rejected.items()):
        values[f'rejected_{cause}'] = str(n)
    for cause, n in sorted(events.items()):
        values[f'event_{cause}'] = str(n)
    if rejected:
        level = max(level, WARN)
        problems.append(f'{sum(rejected.values())} input(s) rejected')
    return Health(level, '; '.join(problems) or 'ok', values)


def summary(rt: AgentRuntime, rejected: Counter[str], events: Counter[str],
            wall: float) -> str:
    """What an agent achieved, for the end of its log: steps, their rate in wall time, what
    was rejected, bridged, waited for, left out and carried, and the neighbours' inputs
    stamped more than ``max_clock_lead`` ahead of its clock."""
    return (f'{rt.k} steps ({rt.k * rt.h:.2f} s of state time) in {wall:.1f} s wall: '
            f'{rt.k / max(wall, 1e-9):.1f} steps/s; rejected: {dict(rejected) or 0}; events: '
            f'{dict(events) or 0}; lost-sample gaps bridged: gyro {rt.gyro.bridged}, odometry '
            f'{rt.odometry.bridged}; warm starts: {dict(rt.warm_starts) or 0}; neighbour resets: '
            f'{dict(rt.resets) or 0}; unpaired '
            f'neighbour values: {rt.unpaired}; waited for: '
            f'{dict(rt.waits) or 0}; left out: {dict(+rt.missing) or 0}; carried: {rt.carried}; '
            f'inputs of clocks ahead of ours: {dict(rt.ahead) or 0}; '
            f'steps without an awaited input: {dict(rt.incomplete) or 0}')
