"""Trajectories of moving fleets: the batch simulator records every agent's true and world-frame
estimated positions (only when the fleet moves), `plot_trajectories` draws them, and
`bearing-pose simulate` writes `trajectories.png` for moving scenarios only."""
import struct
from pathlib import Path

import numpy as np
import pytest

from bearing_pose_estimation.cli.main import main
from bearing_pose_estimation.estimators.base import EstimateFrame
from bearing_pose_estimation.scenario import load_scenario
from bearing_pose_estimation.sim.batch import BatchSimulator
from bearing_pose_estimation.scenario.truth import Truth
from bearing_pose_estimation.studies import plots
from bearing_pose_estimation.metrics.results import PoseErrors, Recording

CONFIG = Path(__file__).resolve().parents[1] / 'config'
MOVING = CONFIG / 'paper_8_agents_moving.yaml'
STATIC = CONFIG / 'paper_8_agents.yaml'
PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


def _png_size(path):
    """Width and height from the PNG's IHDR chunk (after checking the signature)."""
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC and data[12:16] == b'IHDR'
    return struct.unpack('>II', data[16:24])


@pytest.fixture(scope='module')
def moving_run():
    scenario = load_scenario(str(MOVING))
    sim = BatchSimulator(scenario)
    return scenario, sim, sim.run(3.0, record_every=0.1)


def test_a_moving_run_records_the_true_trajectories(moving_run):
    scenario, sim, rec = moving_run
    tr = rec.trajectories
    assert tr is not None
    names = [a.name for a in scenario.agents]
    assert tr.agents == names and tr.leaders == ['agent_1', 'agent_2']
    assert tr.is_leader.tolist() == [True, True] + [False] * 6
    assert tr.p.shape == tr.p_hat.shape == (len(rec.t), 8, 3) == (31, 8, 3)
    # The truth re-run on its own, stepped to each record time: the same positions, exactly.
    truth = Truth(scenario, sim.h)
    for k, t in enumerate(rec.t):
        while truth.k < int(round(t / sim.h)):
            truth.advance()
        assert truth.t == pytest.approx(t)
        np.testing.assert_array_equal(tr.p[k], truth.p)
    # They do move (0.3 m/s for 3 s: about 0.9 m of path, a chord of more than 0.5 m).
    assert np.linalg.norm(tr.p[-1] - tr.p[0], axis=1).min() > 0.5


def test_the_recorded_estimates_are_the_world_frame_ones_the_errors_measure(moving_run):
    scenario, sim, rec = moving_run
    tr = rec.trajectories
    rows = [scenario.index[name] for name in rec.followers]
    # The followers' position errors are the distances between the two trajectories ...
    np.testing.assert_allclose(np.linalg.norm(tr.p[:, rows] - tr.p_hat[:, rows], axis=2),
                               rec.pos_err, rtol=0, atol=1e-12)
    # ... the estimates start at the scenario's initial estimates (a world-frame method) ...
    np.testing.assert_array_equal(tr.p_hat[0, scenario.index['agent_3']], [-2.0, 0.0, -1.0])
    assert rec.pos_err[0].min() > 0.5
    # ... and the leaders' estimates are their truth.
    np.testing.assert_allclose(tr.p_hat[:, :2], tr.p[:, :2], rtol=0, atol=1e-12)


def test_estimates_are_recorded_after_the_methods_alignment(monkeypatch):
    """For estimates in an unknown common yaw-and-translation frame, the recording holds them
    aligned to the world (as the errors are), not as the estimator holds them."""
    scenario = load_scenario(str(MOVING))
    sim = BatchSimulator(scenario)
    monkeypatch.setattr(type(sim.estimator), 'frame', EstimateFrame.COMMON_YAW_TRANSLATION)
    rec = sim.run(0.5, record_every=0.1)
    tr = rec.trajectories
    raw = sim.x.p_hat
    assert np.abs(tr.p_hat[-1] - raw).max() > 0.1          # the alignment moved them
    # The centroid is aligned onto the truth's; the errors are the distances.
    np.testing.assert_allclose(tr.p_hat[-1].mean(axis=0), tr.p[-1].mean(axis=0), atol=1e-12)
    rows = [scenario.index[name] for name in rec.followers]
    np.testing.assert_allclose(np.linalg.norm(tr.p[:, rows] - tr.p_hat[:, rows], axis=2),
                               rec.pos_err, rtol=0, atol=1e-12)


