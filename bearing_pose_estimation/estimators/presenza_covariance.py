"""Covariance of Presenza et al.'s estimates: the step of :mod:`.presenza` linearised.

Robot i's error in the anchor frame, ``x_i = (q̃_i, φ_i)``, ``q̃_i = q̂_i − q_i`` [m] and ``Q̂_i =
exp([φ_i]x) Q_i`` [rad] (the notes' ``ξ_i`` of (20) is ``Q_iᵀ φ_i``); the anchor fixes the gauge
(§11).

**The own error** (the notes' §5, Step 1, through the preconditioned step; ``M_i = (I + 2 w h
κ_q D̂_i)⁻¹``, ``N_i = (I + w h κ_Q K_i)⁻¹`` with ``K_i = Σ_j d_ij Π(𝔟_ij)`` for sensing robots
and ``S(γ_i)ᵀ S(γ_i)`` for free ones, all in the anchor frame; ``G_q = h κ_q M_i``, ``G_Q = h
κ_Q N_i``). At the truth the angle cost's Hessian is its Gauss-Newton form, so ``∂ζ_i/∂q̂_i =
D̂_i`` exactly (Lemma 1)::

    sensing:  q̃⁺ = (I − G_q D̂) q̃ − [R̂ δ_i]x φ
              φ⁺ = (I − G_Q K) φ − G_Q Σ_j [𝔟_ij]x q̃          (Q̂_i Ω_i of (12) linearised)
    free:     q̃⁺ = (I − G_q D̂ + h L) q̃ + h dυ_i,  L = [ω_a]x + P̂⁻¹ Σ_j ṙ_ji 𝔟_jiᵀ
              φ⁺ = (I − G_Q K) φ + G_Q [γ]x (L q̃ + dυ_i)       ((13) linearised)

then turned by ``ΔR_aᵀ``; ``ṙ_ji`` the rate of 𝔟_ji, ``dυ_i = P̂⁻¹ Σ_j dn'_ji`` the error of
the reconstructed velocity (11) from what the sensing robots j know.

**What comes from elsewhere**, as in covariance.py: white noise per step, and the neighbours'
errors, slow inputs that enter as white noise of ``c / ρ`` times their covariance, ``ρ`` the
loop's decay per step (matrix-valued, ``A_q = G_q D̂``, ``A_Q = G_Q K``: inputs scaled by
``A^{-1/2}``): ``c_Q = 2`` (a fast loop under slow errors: their steady state), ``c_q = 1.3`` (the
position NEES on config/presenza_noisy.yaml: 3.01, 4.06 with 1; at 2 the covariances feed each
other without bound). The robots that see i send, in round 2, what only they know (TERM_COV):

- the covariance of their angle terms of ``ζ_i`` (6): white from their bearings' noise
  (``dα_jik = β_kᵀ ν_i + β_iᵀ ν_k``), slow from their own and the other robot's position
  errors (``χ_jik (g_jᵀ q̃_j + χ_jkiᵀ q̃_k)``);
- for a free listener, the covariance of their velocity term ``dn'_ji = dn_ji + dP̂ υ_i``
  (white: bearing, bearing-rate, odometry and gyro noise; slow: their ``(q̃_j, φ_j)``) and the
  bearing rate ``ṙ_ji`` (:func:`velocity_maps`; the range rate's part, about a tenth, is out).

Variances are capped (:data:`MAX_POSITION_STD`: the robot is lost). Not modelled: held samples,
a free robot holding ``γ̂``, and the time correlation of bearing rates differenced from noisy
bearings (``bearing_rate_std`` then defaults to their per-sample std ``σ √2 f``)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..core import so3
from .base import Array, Channel, Index, Mask, gain
from .covariance import DOF, EYE3, CovarianceModel

# The slow inputs' weights c (module docstring): position rows, attitude rows.
C_POSITION, C_ATTITUDE = 1.3, 2.0
# A loop's decay per step is floored at this fraction of its fastest direction's (a free
# robot's attitude about its velocity has none at an instant: the motion's turns give it one).
MIN_DECAY_RATIO = 1e-2
MIN_DECAY = 1e-9
# The covariance says "lost" at these stds [m], [rad] and grows no further: past them the
# linearisation means nothing, and an unbounded recursion would end in overflow (a receiver
# takes values up to TERM_COV's bound, 1e4, here m²).
MAX_POSITION_STD, MAX_ATTITUDE_STD = 100.0, np.pi
# The layout of TERM_COV: four packed symmetric blocks and a vector.
ANGLE_WHITE, ANGLE_SLOW, VELOCITY_WHITE, VELOCITY_SLOW = (slice(6 * k, 6 * k + 6)
                                                          for k in range(4))
RATE = slice(24, 27)
TERM_SIZE = 27

# The point fields of term_cov on the wire: the four blocks, each packed, then the rate.
TERM_FIELDS = tuple(f'{block}_{f}' for block in ('angle_white', 'angle_slow', 'velocity_white',
                                                   'velocity_slow')
                    for f in ('xx', 'yy', 'zz', 'xy', 'xz', 'yz')) + ('rate_x', 'rate_y', 'rate_z')
TERM_COV = Channel('term_cov', per='edge', frame='estimate', round=2, shape=(TERM_SIZE,),
                   optional=True, on='sensed_by', pairing='exact', bound=1e4,
                   topic='term_covariance', fields=TERM_FIELDS, psd_blocks=4,
                   doc='what only sensing robot j knows of the listener\'s covariance: its '
                       'angle terms\' covariance (white, slow), its velocity term\'s '
                       '(white, slow; free listeners) as xx, yy, zz, xy, xz, yz each, and '
                       'the bearing rate ṙ_ji (presenza_covariance.py)')


@dataclass(frozen=True, kw_only=True)
class PresenzaCovarianceModel(CovarianceModel):
    """The leader-follower model and the anchor's relative positions and the bearing rates."""

    relative_position_std: float = gain(0.0, "relative position noise std [m] per component "
                                        "(the anchor's ranged robots), for the covariance",
                                        zero_allowed=True, model=True)
    bearing_rate_std: float = gain(0.0, 'bearing rate noise std [1/s] per component, for the '
                                   'covariance', zero_allowed=True, model=True)


