"""Adding a method is adding one module: three toy estimators, one per communication pattern
(leader bearings, two-way links, two rounds), written from the interface alone in
``toy_methods.py`` and known to no module of the package, pass the contract and run through
the batch simulator, netsim and a short DDS run. A scenario names each by its import path; the
registry imports it, in this process and in every node's.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from bearing_pose_estimation import estimators
from bearing_pose_estimation.cli.main import main
from bearing_pose_estimation.estimators.base import Roles
from bearing_pose_estimation.scenario import (ScenarioError, check_scenario, load_scenario,
                                              parse_scenario)
from bearing_pose_estimation.scenario.model import initial_truth
from bearing_pose_estimation.sim.batch import BatchSimulator
from bearing_pose_estimation.sim.netsim import simulate_network
from bearing_pose_estimation.studies.summary import read_metrics_csv

import test_estimator_contract as contract
from toy_methods import ToyBearings

HERE = Path(__file__).resolve().parent
CONFIG = HERE.parent / 'config'
PAPER = CONFIG / 'paper_8_agents.yaml'
TOYS = ('toy_methods:ToyBearings', 'toy_methods:ToyLinks', 'toy_methods:ToyRounds')
DOMAIN = int(os.environ['ROS_DOMAIN_ID'])


@pytest.fixture(autouse=True)
def toys_on_the_path(monkeypatch):
    """The nodes' processes find the toys where this one does; no toy stays registered."""
    paths = [str(HERE)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]
    monkeypatch.setenv('PYTHONPATH', os.pathsep.join(paths))
    yield
    for method in estimators.methods():
        if method.startswith('toy_methods:'):
            estimators.unregister(method)


def toy_data(method: str) -> dict:
    """The toy's reference scenario for a run that converges: exogenous motion, every
    attitude estimate exact where the toy does not estimate attitudes (it knows them), the
    anchor pinned and the fleet static for the two-round toy."""
    data = contract.reference_data(method)
    data['method'], data['gains'] = method, {}
    if method.endswith('ToyBearings'):
        return data
    data.get('formation_control', {})['mode'] = 'exogenous'
    if 'anchor' in data:
        data['anchor']['pinned'] = True
        for agent in data['agents']:
            agent.pop('velocity', None)
    R, _ = initial_truth(parse_scenario(data))
    for agent, Q in zip(data['agents'], R):
        estimate = agent.setdefault('initial_estimate', {'position': agent['position']})
        estimate['attitude'] = {'quaternion': Rotation.from_matrix(Q).as_quat().tolist()}
    return data


@pytest.mark.parametrize('method', TOYS)
@pytest.mark.parametrize('check', contract.CONTRACT,
                         ids=lambda c: c.__name__.removeprefix('check_'))
def test_each_toy_keeps_the_contract(check, method):
    check(method)


@pytest.mark.parametrize('method', TOYS)
def test_each_toy_converges_in_the_batch_simulator_and_netsim_follows_it(method):
    """The batch simulator takes each toy's declarations alone; netsim, one agent runtime per
    agent fed as the simulator node feeds it, stays within 2 % of it."""
    scenario = parse_scenario(toy_data(method), source=f'<{method}>')
    assert check_scenario(scenario).ok
    rec = BatchSimulator(scenario).run(8.0, record_every=2.0)
    att, pos = rec.mean_errors()
    assert pos[-1] < 0.2 * pos[0], pos
    net = simulate_network(scenario, 4.0, record_every=2.0).recording
    batch = BatchSimulator(scenario).run(4.0, record_every=2.0)
    for a, b in ((net.pos_err, batch.pos_err), (net.att_err, batch.att_err)):
        assert abs(a[-1].mean() - b[-1].mean()) <= 0.02 * b[-1].mean() + 1e-9


@pytest.mark.dds
@pytest.mark.parametrize('method', TOYS)
def test_each_toy_runs_over_dds_as_in_netsim(method, tmp_path):
    """A short run of each toy over DDS, one process per agent, equals netsim's to 1e-9."""
    scenario_file = tmp_path / 'toy.yaml'
    scenario_file.write_text(yaml.safe_dump(toy_data(method), sort_keys=False))
    out = tmp_path / 'out'
    assert main(['run', str(scenario_file), '--duration', '0.5', '--out', str(out),
                 '--domain-id', str(DOMAIN), '--no-plots']) == 0
    dds = read_metrics_csv(out / 'metrics.csv')
    net = simulate_network(load_scenario(scenario_file), 0.5, record_every=0.1).recording
    n = len(net.t)
    np.testing.assert_allclose(dds.t[-n:], net.t, atol=1e-9)
    np.testing.assert_allclose(dds.pos_err[-n:], net.pos_err, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(dds.att_err[-n:], net.att_err, rtol=1e-9, atol=1e-12)


def test_an_unregistered_method_is_refused_with_the_known_ones():
    data = yaml.safe_load(PAPER.read_text())
    data['method'] = ToyBearings.method
    with pytest.raises(ScenarioError, match='unknown method .toy_bearings.*boughellaba_tayebi'):
        parse_scenario(data)
    data['method'] = 'toy_methods:NoSuchToy'
    with pytest.raises(ScenarioError, match='cannot import it.*Fix: put toy_methods on'):
        parse_scenario(data)
    with pytest.raises(ValueError, match='built in'):
        estimators.unregister('boughellaba_tayebi')


class AnchorToy(ToyBearings):
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
