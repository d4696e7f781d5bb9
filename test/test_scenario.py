"""Scenario files: the paper's Section V exactly, and clear errors for bad input."""
import copy
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.scenario import check_scenario
from bearing_pose_estimation.scenario import (ScenarioError, initial_estimates, load_scenario,
                                              parse_scenario)

CONFIG = Path(__file__).resolve().parents[1] / 'config'
PAPER = CONFIG / 'paper_8_agents.yaml'


@pytest.fixture()
def paper_data() -> dict:
    return yaml.safe_load(PAPER.read_text())


def test_paper_scenario_is_section_v():
    s = load_scenario(PAPER)
    cube = [[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0], [0, 0, 2], [2, 0, 2], [2, 2, 2], [0, 2, 2]]
    np.testing.assert_array_equal([a.position for a in s.agents], cube)
    assert s.leaders == ('agent_1', 'agent_2')
    nbrs = {a.name: [n.name for n in a.neighbours] for a in s.followers}
    assert nbrs == {'agent_3': ['agent_1', 'agent_2'], 'agent_4': ['agent_2', 'agent_3'],
                    'agent_5': ['agent_1', 'agent_4'], 'agent_6': ['agent_2', 'agent_4', 'agent_5'],
                    'agent_7': ['agent_3', 'agent_4', 'agent_6'], 'agent_8': ['agent_1', 'agent_7']}
    assert (s.gains.k_R, s.gains.k_p) == (1.0, 1.0)
    assert all(n.k == 1.0 for a in s.followers for n in a.neighbours)
    R0, p0 = initial_estimates(s)
    np.testing.assert_array_equal(p0[2:], [[-2, 0, -1], [-1, 2, 2], [-2, 2, 4], [0, 0, 0],
                                           [-4, 0, 1], [-3, 0.5, 2]])
    for i, frac in zip(range(2, 8), (0.1, 0.2, 0.3, 0.9, 0.4, 0.5)):
        np.testing.assert_allclose(R0[i], so3.axis_angle([1, 0, 0], frac * math.pi), atol=1e-15)
    np.testing.assert_array_equal(R0[:2], [np.eye(3)] * 2)  # leaders: exact
    assert all(np.array_equal(a.attitude, np.eye(3)) for a in s.agents)
    assert s.noise.gyro_std == 0 and s.noise.bearing_std == 0
    assert s.step <= 0.01


@pytest.mark.parametrize('name', ['paper_8_agents', 'de_carli_8_quadrotors', 'presenza_case1'])
def test_fleet_is_what_the_methods_know_of_the_scenario(name):
    """Scenario.fleet(): the estimators' view (estimators/fleet.py), built once, equal to what
    the scenario says (initial estimates drawn from its seed as initial_estimates draws them);
    a replaced scenario builds its own."""
    import dataclasses
    s = load_scenario(CONFIG / f'{name}.yaml')
    fleet = s.fleet()
    assert s.fleet() is fleet
    assert fleet.names == tuple(a.name for a in s.agents)
    assert fleet.index == s.index
    assert fleet.neighbours == tuple(tuple((s.index[n.name], n.k) for n in a.neighbours)
                                     for a in s.agents)
    assert [fleet.names[i] for i in fleet.followers] == [a.name for a in s.followers]
    assert [fleet.names[i] for i in fleet.leaders] == list(s.leaders)
    assert fleet.anchor == s.anchor_index and fleet.moves == s.moves
    assert [fleet.names[i] for i in fleet.ranged] == list(s.ranged)
    assert (fleet.step, fleet.frequency) == (s.step, s.frequency)
    for i, a in enumerate(s.agents):
        assert fleet.agent_id(i) == s.agent_id(a.name)
        assert [fleet.names[j] for j in fleet.listeners(i)] == s.listeners(a.name)
    for mine, theirs in zip(fleet.sensing_edges(), s.sensing_edges()):
        np.testing.assert_array_equal(mine, theirs)
    R0, p0 = initial_estimates(s)
    np.testing.assert_array_equal(fleet.initial_R, R0)
    np.testing.assert_array_equal(fleet.initial_p, p0)
    np.testing.assert_array_equal(fleet.positions, [a.position for a in s.agents])
    np.testing.assert_array_equal(fleet.attitudes, [a.attitude for a in s.agents])
    with pytest.raises(ValueError):
        fleet.initial_p[0, 0] = 1.0   # shared by every caller: read-only
    again = dataclasses.replace(s, duration=1.0)
    assert again.fleet() is not fleet
    np.testing.assert_array_equal(again.fleet().initial_p, p0)


