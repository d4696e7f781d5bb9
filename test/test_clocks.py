"""Robots whose clocks disagree. The runtime counts a neighbour whose stamps lead the own clock
by more than ``Limits.max_clock_lead`` and ``/diagnostics`` warns about it, by name and lead
(runtime/health.py, no DDS). The fault matrix's clock rows (netsim.clock_cases) are in each
method's matrix test (test_robustness.py, test_de_carli_faults.py, test_presenza_faults.py);
Tran et al.'s, which has no matrix test, are here."""
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bearing_pose_estimation.estimators.base import Sensor
from bearing_pose_estimation.runtime.buffers import Limits
from bearing_pose_estimation.runtime.health import OK, WARN, health
from bearing_pose_estimation.scenario import load_scenario
from bearing_pose_estimation.scenario.runtimes import agent_specs, runtime_for
from bearing_pose_estimation.sim.netsim import (Clocks, FaultCase, clock_cases, run_case,
                                                simulate_network)
from bearing_pose_estimation.sim.world import World
from clock_rows import clocks_ahead, flagged

CONFIG = Path(__file__).resolve().parents[1] / 'config'
PAPER = load_scenario(CONFIG / 'paper_8_agents.yaml')


def _fed(leads: dict[int, float], seconds: float = 0.5, with_now: bool = True,
         limits: Limits = Limits()):
    """agent_6's runtime (neighbours agent_2, agent_4, agent_5) fed for ``seconds``, each
    neighbour's messages stamped ``leads[id]`` [s] ahead of its clock (the world's time)."""
    world = World(PAPER)
    i = PAPER.index['agent_6']
    rt = runtime_for(PAPER, agent_specs(PAPER)[i], limits)
    sent = 0
    while world.t < seconds - 1e-9:
        world.step()
        if world.due(world.imu_every):
            assert rt.add_gyro(world.t, world.imu()[i], now=world.t) is None
        if world.due(world.bearing_every):
            j, b = world.bearings(i)
            assert rt.add_points(Sensor.BEARINGS, world.t, j + 1, b) == []
            for peer in rt.peers:
                d = world.p[i] - world.p[peer.agent_id - 1]
                values = {'p_hat': world.p[peer.agent_id - 1],
                          'world_bearing': {rt.agent_id: d / np.linalg.norm(d)}}
                stamp = world.t + leads.get(peer.agent_id, 0.0)
                assert rt.add_message(peer.agent_id, stamp, values,
                                      now=world.t if with_now else None) is None
            sent += 1
        rt.advance()
    return rt, sent


def test_a_neighbour_whose_clock_runs_ahead_is_flagged_by_name_and_lead():
    """agent_2's stamps lead by 50 ms, agent_4's by 5 ms: every message of agent_2 is counted
    and /diagnostics warns with its name and lead; agent_4 is within the limit (a LAN's latency
    and a step); both leads are reported."""
    rt, sent = _fed({2: 0.05, 4: 0.005})
    assert dict(rt.ahead) == {'agent_2': sent}
    assert rt.leads == pytest.approx({'agent_2': 0.05, 'agent_4': 0.005, 'agent_5': 0.0})
    report = health(rt, Counter(), Counter())
    assert report.level == WARN
    assert report.message == 'clock ahead of ours: agent_2 by 0.050 s (max_clock_lead 0.02 s)'
    assert report.values['clock_lead_agent_2_s'] == '0.0500'
    assert report.values['clock_lead_agent_4_s'] == '0.0050'
    assert report.values['clock_ahead_agent_2'] == str(sent)
    assert report.values['clock_ahead_agent_4'] == '0'
    # Its clock set right (or the limit raised), the warning goes; the count stays.
    rt.note_lead('agent_2', 1.0, now=1.0)
    report = health(rt, Counter(), Counter())
    assert report.level == OK and report.values['clock_ahead_agent_2'] == str(sent)
    rt.note_lead('agent_2', 1.05, now=1.0)
    rt.limits = replace(rt.limits, max_clock_lead=0.1)
    assert health(rt, Counter(), Counter()).level == OK


