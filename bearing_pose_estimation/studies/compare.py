"""Several estimators on one scenario, side by side (``bearing-pose compare``); no rclpy. Every
method runs with the same truth, initial estimates and noise seed (:func:`method_data`)."""
from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import estimators
from ..estimators.base import Sensor, format_gains, gain_fields
from ..metrics.results import Recording
from ..scenario.model import Scenario
from ..scenario.parse import EDGE_GAIN, parse_scenario
from ..sim.batch import BatchSimulator
from .summary import ATT_THRESHOLD_RAD, POS_THRESHOLD_M, quantities, when, write_rows

OUTPUT_FILES = ('compare.csv', 'compare.md', 'compare_errors.png')


@dataclass(frozen=True)
class Run:
    """One method's errors on the scenario, from the batch simulator or over DDS."""

    method: str
    mode: str            # 'batch' or 'dds'
    scenario: Scenario   # the derived scenario this run used
    rec: Recording

    @property
    def label(self) -> str:
        return self.method if self.mode == 'batch' else f'{self.method} (DDS)'


def parse_gain_overrides(texts: list[str]) -> dict[str, dict[str, float]]:
    """``['tran_anderson_ahn:k_omega=3,k_c=2', ...]`` → ``{method: {gain: value}}``, or
    ValueError naming the bad text and the fix."""
    out: dict[str, dict[str, float]] = {}
    for text in texts:
        method, sep, assignments = text.partition(':')
        if not sep or method not in estimators.methods():
            raise ValueError(f'--gains {text!r}: expected METHOD:GAIN=VALUE[,GAIN=VALUE...] with '
                             f'METHOD one of {", ".join(estimators.methods())}')
        fields = {f.name: f for f in gain_fields(estimators.get(method).Gains)}
        allowed = sorted(fields)
        for item in assignments.split(','):
            key, eq, value = item.partition('=')
            key = key.strip()
            if not eq or key not in allowed:
                raise ValueError(f'--gains {text!r}: {key or item!r} is not a gain of {method}; '
                                 f'use one of {", ".join(allowed)} ({EDGE_GAIN} is per edge: set '
                                 'it in the scenario file)')
            try:
                number = float(value)
            except ValueError:
                number = math.nan
            zero_ok = fields[key].metadata.get('zero_allowed', False)  # 0 switches it off
            if not (math.isfinite(number) and (number > 0 or (zero_ok and number == 0))):
                raise ValueError(f'--gains {text!r}: {key} must be a '
                                 f'{"non-negative" if zero_ok else "positive"} number, '
                                 f'got {value!r}')
            out.setdefault(method, {})[key] = number
    return out


def incompatible(scenario: Scenario, method: str) -> str | None:
    """Why ``method`` cannot run on ``scenario`` (roles, or a sensor not simulated), or None."""
    cls = estimators.get(method)
    roles = _roles(scenario)
    if cls.roles.leaders and cls.roles.leaders != len(roles.get('leaders', ())):
        return (f'it needs {cls.roles.leaders} leaders, the scenario has '
                f'{len(roles.get("leaders", ()))} (give them under `other_roles: {{leaders: '
                '[...]}}` for a method without leaders)')
    if cls.roles.anchor and 'anchor' not in roles:
        return ('it needs an anchor (give it under `other_roles: {anchor: {agent: ..., '
                'ranged: [..., ...]}}` for a method without one)')
    always = {Sensor.GYRO, Sensor.BEARINGS, Sensor.KNOWN_POSE}
    missing = sorted(s.value for s in cls.sensors - always if not scenario.provides(s.value))
    if missing:
        return (f'it needs {", ".join(missing)}, which the scenario does not simulate (list '
                'them under `sensors:`)')
    return None


def _roles(scenario: Scenario) -> dict[str, Any]:
    """Every role the scenario gives (its method's and ``other_roles``), as a file writes them."""
    roles = dict(scenario.other_roles)
    if scenario.leaders:
        roles['leaders'] = list(scenario.leaders)
    if scenario.anchor is not None:
        roles['anchor'] = {'agent': scenario.anchor, 'ranged': list(scenario.ranged),
                           'pinned': scenario.anchor_pinned}
    return roles


