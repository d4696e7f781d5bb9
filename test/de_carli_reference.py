"""De Carli et al. (2024): a second implementation of the three stages, for the tests only:
vectorised over a whole fleet's sensing edges and pairs in the pairs' ``a < b`` orientation (the
registered method, ``bearing_pose_estimation/estimators/de_carli.py``, runs per robot and per
link, each pair in its owner's orientation). The stage tests check its properties against the
notes, and the method is checked against it tick for tick.

The notes: ``../shared/estimators/de-carli-2024.md`` (§n), the paper's equation numbers in
parentheses.

Setting (§1). Robots have yaw-only body frames ``R_i = R_z(ψ_i)`` (roll and pitch compensated
by the IMU). Horizontal vectors are complex numbers ``x + ιy``; ``z_i = e^{ιψ_i}``. Robot i
measures ``ⁱp_ij = R_iᵀ (p_j − p_i)`` (2) for each sensing edge ``(i, j)``. Over a tick of
length h its odometry gives the yaw increment ``Δψ_i`` and the displacement ``δ_i`` in its
frame at the tick's start; ``δ'_i = e^{−ιΔψ_i} δ_i`` is the same in the frame at the tick's
end. The discrete kinematics are exact for any motion (§7):
``ⁱp_ij(t_{k+1}) = R_z(−Δψ_i) (ⁱp_ij(t_k) − δ_i + ⁱR_j(t_k) δ_j)``.

Pairs: each communication pair ``{a, b}`` with ``a < b`` has one relative-yaw state
``ẑ_ab ≈ e^{ι(ψ_b − ψ_a)}`` (one copy only, §8); a sensing edge k = (i, j) of it uses
``ẑ_k = ẑ_ab`` when ``(i, j) = (a, b)`` and ``conj(ẑ_ab)`` when reversed.

- Stage 1, the relative-yaw observer (7)-(8), every tick, correct-then-predict (§7): with the
  measurement ``y_k`` and ``E_k = P̂_k − y_k``::

      ẑ_ab⁺  = ẑ_ab − k_ψ Σ_k g_k,   g_k = conj(δ'_b) E_k   (k = (a, b))
                                     g_k = δ'_a conj(E_k)   (k = (b, a))
      P̂_k   ← e^{−ιΔψ_i} (P̂_k − δ_i + δ_j ẑ_k⁺ − h k_pe E_k)     (horizontal part)
      p̂_kz  ← p̂_kz − δ_iz + δ_jz − h k_pe e_kz                   (vertical part)
      ẑ_ab  ← e^{ι(Δψ_b − Δψ_a)} ẑ_ab⁺

  with the δ' of the previous tick in the correction (``δ'_{j,−1} = 0``). Its error
  recursion has no forcing term: at the true values it is an exact fixed point.
- Stage 2, the common-yaw consensus (13), every second tick, Jacobi step (implicit in the
  robot's own state; stable and row-stochastic for any ``c = h₂ k_z`` and any graph, §7)::

      ẑ_i ← (ẑ_i + c Σ_{j ∈ N_i} conj(ẑ_ij) ẑ_j) / (1 + c |N_i|)

  with ``ẑ_ij`` the *unit* relative yaw, then, every tick, ``ẑ_i ← e^{ιΔψ_i} ẑ_i``. Plain
  forward Euler diverges when ``h₂ k_z λ_max(L_c) > 2`` (the paper's cube: λ_max = 6).
- Stage 3, the position observer (21) in edge form: dead reckoning ``p̂_i ← p̂_i + R̂_i δ_i``
  every tick, and every fourth tick ``p̂_i ← p̂_i − h₃ k_p Σ_k E_ik r_k``, with the residual
  ``r_k = p̂_a − p̂_b + R̂_a ᵃp_ab`` of edge k = (a, b) and ``E_ik = +1`` for its tail a, −1
  for its head b. ``R̂_i = R_z(∠ẑ_i)``.

Every estimate converges only up to one common yaw a and translation p̄
(``EstimateFrame.COMMON_YAW_TRANSLATION``): ``ψ̂_i → ψ_i + a``, ``p̂_i → R_z(a) p_i + p̄``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from bearing_pose_estimation.core.motion import rot_z

Array = NDArray[np.float64]
Complex = NDArray[np.complex128]
Index = NDArray[np.intp]

from bearing_pose_estimation.estimators.de_carli import (EXCITATION_M2_S, EXCITATION_WINDOW_S,
                                                        NOISE_MARGIN)

@dataclass(frozen=True)
class Pairs:
    """The communication pairs ``{a, b}`` (``a < b``) of the sensing edges ``(tail, head)``:
    ``edge_pair[k]`` is the pair of edge k, ``reversed_[k]`` whether edge k runs b → a."""

    a: Index
    b: Index
    edge_pair: Index
    reversed_: NDArray[np.bool_]

    @staticmethod
    def of(tail: Index, head: Index) -> Pairs:
        lo, hi = np.minimum(tail, head), np.maximum(tail, head)
        keys, edge_pair = np.unique(np.stack([lo, hi], axis=1), axis=0, return_inverse=True)
        return Pairs(a=keys[:, 0].astype(np.intp), b=keys[:, 1].astype(np.intp),
                     edge_pair=edge_pair.reshape(-1).astype(np.intp), reversed_=tail > head)

    def __len__(self) -> int:
        return int(self.a.shape[0])

    def edge_yaw(self, z_pair: Complex) -> Complex:
        """``ẑ_k`` of every edge from the pair states."""
        z = z_pair[self.edge_pair]
        return np.where(self.reversed_, np.conj(z), z)


def relative_yaw_step(P_hat: Complex, pz_hat: Array, z_pair: Complex, pairs: Pairs,
                      tail: Index, head: Index, y: Complex, y_z: Array, delta: Complex,
                      delta_z: Array, dpsi: Array, delta_end_prev: Complex, h: float,
                      k_pe: float, k_psi: float) -> tuple[Complex, Array, Complex, Complex]:
    """One tick of stage 1 for every sensing edge and pair (module docstring; (7)-(8), §7).

    Args:
        P_hat, pz_hat: ``(K,)`` horizontal (complex) and vertical estimates of ``ⁱp_ij``.
        z_pair: ``(M,)`` the pair states ``ẑ_ab``.
        pairs: the pairs of the edges (:meth:`Pairs.of`).
        tail, head: ``(K,)`` the sensing robot i and the sensed robot j of each edge.
        y, y_z: ``(K,)`` the measurements ``ⁱp_ij`` at the tick's start (complex xy, z).
        delta, delta_z: ``(N,)`` every robot's odometry displacement over the tick, in its
            frame at the tick's start (complex xy, z) [m].
        dpsi: ``(N,)`` every robot's yaw increment over the tick [rad].
        delta_end_prev: ``(N,)`` ``δ'`` of the previous tick (the regressor; 0 at first).
        h: the tick [s]; k_pe, k_psi: the gains of (7).

    Returns:
        ``(P̂, p̂_z, ẑ_pair)`` at the tick's end and the errors ``E_k`` used (complex xy).
    """
    E = P_hat - y
    e_z = pz_hat - y_z
    a, b = pairs.a, pairs.b
    # g_k = conj(δ'_b) E_k for k = (a, b); δ'_a conj(E_k) for k = (b, a).
    other = np.where(pairs.reversed_, delta_end_prev[a[pairs.edge_pair]],
                     np.conj(delta_end_prev[b[pairs.edge_pair]]))
    g = other * np.where(pairs.reversed_, np.conj(E), E)
    m = len(pairs)
    z_plus = z_pair - k_psi * (np.bincount(pairs.edge_pair, weights=g.real, minlength=m)
                               + 1j * np.bincount(pairs.edge_pair, weights=g.imag, minlength=m))
    z_k = pairs.edge_yaw(z_plus)
    P_next = np.exp(-1j * dpsi[tail]) * (P_hat - delta[tail] + delta[head] * z_k - h * k_pe * E)
    pz_next = pz_hat - delta_z[tail] + delta_z[head] - h * k_pe * e_z
    z_next = np.exp(1j * (dpsi[b] - dpsi[a])) * z_plus
    return P_next, pz_next, z_next, E


def yaw_consensus_step(z: Complex, u_pair: Complex, pairs: Pairs, active: NDArray[np.bool_],
                       c: float) -> Complex:
    """The Jacobi step of stage 2, (13) (module docstring; §7), over the ``active`` pairs
    (excited ones): ``ẑ_i ← (ẑ_i + c Σ_j conj(ẑ_ij) ẑ_j) / (1 + c |N_i|)``, with the unit
    relative yaws ``u_pair`` ``(M,)`` (``ẑ_ij = u_ab`` for i = a, ``conj(u_ab)`` for i = b)
    and ``c = h₂ k_z``."""
    n = z.shape[0]
    a, b, u = pairs.a[active], pairs.b[active], u_pair[active]
    pull_a = np.conj(u) * z[b]   # conj(ẑ_ab) ẑ_b, for robot a
    pull_b = u * z[a]            # conj(ẑ_ba) ẑ_a = u_ab ẑ_a, for robot b
    total = (np.bincount(a, weights=pull_a.real, minlength=n)
             + np.bincount(b, weights=pull_b.real, minlength=n)
             + 1j * (np.bincount(a, weights=pull_a.imag, minlength=n)
                     + np.bincount(b, weights=pull_b.imag, minlength=n)))
    degree = np.bincount(a, minlength=n) + np.bincount(b, minlength=n)
    return (z + c * total) / (1.0 + c * degree)


def position_correction(p_hat: Array, psi_hat: Array, tail: Index, head: Index,
                        measured: Array, h3: float, k_p: float) -> Array:
    """The correction of stage 3, (21) in edge form: ``p̂_i − h₃ k_p Σ_k E_ik r_k`` with
    ``r_k = p̂_a − p̂_b + R̂_a ᵃp_ab`` for every edge k = (a, b) (``measured`` ``(K, 3)``,
    ``R̂_a = R_z(ψ̂_a)``, ``psi_hat`` ``(N,)``)."""
    n = p_hat.shape[0]
    r = p_hat[tail] - p_hat[head] + np.einsum('kab,kb->ka', rot_z(psi_hat[tail]), measured)
    signed = np.zeros_like(p_hat)
    for axis in range(3):
        signed[:, axis] = (np.bincount(tail, weights=r[:, axis], minlength=n)
                           - np.bincount(head, weights=r[:, axis], minlength=n))
    return p_hat - h3 * k_p * signed


def dead_reckoning(p_hat: Array, psi_hat: Array, delta: Array) -> Array:
    """``p̂_i + R̂_i δ_i`` (every tick of stage 3; ``delta`` ``(N, 3)`` in each robot's frame)."""
    return p_hat + np.einsum('nab,nb->na', rot_z(psi_hat), delta)


class ExcitationMonitor:
    """Per pair: the excitation its sensed robots give it (§5), since the start (:attr:`total`)
    and over an exponential window of length τ (``recent_k = e^{-h/τ} recent_{k-1} + tick_k``);
    the pairs excited within the window (:attr:`excited_now`): above ``threshold`` plus
    ``NOISE_MARGIN`` times the window's mean of pure odometry noise of density ``noise``
    (``2 noise²`` per tick and sensed robot, summed with the window's weights); and the pairs
    the consensus may use (:attr:`active`): excited now at some tick so far.

    Args:
        pairs: the pairs of the sensing edges.
        h: the tick [s] (the excitation of a tick is ``|δ_xy|²/h``).
        noise: the odometry's noise density [m/√s].
    """

    def __init__(self, pairs: Pairs, h: float, threshold: float = EXCITATION_M2_S,
                 window: float = EXCITATION_WINDOW_S, noise: float = 0.0) -> None:
        self.pairs, self.h = pairs, h
        m = len(pairs)
        # The robot each edge senses: its motion excites the edge's pair.
        self._sensed = np.where(pairs.reversed_, pairs.a[pairs.edge_pair],
                                pairs.b[pairs.edge_pair])
        self._decay = np.exp(-h / window)
        weights = sum(self._decay ** k for k in range(int(50 * window / h)))   # Σ e^{-kh/τ}
        sensed = np.bincount(pairs.edge_pair, minlength=m)
        self.threshold = threshold + NOISE_MARGIN * 2.0 * noise ** 2 * weights * sensed
        self.total = np.zeros(m)          # ∫ Σ |v_xy|² dt since the start [m²/s]
        self.recent = np.zeros(m)         # the same over the window
        self.active = np.zeros(m, dtype=bool)

    def add(self, delta: Complex) -> None:
        """One tick's horizontal displacements ``δ`` ``(N,)`` (complex) of every robot."""
        per_edge = np.abs(delta[self._sensed]) ** 2 / self.h
        tick = np.bincount(self.pairs.edge_pair, weights=per_edge, minlength=len(self.pairs))
        self.total += tick
        self.recent = self._decay * self.recent + tick
        self.active |= self.excited_now

    @property
    def excited_now(self) -> NDArray[np.bool_]:
        """Pairs excited within the window (a diagnostic: the fleet may have stopped)."""
        return self.recent >= self.threshold
