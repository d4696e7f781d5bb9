"""The contract every registered estimator keeps. A new method inherits it by registering: the
suite runs over ``estimators.methods()``, each on its own reference scenario (the paper's
simulation in config/), and ``test_estimator_registry.py`` runs it on a toy registered there.

- the truth is a fixed point of the step (whatever the agents' rotation), and stays one when
  the fleet moves (odometry or the method's own sensors of motion);
- the one-agent step (what the node runs) equals the batch row, static or moving;
- finite inputs never give non-finite outputs, degenerate geometry included;
- what it sends matches what it declares (channels, shapes), and so does its state;
- bad gains are refused with the field named, in the gains and through a scenario file;
- the graph check reports a broken assumption (an agent cut off from everyone), naming it.
"""
from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from bearing_pose_estimation import estimators
from bearing_pose_estimation.core import so3
from bearing_pose_estimation.estimators import base
from bearing_pose_estimation.estimators.base import (Edges, Sensor, State, StepInputs, gain_fields,
                                                     parse_gains)
from bearing_pose_estimation.scenario import (ScenarioError, check_scenario, initial_estimates,
                                              parse_scenario)
from bearing_pose_estimation.sim.batch import BatchSimulator

CONFIG = Path(__file__).resolve().parents[1] / 'config'


def reference_data(method: str) -> dict:
    """The method's reference scenario file, as loaded from YAML (its `method:` set)."""
    cls = estimators.get(method)
    data = yaml.safe_load((CONFIG / cls.reference_scenario).read_text())
    if data.get('method', estimators.DEFAULT_METHOD) != method:
        data['method'], data['gains'] = method, {}
    return data


def static_data(method: str) -> dict:
    """The reference scenario with no agent translating (rotations kept)."""
    data = reference_data(method)
    data.pop('formation_control', None)
    for agent in data['agents']:
        agent.pop('formation_position', None)
        agent.pop('velocity', None)
    return data


def moving_data(method: str) -> dict:
    """The reference scenario with every agent translating: its own motion if it has a
    formation controller, else world-frame velocities."""
    data = reference_data(method)
    if 'formation_control' in data:
        return data
    for k, agent in enumerate(data['agents']):
        agent['velocity'] = {'world': [0.2, {'sin': 0.5, 'amplitude': 0.2, 'phase': k},
                                       {'cos': 0.3, 'amplitude': 0.05}]}
    return data


def _sim(method: str, moving: bool = False) -> BatchSimulator:
    data = moving_data(method) if moving else static_data(method)
    return BatchSimulator(parse_scenario(data, source=f'<{method}>'))


def _assert_states_close(a, b, atol: float) -> None:
    for f in dataclasses.fields(a):
        np.testing.assert_allclose(getattr(a, f.name), getattr(b, f.name), rtol=0, atol=atol,
                                   err_msg=f.name)


# ----------------------------------------------------------------------------- the checks
def check_truth_is_a_fixed_point(method: str) -> None:
    for moving in (False, True):
        sim = _sim(method, moving)
        p0 = sim.p.copy()
        sim.x = sim.estimator.initial_state(*sim.true_estimates())
        for _ in range(max(300, int(round(0.6 / sim.h)))):   # at least 0.6 s: they move
            sim.step()
        errors = sim.errors()
        atol = sim.estimator.moving_fixed_point_atol if moving else 1e-12
        assert errors.att_err.max() < atol and errors.pos_err.max() < atol, (moving, errors)
        assert np.abs(sim.truth.angular_rate()).max() > 0.1  # the agents did rotate
        assert (np.linalg.norm(sim.p - p0, axis=1).min() > 0.1) == moving   # and moved


def check_one_agent_step_equals_the_batch_row(method: str) -> None:
    for moving in (False, True):
        _one_agent_step_equals_the_batch_row(_sim(method, moving))


def _one_agent_step_equals_the_batch_row(sim: BatchSimulator) -> None:
    for _ in range(25):  # into the transient: every term is non-zero
        sim.step()
    inputs = sim.inputs()
    batch, diag = sim.estimator.step(sim.x, sim.h, inputs)
    assert set(diag) >= {'innovation'} and diag['innovation'].shape[0] == sim.n
    for i in sim.follower_idx:
        one, one_diag = sim.estimator.step(sim.x.rows([i]), sim.h, inputs.agent_inputs(int(i)))
        _assert_states_close(one, batch.rows([i]), atol=1e-13)
        np.testing.assert_allclose(one_diag['innovation'][0], diag['innovation'][i], atol=1e-13)


