"""Adding a method is adding one module: a toy third estimator, written here from the interface
alone (no code of the two methods), registered inside the test, passes the contract and runs
through the batch simulator and the node logic (netsim) without any other module knowing it.

The toy: the attitude observer (3) of Boughellaba & Tayebi and a first-order bearing-only
position observer ``dp̂_i/dt = -k Σ_j P_{R̂_i b^i_ij} (p̂_i - p̂_j)``, one gain ``k`` for both,
its own name for the position channel, and odometry feed-forward ``+ R̂_i v_i`` for moving
fleets."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import yaml

from bearing_pose_estimation import estimators
from bearing_pose_estimation.core import so3
from bearing_pose_estimation.estimators.base import (Channel, CheckReport, EstimateFrame,
                                                     Estimator, Finding, Roles, Sensor, State,
                                                     StepInputs, gain)
from bearing_pose_estimation.scenario import ScenarioError, check_scenario, parse_scenario
from bearing_pose_estimation.sim.batch import BatchSimulator
from bearing_pose_estimation.sim.netsim import run_network

import test_estimator_contract as contract

PAPER = Path(__file__).resolve().parents[1] / 'config' / 'paper_8_agents.yaml'


@dataclass(frozen=True)
class ToyGains:
    k: float = gain(1.5, 'attitude and position gain k')


class Toy(Estimator[ToyGains, State]):
    method: ClassVar[str] = 'toy_first_order'
    title: ClassVar[str] = 'first-order toy'
    Gains: ClassVar[type] = ToyGains
    roles: ClassVar[Roles] = Roles(leaders=2)
    sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.GYRO, Sensor.BEARINGS,
                                                     Sensor.KNOWN_POSE})
    optional_sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.ODOMETRY})
    sends: ClassVar[tuple[Channel, ...]] = (
        Channel('position', per='agent', frame='world'),
        Channel('world_bearing', per='edge', frame='world', unit=True))
    frame: ClassVar[EstimateFrame] = EstimateFrame.WORLD
    reference_scenario: ClassVar[str] = 'paper_8_agents.yaml'

    def initial_state(self, R_hat, p_hat):
        return State(R_hat=np.array(R_hat, dtype=float), p_hat=np.array(p_hat, dtype=float))

    def outbox(self, x, sender, bearings, slot=None):
        return {'position': x.p_hat,
                'world_bearing': np.einsum('eab,eb->ea', x.R_hat[sender], bearings)}

    def step(self, x, h, inputs: StepInputs, reorthonormalize=True):
        e, k = inputs.edges, self.gains.k
        d = -inputs.received['world_bearing']
        y = np.einsum('eab,eb->ea', x.R_hat[e.agent], inputs.bearings)
        sigma = e.sum_by_agent(e.weighted(np.cross(d, y)))
        R = so3.reorthonormalize(so3.exp(-h * k * sigma) @ x.R_hat @ inputs.delta_R)
        own = x.p_hat[e.agent] if inputs.p_own is None else inputs.p_own
        diff = own - inputs.received['position']
        along = np.sum(y * diff, axis=1) / np.sum(y * y, axis=1)
        pull = e.sum_by_agent(diff - y * along[:, None])
        p_hat = x.p_hat - h * k * pull
        if inputs.displacement is not None:
            p_hat = p_hat + np.einsum('nab,nb->na', x.R_hat, inputs.displacement)
        return State(R_hat=R, p_hat=p_hat), {'innovation': sigma}

    def check(self, fleet):
        report = CheckReport(spectra_of='none')
        for i in fleet.followers:
            if len(fleet.neighbours[i]) < 2:
                report.findings.append(Finding('error', fleet.names[i], 'neighbours',
                                               'the toy needs two neighbours', 'add one'))
        return report


@pytest.fixture
def toy():
    estimators.register(Toy)
    yield Toy.method
    estimators.unregister(Toy.method)
    assert Toy.method not in estimators.methods()


@pytest.fixture
def toy_scenario(toy):
    data = yaml.safe_load(PAPER.read_text())
    data.update(method=toy, gains={'k': 1.5})
    return parse_scenario(data, source='toy.yaml')


@pytest.mark.parametrize('check', contract.CONTRACT,
                         ids=lambda c: c.__name__.removeprefix('check_'))
def test_the_toy_keeps_the_contract(toy, check):
    check(toy)


def test_the_toy_runs_in_the_batch_simulator_and_converges(toy_scenario):
    assert check_scenario(toy_scenario).ok
    rec = BatchSimulator(toy_scenario).run(40.0, record_every=5.0)
    att, pos = rec.mean_errors()
    assert att[0] > 1.0 and pos[0] > 3.0
    assert att[-1] < 1e-5 and pos[-1] < 1e-3, (att[-1], pos[-1])


def test_the_toy_runs_through_the_node_logic_like_the_batch(toy_scenario):
    """netsim: one AgentEstimator per agent, fed as the simulator node feeds it, exchanging the
    toy's own channels: within 2 % of the batch simulator at 10 s."""
    net = run_network(toy_scenario, 10.0, record_every=5.0)
    batch = BatchSimulator(toy_scenario).run(10.0, record_every=5.0)
    for a, b in ((net.att_err, batch.att_err), (net.pos_err, batch.pos_err)):
        assert abs(a[-1].mean() / b[-1].mean() - 1.0) < 0.02
    assert net.pos_err[-1].mean() < 0.5 * net.pos_err[0].mean()


