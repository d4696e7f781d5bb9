"""De Carli, Restrepo & Robuffo Giordano (2024): moving robots localised from body-frame relative
positions and their own odometry, with no anchor (``method: de_carli``).

Equations, corrections and discretisation: ``../shared/estimators/de-carli-2024.md`` (§n),
the paper's numbers in parentheses; ``test/de_carli_reference.py`` is the whole-fleet reference
the stage tests check. Here the stages run per robot and per link, so one step serves the batch
simulator and a node alike.

Robots have yaw-only body frames ``R_i = R_z(ψ_i)`` (roll and pitch compensated), horizontal
vectors are complex numbers, ``ẑ_i ≈ e^{ι(ψ_i + a)}`` is the (unnormalised) yaw estimate and
``R̂_i = R_z(∠ẑ_i)``. Robot i measures ``ⁱp_ij = R_iᵀ (p_j - p_i)`` (2) of the robots it senses.

Links (``links = 'communication'``): robot i has one link per communication neighbour j (i
senses j, j senses i, or both). Every pair ``{i, j}`` has exactly one relative-yaw state (§8),
kept by its owner: the sensing robot of a one-way pair, the lower id of a two-way one; the
owner holds ``ẑ_ij ≈ e^{ι(ψ_j - ψ_i)}`` in its own orientation, its estimate ``ⁱp̂_ij`` and,
for a two-way pair, ``ʲp̂_ji`` too (fed by j's measurement). Channels:

- ``z_hat`` (per robot): ``ẑ_j`` as a complex number, never an angle (§8: exchanging angles
  turns (13) into another, nonlinear algorithm);
- ``p_hat`` (per robot): ``p̂_j``;
- ``meas`` (per link): ``ʲp_ji``, j's measurement of the listener i (zeros where j does not
  sense i). With ``z_hat`` of the same instant it gives ``R̂_j ʲp_ji``, the in-neighbour term of
  (21), and the owner of a two-way pair gets the measurement its ``ʲp̂_ji`` needs;
- ``relyaw`` (per link): the owner's ``unit(ẑ_ji)`` for the other robot's (13) (Remark 4).
- ``pose_cov`` (per robot, optional: never waited for): the covariance of its pose, from
  :mod:`.de_carli_covariance`, on its ``pose``. Each end of a pair propagates the pair's own
  covariance from what it has already, so none travels.

The other end's odometry over the step (``δ_j``, ``Δψ_j``; :data:`base.PEER_DISPLACEMENT`)
feeds the owner's prediction of ``ⁱp̂_ij``.

One step ``h`` (the estimator frequency, the relative-yaw observer's 200 Hz), everything on the
right from the step's start ``t`` (the state and what the neighbours sent at t):

1. Stage 3's correction, every ``1/position_rate`` (``h₃``), (21) in edge form::

       p̂_i ← p̂_i - h₃ k_p Σ_j [senses (p̂_i - p̂_j + R̂_i ⁱp_ij)
                                + sensed_by (p̂_i - p̂_j - R̂_j ʲp_ji)]

2. Stage 2, every ``1/yaw_rate`` (``h₂``), the Jacobi step of (13) over the excited pairs
   (stable and row-stochastic for every ``c = h₂ k_z`` and every graph; forward Euler diverges
   on the paper's cube, §7)::

       ẑ_i ← (ẑ_i + c Σ_j conj(u_ij) ẑ_j) / (1 + c n_i),   u_ij = unit(ẑ_ij)

3. Stage 1, every step, on the owned pairs: correct, then predict with the odometry
   increments (§7; exact kinematics, ``E = P̂ - y``, ``δ'`` the previous step's displacement in
   the frame at its end, 0 at first)::

       ẑ⁺     = ẑ_ij - k_ψ (conj(δ'_j) E_ij + [two-way] δ'_i conj(E_ji))          (8)
       P̂_ij  ← e^{-ιΔψ_i} (P̂_ij - δ_i + δ_j ẑ⁺ - h k_pe E_ij)                     (7)
       P̂_ji  ← e^{-ιΔψ_j} (P̂_ji - δ_j + δ_i conj(ẑ⁺) - h k_pe E_ji)   [two-way]
       ẑ_ij  ← e^{ι(Δψ_j - Δψ_i)} ẑ⁺

   (vertical parts: ``p̂_z ← p̂_z - δ_iz + δ_jz - h k_pe e_z``).
4. Dead reckoning and the yaw's rotation: ``p̂_i ← p̂_i + R̂_i δ_i``, ``ẑ_i ← e^{ιΔψ_i} ẑ_i``.

Initial values (§8, §9): ``ẑ_i(0) = e^{ιψ̂_i(0)}``; each ``P̂`` is its first measurement;
each pair starts at ``unit(conj(ẑ_i) ẑ_j)`` from the first ``ẑ_j`` received.

Persistent excitation (Theorem 1, §5): only the sensed robots' horizontal motion excites a
pair. Both ends sum it from the odometry they both have (``|δ_xy|²/h`` per step) since the start
(``excitation``, ``∫|v_xy|² dt``) and over an exponential window of :data:`EXCITATION_WINDOW_S`
(``excitation_recent``). A pair joins the consensus, and stays in (``excited``), once its
window is above ``pe_threshold`` plus :data:`NOISE_MARGIN` times the odometry noise's share
(:meth:`DeCarli.excitation_threshold`): a hovering robot's noise alone crosses a threshold on
the integral since the start, never a window's (BENCHMARKS.md, "The excitation monitor").

Everything converges only up to one common yaw and translation
(``EstimateFrame.COMMON_YAW_TRANSLATION``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from collections.abc import Mapping, Sequence
from typing import ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.sparse.csgraph import connected_components

from ..core import warm_start as warm
from ..core.motion import rot_z, yaw_of
from . import de_carli_covariance as cov
from .base import (PEER_DELTA_R, PEER_DISPLACEMENT, PEER_ODOMETRY, POSE_POSITION, VECTOR, Array,
                   Channel, CheckReport, Edges, EstimateFrame, Estimator, Finding, Index, Mask,
                   Motion, Roles, Sensor, State, StepInputs, WarmStart, gain)
from .covariance import DOF, POSE_COV, PoseCovarianceModel
from .fleet import Fleet

Complex = NDArray[np.complex128]

# Every value a robot receives is checked against this bound [m] (a depth camera sees metres).
MAX_VALUE = 1e4
Z_HAT = Channel('z_hat', per='agent', frame='estimate', shape=(2,), topic='yaw_estimate',
                kind=VECTOR, pairing='exact', bound=MAX_VALUE,
                doc='ẑ_j = |ẑ_j| e^{ιψ̂_j}, the unnormalised yaw estimate, [re, im]')
P_HAT = Channel('p_hat', per='agent', frame='estimate', doc='p̂_j, the position estimate [m]',
                topic='pose', kind=POSE_POSITION, pairing='exact', bound=MAX_VALUE)
MEAS = Channel('meas', per='edge', frame='body', sensor=Sensor.RELATIVE_POSITIONS,
               on='sensed_by', pairing='exact', bound=MAX_VALUE,
               doc='ʲp_ji, j\'s measurement of the listener i (body frame of j) [m]; zeros if '
                   'j does not sense i')
RELYAW = Channel('relyaw', per='edge', frame='body', shape=(2,), owner_only=True, unit=True,
                 topic='relative_yaws', pairing='exact', bound=MAX_VALUE,
                 doc='unit(ẑ_ji), the relative yaw of the pair j owns, [re, im] (a node sends '
                     'it only to the other robot of each pair it owns)')

# |ẑ| below this has no usable angle (Remark 3): its unit value is taken as 1.
MIN_MODULUS = 1e-12
# Persistent excitation (module docstring): the window [s], and the default floor besides the
# noise's, EXCITATION_M2_S [m²/s]: 1 mm/s held over the window, far above rounding and far below
# what a real odometry's noise lets one see (0.028 m/s with config/de_carli_noisy.yaml).
EXCITATION_WINDOW_S = 1.0
EXCITATION_M2_S = 1e-6
# The window's excitation must exceed this many times the noise's mean in it (2σ² for a 2-D
# velocity). The noise alone never gets there: its std in the window is sqrt(h / (2 c τ)) times
# its mean (c sensed robots), 1/20 of it at 200 Hz, 1/10 at 50 Hz.
NOISE_MARGIN = 2.0
# The diagnostics' stage of a robot: the first stage whose residual [m, rad, m] is above its
# threshold, or 'converged'.
RELATIVE_DONE_M = 1e-3
YAW_DONE = 1e-3
POSITION_DONE_M = 1e-2
# The position residual before the first correction: unknown, finite (a state holds no inf).
UNKNOWN_RESIDUAL = 1e300
# Stage 3's Euler correction diverges when h₃ k_p λ_max(L̄) reaches this (§7).
EULER_LIMIT = 2.0


def usable(inputs: StepInputs) -> tuple[Mask, Mask, Mask, Mask]:
    """``(y_ok, m_ok, present, fresh)`` ``(E,)``: here are the own measurement of j, j's of the
    robot, j's odometry over the step, and j's channels of this instant (or carried to it)."""
    edges = inputs.edges
    return (edges.flag('senses') & inputs.here('relative_positions'),
            edges.flag('sensed_by') & inputs.here('meas'), inputs.here(PEER_ODOMETRY),
            inputs.here('z_hat') & inputs.here('p_hat'))


def unit(z: Complex) -> Complex:
    """``z/|z|`` (Remark 3), and 1 where ``|z|`` is below :data:`MIN_MODULUS`."""
    r = np.abs(z)
    return np.where(r > MIN_MODULUS, z / np.where(r > MIN_MODULUS, r, 1.0), 1.0 + 0j)


def as_complex(v: Array) -> Complex:
    """``x + ιy`` of the first two components of ``v`` ``(..., ≥2)``."""
    return v[..., 0] + 1j * v[..., 1]


def as_pair(z: Complex) -> Array:
    """``[re, im]`` of ``z``, ``(..., 2)``: how complex numbers travel."""
    return np.stack([z.real, z.imag], axis=-1)


@dataclass(frozen=True)
class DeCarliGains(PoseCovarianceModel):
    """Gains of (7)-(8), (13), (21) and the two slower stages' rates; the covariance's model
    (:mod:`.de_carli_covariance`)."""

    k_pe: float = gain(20.0, 'relative-position gain k_pe of (7)-(8) [1/s]')
    k_psi: float = gain(600.0, 'relative-yaw gain k_psi of (7)-(8) [1/m^2]')
    k_z: float = gain(40.0, 'yaw consensus gain k_z of (13) [1/s]')
    k_p: float = gain(1.0, 'position gain k_p of (21) [1/s]')
    yaw_rate: float = gain(100.0, 'rate of the yaw consensus (13) [Hz]; divides the '
                                  'estimator frequency')
    position_rate: float = gain(50.0, 'rate of the position correction (21) [Hz]; divides the '
                                      'estimator frequency')
    pe_threshold: float = gain(EXCITATION_M2_S, 'excitation a pair needs to join the yaw '
                               'consensus, beyond the odometry noise\'s, integral of |v_xy|^2 '
                               'over the last second [m^2/s] (0: every pair from the start)',
                               zero_allowed=True)
    relative_position_std: float = gain(0.0, 'relative position noise std [m] per component, '
                                        'for the covariance', zero_allowed=True, model=True)


@dataclass
class DeCarliState(State):
    """Per robot: ``ẑ_i``, and per link slot (``(N, D)``, D the most links of a robot; grown
    at the first step that has them) what the robot keeps of the pair."""

    z_hat: Complex            # (N,) ẑ_i, unnormalised
    d_own: Complex            # (N,) δ'_i of the last step (the regressor of reversed edges)
    p_residual: Array         # (N,) |Σ of (21)'s edge residuals| at the last correction [m]
    P_out: Complex            # (N, D) ⁱp̂_ij, horizontal (owned pairs)
    Pz_out: Array             # (N, D) its vertical part
    P_in: Complex             # (N, D) ʲp̂_ji (owned two-way pairs)
    Pz_in: Array
    z_pair: Complex           # (N, D) ẑ_ij ≈ e^{ι(ψ_j - ψ_i)} (owned pairs)
    d_other: Complex          # (N, D) δ'_j of the last step
    ready_out: NDArray[np.bool_]    # (N, D) P_out initialised (first measurement)
    ready_in: NDArray[np.bool_]
    ready_pair: NDArray[np.bool_]
    excitation: Array         # (N, D) ∫ |v_xy|² dt of the pair's sensed robots [m²/s]
    excitation_recent: Array  # (N, D) the same over the exponential window
    excited_now: NDArray[np.bool_]  # (N, D) the window's excitation is measurable
    excited: NDArray[np.bool_]      # (N, D) it was once: in the consensus from then on
    P: Array                  # (N, 6, 6) the pose covariance (de_carli_covariance.py)
    P_pair: Array             # (N, D, 6, 6) each pair's (E_out, ζ, E_in); 0: not started

    LINK_FIELDS: ClassVar[tuple[str, ...]] = (
        'P_out', 'Pz_out', 'P_in', 'Pz_in', 'z_pair', 'd_other', 'ready_out', 'ready_in',
        'ready_pair', 'excitation', 'excitation_recent', 'excited_now',
        'excited', 'P_pair')

    @property
    def slots(self) -> int:
        return int(self.P_out.shape[1])

    @classmethod
    def stack(cls, parts: Sequence[DeCarliState]) -> DeCarliState:
        """Several robots' states as one, each grown to the most link slots among them
        (a robot's extra slots stay zero: no edge of its own reaches them)."""
        slots = max(x.slots for x in parts)
        return super().stack([x.grown(slots) for x in parts])

    def grown(self, slots: int) -> DeCarliState:
        """This state with at least ``slots`` link slots (new ones zero, not initialised)."""
        if slots <= self.slots:
            return self
        out = self.rows(slice(None))
        pad = slots - self.slots
        for name in self.LINK_FIELDS:
            v = getattr(out, name)
            setattr(out, name, np.concatenate(
                [v, np.zeros((v.shape[0], pad) + v.shape[2:], v.dtype)], 1))
        return out


class DeCarli(Estimator[DeCarliGains, DeCarliState]):
    """De Carli, Restrepo & Robuffo Giordano (2024): module docstring."""

    method: ClassVar[str] = 'de_carli'
    title: ClassVar[str] = 'De Carli et al.'
    Gains: ClassVar[type] = DeCarliGains
    roles: ClassVar[Roles] = Roles()
    sensors: ClassVar[frozenset[Sensor]] = frozenset({Sensor.GYRO, Sensor.ODOMETRY,
                                                     Sensor.RELATIVE_POSITIONS})
    sends: ClassVar[tuple[Channel, ...]] = (
        Z_HAT, P_HAT, MEAS, RELYAW, replace(POSE_COV, pairing='exact', bound=MAX_VALUE ** 2))
    frame: ClassVar[EstimateFrame] = EstimateFrame.COMMON_YAW_TRANSLATION
    edge_gains: ClassVar[bool] = False
    links: ClassVar[Literal['sensing', 'communication']] = 'communication'
    measures: ClassVar[Mapping[Sensor, str | None]] = {Sensor.RELATIVE_POSITIONS: 'senses'}
    own_pairing = 'interpolated'
    peer_odometry = 'links'
    partial_edges: ClassVar[bool] = True
    timed_step: ClassVar[bool] = True   # stages 2 and 3 run at their own rates (13), (21)
    partner_sensor: ClassVar[Sensor | None] = Sensor.RELATIVE_POSITIONS
    stages: ClassVar[tuple[str, ...]] = ('waiting_for_excitation', 'relative_yaw', 'yaw',
                                         'position', 'converged')
    reference_scenario: ClassVar[str] = 'de_carli_8_quadrotors.yaml'

    # --- state
    def initial_state(self, R_hat: Array, p_hat: Array) -> DeCarliState:
        n = R_hat.shape[0]
        psi = yaw_of(R_hat)
        links = {name: np.zeros((n, 0), complex if name.startswith(('P_', 'z_', 'd_'))
                                else bool if name.startswith(('ready', 'excited')) else float)
                 for name in DeCarliState.LINK_FIELDS}
        links['P_pair'] = np.zeros((n, 0, cov.PAIR, cov.PAIR))
        return DeCarliState(R_hat=rot_z(psi), p_hat=np.array(p_hat, dtype=float),
                            z_hat=np.exp(1j * psi), d_own=np.zeros(n, complex),
                            p_residual=np.full(n, UNKNOWN_RESIDUAL), P=self.prior(n), **links)

    def prior(self, n: int) -> Array:
        """The covariance of ``n`` initial estimates: the gains' ``initial_position_std²`` on x,
        y, z, ``initial_attitude_std²`` on yaw, 0 on roll and pitch (known)."""
        P = np.zeros((n, DOF, DOF))
        P[:, [0, 1, 2], [0, 1, 2]] = self.gains.initial_position_std ** 2
        P[:, 5, 5] = self.gains.initial_attitude_std ** 2
        return P

    def missing(self, channel: str) -> Array:
        """A neighbour's covariance not received (yet): the prior."""
        if channel != POSE_COV.name:
            return super().missing(channel)
        return self.prior(1)[0]

    def warm_start(self, x: DeCarliState, inputs: StepInputs) -> WarmStart | None:
        """``ψ̂_i``, ``p̂_i`` in the fleet's common frame at a position tick (docs/warm_start.md):
        ``p̂_j = p̂_i + R̂_i ⁱp_ij`` per robot i senses, ``p̂_i = p̂_j + R̂_j ʲp_ji`` per one that
        senses i (21), fitted by :func:`core.warm_start.planar`; refused beyond ``WARM_SIGMAS``
        of the noise. ``ẑ_i`` takes the neighbours' mean modulus; the pairs it owns start from it
        (the step, §8) and join the consensus at once: the fit determined them. None at the
        fleet's start (a simulator restart restarts every robot): the common frame is then the
        robots' initial estimates themselves, nothing to land on."""
        g, edges, rec = self.gains, inputs.edges, inputs.edge
        tick = inputs.t * g.position_rate
        if tick < 1.0 - 1e-6:
            return None
        y_ok, m_ok, _, fresh = usable(inputs)
        out_, in_ = fresh & y_ok, fresh & m_ok
        if abs(tick - round(tick)) > 1e-6 or not (out_ | in_).any():
            return WarmStart(None, 'not determined: no neighbour\'s z_hat and p_hat of this '
                                   'instant (a position tick)')
        z_j, P_j = as_complex(rec['z_hat']), rec[POSE_COV.name]
        m_j = np.einsum('kab,kb->ka', rot_z(np.angle(z_j)), rec['meas'])   # R̂_j ʲp_ji
        world = np.concatenate([rec['p_hat'][out_], rec['p_hat'][in_] + m_j[in_]])
        body = np.concatenate([rec['relative_positions'][out_], np.zeros((in_.sum(), 3))])
        nbr = np.concatenate([np.flatnonzero(out_), np.flatnonzero(in_)])
        turned = np.concatenate([np.zeros(out_.sum()), np.sum(m_j[in_, :2] ** 2, axis=1)])
        var = g.relative_position_std ** 2 + (np.trace(P_j[nbr, :3, :3], axis1=1, axis2=2)
                                              + P_j[nbr, 5, 5] * turned) / 3.0
        sigma = np.maximum(np.sqrt(var), warm.WARM_FLOOR_M)
        fit = warm.planar(body, world, sigma ** -2)
        # Determined: one measurement's noise turns the yaw by MIN_SPREAD_RAD at most.
        noise = max(g.relative_position_std, warm.WARM_FLOOR_M)
        if fit is None or noise > warm.MIN_SPREAD_RAD * fit.lever:
            return WarmStart(None, f'not determined: {len(nbr)} relative position(s) within '
                                   f'{0.0 if fit is None else fit.lever:.2g} m of one point')
        P_fit = np.linalg.inv(fit.information)
        miss = np.linalg.norm(fit.residuals, axis=1)
        residual = f'residual {miss.max():.2g} m ({(miss / sigma).max():.2g} sigma)'
        if (miss / sigma).max() > warm.WARM_SIGMAS:
            return WarmStart(None, f'refused: {residual} from {len(nbr)} relative positions')
        assert edges.slot is not None
        x0 = self.initial_state(rot_z(np.array([fit.psi])), fit.c[None]).grown(
            int(edges.slot.max()) + 1)
        x0.z_hat *= np.mean(np.abs(z_j[nbr]))
        x0.P[0][np.ix_(cov.POSE, cov.POSE)] = P_fit
        mine = np.flatnonzero((out_ | in_) & edges.flag('owns'))
        x0.excited[0, edges.slot[mine]] = True
        pairs = cov.pair_prior(len(mine), g.relative_position_std, 0.0)   # ζ: both yaws' error
        pairs[:, [2, 3], [2, 3]] = np.minimum(P_fit[3, 3] + P_j[mine, 5, 5],
                                              cov.ZETA_PRIOR_MAX)[:, None]
        x0.P_pair[0, edges.slot[mine]] = pairs
        return WarmStart(x0, f'accepted: {residual} from {len(nbr)} relative positions')

    def propagate(self, x: DeCarliState, delta_R: Array,
                  displacement: Array | None = None) -> DeCarliState:
        out = x.rows(slice(None))
        if displacement is not None:
            out.p_hat = x.p_hat + np.einsum('nab,nb->na', x.R_hat, displacement)
        out.z_hat = np.exp(1j * yaw_of(delta_R)) * x.z_hat
        out.R_hat = rot_z(np.angle(out.z_hat))
        return out

    def window_noise(self, h: float) -> float:
        """The mean excitation the odometry's noise alone puts in a pair's window, per sensed
        robot [m²/s]. A tick's ``|δ_xy|²/h`` of noise of density n has mean ``2n²`` (``h n²``
        per component of δ, §7; less when the odometry is slower than the step), and the
        window weighs the ticks by ``e^{-kh/τ}``: ``2n²/(1 - e^{-h/τ})``."""
        return float(2.0 * self.gains.odometry_noise_density ** 2
                     / -np.expm1(-h / EXCITATION_WINDOW_S))

    def excitation_threshold(self, sensed: Array | float, h: float) -> Array:
        """What a pair's window must reach to be excited (module docstring), ``sensed`` the
        number of robots its edges sense."""
        return self.gains.pe_threshold + NOISE_MARGIN * self.window_noise(h) * np.asarray(
            sensed, dtype=float)

    def every(self, rate: float, h: float) -> int:
        """Estimator steps per period of a stage running at ``rate``."""
        return max(1, int(round(1.0 / (rate * h))))

    # --- messages
    def outbox(self, x: DeCarliState, sender: Index, bearings: Array,
               slot: Index | None = None) -> dict[str, Array]:
        relyaw = np.zeros((len(sender), 2))
        if slot is not None and x.slots:
            inside = slot < x.slots
            s, k = sender[inside], slot[inside]
            ready = x.ready_pair[s, k]
            relyaw[inside] = np.where(ready[:, None], as_pair(unit(x.z_pair[s, k])), 0.0)
        return {'z_hat': as_pair(x.z_hat), 'p_hat': x.p_hat,
                'meas': np.array(bearings, dtype=float), 'relyaw': relyaw, 'pose_cov': x.P}

    def due(self, channel: str, t: float, h: float) -> bool:
        """``z_hat`` at the consensus and position ticks (R̂_j pairs with ʲp_ji), ``relyaw``
        at the consensus ticks, ``p_hat`` at the position ticks, ``meas`` every step."""
        tick = int(round(t / h))
        yaw = tick % self.every(self.gains.yaw_rate, h) == 0
        position = tick % self.every(self.gains.position_rate, h) == 0
        return {'z_hat': yaw or position, 'relyaw': yaw, 'p_hat': position}.get(channel, True)

    def carry(self, values: Mapping[str, Array], motion: Motion) -> dict[str, Array] | None:
        """j's values of ``t_s`` at t (§8): ``ẑ_j`` turned by j's yaw increment, ``p̂_j``
        dead-reckoned with ``R̂_j(t_s) δ_j``, the relative yaw turned by ``Δψ_i - Δψ_j`` (exact
        without corrections meanwhile); None without j's odometry and the own gyro."""
        own_delta_R, other_delta_R = motion.own_delta_R, motion.peer_delta_R
        other_displacement = motion.peer_displacement
        if own_delta_R is None or other_delta_R is None or other_displacement is None:
            return None
        out: dict[str, Array] = {}
        dpsi_j, dpsi_i = float(yaw_of(other_delta_R)), float(yaw_of(own_delta_R))
        if 'z_hat' in values:
            out['z_hat'] = as_pair(np.exp(1j * dpsi_j) * as_complex(values['z_hat']))
        if 'p_hat' in values:
            if 'z_hat' not in values:
                return None
            psi = float(np.angle(as_complex(values['z_hat'])))
            out['p_hat'] = values['p_hat'] + rot_z(np.array(psi)) @ other_displacement
        if 'relyaw' in values:
            out['relyaw'] = as_pair(np.exp(1j * (dpsi_i - dpsi_j)) * as_complex(values['relyaw']))
        return out

    # --- the step
    def step(self, x: DeCarliState, h: float, inputs: StepInputs,
             reorthonormalize: bool = True) -> tuple[DeCarliState, dict[str, Array]]:
        g, edges, rec = self.gains, inputs.edges, inputs.edge
        assert edges.slot is not None
        n = x.p_hat.shape[0]
        ag, sl = edges.agent, edges.slot
        x = x.grown(int(sl.max()) + 1 if len(sl) else 0)
        out = x.rows(slice(None))
        tick = int(round(inputs.t / h))
        h2, h3 = self.every(g.yaw_rate, h) * h, self.every(g.position_rate, h) * h

        dpsi_i = yaw_of(inputs.delta_R)
        delta_i = (np.zeros((n, 3)) if inputs.displacement is None
                   else np.asarray(inputs.displacement, dtype=float))
        dc_i = as_complex(delta_i)
        dpsi_j = yaw_of(rec[PEER_DELTA_R])
        delta_j = rec[PEER_DISPLACEMENT]
        dc_j = as_complex(delta_j)
        z_j = as_complex(rec['z_hat'])
        y, meas = rec['relative_positions'], rec['meas']
        y_c, meas_c = as_complex(y), as_complex(meas)
        senses, sensed_by, owns = edges.flag('senses'), edges.flag('sensed_by'), edges.flag('owns')
        y_ok, m_ok, present, fresh = usable(inputs)

        # Without the other end's odometry (δ_j) an edge sits the step out; its relative
        # estimates restart from the next measurements.
        gone = ~present
        out.ready_out[ag[gone], sl[gone]] = False
        out.ready_in[ag[gone], sl[gone]] = False
        # First use of an edge: the first measurement, the pair from the first ẑ_j (§8).
        new = owns & y_ok & present & ~out.ready_out[ag, sl]
        out.P_out[ag[new], sl[new]], out.Pz_out[ag[new], sl[new]] = y_c[new], y[new, 2]
        out.ready_out[ag[new], sl[new]] = True
        new = owns & m_ok & present & ~out.ready_in[ag, sl]
        out.P_in[ag[new], sl[new]], out.Pz_in[ag[new], sl[new]] = meas_c[new], meas[new, 2]
        out.ready_in[ag[new], sl[new]] = True
        new = owns & fresh & ~x.ready_pair[ag, sl] & (np.abs(z_j) > 0)
        out.z_pair[ag[new], sl[new]] = unit(np.conj(x.z_hat[ag[new]]) * z_j[new])
        out.ready_pair[ag[new], sl[new]] = True

        # 1. Stage 3's correction (21), from the state at t.
        correction = np.zeros((n, 3))
        if tick % self.every(g.position_rate, h) == 0:
            R_j = rot_z(np.angle(z_j))
            diff = x.p_hat[ag] - rec['p_hat']
            term = fresh[:, None] * (
                y_ok[:, None] * (diff + np.einsum('kab,kb->ka', x.R_hat[ag], y))
                + m_ok[:, None] * (diff - np.einsum('kab,kb->ka', R_j, meas)))
            correction = edges.sum_by_agent(term)
            out.p_hat = x.p_hat - h3 * g.k_p * correction
            out.p_residual = np.linalg.norm(correction, axis=1)

        # 2. Stage 2: the Jacobi step of (13) over the excited pairs.
        pair_u = np.where(owns, unit(out.z_pair[ag, sl]), np.conj(unit(as_complex(rec['relyaw']))))
        active = (x.excited[ag, sl] | (g.pe_threshold == 0.0)) & fresh & np.where(
            owns, out.ready_pair[ag, sl], np.hypot(*rec['relyaw'].T) > 0.5)
        pull = np.where(active, np.conj(pair_u) * z_j, 0.0)
        yaw_target = edges.sum_by_agent(as_pair(pull))
        n_active = np.bincount(ag[active], minlength=n)
        z_hat = x.z_hat
        if tick % self.every(g.yaw_rate, h) == 0:
            c = h2 * g.k_z
            z_hat = (z_hat + c * as_complex(yaw_target)) / (1.0 + c * n_active)

        # 3. Stage 1 on the owned pairs: correct (8), then predict (7).
        k = owns & present & out.ready_pair[ag, sl] & out.ready_out[ag, sl]
        a, s = ag[k], sl[k]
        E_out = np.where(y_ok[k], out.P_out[a, s] - y_c[k], 0.0)
        e_out_z = np.where(y_ok[k], out.Pz_out[a, s] - y[k, 2], 0.0)
        tw = sensed_by[k] & out.ready_in[a, s]
        E_in = np.where(tw & m_ok[k], out.P_in[a, s] - meas_c[k], 0.0)
        e_in_z = np.where(tw & m_ok[k], out.Pz_in[a, s] - meas[k, 2], 0.0)
        z_plus = out.z_pair[a, s] - g.k_psi * (np.conj(x.d_other[a, s]) * E_out
                                              + x.d_own[a] * np.conj(E_in))
        z_lin = out.z_pair[a, s].copy()     # where the covariance linearises the pair
        rot_i, rot_j = np.exp(-1j * dpsi_i[a]), np.exp(-1j * dpsi_j[k])
        out.P_out[a, s] = rot_i * (out.P_out[a, s] - dc_i[a] + dc_j[k] * z_plus
                                   - h * g.k_pe * E_out)
        out.Pz_out[a, s] = (out.Pz_out[a, s] - delta_i[a, 2] + delta_j[k, 2]
                            - h * g.k_pe * e_out_z)
        out.P_in[a, s] = np.where(tw, rot_j * (out.P_in[a, s] - dc_j[k]
                                               + dc_i[a] * np.conj(z_plus) - h * g.k_pe * E_in),
                                  out.P_in[a, s])
        out.Pz_in[a, s] = np.where(tw, out.Pz_in[a, s] - delta_j[k, 2] + delta_i[a, 2]
                                   - h * g.k_pe * e_in_z, out.Pz_in[a, s])
        out.z_pair[a, s] = np.exp(1j * (dpsi_j[k] - dpsi_i[a])) * z_plus
        out.d_other[ag, sl] = np.where(present, np.exp(-1j * dpsi_j) * dc_j, 0.0)
        out.d_own = np.exp(-1j * dpsi_i) * dc_i

        # Excitation: the horizontal motion of the robots the pair's edges sense (Theorem 1).
        tick_excitation = present * (senses * np.abs(dc_j) ** 2
                                     + sensed_by * np.abs(dc_i[ag]) ** 2) / h
        out.excitation[ag, sl] = x.excitation[ag, sl] + tick_excitation
        decay = np.exp(-h / EXCITATION_WINDOW_S)
        out.excitation_recent[ag, sl] = decay * x.excitation_recent[ag, sl] + tick_excitation
        out.excited_now[ag, sl] = out.excitation_recent[ag, sl] >= self.excitation_threshold(
            senses.astype(float) + sensed_by, h)
        out.excited[ag, sl] = x.excited[ag, sl] | out.excited_now[ag, sl]

        # 4. Dead reckoning with the new yaw, then the yaw's rotation over the step.
        out.p_hat = out.p_hat + np.einsum('nab,nb->na', rot_z(np.angle(z_hat)), delta_i)
        out.z_hat = np.exp(1j * dpsi_i) * z_hat
        out.R_hat = rot_z(np.angle(out.z_hat))

        # The covariance (de_carli_covariance.py), linearised at the state before the step.
        z_pre = np.zeros(len(ag), complex)
        z_pre[k] = unit(z_lin)
        out.P_pair[ag[gone], sl[gone]] = 0.0
        pairs, z_pair, maps, two_way = self.pair_maps(x, h, inputs, k, z_pre)
        P = out.P_pair[ag[pairs], sl[pairs]]
        start = np.einsum('kii->k', P) == 0.0
        if start.any():
            P[start] = cov.pair_prior(int(start.sum()), g.relative_position_std,
                                      g.initial_attitude_std)
        odo_var, gyro_var = h * g.odometry_noise_density ** 2, h * g.gyro_noise_density ** 2
        out.P_pair[ag[pairs], sl[pairs]] = cov.pair_step(
            P, maps, two_way, g.relative_position_std ** 2, odo_var, gyro_var)
        eps_var = np.zeros(len(ag))
        live = out.P_pair[ag, sl, 2, 2] + out.P_pair[ag, sl, 3, 3] > 0.0
        eps_var[live] = cov.yaw_error_var(out.P_pair[ag[live], sl[live]], z_pair[live])
        out.P = cov.robot_step(x.P, rec[POSE_COV.name], edges,
                               self.robot_maps(x, h, inputs, active, z_hat), eps_var,
                               inputs.displacement is not None, odo_var, gyro_var)

        residual = np.zeros(n)
        np.maximum.at(residual, a, np.abs(E_out))
        yaw_residual = np.abs(as_complex(yaw_target) - n_active * x.z_hat) / np.maximum(
            n_active * np.abs(x.z_hat), MIN_MODULUS)
        stage = np.select([n_active == 0, residual > RELATIVE_DONE_M, yaw_residual > YAW_DONE,
                           out.p_residual > POSITION_DONE_M], [0, 1, 2, 3], 4)
        return out, {'innovation': correction, 'z_modulus': np.abs(out.z_hat),
                     'pairs_excited': n_active.astype(float), 'relative_residual_m': residual,
                     'yaw_residual': yaw_residual, 'position_residual_m': out.p_residual,
                     'stage': stage.astype(float)}

    def robot_maps(self, x: DeCarliState, h: float, inputs: StepInputs,
                   active: NDArray[np.bool_], z_mid: Complex) -> cov.RobotMaps:
        """The linearised step of the robots' poses at ``x`` (de_carli_covariance.py):
        ``active`` the pairs stage 2 used, ``z_mid`` the yaws after it."""
        g, edges, rec = self.gains, inputs.edges, inputs.edge
        tick = int(round(inputs.t / h))
        every_2, every_3 = self.every(g.yaw_rate, h), self.every(g.position_rate, h)
        y_ok, m_ok, _, fresh = usable(inputs)
        moved = (None if inputs.displacement is None else np.einsum(
            'nab,nb->na', rot_z(np.angle(z_mid)), np.asarray(inputs.displacement, float)))
        return cov.robot_maps(
            edges, every_3 * h, g.k_p, tick % every_3 == 0,
            every_2 * h * g.k_z if tick % every_2 == 0 else None,
            rec['p_hat'] - x.p_hat[edges.agent], (fresh & y_ok).astype(float),
            (fresh & m_ok).astype(float),
            x.z_hat, as_complex(rec['z_hat']), active.astype(float), moved,
            g.relative_position_std ** 2)

    def pair_maps(self, x: DeCarliState, h: float, inputs: StepInputs,
                  owned: NDArray[np.bool_], z_owned: Complex
                  ) -> tuple[Index, Complex, tuple[Array, Array], NDArray[np.bool_]]:
        """The pairs' linearised stage 1 (de_carli_covariance.py), in the owner's orientation, on
        ``owned`` pairs (``z_owned``: their unit relative yaws) and, from the owner's ``relyaw``,
        the other end's replica: both ends hold the same covariance. Returns the links ``(K,)``,
        edges' relative yaws ``(E,)``, :func:`.de_carli_covariance.pair_maps`, two-way flags."""
        edges, rec = inputs.edges, inputs.edge
        assert edges.slot is not None
        ag, sl = edges.agent, edges.slot
        y_ok, m_ok, present, fresh = usable(inputs)
        relyaw = as_complex(rec['relyaw'])
        replica = ~edges.flag('owns') & present & fresh & (np.abs(relyaw) > 0.5)
        z_all = np.where(owned, z_owned, np.where(replica, relyaw, 0.0))
        e = np.flatnonzero(owned | replica)
        o = owned[e]
        a_, s_ = ag[e], sl[e]
        dpsi_i = yaw_of(inputs.delta_R)[a_]
        dpsi_j = yaw_of(rec[PEER_DELTA_R])[e]
        d_i = (np.zeros(len(e), complex) if inputs.displacement is None
               else as_complex(np.asarray(inputs.displacement, dtype=float))[a_])
        d_j = as_complex(rec[PEER_DISPLACEMENT])[e]
        y_c, meas_c = as_complex(rec['relative_positions'])[e], as_complex(rec['meas'])[e]
        # In the owner's orientation: the owner o and the other robot x of each pair.
        z, dpsi_o, dpsi_x = z_all[e], np.where(o, dpsi_i, dpsi_j), np.where(o, dpsi_j, dpsi_i)
        two_way = edges.flag('senses')[e] & edges.flag('sensed_by')[e]
        maps = cov.pair_maps(
            h, self.gains.k_pe, self.gains.k_psi, z, np.exp(1j * (dpsi_x - dpsi_o)) * z,
            np.where(o, x.d_other[a_, s_], x.d_own[a_]),
            np.where(o, x.d_own[a_], x.d_other[a_, s_]), np.where(o, d_i, d_j),
            np.where(o, d_j, d_i), dpsi_o, dpsi_x, np.where(o, y_c, meas_c),
            np.where(o, meas_c, y_c), np.where(o, y_ok[e], m_ok[e]),
            np.where(o, m_ok[e], y_ok[e]), two_way)
        return e, z_all, maps, two_way

    # --- what the recordings and the health report show
    edge_error_label: ClassVar[str] = 'rel_yaw_err'

    def neighbour_report(self, x: DeCarliState, slots: int) -> dict[str, list[str]]:
        """Each pair's excitation so far [m²/s], whether the consensus uses it and whether it
        is excited now (Theorem 1)."""
        total, used, now = x.excitation[0], x.excited[0], x.excited_now[0]
        every = self.gains.pe_threshold == 0.0
        return {'excitation': [
            f'{float(total[e]) if e < total.size else 0.0:.3g} m2/s, '
            + ('in the consensus, ' if every or (e < used.size and used[e]) else 'left out, ')
            + ('excited now' if e < now.size and now[e] else 'not excited now')
            for e in range(slots)]}

    def edge_errors(self, x: DeCarliState, R: Array, edges: Edges, other: Index) -> Array:
        """Fig. 2(a): per link, ``|ẑ_ij - e^{ι(ψ_j - ψ_i)}|`` (chordal, no alignment needed)
        where its robot owns the pair, NaN elsewhere; ``R`` the true attitudes."""
        psi = yaw_of(R)
        agent, slot = edges.agent, edges.slot
        assert slot is not None
        out = np.full(len(agent), np.nan)
        if not x.slots:
            return out
        k = np.flatnonzero(slot < x.slots)
        k = k[x.ready_pair[agent[k], slot[k]]]
        out[k] = np.abs(x.z_pair[agent[k], slot[k]] - np.exp(1j * (psi[other[k]] - psi[agent[k]])))
        return out

    # --- assumptions
    def check(self, fleet: Fleet) -> CheckReport:
        report = CheckReport()
        names = list(fleet.names)
        n = len(names)
        tail, head = fleet.sensing_edges()
        adjacency = np.zeros((n, n))
        adjacency[tail, head] = adjacency[head, tail] = 1.0
        count, label = connected_components(adjacency, directed=False)
        if count > 1:
            main = np.bincount(label).argmax()
            for i in np.flatnonzero(label != main):
                report.findings.append(Finding(
                    'error', names[i], 'neighbours', 'not connected to the rest of the fleet '
                    'in the communication graph (every sensing edge, both ways)',
                    'add a sensing edge between it and the fleet'))
        for name, attitude, omega, yaw in zip(names, fleet.attitudes,
                                              fleet.angular_velocities, fleet.yaws):
            if yaw is None and (abs(attitude[2, 2] - 1.0) > 1e-9
                                or any(c.constant or c.terms for c in (omega.x, omega.y))):
                report.findings.append(Finding(
                    'error', name, 'attitude', 'De Carli et al. need yaw-only body frames '
                    '(roll and pitch compensated by the IMU)',
                    'give it a `yaw:` spline, or an attitude about z and an angular velocity '
                    '[0, 0, w]'))
        for rate_name in ('yaw_rate', 'position_rate'):
            rate = getattr(self.gains, rate_name)
            ratio = fleet.frequency / rate
            if ratio < 1.0 - 1e-9 or abs(ratio - round(ratio)) > 1e-6:
                report.findings.append(Finding(
                    'error', 'gains', rate_name, f'{rate:g} Hz does not divide the estimator '
                    f'frequency {fleet.frequency:g} Hz',
                    f'use frequency / n, e.g. {fleet.frequency / 2:g}'))
        lam = float(np.linalg.eigvalsh(edge_laplacian(tail, head, n))[-1]) if len(tail) else 0.0
        h3 = self.every(self.gains.position_rate, fleet.step) * fleet.step
        if h3 * self.gains.k_p * lam >= EULER_LIMIT:
            report.findings.append(Finding(
                'error', 'gains', 'k_p', f'the position correction diverges: h3 k_p '
                f'lambda_max(L) = {h3 * self.gains.k_p * lam:.3g} >= {EULER_LIMIT:g}',
                f'lower k_p below {EULER_LIMIT / (h3 * lam):.3g} or raise position_rate'))
        if not fleet.moves:
            for a_, b_, sensed in pairs_and_sensed(fleet):
                report.findings.append(unexcited(names, a_, b_, sensed, 0.0, max(
                    self.gains.pe_threshold, EXCITATION_M2_S)))
        return report

    def check_motion(self, fleet: Fleet, times: Array, positions: Array) -> list[Finding]:
        """Warn for every pair whose window's excitation (true, plus the noise's mean) never
        reaches :meth:`excitation_threshold` along the sampled truth (the exogenous motion)."""
        names = list(fleet.names)
        dt = np.diff(times)
        energy = (np.sum(np.diff(positions[:, :, :2], axis=0) ** 2, axis=2)
                  / np.maximum(dt, 1e-300)[:, None])   # (K-1, N): ∫|v_xy|² over each interval
        window = np.zeros_like(energy)   # each robot's exponential window at each sample
        now = np.zeros(energy.shape[1])
        for k in range(len(dt)):
            now = window[k] = np.exp(-dt[k] / EXCITATION_WINDOW_S) * now + energy[k]
        found = []
        for a, b, sensed in pairs_and_sensed(fleet):
            peak = float(window[:, list(sensed)].sum(axis=1).max(initial=0.0))
            # The true motion the window needs, plus the noise's mean (pe_threshold 0: in anyway).
            needed = (max(self.gains.pe_threshold, EXCITATION_M2_S) + (NOISE_MARGIN - 1.0)
                      * self.window_noise(fleet.step) * len(sensed))
            if peak < needed:
                found.append(unexcited(names, a, b, sensed, peak, needed))
        return found


def edge_laplacian(tail: Index, head: Index, n: int) -> Array:
    """``L̄ = E Eᵀ`` (24, corrected: off-diagonals -1 or -2) of the sensing edges."""
    incidence = np.zeros((n, len(tail)))
    incidence[tail, np.arange(len(tail))] = 1.0
    incidence[head, np.arange(len(tail))] = -1.0
    return incidence @ incidence.T


def pairs_and_sensed(fleet: Fleet) -> list[tuple[int, int, set[int]]]:
    """Every communication pair ``(a, b)``, ``a < b``, with the robots its edges sense."""
    tail, head = fleet.sensing_edges()
    pairs: dict[tuple[int, int], set[int]] = {}
    for i, j in zip(tail.tolist(), head.tolist()):
        pairs.setdefault((min(i, j), max(i, j)), set()).add(j)
    return [(a, b, sensed) for (a, b), sensed in sorted(pairs.items())]


def unexcited(names: list[str], a: int, b: int, sensed: set[int], peak: float,
              needed: float) -> Finding:
    who = ' and '.join(names[k] for k in sorted(sensed))
    return Finding('warning', names[b], 'neighbours',
                   f'the pair {names[a]}-{names[b]} is never excited: {who} (what its edges '
                   f'sense) moves at most {peak:.3g} m^2/s horizontally (integral of |v_xy|^2 '
                   f'over the last {EXCITATION_WINDOW_S:g} s), below the {needed:.3g} its '
                   'odometry would show above its noise; its relative yaw cannot converge and '
                   'the consensus leaves it out',
                   f'make {who} move horizontally, or add a sensing edge to a robot that does')
