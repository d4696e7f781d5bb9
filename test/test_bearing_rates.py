"""Bearing rates from consecutive bearings (core.bearing_rates, `sensors.bearing_rates:
{from_bearings: true, tau: ...}`) for Presenza et al.'s free robots, without a bearing-rate
sensor: the differences against the analytic rate, the filter's lag, the node logic equal to
the batch simulator, and what the choice costs on case 1 at 30 Hz."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.core.bearing_rates import BearingRateFilter
from bearing_pose_estimation.scenario import ScenarioError, parse_scenario
from bearing_pose_estimation.sim.batch import BatchSimulator

sys.path.insert(0, str(Path(__file__).resolve().parent))
from presenza_fleet import CAMERA_RATE, Fleet  # noqa: E402


def _bearing(t: float) -> tuple[np.ndarray, np.ndarray]:
    """A body turning at ω about a tilted axis sees a target moving on a circle: the body
    bearing at t and the body's attitude."""
    omega = np.array([0.3, -0.2, 1.1])
    R = so3.exp(omega * t)
    target = np.array([5.0 + np.cos(t), 2.0 * np.sin(t), 1.0 + 0.5 * t])
    b_world = target / np.linalg.norm(target)
    return R.T @ b_world, R


def _derotated(t: float) -> np.ndarray:
    """d/dt of the world bearing, in the body frame at t (what the differences estimate)."""
    eps = 1e-6
    (_, R), (b1, R1), (b0, R0) = _bearing(t), _bearing(t + eps), _bearing(t - eps)
    return R.T @ (R1 @ b1 - R0 @ b0) / (2 * eps)


@pytest.mark.parametrize('h', [0.01, 0.002])
def test_raw_differences_are_the_derotated_rate_to_first_order(h):
    filt = BearingRateFilter(1, tau=0.0)
    errors = []
    for k in range(50):
        t = k * h
        b, R = _bearing(t)
        dR = (_bearing(t - h)[1].T @ R) if k else np.eye(3)
        rate, have = filt.update(t, b[None], dR[None])
        assert bool(have[0]) == (k > 0)   # no rate before the second sample
        if k:
            errors.append(np.linalg.norm(rate[0] - _derotated(t)))
    # First order in h (0.043 h here, the rate itself about 0.33/s).
    assert max(errors) < 0.1 * h


def test_the_filter_lags_by_about_tau():
    """A bearing turning at a constant rate that starts at t = 0.5 s: the filtered rate
    reaches 63 % of it about tau after the start."""
    tau, h = 0.2, 0.005
    filt = BearingRateFilter(1, tau=tau)
    w = 0.4   # [rad/s] about z
    reached = None
    for k in range(400):
        t = k * h
        angle = w * max(0.0, t - 0.5)
        b = np.array([np.cos(angle), np.sin(angle), 0.0])
        rate, _ = filt.update(t, b[None], np.eye(3)[None])
        if reached is None and rate[0, 1] >= 0.63 * w:
            reached = t - 0.5
    assert reached == pytest.approx(tau, abs=2 * h)
    with pytest.raises(ValueError, match='tau must be >= 0'):
        BearingRateFilter(1, tau=-1.0)


def _scenario(rates: dict, noise: float = 0.0, duration: float = 2.0):
    d = yaml.safe_load(CAMERA_RATE.read_text())
    d['sensors'] = {**d['sensors'], 'bearing_rates': rates}
    d['duration'] = duration
    if noise:
        d['noise'] = {'bearing_std': noise, 'seed': 1}
    return parse_scenario(d)


def test_the_robots_logic_estimates_them_as_the_batch_simulator_does():
    s = _scenario({'from_bearings': True})
    assert not s.simulates('bearing_rates') and s.provides('bearing_rates')
    fleet = Fleet(s)
    fleet.run(2.0)
    batch = BatchSimulator(s)
    batch.run(2.0, record_every=1.0)
    for name in fleet.names:
        agent, i = fleet.agents[name], s.index[name]
        assert agent.rate_tau == 0.0 and agent.k == 60
        np.testing.assert_allclose(agent.p_hat[0], batch.x.p_hat[i], atol=1e-9)
        np.testing.assert_allclose(agent.R_hat[0], batch.x.R_hat[i], atol=1e-9)


def _free_attitude_error(s, T: float = 10.0) -> float:
    rec = BatchSimulator(s).run(T, record_every=0.5)
    free = [rec.followers.index(a.name) for a in s.agents if len(a.neighbours) < 2]
    return float(rec.att_err[rec.t >= T - 3.0][:, free].mean())


def test_raw_differences_converge_and_a_slow_filter_costs_more_than_noise():
    """Case 1 at 30 Hz with 1 mrad of bearing noise, the free robots' attitude error over the
    last 3 of 10 s: a sensor does best; raw differences of the noisy bearings converge too;
    a filter with tau = 0.3 s is worse than no filter (its lag, at these motions)."""
    sensor = _free_attitude_error(_scenario({'rate': 30.0}, noise=1e-3))
    raw = _free_attitude_error(_scenario({'from_bearings': True}, noise=1e-3))
    slow = _free_attitude_error(_scenario({'from_bearings': True, 'tau': 0.3}, noise=1e-3))
    assert sensor < raw < 0.3 < slow, (sensor, raw, slow)


@pytest.mark.parametrize('rates, message', [
    ({'tau': 0.1}, 'sensors.bearing_rates.tau: tau filters bearing rates estimated from '
                   'bearings'),
    ({'from_bearings': 'yes'}, 'sensors.bearing_rates.from_bearings: expected true or false'),
    ({'from_bearings': True, 'std': 0.01}, 'rate and std describe a bearing-rate sensor'),
    ({'from_bearings': True, 'tau': -1}, 'sensors.bearing_rates.tau'),
])
def test_bad_options_name_the_field_and_the_fix(rates, message):
    with pytest.raises(ScenarioError, match='Fix:') as info:
        _scenario(rates)
    assert message in str(info.value)
