"""Noise models (noise.py): parsing, each model's exact effect, reproducibility, and the same
models in the batch simulator and the simulator node's world."""
import copy
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.sim.noise import NoiseModel
from bearing_pose_estimation.scenario import (BearingPerturbation, Noise, ScenarioError,
                                              parse_scenario)
from bearing_pose_estimation.sim.batch import BatchSimulator
from bearing_pose_estimation.sim.world import World

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'
ALL_ON = {'gyro_std': 0.01, 'gyro_bias': [0.002, -0.001, 0.003], 'gyro_bias_std': 0.002,
          'bearing_std': 0.01, 'bearing_perturbation': {'amplitude_deg': 2.0, 'frequency_hz': 0.5},
          'outlier_probability': 0.01, 'seed': 7}


@pytest.fixture()
def paper_data() -> dict:
    return yaml.safe_load(PAPER.read_text())


def _with_noise(data: dict, **noise) -> dict:
    data = copy.deepcopy(data)
    data['noise'] = noise
    return data


def _unit(n: int, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# ----------------------------------------------------------------------------- parsing
def test_noise_is_off_by_default_and_parses(paper_data):
    del paper_data['noise']
    assert parse_scenario(paper_data).noise == Noise()
    nz = parse_scenario(_with_noise(paper_data, **ALL_ON)).noise
    assert nz.gyro_bias == (0.002, -0.001, 0.003) and nz.gyro_bias_std == 0.002
    assert nz.bearing_perturbation == BearingPerturbation(amplitude_deg=2.0, frequency_hz=0.5)
    tilted = _with_noise(paper_data, bearing_perturbation={'amplitude_deg': 2, 'frequency_hz': 1,
                                                           'axis': [0, 0, 2]})
    assert parse_scenario(tilted).noise.bearing_perturbation.axis == (0.0, 0.0, 1.0)
    assert nz.outlier_probability == 0.01 and nz.seed == 7


@pytest.mark.parametrize('noise, message', [
    ({'outlier_probability': 1.0}, 'noise.outlier_probability: must be in [0, 1)'),
    ({'outlier_probability': -0.1}, 'noise.outlier_probability: must be in [0, 1)'),
    ({'outlier_probability': 'often'}, 'noise.outlier_probability: expected a number'),
    ({'bearing_perturbation': {'amplitude_deg': 91, 'frequency_hz': 1}},
     'noise.bearing_perturbation.amplitude_deg: must be in [0, 90]'),
    ({'bearing_perturbation': {'amplitude_deg': -1, 'frequency_hz': 1}},
     'noise.bearing_perturbation.amplitude_deg: must be in [0, 90]'),
    ({'bearing_perturbation': {'amplitude_deg': 5, 'frequency_hz': 0}},
     'noise.bearing_perturbation.frequency_hz: must be > 0'),
    ({'bearing_perturbation': {'amplitude_deg': 5}},
     'noise.bearing_perturbation.frequency_hz: missing required field'),
    ({'bearing_perturbation': {'amplitude': 5, 'frequency_hz': 1}},
     'noise.bearing_perturbation.amplitude: unknown key'),
    ({'bearing_perturbation': 5}, 'noise.bearing_perturbation: expected a mapping'),
    ({'bearing_perturbation': {'amplitude_deg': 5, 'frequency_hz': 1, 'axis': [0, 0, 0]}},
     'noise.bearing_perturbation.axis: axis is zero'),
    ({'gyro_bias': [0.1, 0.2]}, 'noise.gyro_bias: expected a list of 3 numbers'),
    ({'gyro_bias': [0.1, 'x', 0.2]}, 'noise.gyro_bias[1]: expected a number'),
    ({'gyro_bias_std': -0.01}, 'noise.gyro_bias_std: must be >= 0'),
    ({'gyro_drift': 0.01}, 'noise.gyro_drift: unknown key'),
    ({'seed': 1.5}, 'noise.seed: expected an integer'),
])
def test_noise_errors_name_the_field(paper_data, noise, message):
    with pytest.raises(ScenarioError) as exc:
        parse_scenario(_with_noise(paper_data, **noise), source='s.yaml')
    assert f's.yaml: {message}' in str(exc.value) and 'Fix:' in str(exc.value)


# ----------------------------------------------------------------------------- the models
@pytest.mark.parametrize('axis', [(1.0, 0.0, 0.0), (0.0, 0.6, 0.8)])
def test_deterministic_perturbation_is_exactly_rot_X(axis):
    theta0, f, t = 20.0, 0.7, 0.37
    bp = BearingPerturbation(theta0, f, axis)
    model = NoiseModel(Noise(bearing_perturbation=bp), 3)
    b = _unit(50)
    angle = math.radians(theta0) * math.sin(2 * math.pi * f * t)
    expected = Rotation.from_rotvec(angle * np.array(axis)).apply(b)  # scipy, independently
    np.testing.assert_allclose(model.bearings(b, t), expected, atol=1e-15)
    assert abs(angle) > 0.1  # a real rotation at this t
    # Deterministic: no randomness, same output every call; zero at t = 0.
    np.testing.assert_array_equal(model.bearings(b, t), model.bearings(b, t))
    np.testing.assert_allclose(model.bearings(b, 0.0), b, atol=1e-16)


def test_outliers_have_the_configured_frequency_and_are_unit_vectors():
    p, n = 0.1, 10000
    model = NoiseModel(Noise(outlier_probability=p, seed=3), 2)
    b = np.tile([0.0, 0.0, 1.0], (n, 1))
    out = model.bearings(b, 1.0)
    hit = np.any(out != b, axis=1)
    assert abs(hit.mean() - p) < 0.02          # binomial std is 0.003: 6.7 sigma
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-14)
    # Uniform on the sphere: mean near 0 (std of the mean of ~1000 is ~0.018).
    assert np.abs(out[hit].mean(axis=0)).max() < 0.1
    np.testing.assert_array_equal(out[~hit], b[~hit])   # the others are untouched