def _t(a: Array) -> Array:
    return np.swapaxes(a, -1, -2)


def _sandwich(A: Array, C: Array) -> Array:
    """``A C Aᵀ`` batched."""
    return A @ C @ _t(A)


def projector(b: Array) -> Array:
    return EYE3 - b[..., :, None] * b[..., None, :]


class AngleTerms(NamedTuple):
    """A robot's own angles (pairs of its sensing links ``e1 < e2``): the Jacobian blocks
    ``χ_jk``, ``χ_kj``, ``g_own = −(χ_jk + χ_kj)`` and the estimated cosine ``(A, 1)``."""

    e1: Index
    e2: Index
    chi_jk: Array
    chi_kj: Array
    g_own: Array
    cos: Array


def angle_terms(x_p: Array, q_other: Array, agent: Index, e1: Index, e2: Index,
                min_distance: float) -> AngleTerms:
    """:class:`AngleTerms` of the angles ``(e1, e2)`` from the estimates ((3), (6))."""
    i = agent[e1]
    d1, d2 = q_other[e1] - x_p[i], q_other[e2] - x_p[i]
    r1 = np.maximum(np.linalg.norm(d1, axis=1, keepdims=True), min_distance)
    r2 = np.maximum(np.linalg.norm(d2, axis=1, keepdims=True), min_distance)
    u1, u2 = d1 / r1, d2 / r2
    c = np.sum(u1 * u2, axis=1, keepdims=True)
    chi_jk, chi_kj = (u2 - c * u1) / r1, (u1 - c * u2) / r2
    return AngleTerms(e1, e2, chi_jk, chi_kj, -(chi_jk + chi_kj), c)


class VelocityTerms(NamedTuple):
    """A sensing robot j's velocity term ``n_ji`` of (11), per link: ``𝔟̂_ji``, ``d``,
    ``ṙ_ji = s − ω_a × 𝔟̂_ji``, ``s = Q̂_j (β̇_ji + ω_j × β_ji)``, ``Q̂_j``, ``Q̂_j u_j``,
    ``ω_j``, ``ω_a``."""

    b_hat: Array
    d: Array
    r_dot: Array
    s: Array
    R_hat: Array
    Ru: Array
    omega: Array
    omega_a: Array


