"""`check` along the motion of moving scenarios: close approaches, what the motion breaks of the
leader-follower methods' assumptions, static scenarios untouched, `generate --speed`."""
import hashlib
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from bearing_pose_estimation.cli.main import main
from bearing_pose_estimation.core import graph
from bearing_pose_estimation.estimators import bearing_leaders
from bearing_pose_estimation.scenario import check as check_module
from bearing_pose_estimation.scenario import check_scenario, load_scenario, parse_scenario
from bearing_pose_estimation.scenario.generate import MAX_RELATIVE_DRIFT_M, MIN_SPACING_M
from bearing_pose_estimation.scenario.truth import Truth

CONFIG = Path(__file__).resolve().parent.parent / 'config'
PAPER = str(CONFIG / 'paper_8_agents.yaml')
TIME = re.compile(r'at t = ([0-9.]+) s')


def _scenario(agents, duration=10.0, method='boughellaba_tayebi'):
    return parse_scenario({'name': 'motion_test', 'method': method, 'duration': duration,
                           'leaders': ['agent_1', 'agent_2'],
                           'initial_estimates': {'random': {'seed': 0}}, 'agents': agents})


def _head_on(offset, v1=0.3, v2=-0.4, gap=3.0):
    """Leaders on parallel lines ``offset`` apart, closing at ``v1 - v2``: closest (``offset``)
    at ``t = gap / (v1 - v2)``. A static follower far above."""
    return _scenario([
        {'name': 'agent_1', 'position': [0, 0, 0], 'velocity': {'world': [v1, 0, 0]}},
        {'name': 'agent_2', 'position': [gap, offset, 0], 'velocity': {'world': [v2, 0, 0]}},
        {'name': 'agent_3', 'position': [1.5, 5, 3], 'neighbours': ['agent_1', 'agent_2']}])


def _approaches(report):
    return [f for f in report.findings if f.field == 'velocity'
            and ('comes within' in f.problem or 'collides' in f.problem)]


# ----------------------------------------------------------------------------- close approaches
def test_head_on_pass_warns_at_the_closest_approach():
    report = check_scenario(_head_on(offset=0.1))
    [f] = _approaches(report)
    t_star = 3.0 / 0.7   # 4.2857 s: between two samples (every 0.05 s)
    assert f.severity == 'warning' and f.agent == 'agent_2'
    assert f.problem.startswith(f'comes within 0.100 m of agent_1 at t = {t_star:.2f} s')
    assert 'agent_1 or agent_2' in f.fix
    assert report.ok  # a warning only


def test_head_on_collision_is_an_error_at_the_right_time():
    report = check_scenario(_head_on(offset=0.0, v1=0.25, v2=-0.5, gap=2.0))
    [f] = _approaches(report)
    assert f.severity == 'error' and f.agent == 'agent_2' and f.field == 'velocity'
    assert f'collides with agent_1 at t = {2.0 / 0.75:.2f} s' in f.problem
    assert not report.ok


def test_pairs_far_apart_get_no_finding():
    assert _approaches(check_scenario(_head_on(offset=0.25))) == []


def test_body_frame_velocity_is_integrated_with_the_attitude():
    """agent_1 turns at w about z with body velocity (v, 0, 0): a circle of radius v/w through
    the origin, at (0, 2 v/w, 0) at t = π/w; a world-frame reading would go straight along x."""
    w, v = 0.5, 0.5
    scenario = _scenario([
        {'name': 'agent_1', 'position': [0, 0, 0], 'angular_velocity': [0, 0, w],
         'velocity': {'body': [v, 0, 0]}},
        {'name': 'agent_2', 'position': [0, 2 * v / w + 0.1, 0]},
        {'name': 'agent_3', 'position': [5, 5, 5], 'neighbours': ['agent_1', 'agent_2']}])
    [f] = _approaches(check_scenario(scenario))
    dist = float(re.search(r'within ([0-9.]+) m', f.problem).group(1))
    t = float(TIME.search(f.problem).group(1))
    assert dist == pytest.approx(0.1, abs=1e-3)
    assert t == pytest.approx(math.pi / w, abs=0.03)


