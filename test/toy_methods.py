"""Three toy estimators, one per communication pattern, written from the interface alone (no
code of the four methods) and known to no module of the package: a scenario names one by its
import path (``method: toy_methods:ToyLinks``), and every process that runs it imports it
from the Python path (``test_estimator_registry.py``).

- :class:`ToyBearings`, leader bearings: the attitude observer (3) of Boughellaba & Tayebi
  and a first-order bearing-only position observer ``dp̂_i/dt = -k Σ_j P_{R̂_i b^i_ij} (p̂_i -
  p̂_j)``, one gain ``k``, its own name for the position channel, odometry fed forward.
- :class:`ToyLinks`, two-way links: robots that know their attitude (propagated from an exact
  start) estimate positions up to one translation from relative positions, their own and
  those the other end measures of them, ``dp̂_i/dt = R̂_i v_i - k Σ_j [i senses j] (p̂_i - p̂_j
  + R̂_i ⁱp_ij) + [j senses i] (p̂_i - p̂_j - R̂_j ʲp_ji)``; a late value is carried with the
  other end's odometry.
- :class:`ToyRounds`, two rounds and an anchor: in the anchor's frame, each sensing robot j
  sends each robot i it sees (round 2, from i's ``q̂_i`` of round 1) the projection
  ``P_{Q̂_j β_ji} (q̂_i - q̂_j)``; i descends the sum of what it receives and, ranged by the
  anchor, ``q̂_i - q_ranged``; attitudes known, everything turned with the anchor's motion.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from bearing_pose_estimation.core import so3
from bearing_pose_estimation.estimators.base import (
    ANCHOR_DELTA_R, ANCHOR_DISPLACEMENT, PEER_ODOMETRY, PINNED, POSE_POSITION, VECTOR, Channel,
    CheckReport, EstimateFrame, Estimator, Finding, Roles, Sensor, State, StepInputs, gain)
from bearing_pose_estimation.estimators.fleet import Fleet


@dataclass(frozen=True)
class ToyGains:
    k: float = gain(1.5, 'attitude and position gain k')


def _isolated(fleet: Fleet, report: CheckReport) -> CheckReport:
    """An error for every estimating agent that nobody senses and that senses nobody."""
    sensed = {j for nbrs in fleet.neighbours for j, _ in nbrs}
    for i in fleet.followers:
        if not fleet.neighbours[i] and i not in sensed:
            report.findings.append(Finding('error', fleet.names[i], 'neighbours', 'it senses '
                                           'nobody and nobody senses it', 'add a neighbour'))
    return report


def _project(b: np.ndarray, e: np.ndarray) -> np.ndarray:
    """``P_b e = e - b (b·e)/‖b‖²`` per row."""
    return e - b * (np.sum(b * e, axis=1) / np.sum(b * b, axis=1))[:, None]


class ToyBearings(Estimator[ToyGains, State]):
    method: ClassVar[str] = 'toy_bearings'
    title: ClassVar[str] = 'toy: leader bearings'
    Gains: ClassVar[type] = ToyGains
    roles: ClassVar[Roles] = Roles(leaders=2)
    sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.GYRO, Sensor.BEARINGS,
                                                     Sensor.KNOWN_POSE})
    optional_sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.ODOMETRY})
    sends: ClassVar[tuple[Channel, ...]] = (
        Channel('position', per='agent', frame='world', topic='pose', kind=POSE_POSITION),
        Channel('world_bearing', per='edge', frame='world', unit=True, topic='toy_bearings'))
    measures = {Sensor.BEARINGS: None}
    partner_sensor = Sensor.BEARINGS
    frame: ClassVar[EstimateFrame] = EstimateFrame.WORLD
    reference_scenario: ClassVar[str] = 'paper_8_agents.yaml'

    def initial_state(self, R_hat, p_hat):
        return State(R_hat=np.array(R_hat, dtype=float), p_hat=np.array(p_hat, dtype=float))

    def outbox(self, x, sender, bearings, slot=None):
        return {'position': x.p_hat,
                'world_bearing': np.einsum('eab,eb->ea', x.R_hat[sender], bearings)}

    def step(self, x, h, inputs: StepInputs, reorthonormalize=True):
        e, k = inputs.edges, self.gains.k
        d = -inputs.edge['world_bearing']
        y = np.einsum('eab,eb->ea', x.R_hat[e.agent], inputs.edge['bearings'])
        sigma = e.sum_by_agent(e.weighted(np.cross(d, y)))
        R = so3.reorthonormalize(so3.exp(-h * k * sigma) @ x.R_hat @ inputs.delta_R)
        own = inputs.edge.get('p_own', x.p_hat[e.agent])
        pull = e.sum_by_agent(_project(y, own - inputs.edge['position']))
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


class ToyLinks(Estimator[ToyGains, State]):
    method: ClassVar[str] = 'toy_links'
    title: ClassVar[str] = 'toy: two-way links'
    Gains: ClassVar[type] = ToyGains
    roles: ClassVar[Roles] = Roles()
    sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.GYRO, Sensor.ODOMETRY,
                                                     Sensor.RELATIVE_POSITIONS})
    sends: ClassVar[tuple[Channel, ...]] = (
        Channel('position', per='agent', frame='estimate', topic='pose', kind=POSE_POSITION,
                pairing='exact', bound=1e4),
        Channel('heading', per='agent', frame='estimate', kind=VECTOR, pairing='exact',
                bound=10.0, doc='log(R̂_j), its known attitude as a rotation vector'),
        Channel('seen', per='edge', frame='body', sensor=Sensor.RELATIVE_POSITIONS,
                on='sensed_by', pairing='exact', bound=1e4))
    links = 'communication'
    measures = {Sensor.RELATIVE_POSITIONS: 'senses'}
    own_pairing = 'interpolated'
    peer_odometry = 'links'
    partial_edges: ClassVar[bool] = True
    partner_sensor = Sensor.RELATIVE_POSITIONS
    edge_gains: ClassVar[bool] = False
    frame: ClassVar[EstimateFrame] = EstimateFrame.COMMON_YAW_TRANSLATION
    reference_scenario: ClassVar[str] = 'de_carli_8_quadrotors.yaml'

    def initial_state(self, R_hat, p_hat):
        return State(R_hat=np.array(R_hat, dtype=float), p_hat=np.array(p_hat, dtype=float))

    def outbox(self, x, sender, bearings, slot=None):
        return {'position': x.p_hat, 'heading': so3.log(x.R_hat),
                'seen': np.array(bearings, dtype=float)}

    def carry(self, values, motion):
        """Its position dead-reckoned with its odometry, its attitude turned by it."""
        if motion.peer_delta_R is None or motion.peer_displacement is None:
            return None
        R = so3.exp(values['heading'][None])[0]
        return {'position': values['position'] + R @ motion.peer_displacement,
                'heading': so3.log((R @ motion.peer_delta_R)[None])[0]}

    def step(self, x, h, inputs: StepInputs, reorthonormalize=True):
        e, r = inputs.edges, inputs.edge
        fresh = (inputs.here('position') & inputs.here('heading'))[:, None]
        own = (e.flag('senses') & inputs.here('relative_positions'))[:, None]
        theirs = (e.flag('sensed_by') & inputs.here('seen'))[:, None]
        diff = x.p_hat[e.agent] - r['position']
        R_j = so3.exp(r['heading'])
        terms = fresh * (own * (diff + np.einsum('eab,eb->ea', x.R_hat[e.agent],
                                                 r['relative_positions']))
                         + theirs * (diff - np.einsum('eab,eb->ea', R_j, r['seen'])))
        correction = e.sum_by_agent(terms)
        p_hat = x.p_hat - h * self.gains.k * correction
        if inputs.displacement is not None:
            p_hat = p_hat + np.einsum('nab,nb->na', x.R_hat, inputs.displacement)
        R = so3.matmul(x.R_hat, inputs.delta_R)
        if reorthonormalize:
            R = so3.reorthonormalize(R)
        moved = inputs.here(PEER_ODOMETRY)   # read, for the pattern's sake: nothing more
        assert moved.shape == (len(e),)
        return State(R_hat=R, p_hat=p_hat), {'innovation': correction}

    def check(self, fleet):
        return _isolated(fleet, CheckReport(spectra_of='none'))


class ToyRounds(Estimator[ToyGains, State]):
    method: ClassVar[str] = 'toy_rounds'
    title: ClassVar[str] = 'toy: two rounds'
    Gains: ClassVar[type] = ToyGains
    roles: ClassVar[Roles] = Roles(anchor=True)
    # Odometry: the anchor's motion turns the frame the estimates are in.
    sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.GYRO, Sensor.BEARINGS,
                                                     Sensor.ODOMETRY,
                                                     Sensor.RELATIVE_POSITIONS})
    sends: ClassVar[tuple[Channel, ...]] = (
        Channel('q_estimate', per='agent', frame='estimate', topic='pose', kind=POSE_POSITION,
                on='senses', pairing='exact', bound=1e4),
        Channel('range_seen', per='edge', frame='body', sensor=Sensor.RELATIVE_POSITIONS,
                on='ranged_by', pairing='exact', bound=1e4),
        Channel('pull', per='edge', frame='estimate', round=2, on='sensed_by',
                pairing='exact', bound=1e4, doc='P_{Q̂_j β_ji} (q̂_i - q̂_j) [m]'))
    links = 'communication'
    directed_sensing: ClassVar[bool] = True
    measures = {Sensor.BEARINGS: 'senses'}
    own_pairing = 'interpolated'
    peer_odometry = 'anchor'
    partial_edges: ClassVar[bool] = True
    partner_sensor = Sensor.RELATIVE_POSITIONS
    edge_gains: ClassVar[bool] = False
    frame: ClassVar[EstimateFrame] = EstimateFrame.ANCHOR_BODY
    reference_scenario: ClassVar[str] = 'presenza_case1.yaml'

    def initial_state(self, R_hat, p_hat):
        return State(R_hat=np.array(R_hat, dtype=float), p_hat=np.array(p_hat, dtype=float))

    def outbox(self, x, sender, bearings, slot=None):
        return {'q_estimate': x.p_hat, 'range_seen': np.array(bearings, dtype=float)}

    def carry(self, values, motion):
        """A position seen in the anchor frame at t: turned by the anchor's motion."""
        dR, d = motion.anchor_delta_R, motion.anchor_displacement
        if dR is None or d is None:
            return None
        return {name: dR.T @ (v - d) if name == 'q_estimate' else dR.T @ v
                for name, v in values.items()}

    def reply(self, x, h, inputs: StepInputs):
        e = inputs.edges
        used = (e.flag('senses') & inputs.here('bearings') & inputs.here('q_estimate'))[:, None]
        b = np.einsum('eab,eb->ea', x.R_hat[e.agent], inputs.edge['bearings'])
        b = np.where(used, b, np.array([1.0, 0.0, 0.0]))
        pull = _project(b, inputs.edge['q_estimate'] - x.p_hat[e.agent])
        return {'pull': np.where(used, pull, 0.0)}

    def step(self, x, h, inputs: StepInputs, reorthonormalize=True):
        e, r, k = inputs.edges, inputs.edge, self.gains.k
        ranged = (e.flag('ranged_by') & inputs.here('range_seen'))[:, None]
        into = (e.flag('sensed_by') & inputs.here('pull'))[:, None]
        grad = e.sum_by_agent(np.where(into, r['pull'], 0.0)
                              + np.where(ranged, x.p_hat[e.agent] - r['range_seen'], 0.0))
        dR_a, d_a = inputs.agent[ANCHOR_DELTA_R], inputs.agent[ANCHOR_DISPLACEMENT]
        moved = np.zeros_like(x.p_hat) if inputs.displacement is None else np.einsum(
            'nab,nb->na', x.R_hat, inputs.displacement)
        turn = np.swapaxes(dR_a, -1, -2)
        p_hat = np.einsum('nab,nb->na', turn, x.p_hat - h * k * grad + moved - d_a)
        R = so3.matmul(turn, x.R_hat, inputs.delta_R)
        if reorthonormalize:
            R = so3.reorthonormalize(R)
        hold = inputs.agent[PINNED]
        p_hat[hold], R[hold] = 0.0, np.eye(3)
        return State(R_hat=R, p_hat=p_hat), {'innovation': grad}

    def check(self, fleet):
        return _isolated(fleet, CheckReport(spectra_of='none'))