def velocity_maps(v: VelocityTerms) -> tuple[Array, Array, Array]:
    """``(E, 3, 3)`` maps of the sender's position error ``q̃_j``, its attitude error ``φ_j``
    and its bearing's noise ``ν`` (body) into ``dn'_ji = dn_ji + dP̂ υ_i``::

        dn' = Π(𝔟) dυ_j + 𝔟 (d ṙ)ᵀ δ𝔟 − ṙ 𝔟ᵀ q̃_j + d (φ_j × s − ω_a × (φ_j × 𝔟)
              + Q̂_j (ω_j × ν) − ω_a × Q̂_j ν),     δ𝔟 = φ_j × 𝔟 + Q̂_j ν,
        dυ_j = −[Q̂_j u_j]x φ_j − [ω_a]x q̃_j

    (``Π(𝔟̂)υ̂_j + d̂ ṙ̂`` differentiated; ``υ_i − υ_j = d ṙ + 𝔟 ḋ``, whose range-rate part
    ``δ𝔟 ḋ`` is left out: j does not know ``ḋ``)."""
    b, d, r_dot, s, R = v.b_hat, v.d[:, None, None], v.r_dot, v.s, v.R_hat
    Pb = projector(b)
    S_b, S_wa = so3.hat(b), so3.hat(v.omega_a)
    br = b[:, :, None] * r_dot[:, None, :]                          # 𝔟 ṙᵀ
    of_q = -Pb @ S_wa - r_dot[:, :, None] * b[:, None, :]
    of_phi = -Pb @ so3.hat(v.Ru) - d * br @ S_b + d * (S_wa @ S_b - so3.hat(s))
    of_nu = d * (br @ R + R @ so3.hat(v.omega) - S_wa @ R)
    return of_q, of_phi, of_nu


def sender_terms(n_edges: int, angles: AngleTerms, bearings: Array, P_own: Array,
                 P_other: Array, agent: Index, velocity: VelocityTerms | None,
                 bearing_var: float, rate_var: float, odometry_density2: float,
                 gyro_density2: float, h: float) -> Array:
    """:data:`TERM_COV` ``(E, 27)`` of a sensing robot j to each robot i it sees, from j's
    ``angles``, bearings ``β_ji`` ``(E, 3)``, ``P_own`` ``(N, 6, 6)``, listeners' ``P_other``
    ``(E, 6, 6)``, free listeners' ``velocity`` terms (None: no bearing rates), the variances
    [rad²], [1/s²] and squared noise densities of odometry [m²/s] and gyro [rad²/s]."""
    out = np.zeros((n_edges, TERM_SIZE))
    e1, e2, chi_jk, chi_kj, g_own, _ = angles
    if len(e1):
        # Each angle (j; e1, e2) adds to both listeners: (listener, χ of it, the other link,
        # χ of the other robot).
        ls = np.concatenate([e1, e2])
        oth = np.concatenate([e2, e1])
        chi_l = np.concatenate([chi_jk, chi_kj])
        chi_o = np.concatenate([chi_kj, chi_jk])
        g_j = np.concatenate([g_own, g_own])
        b_l, b_o = bearings[ls], bearings[oth]
        # White: dα = β_oᵀ ν_l + β_lᵀ ν_o; ν_l is shared by the listener's angles, ν_o not.
        # Slow: the sender's q̃_j through Σ χ_l g_jᵀ (shared), the other robot's q̃_o.
        w_o = bearing_var * np.einsum('ka,kab,kb->k', b_l, projector(b_o), b_l)
        v_o = np.einsum('ka,kab,kb->k', chi_o, P_other[oth][:, :3, :3], chi_o)
        outer_l = chi_l[:, :, None] * chi_l[:, None, :]
        sum_map, J, own_white, other_slow = binned(
            ls, n_edges, chi_l[:, :, None] * b_o[:, None, :],        # of ν_l, per angle
            chi_l[:, :, None] * g_j[:, None, :], w_o[:, None, None] * outer_l,
            v_o[:, None, None] * outer_l)
        white = bearing_var * _sandwich(sum_map, projector(bearings)) + own_white
        slow = _sandwich(J, P_own[agent][:, :3, :3]) + other_slow
        out[:, ANGLE_WHITE], out[:, ANGLE_SLOW] = so3.sym_pack(white), so3.sym_pack(slow)
    if velocity is not None:
        b, d, r_dot = velocity.b_hat, velocity.d, velocity.r_dot
        of_q, of_phi, of_nu = velocity_maps(velocity)
        A = np.concatenate([of_q, of_phi], axis=2)                  # (E, 3, 6)
        slow_v = _sandwich(A, P_own[agent][:, :DOF, :DOF])
        white_v = (bearing_var * _sandwich(of_nu, projector(bearings))
                   + (rate_var * d ** 2)[:, None, None] * EYE3
                   + (odometry_density2 / h + gyro_density2 / h * d ** 2)[:, None, None]
                   * projector(b))
        out[:, VELOCITY_WHITE] = so3.sym_pack(white_v)
        out[:, VELOCITY_SLOW] = so3.sym_pack(slow_v)
        out[:, RATE] = r_dot
    return out