def test_paper_scenario_warns_about_agent_8_spectrum():
    report = check_scenario(load_scenario(PAPER))
    assert report.ok
    np.testing.assert_allclose(report.spectra['agent_8'], [0, 1, 1], atol=1e-12)
    assert [w.agent for w in report.warnings] == ['agent_8']
    assert 'repeated eigenvalues' in report.warnings[0].problem


def test_per_edge_gains_remove_the_warning(paper_data):
    paper_data['agents'][7]['neighbours'] = [{'name': 'agent_1', 'k': 2.0}, 'agent_7']
    report = check_scenario(parse_scenario(paper_data))
    assert report.ok and not report.warnings
    np.testing.assert_allclose(report.spectra['agent_8'], [0, 1, 2], atol=1e-12)


def _error(data) -> str:
    with pytest.raises(ScenarioError) as exc:
        parse_scenario(data, source='s.yaml')
    msg = str(exc.value)
    assert 'Fix:' in msg and msg.startswith('s.yaml: ')
    return msg


def test_missing_field_is_named(paper_data):
    del paper_data['agents'][3]['position']
    assert 'agents[3] (agent_4).position: missing required field' in _error(paper_data)


def test_unknown_key_is_named(paper_data):
    paper_data['agents'][4]['neighbors'] = ['agent_1', 'agent_2']  # US spelling
    assert 'agents[4] (agent_5).neighbors: unknown key' in _error(paper_data)
    del paper_data['agents'][4]['neighbors']
    paper_data['gains']['kR'] = 2.0
    assert 'gains.kR: unknown key' in _error(paper_data)


@pytest.mark.parametrize('value, problem', [('.nan', 'not finite'), (-1.0, 'must be > 0'),
                                            (0, 'must be > 0'), ('fast', 'expected a number'),
                                            (True, 'expected a number')])
def test_bad_gain_values(paper_data, value, problem):
    paper_data['gains']['k_R'] = float('nan') if value == '.nan' else value
    msg = _error(paper_data)
    assert 'gains.k_R' in msg and problem in msg


def test_bad_vectors_and_attitudes(paper_data):
    bad = copy.deepcopy(paper_data)
    bad['agents'][2]['position'] = [1, 2]
    assert 'agents[2] (agent_3).position: expected a list of 3 numbers' in _error(bad)
    bad = copy.deepcopy(paper_data)
    bad['agents'][2]['initial_estimate']['attitude'] = {'quaternion': [0, 0, 0, 2]}
    assert 'initial_estimate.attitude.quaternion: norm is 2' in _error(bad)
    bad = copy.deepcopy(paper_data)
    bad['agents'][2]['initial_estimate']['attitude'] = {'axis': [1, 0, 0]}
    assert 'needs `axis` and exactly one of' in _error(bad)
    bad = copy.deepcopy(paper_data)
    bad['agents'][5]['angular_velocity'] = [1, {'tan': 3}, 0]
    assert 'angular_velocity[1].tan: unknown key' in _error(bad)
    bad = copy.deepcopy(paper_data)
    bad['agents'][5]['angular_velocity'] = [1, {'sin': 3, 'cos': 2}, 0]
    assert 'exactly one of `sin` or `cos`' in _error(bad)


def test_graph_reference_errors(paper_data):
    bad = copy.deepcopy(paper_data)
    bad['agents'][2]['neighbours'] = ['agent_1', 'agent_9']
    assert "neighbours[1]: 'agent_9' is not an agent" in _error(bad)
    bad = copy.deepcopy(paper_data)
    bad['agents'][0]['neighbours'] = ['agent_2', 'agent_3']
    assert 'agents[0] (agent_1).neighbours: a leader knows its pose' in _error(bad)
    bad = copy.deepcopy(paper_data)
    bad['leaders'] = ['agent_1']
    assert 'leaders: expected the names of exactly 2 distinct agents' in _error(bad)
    bad = copy.deepcopy(paper_data)
    bad['agents'][3]['name'] = 'agent_3'
    assert "duplicate agent name 'agent_3'" in _error(bad)
    bad = copy.deepcopy(paper_data)
    bad['agents'][3]['neighbours'] = ['agent_2', 'agent_2']
    assert "'agent_2' is listed twice" in _error(bad)
    bad = copy.deepcopy(paper_data)
    del bad['agents'][3]['initial_estimate']
    assert 'agents[3] (agent_4).initial_estimate: missing' in _error(bad)


def _check_errors(data) -> list:
    report = check_scenario(parse_scenario(data))
    assert not report.ok
    return report.errors


def test_cyclic_graph_is_rejected_with_the_cycle(paper_data):
    paper_data['agents'][2]['neighbours'] = ['agent_1', 'agent_2', 'agent_5']  # 3 → 5 → 4 → 3
    errors = _check_errors(paper_data)
    cyc = [e for e in errors if 'cycle' in e.problem]
    assert len(cyc) == 1 and 'agent_3 -> agent_5 -> agent_4 -> agent_3' in cyc[0].problem