def test_gyro_bias_fixed_and_per_agent_draw():
    model = NoiseModel(Noise(gyro_bias=(0.1, -0.2, 0.3)), 4)
    np.testing.assert_array_equal(model.bias, np.tile([0.1, -0.2, 0.3], (4, 1)))
    omega = np.ones((4, 3))
    np.testing.assert_array_equal(model.gyro_rate(omega), omega + model.bias)
    drawn = NoiseModel(Noise(gyro_bias_std=0.05, seed=1), 2000).bias
    assert np.std(drawn) == pytest.approx(0.05, rel=0.05) and abs(drawn.mean()) < 0.005
    assert not np.array_equal(drawn[0], drawn[1])       # each agent its own
    np.testing.assert_array_equal(drawn, NoiseModel(Noise(gyro_bias_std=0.05, seed=1),
                                                    2000).bias)   # seeded
    assert not np.array_equal(drawn, NoiseModel(Noise(gyro_bias_std=0.05, seed=2), 2000).bias)


# ----------------------------------------------------------------------------- batch simulator
def test_batch_gyro_increment_includes_the_bias(paper_data):
    s = parse_scenario(_with_noise(paper_data, gyro_bias=[0.01, -0.02, 0.03]))
    sim = BatchSimulator(s)
    dR = so3.exp(np.random.default_rng(0).normal(size=(sim.n, 3)) * 0.01)
    expected = dR @ so3.exp(sim.h * np.array([0.01, -0.02, 0.03]))
    np.testing.assert_allclose(sim.gyro_increment(dR), expected, atol=1e-15)


def test_gyro_bias_moves_the_converged_estimate(paper_data):
    """Noise-free otherwise: without bias the errors go to ~0; a 0.01-0.02 rad/s bias leaves
    a finite, clearly measurable steady error."""
    clean = BatchSimulator(parse_scenario(paper_data)).run(40.0, record_every=1.0)
    biased = BatchSimulator(parse_scenario(
        _with_noise(paper_data, gyro_bias=[0.01, -0.02, 0.01]))).run(40.0, record_every=1.0)
    for rec in (clean, biased):
        assert np.all(np.isfinite(rec.att_err)) and np.all(np.isfinite(rec.pos_err))
    att_c, att_b = clean.att_err[-5:].mean(), biased.att_err[-5:].mean()
    pos_c, pos_b = clean.pos_err[-5:].mean(), biased.pos_err[-5:].mean()
    assert att_c < 1e-4 and pos_c < 1e-2
    assert 3e-3 < att_b < 0.2 and att_b > 50 * att_c
    assert pos_b > 10 * pos_c and pos_b < 1.0