def test_a_static_run_records_no_trajectories():
    rec = BatchSimulator(load_scenario(str(STATIC))).run(0.5)
    assert rec.trajectories is None
    with pytest.raises(ValueError, match='no trajectories'):
        plots.plot_trajectories(rec, Path('/nonexistent/never_written.png'))


def test_recording_of_checks_the_trajectories():
    errors = PoseErrors(*(np.zeros(1) for _ in PoseErrors._fields))
    p = [np.zeros((2, 3)), np.ones((2, 3))]
    rec = Recording.of([0.0, 1.0], ['b'], [errors, errors], agents=['a', 'b'], leaders=['a'],
                       p=p, p_hat=p)
    assert rec.trajectories is not None and rec.trajectories.p.shape == (2, 2, 3)
    assert Recording.of([0.0, 1.0], ['b'], [errors, errors]).trajectories is None
    with pytest.raises(ValueError, match='together'):
        Recording.of([0.0, 1.0], ['b'], [errors, errors], agents=['a', 'b'], p=p)
    with pytest.raises(ValueError, match=r'must be \(2, 2, 3\)'):
        Recording.of([0.0, 1.0], ['b'], [errors, errors], agents=['a', 'b'], p=p, p_hat=p[:1])
    with pytest.raises(ValueError, match='not among the agents: c'):
        Recording.of([0.0, 1.0], ['b'], [errors, errors], agents=['a', 'b'], leaders=['c'],
                     p=p, p_hat=p)


def test_the_trajectory_plot_is_a_png(moving_run, tmp_path):
    _, _, rec = moving_run
    path = plots.plot_trajectories(rec, tmp_path / 'trajectories.png', title='moving')
    assert path == tmp_path / 'trajectories.png'
    width, height = _png_size(path)
    assert width > height > 400
    assert path.stat().st_size > 40_000  # lines and markers, not an empty canvas


def test_a_large_fleet_draws_a_sample_including_the_leaders(tmp_path):
    is_leader = np.zeros(50, dtype=bool)
    is_leader[[3, 40]] = True
    shown = plots._shown_agents(is_leader, plots.MAX_TRAJECTORIES)
    assert len(shown) == plots.MAX_TRAJECTORIES == 20 and len(set(shown.tolist())) == 20
    assert {3, 40} <= set(shown.tolist()) and shown[0] == 0 and shown[-1] == 49
    assert plots._shown_agents(is_leader[:8], 20).tolist() == list(range(8))
    # A whole plot of a 50-agent recording is written too.
    K, N = 5, 50
    names = [f'agent_{k + 1}' for k in range(N)]
    rng = np.random.default_rng(1)
    p = rng.normal(size=(K, N, 3)).cumsum(axis=0)
    followers = [n for n, lead in zip(names, is_leader) if not lead]
    errs = [PoseErrors(*(rng.uniform(0.1, 1.0, len(followers)) for _ in PoseErrors._fields))
            for _ in range(K)]
    rec = Recording.of(np.arange(K, dtype=float), followers, errs, agents=names,
                       leaders=[names[3], names[40]], p=list(p), p_hat=list(p + 0.1))
    _png_size(plots.plot_trajectories(rec, tmp_path / 'big.png'))


def test_simulate_writes_trajectories_for_moving_scenarios_only(tmp_path, capsys):
    out = tmp_path / 'moving'
    argv = ['simulate', str(MOVING), '--duration', '1', '--out', str(out), '--quiet']
    assert main(argv) == 0
    _png_size(out / 'trajectories.png')
    assert str(out / 'trajectories.png') in capsys.readouterr().out
    # It is an output like the others: never overwritten without --force.
    for name in ('metrics.csv', 'summary.json', 'fig2_attitude_error.png',
                 'fig3_position_error.png'):
        (out / name).unlink()
    before = (out / 'trajectories.png').stat().st_mtime_ns
    assert main(argv) == 1
    assert f'{out / "trajectories.png"}: exists' in capsys.readouterr().err
    assert (out / 'trajectories.png').stat().st_mtime_ns == before
    assert main(argv + ['--force']) == 0
    # --no-plots: no trajectory plot either.
    bare = tmp_path / 'bare'
    assert main(argv[:5] + [str(bare), '--quiet', '--no-plots']) == 0
    assert sorted(f.name for f in bare.iterdir()) == ['metrics.csv', 'summary.json']
    # A static scenario: the usual outputs only.
    static = tmp_path / 'static'
    capsys.readouterr()
    assert main(['simulate', str(STATIC), '--duration', '1', '--out', str(static),
                 '--quiet']) == 0
    assert not (static / 'trajectories.png').exists()
    assert 'trajectories' not in capsys.readouterr().out