def test_close_approaches_match_brute_force():
    """The KD-tree search finds exactly the pairs a brute-force search over every segment does,
    approaches between samples included."""
    rng = np.random.default_rng(1)
    k, n = 6, 30     # segments of 0.8 s: most approaches fall between samples
    times = np.linspace(0.0, 4.0, k)
    start = rng.uniform(0, 3, size=(n, 3))
    vel = rng.normal(scale=0.5, size=(n, 3))
    pos = start[None] + times[:, None, None] * vel[None]
    radius = 0.3
    i, j, dist, when = graph.close_approaches(times, pos, radius)
    found = {(a, b): (d, t) for a, b, d, t in zip(i, j, dist, when)}
    expected = {}
    for a in range(n):
        for b in range(a + 1, n):
            # straight lines: the exact minimum of |d0 + t dv| over [0, 4]
            d0, dv = start[b] - start[a], vel[b] - vel[a]
            t = float(np.clip(-(d0 @ dv) / (dv @ dv), 0.0, 4.0))
            d = float(np.linalg.norm(d0 + t * dv))
            if d < radius:
                expected[(a, b)] = (d, t)
    assert expected and set(found) == set(expected)
    for key, (d, t) in expected.items():
        assert found[key][0] == pytest.approx(d, abs=1e-9)
        assert found[key][1] == pytest.approx(t, abs=1e-9)


# ----------------------------------------------------------------------------- the method's check
def _passing_follower(y0, vy, method='boughellaba_tayebi', duration=5.0):
    """Static leaders at x = 0 and x = 2; the follower at (1, y0, 0) moves along y at ``vy``:
    its two bearings are collinear when it crosses y = 0, at t = -y0 / vy."""
    return _scenario([
        {'name': 'agent_1', 'position': [0, 0, 0]},
        {'name': 'agent_2', 'position': [2, 0, 0]},
        {'name': 'agent_3', 'position': [1, y0, 0], 'velocity': {'world': [0, vy, 0]},
         'neighbours': ['agent_1', 'agent_2']}], duration=duration, method=method)


def test_bearings_becoming_collinear_is_an_error_at_that_time():
    report = check_scenario(_passing_follower(y0=3.0, vy=-1.0))
    [f] = [f for f in report.findings if 'collinear' in f.problem]
    assert f.severity == 'error' and f.agent == 'agent_3' and f.field == 'velocity'
    assert f.problem.startswith('at t = 3.00 s its bearings to its neighbours become collinear')
    assert 'agent_1, agent_2' in f.fix
    assert not report.ok


def test_spectrum_along_the_motion():
    """B&T's M_i = b_1 b_1ᵀ + b_2 b_2ᵀ has eigenvalues {0, 1 - |c|, 1 + |c|}, c = b_1·b_2: they
    repeat ({0, 1, 1}) when the bearings are orthogonal, at y = 1 (t = 2 s), not at t = 0
    (y = 3). Tran's K_i gets the same moment as a repeated spectrum too. (At 1 m/s the
    bearings turn by more than SPECTRUM_STEP_DEG per sample there: every sample is
    evaluated, the one at t = 2 s included.)"""
    for method in ('boughellaba_tayebi', 'tran_anderson_ahn'):
        report = check_scenario(_passing_follower(y0=3.0, vy=-1.0, method=method))
        assert not [f for f in report.findings if f.field == 'neighbours']  # fine at t = 0
        [f] = [f for f in report.findings if 'eigenvalues' in f.problem]
        assert f.severity == 'warning' and f.agent == 'agent_3'
        assert f.problem.startswith('at t = 2.00 s')
        assert 'change the velocities of agent_3' in f.fix