def test_neighbour_order_and_count(paper_data):
    bad = copy.deepcopy(paper_data)
    bad['agents'][4]['neighbours'] = ['agent_1']
    errors = _check_errors(bad)
    assert any(e.agent == 'agent_5' and 'needs at least 2' in e.problem for e in errors)
    bad = copy.deepcopy(paper_data)
    bad['agents'][2], bad['agents'][3] = bad['agents'][3], bad['agents'][2]  # 4 before 3
    errors = _check_errors(bad)
    assert any(e.agent == 'agent_4' and 'agent_3 comes after agent_4' in e.problem
               and 'move agent_3 above agent_4' in e.fix for e in errors)


def test_collinear_neighbours_are_rejected(paper_data):
    # agent_3 at (2,2,0) sees agent_1 (0,0,0) and a new agent_x (1,1,0): the same line.
    paper_data['agents'].insert(2, {'name': 'agent_x', 'position': [1, 1, 0],
                                    'neighbours': ['agent_1', 'agent_2'],
                                    'initial_estimate': {'position': [0, 0, 0],
                                                         'attitude': 'identity'}})
    paper_data['agents'][3]['neighbours'] = ['agent_1', 'agent_x']
    errors = _check_errors(paper_data)
    assert [e.agent for e in errors] == ['agent_3'] and 'collinear' in errors[0].problem


def test_collocated_agents_are_rejected(paper_data):
    paper_data['agents'][7]['position'] = [2, 2, 2]  # on top of agent_7
    errors = _check_errors(paper_data)
    assert any(e.agent == 'agent_8' and 'collocated with agent_7' in e.problem for e in errors)


def test_follower_unreachable_from_a_leader():
    """With ordered neighbours and |N_i| >= 2, reachability from both leaders follows by
    induction; it fails only next to a count violation, and then downstream agents are named."""
    data = {'name': 'x', 'leaders': ['a', 'b'], 'initial_estimates': {'random': {'seed': 1}},
            'agents': [{'name': 'a', 'position': [0, 0, 0]}, {'name': 'b', 'position': [5, 0, 0]},
                       {'name': 'c', 'position': [0, 1, 0], 'neighbours': ['a', 'b']},
                       {'name': 'd', 'position': [0, 0, 1], 'neighbours': ['a', 'c']}]}
    assert check_scenario(parse_scenario(data)).ok
    data['agents'][2]['neighbours'] = ['a']
    errors = check_scenario(parse_scenario(data)).errors
    unreachable = sorted(e.agent for e in errors if 'not reachable from leader b' in e.problem)
    assert unreachable == ['c', 'd']
    assert any(e.agent == 'c' and 'needs at least 2' in e.problem for e in errors)


def test_yaml_syntax_error_names_line(tmp_path):
    f = tmp_path / 'broken.yaml'
    f.write_text('name: x\nleaders: [a, b\nagents: []\n')
    with pytest.raises(ScenarioError, match=r'broken.yaml: YAML syntax error at line \d+, '
                                            r'column \d+.*Fix:'):
        load_scenario(f)


def test_missing_file_and_non_mapping(tmp_path):
    with pytest.raises(ScenarioError, match='cannot read the scenario file'):
        load_scenario(tmp_path / 'nope.yaml')
    f = tmp_path / 'list.yaml'
    f.write_text('- 1\n- 2\n')
    with pytest.raises(ScenarioError, match='top level: expected a mapping'):
        load_scenario(f)


def test_random_initial_estimates_are_seeded(paper_data):
    for a in paper_data['agents'][2:]:
        del a['initial_estimate']
    paper_data['initial_estimates'] = {'random': {'seed': 4, 'position_std': 2.0,
                                                  'max_angle_deg': 30}}
    s = parse_scenario(paper_data)
    (R1, p1), (R2, p2) = initial_estimates(s), initial_estimates(s)
    np.testing.assert_array_equal(p1, p2)
    np.testing.assert_array_equal(R1, R2)
    angles = so3.angle(np.stack([a.attitude for a in s.agents]) @ np.swapaxes(R1, 1, 2))
    assert np.all(angles[2:] <= math.radians(30) + 1e-12) and np.all(angles[2:] > 0)
    paper_data['initial_estimates']['random']['seed'] = 5
    assert not np.array_equal(initial_estimates(parse_scenario(paper_data))[1], p1)


def test_empty_file_says_so(tmp_path):
    f = tmp_path / 'empty.yaml'
    f.write_text('# nothing yet\n')
    with pytest.raises(ScenarioError, match='the file is empty'):
        load_scenario(f)
