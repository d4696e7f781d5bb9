"""`bearing-pose montecarlo`: outputs, reproducibility by seed, statistics, replay."""
import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from bearing_pose_estimation.studies import montecarlo as mc
from bearing_pose_estimation.cli.main import main
from bearing_pose_estimation.scenario import initial_estimates, load_scenario, parse_scenario
from bearing_pose_estimation.metrics.results import Recording
from bearing_pose_estimation.studies.summary import SETTLE_FACTOR

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'
COLUMNS = ['run', 'seed', 'final_attitude_error_mean_rad', 'final_position_error_mean_m',
           'final_attitude_error_max_rad', 'final_position_error_max_m',
           'steady_attitude_error_mean_rad', 'steady_position_error_mean_m',
           'steady_attitude_error_max_rad', 'steady_position_error_max_m',
           'attitude_below_1e-3_rad_from_s', 'position_below_1e-2_m_from_s',
           'attitude_settled_from_s', 'position_settled_from_s']


@pytest.fixture(scope='module')
def noisy(tmp_path_factory) -> Path:
    data = yaml.safe_load(PAPER.read_text())
    data['noise'] = {'bearing_std': 0.017453, 'gyro_std': 0.01, 'seed': 0}
    path = tmp_path_factory.mktemp('mc') / 'noisy.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


def _rows(path: Path) -> list[dict]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope='module')
def two_studies(noisy, tmp_path_factory):
    """The same 4-run study twice (seed 5), into two directories."""
    base = tmp_path_factory.mktemp('mc_out')
    outs = [base / 'a', base / 'b']
    for out in outs:
        assert main(['montecarlo', str(noisy), '--runs', '4', '--seed', '5', '--duration', '10',
                     '--jobs', '2', '--out', str(out)]) == 0
    return outs