def test_nearly_collinear_onset_after_t0_and_the_narrowest_angle():
    """y(t) = 0.03 + 0.5 sin t: nearly collinear at t = 0 (the static check's warning, not
    repeated), clear, then again around t = π, narrowest at the sample nearest y = 0."""
    scenario = _scenario([
        {'name': 'agent_1', 'position': [0, 0, 0]},
        {'name': 'agent_2', 'position': [2, 0, 0]},
        {'name': 'agent_3', 'position': [1, 0.03, 0],
         'velocity': {'world': [0, {'cos': 1, 'amplitude': 0.5}, 0]},
         'neighbours': ['agent_1', 'agent_2']}], duration=5.0)
    times, _ = check_module.sample_truth(scenario)
    angle = np.degrees(2 * np.arctan(np.abs(0.03 + 0.5 * np.sin(times))))
    near = angle < bearing_leaders.COLLINEAR_WARN_DEG
    assert near[0] and not near[1]
    later = np.flatnonzero(near[1:]) + 1
    first, worst = later[0], later[np.argmin(angle[later])]
    report = check_scenario(scenario)
    static = [f for f in report.findings if f.field == 'neighbours' and 'collinear' in f.problem]
    moving = [f for f in report.findings if f.field == 'velocity' and 'collinear' in f.problem]
    assert len(static) == 1 and len(moving) == 1
    assert moving[0].severity == 'warning'
    assert moving[0].problem.startswith(
        f'at t = {times[first]:.2f} s its bearings become nearly collinear (widest angle '
        f'{angle[first]:.2f} deg, down to {angle[worst]:.2f} deg at t = {times[worst]:.2f} s)')


def test_what_holds_from_t0_is_not_repeated():
    """A follower that moves with its neighbours keeps the t = 0 geometry: the static check's
    findings (nearly collinear, repeated eigenvalues) only."""
    v = {'world': [0.2, {'sin': 0.5, 'amplitude': 0.3}, 0.1]}
    scenario = _scenario([
        {'name': 'agent_1', 'position': [0, 0, 0], 'velocity': v},
        {'name': 'agent_2', 'position': [2, 0, 0], 'velocity': v},
        {'name': 'agent_3', 'position': [1, 0.03, 0], 'velocity': v,
         'neighbours': ['agent_1', 'agent_2']}])
    report = check_scenario(scenario)
    assert scenario.moves
    assert [f.field for f in report.findings] == ['neighbours'] * len(report.findings)
    assert any('nearly collinear' in f.problem for f in report.findings)


# ----------------------------------------------------------------------------- static: unchanged
PAPER_REPORT = """\
warning: agent_8.neighbours: M_i = Σ k_ij b_ij b_ijᵀ has repeated eigenvalues {0, 1, 1}: \
Lemma 1's hypothesis fails (convergence is then not guaranteed). Fix: use different per-edge \
gains, e.g. `neighbours: [{name: agent_1, k: 2.0}, ...]`
spectra (eigenvalues of M_i = Σ_j k_ij b_ij b_ijᵀ):
  agent_3: {0, 0.2929, 1.707}
  agent_4: {0, 0.2929, 1.707}
  agent_5: {0, 0.2929, 1.707}
  agent_6: {0.1835, 1, 1.816}
  agent_7: {0.2929, 1, 1.707}
  agent_8: {0, 1, 1}"""


def test_static_scenarios_are_checked_as_before_without_sampling(monkeypatch):
    def no_sampling(*args, **kwargs):
        raise AssertionError('a static scenario was sampled')

    monkeypatch.setattr(check_module, 'sample_truth', no_sampling)
    scenario = load_scenario(PAPER)
    assert not scenario.moves
    assert check_scenario(scenario).format() == PAPER_REPORT


def test_a_moving_scenario_is_sampled_over_its_duration():
    scenario = _passing_follower(y0=3.0, vy=-1.0, duration=2.0)
    times, pos = check_module.sample_truth(scenario)
    assert times[0] == 0 and times[-1] == pytest.approx(2.0) and len(times) == 41
    np.testing.assert_allclose(pos[:, 2, 1], 3.0 - times, atol=1e-12)
    np.testing.assert_allclose(pos[:, :2], np.broadcast_to(pos[:1, :2], pos[:, :2].shape))