def test_same_seed_same_recording_different_seed_different(paper_data):
    def run(seed: int):
        s = parse_scenario(_with_noise(paper_data, **{**ALL_ON, 'seed': seed}))
        return BatchSimulator(s).run(3.0, record_every=0.5)

    a, b, c = run(7), run(7), run(8)
    for field in ('t', 'att_err', 'pos_err', 'att_dist_I', 'pos_err_paper'):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.followers == b.followers
    assert not np.array_equal(a.att_err, c.att_err)
    assert not np.array_equal(a.pos_err, c.pos_err)


# ----------------------------------------------------------------------------- world (node)
def _imu_after_one_period(world: World) -> np.ndarray:
    for _ in range(world.imu_every):
        world.step()
    return world.imu()


def test_world_applies_the_same_models(paper_data):
    bias = [0.01, -0.02, 0.03]
    clean = World(parse_scenario(paper_data))
    biased = World(parse_scenario(_with_noise(paper_data, gyro_bias=bias)))
    np.testing.assert_allclose(_imu_after_one_period(biased) - _imu_after_one_period(clean),
                               np.tile(bias, (8, 1)), atol=1e-12)

    theta0, f = 10.0, 2.0
    pert = World(parse_scenario(_with_noise(
        paper_data, bearing_perturbation={'amplitude_deg': theta0, 'frequency_hz': f})))
    clean = World(parse_scenario(paper_data))
    for _ in range(37):
        pert.step()
        clean.step()
    t = pert.t
    angle = math.radians(theta0) * math.sin(2 * math.pi * f * t)
    assert abs(angle) > 0.05
    j, b = pert.bearings(5)
    j0, b_clean = clean.bearings(5)
    np.testing.assert_array_equal(j, j0)
    np.testing.assert_allclose(b, Rotation.from_rotvec([angle, 0, 0]).apply(b_clean),
                               atol=1e-14)


def test_world_noise_is_reproducible(paper_data):
    def samples(seed: int):
        w = World(parse_scenario(_with_noise(paper_data, **{**ALL_ON, 'seed': seed})))
        out = []
        for _ in range(3):
            out.append(_imu_after_one_period(w))
            out.append(w.bearings(3)[1])
        return out

    a, b, c = samples(7), samples(7), samples(8)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))


def _agent_4_errors(bias_std: float, seed: int) -> np.ndarray:
    """agent_4's position errors p̂ - p every 0.1 s over 30-50 s of paper_noisy (1° bearing
    noise, 0.01 rad/s gyro noise), with the projector compensation ``bias_std``."""
    from dataclasses import replace

    from bearing_pose_estimation.scenario import load_scenario
    from bearing_pose_estimation.studies.montecarlo import reseed

    s = reseed(load_scenario(PAPER.parent / 'paper_noisy.yaml'), seed)
    s = replace(s, gains=replace(s.gains, bias_std=bias_std))
    b = BatchSimulator(s)
    out = []
    for k in range(5000):
        b.step()
        if k >= 3000 and k % 10 == 0:
            out.append(b.x.p_hat[3] - b.p[3])
    return np.array(out)


def test_the_projector_compensation_removes_the_noise_bias_of_the_positions():
    """With 1° of bearing noise, the paper's position correction settles 2 cm off (the same
    in every run: the noisy projector's bias, bench/noise_bias.py); bias_std = that noise
    removes the bias and leaves the spread as it was."""
    sigma_b = np.radians(1.0)
    off = [_agent_4_errors(0.0, seed) for seed in range(3)]
    on = [_agent_4_errors(sigma_b, seed) for seed in range(3)]
    bias_off = np.linalg.norm(np.mean([e.mean(axis=0) for e in off], axis=0))
    bias_on = np.linalg.norm(np.mean([e.mean(axis=0) for e in on], axis=0))
    spread_off = np.mean([np.linalg.norm(e.std(axis=0)) for e in off])
    spread_on = np.mean([np.linalg.norm(e.std(axis=0)) for e in on])
    assert bias_off > 0.015 and bias_off > 2 * spread_off   # a bias, larger than the spread
    assert bias_on < 0.1 * bias_off
    assert spread_on < 1.2 * spread_off
