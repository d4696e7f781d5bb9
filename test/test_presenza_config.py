"""config/presenza_case{1,2}.yaml are the notes' explicit Section V
(data/presenza-2026-scenarios.json) number for number: graph, anchor and ranged robots,
gains, step, duration, velocities, world poses, initial estimates; the parsed scenarios rebuild
the JSON's derived values (anchor-frame truth, sensing and free robots, angle count) and the
margins the notes quote at t = 0 (§2, §3, §7, §9)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bearing_pose_estimation.scenario import check_scenario, initial_estimates, load_scenario
from bearing_pose_estimation.scenario.model import initial_truth

ROOT = Path(__file__).resolve().parents[1]
JSON = json.loads((ROOT / 'test' / 'data' / 'presenza-2026-scenarios.json').read_text())
CASES = ('case1', 'case2')


def load(case):
    return load_scenario(ROOT / 'config' / f'presenza_{case}.yaml')


def value(profile, t):
    return np.array([profile.components[k].constant + sum(
        term.amplitude * np.sin(term.frequency * t + term.phase)
        for term in profile.components[k].terms) for k in range(3)])


def json_value(spec, t):
    out = np.zeros(3)
    for axis, terms in enumerate(spec['components']):
        for term in terms:
            f = {'const': lambda _: 1.0, 'cos': np.cos, 'sin': np.sin}[term['fn']]
            out[axis] += term['amp'] * (1.0 if term['fn'] == 'const' else f(term['w'] * t))
    return out


@pytest.mark.parametrize('case', CASES)
def test_every_number_is_the_json_s(case):
    s, c = load(case), JSON['cases'][case]
    assert [s.index[a.name] + 1 for a in s.agents] == c['robots']
    assert s.index[s.anchor] + 1 == c['anchor'] and not s.anchor_pinned
    assert [s.index[r] + 1 for r in s.ranged] == [c['ranged_robots']['b'],
                                                  c['ranged_robots']['c']]
    for a in s.agents:
        k = str(s.index[a.name] + 1)
        assert [s.index[nb.name] + 1 for nb in a.neighbours] == c['out_neighbours'][k]
        w, e, v = c['initial_truth_world'][k], c['initial_estimates'][k], c['velocities'][k]
        assert list(a.position) == w['p']
        np.testing.assert_allclose(Rotation.from_matrix(a.attitude).as_rotvec(), w['R_rotvec'],
                                   rtol=0, atol=1e-14)
        assert list(a.initial_position) == e['q_hat']
        np.testing.assert_allclose(a.initial_attitude,
                                   Rotation.from_quat(e['Q_hat_quat_xyzw']).as_matrix(),
                                   rtol=0, atol=1e-15)
        frame = {'body': 'body', 'anchor_via_own_estimate': 'anchor_estimate'}[v['u']['frame']]
        assert a.velocity.frame == frame
        for t in (0.0, 0.7, 3.1, 12.9):
            # cos is stored as sin(w t + π/2): equal to rounding
            np.testing.assert_allclose(value(a.velocity.value, t), json_value(v['u'], t),
                                       rtol=0, atol=4e-15)
            np.testing.assert_allclose(value(a.angular_velocity, t),
                                       json_value(v['omega'], t), rtol=0, atol=4e-15)
    g = c['gains']
    assert (s.gains.kappa_q, s.gains.kappa_s) == (g['kappa_q'], g['kappa_s'])
    assert s.gains.kappa_Q_sensing == s.gains.kappa_Q_free == g['kappa_Q']
    assert s.gains.preconditioning == 0.0   # the paper's explicit update
    assert s.step == c['time']['step_s'] and s.duration == c['time']['duration_s']


@pytest.mark.parametrize('case', CASES)
def test_the_derived_values_are_rebuilt(case):
    s, c = load(case), JSON['cases'][case]
    R, q = initial_truth(s)
    for a in s.agents:
        k = str(s.index[a.name] + 1)
        t = c['initial_truth_anchor_frame'][k]
        np.testing.assert_allclose(q[s.index[a.name]], t['q'], rtol=0, atol=1e-12)
        np.testing.assert_allclose(R[s.index[a.name]],
                                   Rotation.from_quat(t['Q_quat_xyzw']).as_matrix(),
                                   rtol=0, atol=1e-12)
    R_hat, q_hat = initial_estimates(s)
    a = s.index[s.anchor]
    assert np.all(q_hat[a] == 0.0) and np.all(R_hat[a] == np.eye(3))
    d = c['derived']
    sensing = [s.index[x.name] + 1 for x in s.agents if len(x.neighbours) >= 2]
    assert sensing == d['sensing_robots']
    report = check_scenario(s)
    assert report.ok, report.format()
    assert report.margins['angles |A|'] == d['angles']


def test_the_margins_are_the_notes():
    """§2: σ_{3N-7}/σ_1 0.055 / 0.040; §3: A3 0.100, A5 0.81 / 0.21, L2 0.070, 0.39, 0.43 /
    0.39, 0.97; §8: κ_q λ(H) in [0.26, 58.5] / [0.038, 41] 1/s; §9: the explicit step limit
    17.9 / 20.3 ms."""
    one, two = check_scenario(load('case1')), check_scenario(load('case2'))
    m1, m2 = one.margins, two.margins
    rel = 'angle rigidity σ_{3N-7}/σ_1 (normalised)'
    assert round(m1[rel], 3) == 0.055 and round(m2[rel], 3) == 0.040
    assert round(m1['A3 λ_min(Π(β_ab) + Π(β_ac))'], 3) == 0.100
    assert round(one.spectra['robot_1'][0], 2) == 0.81
    assert round(min(two.spectra[f'robot_{k}'][0] for k in (1, 2, 3)), 2) == 0.21
    assert [round(one.spectra[f'robot_{k}'][0], 2) for k in (3, 4, 5)] == [0.07, 0.39, 0.43]
    assert [round(two.spectra[f'robot_{k}'][0], 2) for k in (4, 5)] == [0.39, 0.97]
    assert round(m1['κ_q λ_1(H) [1/s]'], 2) == 0.26 and round(m1['κ_q λ_max(H) [1/s]'], 1) == 58.5
    assert round(m2['κ_q λ_1(H) [1/s]'], 3) == 0.038 and round(m2['κ_q λ_max(H) [1/s]']) == 41
    assert round(m1['explicit update step limit [s]'] * 1e3, 1) == 17.9
    assert round(m2['explicit update step limit [s]'] * 1e3, 1) == 20.3