class OwnLinearisation(NamedTuple):
    """A robot's linearised step before ``ΔR_aᵀ``: ``F`` ``(N, 6, 6)``, ``G_q``, ``G_Q`` ``(N, 3,
    3)``, ``T = √c A^{-1/2}`` ``(N, 6, 6)``, free robots' map of ``Σ_j dn'_ji`` ``(N, 6, 3)``."""

    F: Array
    G_q: Array
    G_Q: Array
    T: Array
    B_v: Array


def own_linearisation(h: float, kappa_q: float, kappa_Q: Array, w: float, D: Array,
                      K_a: Array, sensing: Mask, b_own: Array, agent: Index, used: Mask,
                      moved: Array, gamma: Array, omega_a: Array, P_inv: Array,
                      reconstructed: Mask, b_in: Array, r_in: Array, valid: Mask
                      ) -> OwnLinearisation:
    """:class:`OwnLinearisation` of every robot from its attitude gain ``kappa_Q``, ``D̂_i``
    ``D``, ``K_i`` in the anchor frame ``K_a``, the sensing links' ``Q̂_i β_ij`` ``b_own``,
    ``Q̂_i δ_i`` ``moved``, ``γ̂_i`` ``gamma`` (a free robot's map of ``φ`` through ``Q̂_i Ω_i =
    Q̂_i u_i × γ̂_i`` is taken as ``−K``, symmetric, as at the truth where ``Q̂ u = γ̂``: the exact
    ``[γ̂]x [Q̂ u]x`` gave robot_3 of presenza_noisy an attitude NEES of 150), ``P̂_i⁻¹``
    ``P_inv`` where ``reconstructed``, and the received ``𝔟̂_ji``, ``ṙ_ji``."""
    n = D.shape[0]
    # D̂ and K commute with their gains: one eigendecomposition gives G, A and A^{-1/2}.
    lam, V = np.linalg.eigh(np.concatenate([D, K_a]))
    lam = np.maximum(lam, 0.0)
    rate = np.concatenate([np.full(n, h * kappa_q), h * kappa_Q])[:, None]
    g = rate / (1.0 + np.concatenate([np.full(n, 2.0 * w), np.full(n, w)])[:, None] * rate * lam)
    a = g * lam
    floor = np.maximum(MIN_DECAY_RATIO * a.max(axis=1, keepdims=True), MIN_DECAY)
    c = np.concatenate([np.full(n, C_POSITION), np.full(n, C_ATTITUDE)])[:, None]
    Vt = _t(V)
    G, A = (V * g[:, None, :]) @ Vt, (V * a[:, None, :]) @ Vt
    scale = (V * np.sqrt(c / np.maximum(a, floor))[:, None, :]) @ Vt
    G_q, G_Q = G[:n], G[n:]
    T = np.zeros((n, DOF, DOF))
    T[:, :3, :3], T[:, 3:, 3:] = scale[:n], scale[n:]
    F = np.zeros((n, DOF, DOF))
    F[:, :3, :3] = EYE3 - A[:n]
    F[:, 3:, 3:] = EYE3 - A[n:]
    free = ~sensing
    # Sensing: the attitude innovation reads the own position, the prediction the attitude.
    sums = binned(agent, n, np.where(used[:, None, None], so3.hat(b_own), 0.0),
                    np.where(valid[:, None, None], r_in[:, :, None] * b_in[:, None, :], 0.0))
    F[:, 3:, :3] = np.where(sensing[:, None, None], -G_Q @ sums[0], 0.0)
    F[:, :3, 3:] = np.where(sensing[:, None, None], -so3.hat(moved), 0.0)
    # Free: γ̂ reads q̂_i through ω_a × q̂_i and the velocity terms' distances.
    L = so3.hat(omega_a) + P_inv @ sums[1]
    L = np.where((free & reconstructed)[:, None, None], L, 0.0)
    S_g = so3.hat(gamma)
    F[:, :3, :3] += np.where(free[:, None, None], h * L, 0.0)
    F[:, 3:, :3] += np.where(free[:, None, None], G_Q @ S_g @ L, 0.0)
    B_v = np.concatenate([h * P_inv, G_Q @ S_g @ P_inv], axis=1)
    B_v = np.where((free & reconstructed)[:, None, None], B_v, 0.0)
    return OwnLinearisation(F, G_q, G_Q, T, B_v)