def check_declared_messages_and_state(method: str) -> None:
    sim = _sim(method)
    est, x = sim.estimator, sim.x
    for f in dataclasses.fields(x):
        assert getattr(x, f.name).shape[0] == sim.n, f.name
    assert isinstance(x, State)
    sender = sim.edge_nbr
    bearings = np.tile([0.0, 0.0, 1.0], (len(sender), 1))
    sent = est.outbox(x, sender, bearings)
    assert set(sent) == {c.name for c in est.sends if c.round == 1}
    if est.rounds() == 2:   # round 2 from what round 1 delivered, one row per edge
        sent.update(est.reply(x, sim.h, sim.inputs()))
        assert set(sent) == {c.name for c in est.sends}
    for c in est.sends:
        rows = len(sender) if c.per == 'edge' else sim.n
        assert sent[c.name].shape == (rows,) + c.shape, c.name
    assert est.roles.leaders == len(sim.scenario.leaders)


def check_finite_inputs_give_finite_outputs(method: str) -> None:
    """Random states and inputs, including degenerate ones: parallel bearings, neighbours at
    the agent's estimated position, zero rates, huge positions."""
    sim = _sim(method)
    est, n = sim.estimator, sim.n
    rng = np.random.default_rng(3)
    cases = 0
    for trial in range(60):
        n_edges = int(rng.integers(0, 3 * n))
        agent = np.sort(rng.integers(0, n, n_edges)).astype(np.intp)
        cls = type(est)
        flags = {'senses': np.ones(n_edges, bool), 'sensed_by': np.ones(n_edges, bool)}
        if cls.links == 'communication':   # both ends, the other end's odometry
            senses = rng.uniform(size=n_edges) < 0.7
            sensed_by = ~senses | (rng.uniform(size=n_edges) < 0.3)
            flags = {'senses': senses, 'sensed_by': sensed_by,
                     'owns': senses & (rng.uniform(size=n_edges) < 0.6)}
            if cls.roles.anchor:   # random ranged links
                flags.update(ranges=rng.uniform(size=n_edges) < 0.2,
                             ranged_by=rng.uniform(size=n_edges) < 0.2)
        edges = Edges(agent=agent, k=rng.uniform(0.1, 5.0, n_edges), n_agents=n, flags=flags)
        scale = 10.0 ** rng.integers(-3, 7)
        x = est.initial_state(so3.exp(rng.normal(size=(n, 3)) * 3.0),
                              rng.normal(size=(n, 3)) * scale)
        for f in dataclasses.fields(x):  # the method's own states at random values too
            if f.name not in ('R_hat', 'p_hat'):
                old = getattr(x, f.name)
                setattr(x, f.name, (rng.normal(size=old.shape) * 10.0).astype(old.dtype))
        bearings = rng.normal(size=(n_edges, 3))
        bearings /= np.linalg.norm(bearings, axis=1, keepdims=True)
        if trial % 3 == 0 and n_edges:
            bearings[:] = bearings[0]  # every bearing parallel
        edge = {s.value: bearings if s is Sensor.BEARINGS
                else rng.normal(size=(n_edges, 3)) * scale for s in cls.measures}
        for c in est.sends:
            v = rng.normal(size=(n_edges,) + c.shape) * scale
            if c.unit:
                v /= np.linalg.norm(v, axis=1, keepdims=True)
                if trial % 3 == 1 and n_edges:
                    v[:] = v[0]
            elif trial % 3 == 2 and c.per == 'agent' and c.shape == (3,):
                v = np.take(x.p_hat, agent, axis=0)  # neighbours where the agent thinks it is
            if c.sensor is not None and c.on is not None:
                v = np.where(flags[c.on][:, None], v, 0.0)
            if trial % 3 == 1 and c.per == 'agent' and c.shape == (2,):
                v[:] = 0.0   # a vanishing yaw estimate
            edge[c.name] = v
        if cls.peer_odometry == 'links':
            edge[base.PEER_DELTA_R] = so3.exp(rng.normal(size=(n_edges, 3)) * 0.1)
            edge[base.PEER_DISPLACEMENT] = rng.normal(size=(n_edges, 3)) * scale
        delta_R = so3.exp(rng.normal(size=(n, 3)) * (0.0 if trial % 4 == 0 else 0.1))
        agent_values = {base.DELTA_R: delta_R,
                        base.DISPLACEMENT: rng.normal(size=(n, 3)) * scale}
        if cls.roles.anchor:   # a random anchor and its random motion
            is_anchor = np.arange(n) == rng.integers(0, n)
            agent_values.update({
                base.ANCHOR_DELTA_R: np.repeat(so3.exp(rng.normal(size=(1, 3)) * 0.1), n, 0),
                base.ANCHOR_DISPLACEMENT: np.repeat(rng.normal(size=(1, 3)) * scale, n, 0),
                base.IS_ANCHOR: is_anchor, base.PINNED: is_anchor & bool(trial % 2)})
        # A node's inputs: some missing (masked), for a method that takes partial edges.
        mask = ({key: rng.uniform(size=n_edges) < 0.8 for key in edge}
                if cls.partial_edges and trial % 2 else {})
        inputs = StepInputs(edges=edges, agent=agent_values, edge=edge, mask=mask,
                            t=float(rng.integers(0, 8)) * 0.005)
        h = 10.0 ** rng.integers(-4, 0)
        if est.rounds() == 2:
            assert all(np.all(np.isfinite(v)) for v in est.reply(x, h, inputs).values()), trial
        out, diag = est.step(x, h, inputs)
        assert out.is_finite(), (trial, n_edges)
        assert all(np.all(np.isfinite(v)) for v in diag.values()), trial
        cases += 1
    assert cases == 60