def test_no_lead_without_the_own_clock():
    """A caller that does not know its clock (``now`` None: the node on a simulated clock,
    which every node shares) measures no lead and flags nothing."""
    rt, _ = _fed({2: 0.05}, with_now=False)
    assert rt.leads == {} and not rt.ahead
    assert health(rt, Counter(), Counter()).level == OK


# ------------------------------------------------------------------------- Tran et al.'s rows
TRAN = load_scenario(CONFIG / 'tran_cube.yaml')
TRAN_DURATION = 5.0


@pytest.fixture(scope='module')
def tran_runs():
    cases = [FaultCase('reference', 'none'), *clock_cases()]
    return {c.key: (c, run_case(TRAN, c, TRAN_DURATION, 0.5)) for c in cases}


def test_tran_anderson_ahn_clock_rows(tran_runs):
    """Tran et al.'s cube is static, as the paper's fleet (test_robustness.py): what a
    neighbour sends is constant in the world frame and each robot pairs its own bearings and
    gyro on its own clock, so a fixed offset costs nothing (the fault-free errors to
    rounding); only the listeners whose clock is 100 ms behind a neighbour's flag it. A
    ±100 ppm drift scales each robot's gyro integration by 1 ± 1e-4: at most 3.4 % off the
    fault-free attitude errors over 5 s (measured), never a non-finite estimate."""
    ref = tran_runs['reference'][1].recording
    for key, (case, run) in tran_runs.items():
        rec = run.recording
        assert run.non_finite_estimates == 0 and run.non_finite_steps == 0
        assert not run.inputs.rejected and not run.inputs.events
        if key in ('clock_5ms', 'clock_50ms'):
            np.testing.assert_allclose(rec.att_err, ref.att_err, rtol=1e-9)
            np.testing.assert_allclose(rec.pos_err, ref.pos_err, rtol=1e-9)
            assert flagged(run.ahead) == clocks_ahead(TRAN, case.clocks)
    assert flagged(tran_runs['clock_50ms'][1].ahead)   # someone is 100 ms behind
    drift = tran_runs['clock_drift'][1].recording
    change = np.abs(drift.att_err / ref.att_err - 1.0).max()
    assert 0.0 < change < 0.05, change


def test_a_static_fleet_stops_hearing_a_neighbour_neighbour_timeout_behind(tran_runs):
    """What bounds the static fleets' indifference to offsets: a neighbour whose stamps are more
    than ``neighbour_timeout`` (0.5 s) behind the own clock reads as silent and is left out. At
    ±200 ms (0.4 s apart) Tran et al.'s cube gives the fault-free estimates; at ±300 ms (0.6 s)
    the followers ahead of a neighbour lose it and do not converge (0.75 rad and 3.2 m after
    60 s, bench/clock_floor.py); with neighbour_timeout 1 s the same ±300 ms costs nothing."""
    ref = tran_runs['reference'][1].recording
    near = simulate_network(TRAN, TRAN_DURATION, 0.5, clocks=Clocks(offset=0.2)).recording
    far = simulate_network(TRAN, TRAN_DURATION, 0.5, clocks=Clocks(offset=0.3)).recording
    patient = simulate_network(TRAN, TRAN_DURATION, 0.5, clocks=Clocks(offset=0.3),
                               limits=Limits(neighbour_timeout=1.0)).recording
    np.testing.assert_allclose(near.att_err, ref.att_err, rtol=1e-9)
    np.testing.assert_allclose(patient.att_err, ref.att_err, rtol=1e-9)
    np.testing.assert_allclose(patient.pos_err, ref.pos_err, rtol=1e-9)
    # agent_3 (clock +0.3 s) hears only leader agent_1: agent_2 (-0.3 s) is stale.
    assert far.att_err[-1, 0] > 10.0 * ref.att_err[-1, 0]   # 0.54 against 0.035 rad