def binned(index: Index, n: int, *rows: Array) -> list[Array]:
    """``out[k] = Σ_{m: index[m] = k} rows[m]`` ``(n, ...)`` of each ``(M, ...)`` array, by one
    ``np.add.reduceat`` in row order: a robot's sums do not depend on the others' (a dense
    product's BLAS blocking does, and robots stepped together must get what they get alone)."""
    M = len(index)
    sizes = [int(np.prod(x.shape[1:], dtype=int)) for x in rows]   # (M = 0: no -1 reshape)
    flat = np.zeros((n, sum(sizes)))
    if M:
        order = np.argsort(index, kind='stable')
        idx = np.asarray(index)[order]
        starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
        stacked = np.concatenate([x.reshape(M, k) for x, k in zip(rows, sizes)], axis=1)
        flat[idx[starts]] = np.add.reduceat(stacked[order], starts, axis=0)
    parts = np.split(flat, np.cumsum(sizes)[:-1], axis=1)
    return [part.reshape((n,) + x.shape[1:]) for x, part in zip(rows, parts)]


def own_input_maps(lin: OwnLinearisation, agent: Index, used: Mask, b_own: Array,
                   own_bearings: Array, angles: AngleTerms, d_own: Array, R_hat: Array
                   ) -> tuple[Array, Array]:
    """``(E, 6, 3)`` maps into a sensing robot's ``(q̃, φ)⁺`` of each own bearing's noise ``ν_ij``
    and each sensed robot's ``q̃_j``, through its angles (``dζ_i = g_own (g_jᵀ q̃_j + g_kᵀ q̃_k −
    dα)``) and its innovation (``Q̂_i Ω_i ∋ [𝔟_ij]x q̃_j − d_ij [𝔟_ij]x Q̂_i ν``)."""
    G_q, G_Q = lin.G_q, lin.G_Q
    E = len(agent)
    V, Gn = np.zeros((E, DOF, 3)), np.zeros((E, DOF, 3))
    e1, e2, chi_jk, chi_kj, g_own, _ = angles
    if len(e1):
        Gi = G_q[agent[e1]]
        both = np.concatenate([e1, e2])
        V[:, :3], Gn[:, :3] = binned(
            both, E, np.concatenate([Gi @ (g_own[:, :, None] * own_bearings[o][:, None, :])
                                     for o in (e2, e1)]),
            np.concatenate([-Gi @ (g_own[:, :, None] * chi[:, None, :])
                            for chi in (chi_jk, chi_kj)]))
    S_b = so3.hat(b_own)
    V[:, 3:] = -G_Q[agent] @ (d_own[:, None, None] * S_b) @ R_hat[agent]
    Gn[:, 3:] = G_Q[agent] @ S_b
    keep = used[:, None, None]
    return np.where(keep, V, 0.0), np.where(keep, Gn, 0.0)