def compatible_methods(scenario: Scenario) -> tuple[list[str], dict[str, str]]:
    """The methods that can run on ``scenario`` (its own first), and why each other cannot."""
    why = {m: incompatible(scenario, m) for m in estimators.methods() if m != scenario.method}
    return ([scenario.method] + [m for m, r in why.items() if r is None],
            {m: r for m, r in why.items() if r is not None})


def method_data(data: Mapping[str, Any], scenario: Scenario, method: str,
                overrides: Mapping[str, float] | None = None) -> dict[str, Any]:
    """The file's ``data`` (parsed: ``scenario``) run by ``method``: its roles at the top level,
    others under ``other_roles``, every gain it reads (then ``overrides``) and the ``k_ij``."""
    derived = copy.deepcopy(dict(data))
    derived['method'] = method
    cls = estimators.get(method)
    uses = {'leaders': cls.roles.leaders > 0, 'anchor': cls.roles.anchor}
    roles = _roles(scenario)
    for key in ('leaders', 'anchor', 'other_roles'):
        derived.pop(key, None)
    derived.update({k: v for k, v in roles.items() if uses[k]})
    others = {k: v for k, v in roles.items() if not uses[k]}
    if others:
        derived['other_roles'] = others
    gains = dataclasses.asdict(scenario.with_method(method, **(overrides or {})).gains)
    if EDGE_GAIN in (data.get('gains') or {}):
        gains[EDGE_GAIN] = data['gains'][EDGE_GAIN]
    derived['gains'] = gains
    return derived


def method_scenarios(data: Mapping[str, Any], scenario: Scenario, methods: list[str],
                     overrides: Mapping[str, Mapping[str, float]] | None = None
                     ) -> dict[str, tuple[dict[str, Any], Scenario]]:
    """Per method: the derived file content and the scenario parsed from it."""
    for m in methods:
        estimators.get(m)  # ScenarioError naming the known methods
    out = {}
    for m in methods:
        d = method_data(data, scenario, m, (overrides or {}).get(m))
        out[m] = (d, parse_scenario(d, source=f'{scenario.source} (method {m})'))
    return out


def run_batch(scenarios: Mapping[str, Scenario], duration: float,
              record_every: float = 0.1) -> list[Run]:
    """One batch run per method; every run starts from the same state."""
    return [Run(m, 'batch', s, BatchSimulator(s).run(duration, record_every=record_every))
            for m, s in scenarios.items()]


def rows(runs: list[Run]) -> list[dict[str, Any]]:
    """Per run: method, mode, gains, duration and every quantity of :mod:`.summary`."""
    return [{'method': run.method, 'mode': run.mode, 'gains': format_gains(run.scenario.gains),
             'duration_s': float(run.rec.t[-1]), **quantities(run.rec)} for run in runs]


def write_csv(runs: list[Run], path: Path) -> None:
    """``t`` then each run's mean attitude [rad] and position [m] errors, on the batch runs'
    time grid (DDS runs interpolated onto it)."""
    t = runs[0].rec.t
    series = [np.interp(t, r.rec.t, e.mean(axis=1), right=np.nan)
              for r in runs for e in (r.rec.att_err, r.rec.pos_err)]
    write_rows(path, ['t'] + [f'{r.method}{"" if r.mode == "batch" else "_dds"}_{q}' for r in runs
                              for q in ('attitude_error_mean_rad', 'position_error_mean_m')],
               ([f'{tk:.6f}'] + [f'{s[k]:.9e}' for s in series] for k, tk in enumerate(t)))


def table(rows_: list[dict[str, Any]]) -> str:
    """The comparison as a Markdown table."""
    lines = ['| method | run | gains | at [s] | mean attitude error [rad] | mean position error '
             f'[m] | attitude < {ATT_THRESHOLD_RAD:g} rad from | position < {POS_THRESHOLD_M:g} '
             'm from |', '|---|---|---|---|---|---|---|---|']
    for r in rows_:
        lines.append(f"| {r['method']} | {r['mode']} | {r['gains']} | {r['duration_s']:g} | "
                     f"{r['final_attitude_error_mean_rad']:.3e} | "
                     f"{r['final_position_error_mean_m']:.3e} | "
                     f"{when(r['attitude_below_1e-3_rad_from_s'])} | "
                     f"{when(r['position_below_1e-2_m_from_s'])} |")
    return '\n'.join(lines) + '\n'