def test_writes_the_documented_files(two_studies, capsys):
    out = two_studies[0]
    with (out / 'runs.csv').open() as fh:
        assert next(csv.reader(fh)) == COLUMNS
    rows = _rows(out / 'runs.csv')
    assert [int(r['run']) for r in rows] == [0, 1, 2, 3]
    assert [int(r['seed']) for r in rows] == [5, 6, 7, 8]
    assert (out / 'montecarlo.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['runs'] == 4 and summary['first_seed'] == 5 and summary['duration_s'] == 10
    assert set(summary['statistics']) == set(COLUMNS[2:])


def test_same_seed_same_runs_and_noisy_runs_differ(two_studies):
    a, b = (_rows(out / 'runs.csv') for out in two_studies)
    assert a == b                                   # every value, to the last digit
    steady = [float(r['steady_attitude_error_mean_rad']) for r in a]
    assert len(set(steady)) == 4                    # the noise differs run to run
    assert all(1e-4 < x < 0.1 for x in steady)      # and is of the size of the noise


def test_summary_statistics_match_the_rows(two_studies):
    out = two_studies[0]
    rows = _rows(out / 'runs.csv')
    stats = json.loads((out / 'summary.json').read_text())['statistics']
    for q in COLUMNS[2:]:
        raw = [r[q] for r in rows]
        values = np.array([float(v) for v in raw if v != ''])
        s = stats[q]
        assert s['never_converged'] == raw.count('')
        assert s['n'] == values.size
        if values.size == 0:
            assert s['mean'] is None and s['max'] is None
            continue
        ordered = np.sort(values)

        def pct(p):  # linear interpolation between order statistics, written out
            pos = p / 100 * (ordered.size - 1)
            lo = math.floor(pos)
            hi = min(lo + 1, ordered.size - 1)
            return ordered[lo] + (pos - lo) * (ordered[hi] - ordered[lo])

        mean = sum(values) / values.size
        assert s['mean'] == pytest.approx(mean, rel=1e-12)
        assert s['std'] == pytest.approx(math.sqrt(sum((values - mean) ** 2) / values.size),
                                         rel=1e-9)
        assert s['max'] == ordered[-1]
        for p in (5, 50, 95):
            assert s[f'p{p}'] == pytest.approx(pct(p), rel=1e-12)


def test_noisy_runs_settle_on_their_floor_not_on_the_fixed_thresholds(two_studies):
    """1° bearing noise: no run stays below 1e-3 rad, yet every run has a settled time."""
    rows = _rows(two_studies[0] / 'runs.csv')
    assert all(r['attitude_below_1e-3_rad_from_s'] == '' for r in rows)
    assert all(0.0 < float(r[q]) <= 10.0 for r in rows
               for q in ('attitude_settled_from_s', 'position_settled_from_s'))
    summary = json.loads((two_studies[0] / 'summary.json').read_text())
    assert summary['runs_never_converged']['attitude_below_1e-3_rad_from_s'] == 4
    assert summary['runs_never_converged']['attitude_settled_from_s'] == 0


def _recording(t, att, pos):
    return Recording(t=t, followers=['a'], att_err=att[:, None], pos_err=pos[:, None],
                     att_dist_I=att[:, None], pos_err_paper=pos[:, None])


def test_settled_time_is_within_a_factor_of_the_floor_or_the_fixed_threshold():
    t = np.round(np.arange(0.0, 60.05, 0.1), 9)
    floor = 3e-3 * (1.0 + 0.5 * np.sin(7.0 * t))          # a noise floor, fluctuating ±50 %
    att, pos = 0.5 * np.exp(-t / 2) + floor, 2 * np.exp(-t / 5) + 10 * floor
    noisy = mc.evaluate(_recording(t, att, pos), run=0, seed=0).values
    k = SETTLE_FACTOR
    assert noisy['steady_attitude_error_mean_rad'] == pytest.approx(3e-3, rel=1e-3)
    assert noisy['attitude_below_1e-3_rad_from_s'] is None
    assert noisy['position_below_1e-2_m_from_s'] is None
    # The last time the decay plus the floor's peak (1.5 floor) reaches k floor, give or take
    # one period of the fluctuation (0.9 s) and one record (0.1 s).
    last_att = 2 * math.log(0.5 / ((k - 1.5) * 3e-3))
    last_pos = 5 * math.log(2 / ((k - 1.5) * 3e-2))
    assert last_att - 1.0 < noisy['attitude_settled_from_s'] <= last_att + 0.1
    assert last_pos - 1.0 < noisy['position_settled_from_s'] <= last_pos + 0.1
    assert np.all(att[t >= noisy['attitude_settled_from_s']] < k * noisy['steady_attitude_error_mean_rad'])
    # Without noise the floor is far below the fixed thresholds: those apply.
    clean = mc.evaluate(_recording(t, np.exp(-t / 2), np.exp(-t / 5)), run=0, seed=0).values
    assert clean['attitude_settled_from_s'] == clean['attitude_below_1e-3_rad_from_s'] == pytest.approx(13.9)
    assert clean['position_settled_from_s'] == clean['position_below_1e-2_m_from_s'] == pytest.approx(23.1)


def test_any_run_can_be_replayed_from_its_seed(two_studies, noisy):
    row = _rows(two_studies[0] / 'runs.csv')[2]
    replay = mc.run_one(str(noisy), run=2, seed=int(row['seed']), duration=10.0)
    for q in COLUMNS[2:]:
        expected = None if row[q] == '' else float(row[q])
        assert replay.values[q] == expected


def test_reseed_sets_noise_and_random_initial_estimates_only():
    data = yaml.safe_load(PAPER.read_text())
    explicit = load_scenario(PAPER)
    r = mc.reseed(explicit, 12)
    assert r.noise.seed == 12 and r.random_init is None
    np.testing.assert_array_equal(initial_estimates(r)[1], initial_estimates(explicit)[1])
    for a in data['agents'][2:]:
        del a['initial_estimate']
    data['initial_estimates'] = {'random': {'seed': 0, 'position_std': 1.0}}
    drawn = parse_scenario(data)
    r12, r13 = mc.reseed(drawn, 12), mc.reseed(drawn, 13)
    assert r12.random_init.seed == 12 and r12.random_init.position_std == 1.0
    assert not np.array_equal(initial_estimates(r12)[1], initial_estimates(r13)[1])


def test_refuses_to_overwrite_without_force(tmp_path, capsys):
    out = tmp_path / 'mc'
    out.mkdir()
    (out / 'runs.csv').write_text('precious')
    argv = ['montecarlo', str(PAPER), '--runs', '1', '--duration', '1', '--jobs', '1',
            '--out', str(out)]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert f'{out / "runs.csv"}: exists' in err and '--force' in err
    assert (out / 'runs.csv').read_text() == 'precious'
    assert not (out / 'summary.json').exists()
    assert main(argv + ['--force']) == 0
    assert (out / 'runs.csv').read_text().startswith('run,seed,')


def test_invalid_scenario_exits_1(tmp_path, capsys):
    bad = tmp_path / 'cyc.yaml'
    bad.write_text(PAPER.read_text().replace('neighbours: [agent_1, agent_2]',
                                             'neighbours: [agent_1, agent_2, agent_5]'))
    assert main(['montecarlo', str(bad), '--runs', '2', '--out', str(tmp_path / 'o')]) == 1
    assert 'cycle' in capsys.readouterr().err
    assert not (tmp_path / 'o').exists()


@pytest.mark.parametrize('argv', [['--runs', '0'], ['--runs', '2', '--jobs', '0'], [],
                                  ['--runs', '2', '--duration', '0'], ['--runs', 'x']])
def test_bad_command_lines_exit_2(argv):
    with pytest.raises(SystemExit) as exc:
        main(['montecarlo', str(PAPER), *argv])
    assert exc.value.code == 2