def propagate(P: Array, lin: OwnLinearisation, dR_a: Array, agent: Index, *, used: Mask,
              b_own: Array, own_bearings: Array, angles: AngleTerms, d_own: Array,
              P_nbr: Array, terms: Array, sensed_by: Mask, valid: Mask,
              ranged_by: Mask, is_anchor: Mask, sensing: Mask, gamma: Array,
              R_hat: Array, q_next: Array, model: PresenzaCovarianceModel, kappa_s: float,
              h: float, pinned: Mask) -> Array:
    """``P⁺`` ``(N, 6, 6)`` of every robot (module docstring) from its ``P``, its linearised
    step ``lin``, the anchor's rotation ``ΔR_a`` ``(N, 3, 3)`` and per link ``(E, ...)``:
    ``used`` (own sensing), ``b_own`` ``Q̂_i β_ij``, ``own_bearings`` ``β_ij``, ``d_own``
    ``‖q̂_j − q̂_i‖``, what the other robot sent, ``P_nbr`` (``pose_cov``) and ``terms``
    (:data:`TERM_COV`, its angle terms where ``sensed_by``, its velocity terms where ``valid``),
    and ``ranged_by``; ``q_next``: ``q̂_i⁺``, which the anchor's gyro noise turns."""
    n = P.shape[0]
    F, G_q, G_Q, T, B_v = lin
    V, Gn = own_input_maps(lin, agent, used, b_own, own_bearings, angles, d_own, R_hat)
    # What the robots that see it sent: their angle terms' and velocity terms' covariances.
    use = np.concatenate([np.repeat(sensed_by[:, None], 12, axis=1),
                          np.repeat(valid[:, None], 12, axis=1)], axis=1)
    received = np.where(use, terms[:, :24], 0.0).reshape(-1, 4, 6)
    W, Y, sums, n_ranged = binned(
        agent, n, model.bearing_std ** 2 * _sandwich(V, projector(own_bearings)),
        _sandwich(Gn, P_nbr[:, :3, :3]), received, ranged_by.astype(float))
    sums = so3.sym_unpack(sums)
    W[:, :3, :3] += _sandwich(G_q, sums[:, 0])
    Y[:, :3, :3] += _sandwich(G_q, sums[:, 1])
    W += _sandwich(B_v, sums[:, 2])
    Y += _sandwich(B_v, sums[:, 3])
    # The anchor's relative positions of its ranged robots (the anchor term of (5)).
    W[:, :3, :3] += ((kappa_s * model.relative_position_std) ** 2 * n_ranged)[:, None, None] * (
        G_q @ _t(G_q))
    # Own motion sensors (the anchor's cancel with its own inputs).
    odo, gyro = h * model.odometry_noise_density ** 2, h * model.gyro_noise_density ** 2
    other = ~is_anchor
    W[:, :3, :3] += np.where((sensing & other)[:, None, None], odo * EYE3, 0.0)
    S_g = so3.hat(gamma)
    W[:, 3:, 3:] += np.where((~sensing)[:, None, None],
                             (odo / h ** 2) * (G_Q @ S_g) @ _t(G_Q @ S_g), 0.0)
    W[:, 3:, 3:] += np.where(other[:, None, None], gyro * EYE3, 0.0)
    # Slow inputs over the robot's own loops (module docstring).
    out = F @ P @ _t(F) + W + T @ Y @ T
    # Everything turns with the anchor's frame; its noise moves the other robots.
    Rt = np.zeros((n, DOF, DOF))
    Rt[:, :3, :3] = Rt[:, 3:, 3:] = _t(dR_a)
    out = _sandwich(Rt, out)
    a_map = np.zeros((n, DOF, 3))
    a_map[:, :3] = np.where(sensing[:, None, None], so3.hat(q_next), 0.0)
    a_map[:, 3:] = -EYE3
    out += np.where(other[:, None, None], gyro * a_map @ _t(a_map), 0.0)
    out[:, :3, :3] += np.where((sensing & other)[:, None, None], odo * EYE3, 0.0)
    out[pinned] = 0.0   # the anchor that holds (I, 0)
    return capped(0.5 * (out + _t(out)))


def capped(P: Array) -> Array:
    """``P`` with each variance at most its cap, its rows and columns scaled with it (``S P S``,
    still positive semi-definite)."""
    cap = np.array([MAX_POSITION_STD ** 2] * 3 + [MAX_ATTITUDE_STD ** 2] * 3)
    var = np.einsum('nii->ni', P)
    if np.all(var <= cap):
        return P
    scale = np.sqrt(np.minimum(1.0, cap / np.maximum(var, 1e-300)))
    return P * scale[:, :, None] * scale[:, None, :]