# ----------------------------------------------------------------------------- generate --speed
# sha256 of `generate --agents 10 --seed 3` before --speed existed: the static output is
# unchanged byte for byte.
STATIC_10_SEED_3 = '10d3e550dc3d437adab0c046f9bd4c86d3872329d75b8a9f7ab387903015d7ca'


def test_generate_static_output_is_unchanged(tmp_path):
    f = tmp_path / 'static.yaml'
    assert main(['generate', '--agents', '10', '--seed', '3', '--out', str(f)]) == 0
    g = tmp_path / 'static0.yaml'
    assert main(['generate', '--agents', '10', '--seed', '3', '--speed', '0',
                 '--out', str(g)]) == 0
    assert f.read_bytes() == g.read_bytes()
    assert hashlib.sha256(f.read_bytes()).hexdigest() == STATIC_10_SEED_3
    assert not load_scenario(str(f)).moves


def test_generate_moving_fleet_round_trip(tmp_path, capsys):
    f, g, h = tmp_path / 'a.yaml', tmp_path / 'b.yaml', tmp_path / 'c.yaml'
    argv = ['generate', '--agents', '50', '--seed', '7', '--speed', '0.3']
    assert main(argv + ['--out', str(f)]) == 0
    assert main(argv + ['--out', str(g)]) == 0
    assert f.read_bytes() == g.read_bytes()                       # seeded
    assert main(['generate', '--agents', '50', '--seed', '8', '--speed', '0.3',
                 '--out', str(h)]) == 0
    assert h.read_bytes() != f.read_bytes()
    text = f.read_text()
    assert text.startswith('# Generated by: bearing-pose generate --agents 50 --seed 7 '
                           '--max-angle-deg 90 --speed 0.3 --turn-rate 0.5\n')
    data = yaml.safe_load(text)
    vel = data['agents'][0]['velocity']['world']
    assert vel[0]['cos'] == 0.5 and vel[0]['amplitude'] == 0.3 and vel[2]['amplitude'] == 0.09

    scenario = load_scenario(str(f))
    assert scenario.moves and len(scenario.agents) == 50
    report = check_scenario(scenario)
    assert report.ok and not _approaches(report)
    capsys.readouterr()
    assert main(['check', str(f)]) == 0
    assert '0 error(s)' in capsys.readouterr().out

    # It moves: 0.3 m/s around a circle of radius 0.6 m ...
    truth = Truth(scenario, 0.01)
    p0 = truth.p.copy()
    for _ in range(300):
        truth.advance()
    moved = np.linalg.norm(truth.p - p0, axis=1)
    assert np.all(moved > 0.3)
    np.testing.assert_allclose(np.linalg.norm(truth.velocity()[:, :2], axis=1), 0.3)
    # ... and the fleet keeps its shape: relative drift within the designed bound.
    times, pos = check_module.sample_truth(scenario)
    rel0 = pos[0][:, None] - pos[0][None]
    drift = np.linalg.norm(pos[:, :, None] - pos[:, None] - rel0, axis=-1).max()
    assert 0.01 < drift <= MAX_RELATIVE_DRIFT_M
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    d[:, np.arange(50), np.arange(50)] = np.inf
    assert d.min() >= MIN_SPACING_M - MAX_RELATIVE_DRIFT_M > graph.CLOSE_APPROACH_M


@pytest.mark.parametrize('extra', [['--speed', '-1'], ['--speed', 'nan'],
                                   ['--speed', '0.3', '--turn-rate', '0']])
def test_generate_bad_motion_options_exit_2(extra):
    with pytest.raises(SystemExit) as exc:
        main(['generate', '--agents', '10', '--out', 'x.yaml'] + extra)
    assert exc.value.code == 2
