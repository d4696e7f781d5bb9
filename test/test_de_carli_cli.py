"""`bearing-pose` with De Carli et al.'s scenario: simulate writes the four quantities of the
paper's Fig. 2 (CSV columns and cascade.png), with the formation mode chosen; compare runs the methods
the scenario can run and names why it skips the others; run refuses the paper's closed loop,
which a simulator node cannot run, with the fix."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from bearing_pose_estimation.cli.main import main

CONFIG = str(Path(__file__).resolve().parents[1] / 'config' / 'de_carli_8_quadrotors.yaml')
PAPER = str(Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml')


def test_simulate_writes_the_fig_2_quantities(tmp_path, capsys):
    """In the exogenous mode (--formation-mode; the file's paper mode is test_de_carli_paper's)."""
    out = tmp_path / 'exogenous'
    assert main(['simulate', CONFIG, '--duration', '3', '--formation-mode', 'exogenous',
                 '--out', str(out), '--quiet']) == 0
    text = capsys.readouterr()
    assert 'final relative yaw error mean' in text.out and 'final formation error mean' in text.out
    with (out / 'metrics.csv').open() as fh:
        rows = list(csv.DictReader(fh))
    header = list(rows[0])
    pairs = [h for h in header if h.startswith('rel_yaw_err_')]
    formation = [h for h in header if h.startswith('formation_err_')]
    assert len(pairs) == 12 and len(formation) == 8   # the cube's 12 pairs, 8 robots
    assert 'rel_yaw_err_robot_0_robot_1' in pairs and 'formation_err_robot_7_m' in formation
    last = rows[-1]
    assert max(float(last[h]) for h in pairs) < 1e-6      # relative yaws converged
    assert float(last['attitude_error_mean_rad']) < 1e-6
    first_formation = np.mean([float(rows[0][h]) for h in formation])
    assert np.mean([float(last[h]) for h in formation]) < 0.5 * first_formation
    assert (out / 'cascade.png').stat().st_size > 20_000
    assert (out / 'trajectories.png').is_file()


def test_compare_runs_what_the_scenario_can_run_and_says_why_not_the_others(tmp_path, capsys):
    out = tmp_path / 'cmp'
    assert main(['compare', CONFIG, '--duration', '1', '--out', str(out), '--no-plots']) == 0
    err = capsys.readouterr().err
    assert 'not running boughellaba_tayebi: it needs 2 leaders, the scenario has 0' in err
    assert 'not running tran_anderson_ahn: it needs 2 leaders' in err
    table = (out / 'compare.md').read_text()
    assert '| de_carli | batch |' in table and 'boughellaba_tayebi' not in table
    with pytest.raises(SystemExit):   # asked for explicitly: refused with the reason
        main(['compare', CONFIG, '--methods', 'boughellaba_tayebi', '--out', str(out)])
    assert 'boughellaba_tayebi cannot run on' in capsys.readouterr().err
    # And the other way round: the bearing scenario does not simulate relative positions.
    assert main(['compare', PAPER, '--duration', '1', '--out', str(tmp_path / 'p'),
                 '--no-plots']) == 0
    assert ('not running de_carli: it needs odometry, relative_positions, which the scenario '
            'does not simulate') in capsys.readouterr().err


def test_run_refuses_the_paper_mode_over_dds(tmp_path, capsys):
    assert main(['run', CONFIG, '--duration', '1', '--out', str(tmp_path / 'r')]) == 1
    err = capsys.readouterr().err
    assert 'formation_control.mode is paper' in err and '--formation-mode exogenous' in err
    assert not (tmp_path / 'r' / 'logs').exists()   # nothing was started
