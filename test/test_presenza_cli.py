"""Presenza et al. beside the other methods: ``bearing-pose compare`` on
config/presenza_compare.yaml (case 1's robots and motion on a cascade, an anchor for Presenza
et al. and ``other_roles.leaders`` for the leader-follower methods), and the ``other_roles``
block's errors."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import yaml

from bearing_pose_estimation.cli.main import main
from bearing_pose_estimation.scenario import ScenarioError, load_scenario, parse_scenario
from bearing_pose_estimation.scenario.parse import read_scenario_data
from bearing_pose_estimation.studies.compare import method_scenarios

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / 'config' / 'presenza_compare.yaml'
RUN = ('presenza', 'boughellaba_tayebi', 'tran_anderson_ahn')


def test_compare_runs_presenza_beside_the_leader_follower_methods(tmp_path, capsys):
    out = tmp_path / 'cmp'
    assert main(['compare', str(CONFIG), '--duration', '3', '--out', str(out),
                 '--no-plots']) == 0
    # De Carli et al. have every role they need (none) and every sensor, but not their
    # yaw-only frames: their own check says so.
    assert ('not running de_carli: its check fails: error: robot_1.attitude: De Carli et al. '
            'need yaw-only body frames') in capsys.readouterr().err
    table = (out / 'compare.md').read_text()
    assert all(f'| {m} | batch |' in table for m in RUN) and 'de_carli' not in table
    with (out / 'compare.csv').open() as fh:
        rows = list(csv.DictReader(fh))
    for m in RUN:   # every method converging from the same initial error
        for what in ('attitude_error_mean_rad', 'position_error_mean_m'):
            first, last = float(rows[0][f'{m}_{what}']), float(rows[-1][f'{m}_{what}'])
            assert np.isfinite(last) and last < 0.75 * first, (m, what, first, last)


def test_each_method_gets_its_roles_and_keeps_the_others_aside():
    derived = method_scenarios(read_scenario_data(CONFIG), load_scenario(CONFIG),
                               ['presenza', 'boughellaba_tayebi'])
    p_data, p = derived['presenza']
    b_data, b = derived['boughellaba_tayebi']
    assert p.anchor == 'robot_5' and p.leaders == () and p.ranged == ('robot_4', 'robot_3')
    assert p_data['other_roles'] == {'leaders': ['robot_1', 'robot_2']}
    assert b.leaders == ('robot_1', 'robot_2') and b.anchor is None
    assert 'anchor' not in b_data and b_data['other_roles']['anchor']['agent'] == 'robot_5'


@pytest.mark.parametrize('other_roles, message', [
    ({'anchor': {'agent': 'robot_5', 'ranged': ['robot_4', 'robot_3']}},
     'other_roles.anchor: Presenza et al. uses anchor itself'),
    ({'leaders': ['robot_1', 'robot_9']}, "other_roles.leaders[1]: 'robot_9' is not an agent"),
    ({'leaders': 'robot_1'}, 'other_roles.leaders: expected a list of agent names'),
    ({'pilots': ['robot_1']}, 'pilots'),
])
def test_other_roles_errors_name_the_field_and_the_fix(other_roles, message):
    data = yaml.safe_load(CONFIG.read_text())
    data['other_roles'] = other_roles
    with pytest.raises(ScenarioError, match='Fix:') as info:
        parse_scenario(data)
    assert message in str(info.value)


def test_a_method_without_its_role_is_refused_with_where_to_give_it(tmp_path, capsys):
    paper = ROOT / 'config' / 'paper_8_agents.yaml'
    with pytest.raises(SystemExit):
        main(['compare', str(paper), '--methods', 'presenza', '--out', str(tmp_path / 'x')])
    err = capsys.readouterr().err
    assert 'presenza cannot run on' in err and 'it needs an anchor (give it under' in err


def test_simulate_writes_the_errors_of_sensing_and_free_robots_apart(tmp_path):
    """errors_by_role.csv: per role the mean of its robots' columns of metrics.csv; the plot
    beside it. Methods without roles write neither."""
    out = tmp_path / 'sim'
    config = ROOT / 'config' / 'presenza_case1_30hz.yaml'
    assert main(['simulate', str(config), '--duration', '1', '--out', str(out), '--quiet']) == 0
    assert (out / 'errors_by_role.png').stat().st_size > 10_000
    with (out / 'metrics.csv').open() as fh:
        per_robot = list(csv.DictReader(fh))
    with (out / 'errors_by_role.csv').open() as fh:
        roles = list(csv.DictReader(fh))
    assert len(roles) == len(per_robot)
    groups = {'sensing': ['robot_1', 'robot_2'], 'free': ['robot_3', 'robot_4', 'robot_5']}
    for row, by_role in zip(per_robot, roles):
        for group, robots in groups.items():
            for q, col in (('position_error_mean_m', 'pos'), ('attitude_error_mean_rad', 'att')):
                mean = np.mean([float(row[f'{col}_{r}']) for r in robots])
                assert float(by_role[f'{group}_{q}']) == pytest.approx(mean, rel=1e-6)
    other = tmp_path / 'tran'
    assert main(['simulate', str(ROOT / 'config' / 'tran_cube.yaml'), '--duration', '0.5',
                 '--out', str(other), '--quiet', '--no-plots']) == 0
    assert not (other / 'errors_by_role.csv').exists()
