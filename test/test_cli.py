"""The `bearing-pose` command line, called in-process through `main(argv)`."""
import csv
import json
from pathlib import Path

import pytest

from bearing_pose_estimation.cli.main import main

PAPER = str(Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml')


def test_check_valid_and_invalid(tmp_path, capsys):
    assert main(['check', PAPER]) == 0
    out = capsys.readouterr().out
    assert '8 agents (6 followers), 14 sensing edges' in out
    assert 'agent_8: {0, 1, 1}' in out and '0 error(s), 1 warning(s)' in out
    bad = tmp_path / 'bad.yaml'
    bad.write_text(Path(PAPER).read_text().replace('neighbours: [agent_1, agent_7]',
                                                   'neighbours: [agent_7]'))
    assert main(['check', str(bad)]) == 1
    assert 'agent_8.neighbours: has 1 neighbour(s), needs at least 2' in capsys.readouterr().out


def test_check_reports_unreadable_yaml(tmp_path, capsys):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('name: [unclosed\n')
    assert main(['check', str(bad)]) == 1
    assert 'YAML syntax error at line' in capsys.readouterr().err


def test_simulate_writes_documented_outputs(tmp_path, capsys):
    out = tmp_path / 'run'
    assert main(['simulate', PAPER, '--duration', '5', '--out', str(out), '--quiet']) == 0
    with (out / 'metrics.csv').open() as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    assert header[:3] == ['t', 'attitude_error_mean_rad', 'position_error_mean_m']
    assert header[3:9] == [f'att_agent_{k}' for k in range(3, 9)]
    assert header[9:] == [f'pos_agent_{k}' for k in range(3, 9)]
    times = [float(r[0]) for r in rows[1:]]
    assert times[0] == 0.0 and times[-1] == pytest.approx(5.0)
    assert max(b - a for a, b in zip(times, times[1:])) <= 0.5 + 1e-9
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['final_attitude_error_mean_rad'] == pytest.approx(float(rows[-1][1]))
    assert set(summary['per_agent']) == {f'agent_{k}' for k in range(3, 9)}
    for png in ('fig2_attitude_error.png', 'fig3_position_error.png'):
        assert (out / png).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert 'final mean attitude error' in capsys.readouterr().out


def test_simulate_refuses_a_file_as_output_dir(tmp_path, capsys):
    f = tmp_path / 'precious.yaml'
    f.write_text('keep me')
    assert main(['simulate', PAPER, '--duration', '1', '--out', str(f)]) == 1
    assert f.read_text() == 'keep me'
    assert '--out must be a directory' in capsys.readouterr().err


def test_simulate_never_overwrites_without_force(tmp_path, capsys):
    out = tmp_path / 'run'
    argv = ['simulate', PAPER, '--duration', '1', '--out', str(out), '--quiet']
    assert main(argv) == 0
    names = ['metrics.csv', 'summary.json', 'fig2_attitude_error.png', 'fig3_position_error.png']
    first = {n: (out / n).read_bytes() for n in names}
    stamps = {n: (out / n).stat().st_mtime_ns for n in names}
    capsys.readouterr()
    assert main(argv[:3] + ['2'] + argv[4:]) == 1
    err = capsys.readouterr().err
    assert f'{out / "metrics.csv"}: exists' in err and 'refusing to overwrite' in err
    assert 'Fix: pass --force to overwrite, or choose another --out' in err
    assert {n: (out / n).read_bytes() for n in names} == first
    assert {n: (out / n).stat().st_mtime_ns for n in names} == stamps
    # One existing output is enough to refuse, even with --no-plots.
    (out / 'metrics.csv').unlink()
    assert main(argv + ['--no-plots']) == 1
    assert f'{out / "summary.json"}: exists' in capsys.readouterr().err
    assert main(argv[:3] + ['2'] + argv[4:] + ['--force']) == 0
    assert json.loads((out / 'summary.json').read_text())['duration_s'] == pytest.approx(2.0)
    assert (out / 'metrics.csv').exists()


def test_run_refuses_an_output_dir_with_outputs(tmp_path, capsys):
    """Checked before any process starts; --force lets the run go ahead."""
    out = tmp_path / 'dds'
    (out / 'logs').mkdir(parents=True)
    (out / 'logs' / 'agent_3.log').write_text('old log')
    assert main(['run', PAPER, '--out', str(out)]) == 1
    err = capsys.readouterr().err
    assert f'{out / "logs" / "agent_3.log"}: exists' in err and '--force' in err
    assert (out / 'logs' / 'agent_3.log').read_text() == 'old log'
    assert not (out / 'params').exists()


def test_compare_runs_each_method_on_the_same_scenario(tmp_path, capsys):
    """`compare`: one table row and two CSV columns per method; each method's numbers are what
    the batch simulator gives for the scenario with that method and its gains (the file's, the
    defaults, or --gains); outputs are not overwritten without --force."""
    import csv

    from bearing_pose_estimation.scenario import load_scenario
    from bearing_pose_estimation.sim.batch import BatchSimulator

    out = tmp_path / 'cmp'
    assert main(['compare', PAPER, '--duration', '5', '--out', str(out),
                 '--gains', 'tran_anderson_ahn:k_omega=3,k_c=0.5']) == 0
    captured = capsys.readouterr()
    assert '| boughellaba_tayebi | batch | k_R=1, k_p=1, k_v=1, bias_std=0 | 5 |' in captured.out
    assert '| tran_anderson_ahn | batch | k_omega=3, k_p=1, k_c=0.5, k_v=1, bias_std=0 | 5 |' in captured.out
    # Tran's own condition on agent_8 (two orthogonal bearings: K_i = I with k_c = 1 would be
    # {1, 1, 1}; with k_c = 0.5 it is {0.5, 1, 1}).
    assert '(tran_anderson_ahn): warning: agent_8.neighbours: K_i' in captured.err
    assert (out / 'compare_errors.png').stat().st_size > 10_000
    assert (out / 'compare.md').read_text().count('\n| ') == 3  # separator + two methods
    with (out / 'compare.csv').open() as fh:
        last = list(csv.DictReader(fh))[-1]
    paper = load_scenario(PAPER)
    for method, gains in (('boughellaba_tayebi', {}),
                          ('tran_anderson_ahn', {'k_omega': 3.0, 'k_c': 0.5})):
        rec = BatchSimulator(paper.with_method(method, **gains)).run(5.0)
        assert float(last[f'{method}_attitude_error_mean_rad']) == pytest.approx(
            rec.att_err[-1].mean(), rel=1e-8)
        assert float(last[f'{method}_position_error_mean_m']) == pytest.approx(
            rec.pos_err[-1].mean(), rel=1e-8)
    assert main(['compare', PAPER, '--duration', '5', '--out', str(out)]) == 1
    assert '--force' in capsys.readouterr().err


@pytest.mark.parametrize('gains, message', [
    ('tran_anderson_ahn:k_R=2', "'k_R' is not a gain of tran_anderson_ahn; use one of "
                                'bearing_std, bias_std, gyro_noise_density'),
    ('boughellaba_tayebi:k_ij=2', 'k_ij is per edge'),
    ('tran_anderson_ahn:k_omega=-1', 'k_omega must be a positive number'),
    ('tran_anderson_ahn:k_omega=nan', 'k_omega must be a positive number'),
    ('kalman:k_R=1', 'expected METHOD:GAIN=VALUE'),
])
def test_compare_rejects_bad_gain_overrides(gains, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(['compare', PAPER, '--gains', gains])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_simulate_refuses_invalid_scenario(tmp_path, capsys):
    bad = tmp_path / 'cyc.yaml'
    bad.write_text(Path(PAPER).read_text().replace('neighbours: [agent_1, agent_2]',
                                                   'neighbours: [agent_1, agent_2, agent_5]'))
    assert main(['simulate', str(bad), '--out', str(tmp_path / 'o')]) == 1
    err = capsys.readouterr().err
    assert f'error: {bad}: agent_3.neighbours: the sensing graph has a cycle' in err
    assert not (tmp_path / 'o' / 'metrics.csv').exists()


def test_generate_never_overwrites_without_force(tmp_path, capsys):
    f = tmp_path / 'fleet.yaml'
    assert main(['generate', '--agents', '10', '--seed', '3', '--out', str(f)]) == 0
    first = f.read_text()
    assert first.startswith('# Generated by: bearing-pose generate --agents 10 --seed 3')
    assert main(['check', str(f)]) == 0
    assert main(['generate', '--agents', '10', '--seed', '4', '--out', str(f)]) == 1
    assert f.read_text() == first
    assert 'refusing to overwrite' in capsys.readouterr().err
    assert main(['generate', '--agents', '10', '--seed', '4', '--out', str(f), '--force']) == 0
    assert f.read_text() != first


@pytest.mark.parametrize('argv', [['generate', '--agents', '2', '--out', 'x.yaml'],
                                  ['simulate', PAPER, '--duration', '-1'],
                                  ['simulate', PAPER, '--duration', 'nan'],
                                  ['simulate', PAPER, '--record-every', '0.6'],
                                  ['frobnicate']])
def test_bad_command_lines_exit_2(argv):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2


def test_simulate_gains_turn_the_feed_forward_off_and_report_the_floor(tmp_path, capsys):
    """`--gains k_v=0` on the moving scenario: the paper's observer lags, and the summary's
    steady-state line reports the position floor (about 0.5 m); a bad gain is refused."""
    moving = PAPER.replace('paper_8_agents.yaml', 'paper_8_agents_moving.yaml')
    assert main(['simulate', moving, '--duration', '20', '--gains', 'k_v=0', '--quiet',
                 '--no-plots', '--out', str(tmp_path / 'off')]) == 0
    out = capsys.readouterr()
    assert 'gains: k_R=1, k_p=1, k_v=0, bias_std=0' in out.err
    summary = json.loads((tmp_path / 'off' / 'summary.json').read_text())
    assert summary['steady_position_error_mean_m'] > 0.2
    assert f'position error {summary["steady_position_error_mean_m"]:.3e} m' in out.out
    assert main(['simulate', moving, '--gains', 'k_v=-1', '--out', str(tmp_path / 'bad')]) == 2
    assert "k_v must be a non-negative number, got '-1'" in capsys.readouterr().err