def check_bad_gains_are_refused_with_the_field_named(method: str) -> None:
    cls = estimators.get(method)
    assert cls.Gains() == parse_gains(cls.Gains, {})
    for f in gain_fields(cls.Gains):
        assert f.metadata['help'], f.name
        zero_ok = f.metadata.get('zero_allowed', False)  # a term that 0 switches off
        if zero_ok:
            assert getattr(parse_gains(cls.Gains, {f.name: 0}), f.name) == 0.0
        for bad in (-1.0, float('nan'), float('inf'), 'fast', True) + (() if zero_ok
                                                                       else (0.0,)):
            with pytest.raises(ScenarioError, match=rf'gains\.{f.name}: .*Fix:'):
                parse_gains(cls.Gains, {f.name: bad})
        data = reference_data(method)
        data['gains'] = {f.name: -2.0}
        with pytest.raises(ScenarioError,
                           match=rf'gains\.{f.name}: must be {">=" if zero_ok else ">"} 0'):
            parse_scenario(data, source='s.yaml')
    data = reference_data(method)
    data['gains'] = {'k_typo': 1.0}
    with pytest.raises(ScenarioError, match=r'gains\.k_typo: unknown key'):
        parse_scenario(data, source='s.yaml')


def check_graph_check_reports_a_broken_assumption(method: str) -> None:
    """Cut one estimating agent off from everyone: no method can localise it."""
    data = reference_data(method)
    assert check_scenario(parse_scenario(data)).ok
    leaders = set(data.get('leaders', []))
    victim = [a['name'] for a in data['agents'] if a['name'] not in leaders][-1]
    broken = copy.deepcopy(data)
    for a in broken['agents']:
        if a['name'] == victim:
            a['neighbours'] = []
        elif 'neighbours' in a:
            a['neighbours'] = [n for n in a['neighbours']
                               if (n['name'] if isinstance(n, dict) else n) != victim]
    report = check_scenario(parse_scenario(broken))
    assert not report.ok
    assert any(e.agent == victim and e.fix for e in report.errors), report.format()


CONTRACT = (check_truth_is_a_fixed_point, check_one_agent_step_equals_the_batch_row,
            check_declared_messages_and_state, check_finite_inputs_give_finite_outputs,
            check_bad_gains_are_refused_with_the_field_named,
            check_graph_check_reports_a_broken_assumption)


@pytest.mark.parametrize('method', estimators.methods())
@pytest.mark.parametrize('check', CONTRACT, ids=lambda c: c.__name__.removeprefix('check_'))
def test_contract(check, method):
    check(method)


def test_every_method_declares_what_the_interface_asks():
    for method in estimators.methods():
        cls = estimators.get(method)
        assert cls.method == method and cls.title
        assert (CONFIG / cls.reference_scenario).is_file()
        assert cls.sensors and cls.sends
        assert dataclasses.is_dataclass(cls.Gains)
        initial = initial_estimates(parse_scenario(reference_data(method)))
        assert isinstance(cls(cls.Gains()).initial_state(*initial), State)
