"""A restarted neighbour announces its reset with its covariance, and its listeners leave it out
until it knows its pose about as well as they know theirs (runtime ``AgentRuntime._distrust``;
issue 29: the returning agent's cold estimate cost its listeners more than its absence)."""
from __future__ import annotations

import math
from collections import Counter

from bearing_pose_estimation.runtime.buffers import Limits
from bearing_pose_estimation.runtime.faults import LinkFaults
from bearing_pose_estimation.runtime.health import health
from bearing_pose_estimation.scenario import load_scenario
from bearing_pose_estimation.sim.netsim import Garbage, Outage, _Network

from presenza_fleet import ROOT

RESTART = (Outage('agent_4', 6.0, 8.0, restart=True),)
RECORDS = (8.0, 8.5, 9.0, 9.5)


def _restart(limits: Limits):
    """netsim (as ``simulate_network``), agent_4 killed at 6 s and restarted at 8 s: the
    network at 9.5 s and agent_5's attitude error at :data:`RECORDS`."""
    scenario = load_scenario(ROOT / 'config' / 'paper_8_agents.yaml')
    net = _Network(scenario, LinkFaults(), RESTART, Garbage(), limits)
    net.start()
    dt, agent_5 = net.world.dt, net.names.index('agent_5')
    err = {}
    for tick in range(1, int(round(RECORDS[-1] / dt)) + 1):
        if tick == int(round(8.0 / dt)):
            net.restart('agent_4', tick * dt)
        net.tick(tick * dt)
        if any(abs(tick * dt - t) < dt / 2 for t in RECORDS):
            err[round(tick * dt, 3)] = net.errors([agent_5]).att_err[0]
    resets = {n: dict(a.resets) for n, a in net.agents.items() if a.resets}
    return net, resets, err


def test_listeners_leave_out_a_neighbour_that_restarted_cold():
    """Without a warm start (``warm_window`` 0, as when it is refused) agent_4 comes back from
    its initial estimate, 2.5 rad off, with the prior's covariance. Its listeners count one
    reset each, say so in /diagnostics, and agent_5 holds its error for the 1.5 s after;
    taking agent_4 at its word (``reset_trust`` inf: no reset is ever announced) multiplies
    it by more than 5."""
    net, resets, err = _restart(Limits(warm_window=0.0))
    assert resets == {n: {'agent_4': 1} for n in ('agent_5', 'agent_6', 'agent_7')}, resets
    assert max(err[t] for t in RECORDS[1:]) <= 1.1 * err[8.0], err
    values = health(net.agents['agent_5'], Counter(), Counter()).values
    assert values['resets_agent_4'] == '1' and values['left_out_agent_4'].endswith('(now)')
    assert 'resets_agent_3' not in values
    _, resets, err = _restart(Limits(warm_window=0.0, reset_trust=math.inf))
    assert not resets
    assert max(err[t] for t in RECORDS[1:]) > 5.0 * err[8.0], err


def test_a_settled_warm_start_announces_no_reset():
    """With its warm start accepted, the restarted agent's covariance is the fit's, small:
    nothing is announced and its listeners take it at once; nor does any agent announce one
    in the 6 s of the fleet's start."""
    net, resets, _ = _restart(Limits())
    assert net.agents['agent_4'].warm_starts == {'accepted': 1} and not resets, resets
