"""config/de_carli_8_quadrotors.yaml is the notes' explicit scenario
(data/de-carli-2024-scenario.json, De Carli et al. Sec. IV) in the scenario format, number for
number: graph, gains, rates, duration, controller, formation, yaw splines, initial state and
estimates; the parsed scenario rebuilds the JSON's derived values (spline coefficients, ẑ(0),
pair states, first relative-position estimates) to rounding."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml
import pytest

from bearing_pose_estimation.core.motion import YawSplines
from bearing_pose_estimation.estimators.base import edge_table
from bearing_pose_estimation.estimators.de_carli import DeCarli
from bearing_pose_estimation.scenario import load_scenario, parse_scenario
from bearing_pose_estimation.scenario.parse import read_scenario_data
from bearing_pose_estimation.sim.batch import BatchSimulator

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / 'config' / 'de_carli_8_quadrotors.yaml'
JSON = json.loads((ROOT / 'test' / 'data' / 'de-carli-2024-scenario.json').read_text())


@pytest.fixture(scope='module')
def scenario():
    return load_scenario(CONFIG)


def test_every_number_is_the_json_s(scenario):
    s, d = scenario, JSON
    assert len(s.agents) == d['n_robots']
    edges = [[s.index[a.name], s.index[nb.name]] for a in s.agents for nb in a.neighbours]
    assert sorted(edges) == sorted(d['sensing_edges'])
    g = s.gains
    assert (g.k_pe, g.k_psi, g.k_z, g.k_p) == tuple(d['gains'][k] for k in
                                                     ('k_pe', 'k_psi', 'k_z', 'k_p'))
    r = d['rates_hz']
    assert (s.frequency, g.yaw_rate, g.position_rate) == (
        r['relative_yaw_observer'], r['yaw_observer'], r['position_observer'])
    assert s.duration == d['duration_s'] and s.formation.mode == d['motion_mode']
    c = d['controller']
    assert (s.formation.k_c, s.formation.nu_max) == (c['k_c'], c['nu_max_mps'])
    assert [list(a.formation_position) for a in s.agents] == c['p_star_m']
    y = d['yaw_trajectory']
    for i, a in enumerate(s.agents):
        assert list(a.yaw.knots) == y['knots_s'] and list(a.yaw.values) == y['knot_values_rad'][i]
    assert [list(a.position) for a in s.agents] == d['initial_state']['p_m']
    ie = d['initial_estimates']
    assert [list(a.initial_position) for a in s.agents] == ie['p_hat_m']
    psi_hat = [np.arctan2(a.initial_attitude[1, 0], a.initial_attitude[0, 0]) for a in s.agents]
    np.testing.assert_allclose(psi_hat, ie['psi_hat_rad'], rtol=0, atol=1e-15)


def test_the_derived_values_are_rebuilt(scenario):
    """The spline's per-interval coefficients, ψ_i(0), ẑ(0), each pair's initial relative yaw
    (the rule conj(ẑ_a(0)) ẑ_b(0), after the first step's rotation) and that every owned
    edge's relative estimate started."""
    d, y = JSON, JSON['yaw_trajectory']
    splines = YawSplines([a.yaw for a in scenario.agents])
    for t in (0.0, 0.7, 3.1, 19.99):
        k = int(t // 2.0)
        s = t - y['knots_s'][k]
        expected = [np.polyval(y['coefficients'][i][k], s) for i in range(d['n_robots'])]
        np.testing.assert_allclose(splines(t), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(splines(0.0), d['initial_state']['psi_rad'], atol=1e-15)
    sim = BatchSimulator(scenario)
    z0 = np.array(d['initial_estimates']['z_hat']) @ [1.0, 1j]
    np.testing.assert_allclose(sim.x.z_hat, z0, rtol=0, atol=1e-15)
    sim.step()   # the pairs and the relative estimates start at the first step
    links = {'agent': sim.table.agent, 'other': sim.table.other, **sim.table.flags}
    pairs = np.array(d['initial_estimates']['z_psi_hat']) @ [1.0, 1j]
    for m, (a, b) in enumerate(d['communication_pairs']):
        ends = {a, b}
        e = next(k for k in range(len(links['agent'])) if links['owns'][k]
                 and {int(links['agent'][k]), int(links['other'][k])} == ends)
        owner, other = int(links['agent'][e]), int(links['other'][e])
        # Rotated over the first step by the relative yaw increment, from the JSON's value.
        first = pairs[m] if owner == a else np.conj(pairs[m])
        dpsi = splines(sim.h) - splines(0.0)
        first = first * np.exp(1j * (dpsi[other] - dpsi[owner]))
        got = sim.x.z_pair[owner, sim.edges.slot[e]]
        # The first correction's regressor is the previous step's displacement: 0.
        assert abs(got - first) < 1e-12
    assert np.all(sim.x.ready_out[links['agent'][links['owns']],
                                  sim.edges.slot[links['owns']]])


def test_the_relative_position_estimates_start_at_the_first_measurement(scenario):
    rel = np.array(JSON['initial_estimates']['p_rel_hat_m'])
    sim = BatchSimulator(scenario)
    for k, (i, j) in enumerate(JSON['sensing_edges']):
        measured = sim.truth.relative_positions(np.array([i]), np.array([j]))[0]
        np.testing.assert_allclose(measured, rel[k], rtol=0, atol=1e-12)


def test_the_communication_graph_is_the_json_s_pairs():
    tail, head = np.array(JSON['sensing_edges']).T
    table = edge_table(DeCarli, JSON['n_robots'], tail, head, np.ones(len(tail)))
    links = {'agent': table.agent, 'other': table.other, **table.flags}
    pairs = {tuple(sorted(p)) for p in zip(links['agent'].tolist(), links['other'].tolist())}
    assert sorted(pairs) == [tuple(p) for p in JSON['communication_pairs']]
    owned = {(int(a), int(b)) for a, b, o in zip(links['agent'], links['other'], links['owns'])
             if o}
    assert len(owned) == len(JSON['communication_pairs'])   # one owner per pair
    assert (0, 1) in owned and (5, 6) in owned   # the two-way pairs: the lower id


def test_edits_take_effect_and_knots_out_of_order_are_refused():
    """The file is a scenario like any other: a changed knot value is the scenario's, and
    knots out of order are refused with the field named."""
    data = read_scenario_data(CONFIG)
    data['agents'][0]['yaw']['values'][1] += 0.1
    assert parse_scenario(data).agents[0].yaw.values[1] == pytest.approx(
        JSON['yaw_trajectory']['knot_values_rad'][0][1] + 0.1)
    data['yaw_knots'][2] = 1.0
    with pytest.raises(Exception, match=r'robot_0\)\.yaw\.knots: the knots must increase'):
        parse_scenario(data)


def _edited(edit) -> dict:
    data = read_scenario_data(CONFIG)
    edit(data)
    return data


@pytest.mark.parametrize('edit, field, problem', [
    (lambda d: d['agents'][0]['yaw']['values'].pop(), r'agents\[0\] \(robot_0\)\.yaw\.values',
     '31 values for 32 knots'),
    (lambda d: d.pop('yaw_knots'), r'agents\[0\] \(robot_0\)\.yaw\.knots',
     'no top-level `yaw_knots`'),
    (lambda d: d['agents'][1].pop('yaw'), r'agents\[1\] \(robot_1\)\.yaw',
     'every agent follows a yaw spline or none'),
    (lambda d: d['agents'][2].update(attitude='identity'), r'robot_2\)\.attitude',
     'a yaw spline sets the attitude'),
    (lambda d: d.pop('formation_control'), r'robot_0\)\.formation_position',
     'no `formation_control:` block'),
    (lambda d: d['agents'][3].update(velocity={'world': [0.1, 0, 0]}),
     r'robot_3\)\.velocity', 'the formation controller sets the velocity'),
    (lambda d: d['formation_control'].update(mode='closed'), r'formation_control\.mode',
     "unknown mode 'closed'"),
    (lambda d: d['formation_control'].update(nu_max=0), r'formation_control\.nu_max',
     'must be > 0'),
    (lambda d: d['gains'].update(k_ij=1.0), r'gains\.k_ij', 'unknown key'),
    (lambda d: d.update(leaders=['robot_0', 'robot_1']), 'leaders', 'has no leaders'),
])
def test_bad_fields_are_named_with_the_fix(edit, field, problem):
    with pytest.raises(Exception, match=rf'{field}: .*{problem}.*Fix:'):
        parse_scenario(_edited(edit))


def test_check_refuses_what_breaks_the_method():
    """A disconnected robot, a rate that does not divide the frequency, and a position gain
    whose Euler correction diverges are errors naming the field; a static fleet (no motion at
    all) gets one warning per pair."""
    from bearing_pose_estimation.scenario import check_scenario

    def cut(d):
        d['agents'][7]['neighbours'] = []
        for a in d['agents']:
            a['neighbours'] = [n for n in a.get('neighbours', []) if n != 'robot_7']

    errors = check_scenario(parse_scenario(_edited(cut))).errors
    assert [(e.agent, e.field) for e in errors] == [('robot_7', 'neighbours')]
    rate = check_scenario(parse_scenario(_edited(lambda d: d['gains'].update(yaw_rate=30.0))))
    assert [(e.agent, e.field) for e in rate.errors] == [('gains', 'yaw_rate')]
    unstable = check_scenario(parse_scenario(_edited(lambda d: d['gains'].update(k_p=20.0))))
    assert [(e.agent, e.field) for e in unstable.errors] == [('gains', 'k_p')]
    assert 'diverges' in unstable.errors[0].problem

    def static(d):
        d.pop('formation_control')
        for a in d['agents']:
            a.pop('formation_position')

    report = check_scenario(parse_scenario(_edited(static)))
    assert report.ok and sum('never excited' in w.problem for w in report.warnings) == 12


def test_the_noisy_scenario_is_this_one_with_noise():
    """config/de_carli_noisy.yaml: everything but name, description, noise and the sensors'
    std is this file's."""
    quiet = yaml.safe_load(CONFIG.read_text())
    noisy = yaml.safe_load((ROOT / 'config' / 'de_carli_noisy.yaml').read_text())
    assert noisy.pop('noise') == {'gyro_std': 0.005, 'seed': 0}
    for name in ('odometry', 'relative_positions'):
        assert noisy['sensors'][name].pop('std') == 0.02
    for key in ('name', 'description'):
        assert noisy.pop(key) != quiet.pop(key)
    assert noisy == quiet