def test_an_unregistered_method_is_refused_with_the_known_ones():
    data = yaml.safe_load(PAPER.read_text())
    data['method'] = Toy.method
    with pytest.raises(ScenarioError, match='unknown method .toy_first_order.*boughellaba_tayebi'):
        parse_scenario(data)
    with pytest.raises(ValueError, match='built in'):
        estimators.unregister('boughellaba_tayebi')


class AnchorToy(Toy):
    """The toy with one anchor instead of two leaders (the role Presenza et al. need)."""

    method: ClassVar[str] = 'toy_anchor'
    roles: ClassVar[Roles] = Roles(anchor=True)


def test_roles_are_what_each_method_declares():
    """Two leaders, one anchor or none: the scenario must give exactly the method's roles,
    and errors name the field and the fix."""
    estimators.register(AnchorToy)
    try:
        data = yaml.safe_load(PAPER.read_text())
        data['method'], data['gains'] = 'toy_anchor', {}
        data['initial_estimates'] = {'random': {'seed': 0}}  # for agent_2, no leader now
        leaders = data.pop('leaders')
        with pytest.raises(ScenarioError, match=r'anchor: .*needs one anchor.*Fix: add'):
            parse_scenario(data)
        data['anchor'] = 'agent_1'
        with pytest.raises(ScenarioError, match=r'anchor: expected a mapping.*Fix:'):
            parse_scenario(data)
        data['anchor'] = {'agent': 'agent_9', 'ranged': ['agent_2', 'agent_3']}
        with pytest.raises(ScenarioError, match=r"anchor\.agent: 'agent_9' is not an agent"):
            parse_scenario(data)
        data['anchor'] = {'agent': 'agent_1', 'ranged': ['agent_2', 'agent_2']}
        with pytest.raises(ScenarioError, match=r'anchor\.ranged: expected two distinct.*Fix:'):
            parse_scenario(data)
        data['anchor'] = {'agent': 'agent_1', 'ranged': ['agent_2', 'agent_1']}
        with pytest.raises(ScenarioError, match=r'anchor\.ranged\[1\]: .*other than the anchor'):
            parse_scenario(data)
        data['anchor'] = {'agent': 'agent_1', 'ranged': ['agent_2', 'agent_3'], 'pinned': 'no'}
        with pytest.raises(ScenarioError, match=r'anchor\.pinned: expected true or false'):
            parse_scenario(data)
        data['anchor']['pinned'] = True
        s = parse_scenario(data)
        assert s.anchor == 'agent_1' and s.anchor_index == 0 and s.leaders == ()
        assert s.ranged == ('agent_2', 'agent_3') and s.anchor_pinned
        assert [a.name for a in s.followers] == [f'agent_{k}' for k in range(2, 9)]
        data['anchor']['pinned'] = False   # the anchor estimates its own pose too
        assert [a.name for a in parse_scenario(data).followers] == [
            f'agent_{k}' for k in range(1, 9)]
        data['leaders'] = leaders
        with pytest.raises(ScenarioError, match=r'leaders: .*has no leaders.*Fix: remove'):
            parse_scenario(data)
        paper = yaml.safe_load(PAPER.read_text())
        paper['anchor'] = {'agent': 'agent_1', 'ranged': ['agent_2', 'agent_3']}
        with pytest.raises(ScenarioError, match=r'anchor: Boughellaba & Tayebi has no anchor'):
            parse_scenario(paper)
    finally:
        estimators.unregister(AnchorToy.method)
