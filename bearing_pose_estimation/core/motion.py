"""Motion profiles and their exact-enough integration. A profile is declarative (no ``eval``):
each component a constant plus sinusoids ``amplitude · sin(frequency · t + phase)``. Rotations
are integrated by the 4th-order Magnus expansion, a world-frame velocity in closed form, a
body-frame one by 3-point Gauss-Legendre quadrature: O(h⁵) locally, far below the observers'
first-order error at the same step."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from . import so3

_SQRT3 = np.sqrt(3.0)


@dataclass(frozen=True)
class Sinusoid:
    """``amplitude · sin(frequency · t + phase)``; frequency in rad/s, phase in rad."""

    amplitude: float
    frequency: float
    phase: float = 0.0


@dataclass(frozen=True)
class Component:
    """One component of a vector profile: ``constant + Σ terms`` (rad/s for ω, m/s for v)."""

    constant: float = 0.0
    terms: tuple[Sinusoid, ...] = ()


@dataclass(frozen=True)
class VectorProfile:
    """A vector of one agent as a function of time, ``(x(t), y(t), z(t))``."""

    x: Component = Component()
    y: Component = Component()
    z: Component = Component()

    @property
    def components(self) -> tuple[Component, Component, Component]:
        return (self.x, self.y, self.z)

    @property
    def is_zero(self) -> bool:
        return all(c.constant == 0.0 and all(t.amplitude == 0.0 for t in c.terms)
                   for c in self.components)


# The body-frame angular velocity ω(t) of one agent [rad/s].
AngularVelocity = VectorProfile
ZERO = VectorProfile()


@dataclass(frozen=True)
class LinearVelocity:
    """An agent's velocity [m/s] in the world frame (``dp/dt = v``), the body frame (``dp/dt = R
    v``), or ``anchor_estimate``: ``u = Q̂ᵀ v`` (Presenza et al., Sec. V, case 2)."""

    frame: Literal['world', 'body', 'anchor_estimate'] = 'world'
    value: VectorProfile = ZERO


class ProfileSet:
    """The vector profiles of N agents, evaluated in one vectorised call: sinusoids packed into
    ``(N, 3, T)`` arrays (T: most terms of any component; unused slots zero)."""

    def __init__(self, profiles: Sequence[VectorProfile]) -> None:
        n = len(profiles)
        n_terms = max([len(c.terms) for p in profiles for c in p.components] + [1])
        self.constant = np.zeros((n, 3))
        self.amplitude = np.zeros((n, 3, n_terms))
        self.frequency = np.zeros((n, 3, n_terms))
        self.phase = np.zeros((n, 3, n_terms))
        for i, profile in enumerate(profiles):
            for axis, comp in enumerate(profile.components):
                self.constant[i, axis] = comp.constant
                for k, term in enumerate(comp.terms):
                    self.amplitude[i, axis, k] = term.amplitude
                    self.frequency[i, axis, k] = term.frequency
                    self.phase[i, axis, k] = term.phase
        # No trigonometry for constant-rate fleets (common in large scenarios).
        self._has_terms = bool(np.any(self.amplitude != 0.0))
        self.is_zero = not self._has_terms and not bool(np.any(self.constant != 0.0))
        # Term-major contiguous copies: a loop over the few terms beats a short-axis sum.
        self._terms = [(np.ascontiguousarray(self.amplitude[..., k]),
                        np.ascontiguousarray(self.frequency[..., k]),
                        np.ascontiguousarray(self.phase[..., k])) for k in range(n_terms)]

    @property
    def is_constant(self) -> bool:
        """Every agent's ω is constant in time."""
        return not self._has_terms

    def __call__(self, t: float | NDArray[np.float64]) -> NDArray[np.float64]:
        """The profiles at ``t``, ``(N, 3)``; at times ``(K,)``, ``(K, N, 3)`` (as K calls)."""
        if np.ndim(t) == 0:
            out = self.constant.copy()
            tt: float | NDArray[np.float64] = t
        else:
            tt = np.asarray(t, dtype=float)[:, None, None]
            out = np.broadcast_to(self.constant, tt.shape[:1] + self.constant.shape).copy()
        if self._has_terms:
            for amplitude, frequency, phase in self._terms:
                out += amplitude * np.sin(frequency * tt + phase)
        return out

    def integral(self, t: float, h: float) -> NDArray[np.float64]:
        """``∫_t^{t+h}`` of every agent's profile, ``(N, 3)``, in closed form:
        ``A sin(f τ + φ)`` integrates to ``2A/f · sin(f h/2) sin(f (t + h/2) + φ)`` (the
        product form loses no digits for small ``h``), and to ``A h sin φ`` when f = 0."""
        out = self.constant * h
        if self._has_terms:
            for amplitude, frequency, phase in self._terms:
                half = 0.5 * frequency * h
                # sin(x)/x with its limit 1 at x = 0: np.sinc(x/π) = sin(x)/x.
                out += amplitude * h * np.sinc(half / np.pi) * np.sin(
                    frequency * (t + 0.5 * h) + phase)
        return out


# 3-point Gauss-Legendre nodes on [0, 1] and weights (exact for polynomials of degree 5).
_GL3_NODES = (0.5 - np.sqrt(0.15), 0.5, 0.5 + np.sqrt(0.15))
_GL3_WEIGHTS = (5.0 / 18.0, 8.0 / 18.0, 5.0 / 18.0)


def magnus_increment(omega: ProfileSet, t: float | NDArray[np.float64],
                     h: float) -> NDArray[np.float64]:
    """Body-frame increment ``ΔR`` over ``[t, t+h]`` for every agent, ``(N, 3, 3)`` (times
    ``t`` ``(K,)``: ``(K, N, 3, 3)``), by the 4th-order Magnus expansion for ``dR/dt = R [ω]x``:
    ``ΔR = exp(h/2 (ω₁ + ω₂) + √3 h²/12 (ω₁ × ω₂))``, ω₁, ω₂ at ``t + (1/2 ∓ √3/6) h``."""
    w1 = omega(t + (0.5 - _SQRT3 / 6.0) * h)
    w2 = omega(t + (0.5 + _SQRT3 / 6.0) * h)
    return so3.exp(0.5 * h * (w1 + w2) + (_SQRT3 / 12.0) * h * h * so3.cross(w1, w2))


def body_displacement(omega: ProfileSet, v_body: ProfileSet, t: float | NDArray[np.float64],
                      h: float) -> NDArray[np.float64]:
    """``∫_0^h ΔR(τ) v_b(t + τ) dτ`` ``(N, 3)`` (times ``t`` ``(K,)``: ``(K, N, 3)``): the
    displacement over ``[t, t+h]`` of agents moving with body-frame velocity ``v_b``, in their
    body frame at t; 3-point Gauss-Legendre with the Magnus increment to each node."""
    out = np.zeros(np.shape(t) + omega.constant.shape)
    for node, weight in zip(_GL3_NODES, _GL3_WEIGHTS):
        tau = node * h
        dR = magnus_increment(omega, t, tau)
        out += (weight * h) * np.einsum('...ab,...b->...a', dR, v_body(t + tau))
    return out


def held_body_displacement(omega: ProfileSet, t: float, h: float,
                           u: NDArray[np.float64]) -> NDArray[np.float64]:
    """``∫_0^h ΔR(τ) dτ · u`` ``(N, 3)``: :func:`body_displacement` with a held ``u``."""
    if omega.is_zero:
        return h * u
    out = np.zeros_like(u)
    for node, weight in zip(_GL3_NODES, _GL3_WEIGHTS):
        out += (weight * h) * np.einsum('nab,nb->na', magnus_increment(omega, t, node * h), u)
    return out


@dataclass(frozen=True)
class YawSpline:
    """``ψ(t)``: the clamped cubic spline through ``values`` [rad] at ``knots`` [s], held
    outside them (De Carli et al., Sec. IV: "a spline with random coefficients")."""

    knots: tuple[float, ...]
    values: tuple[float, ...]


class YawSplines:
    """The yaw splines of N agents, evaluated in one call (scipy's ``CubicSpline`` pieces,
    vectorised over agents that share their knots)."""

    def __init__(self, splines: Sequence[YawSpline]) -> None:
        from scipy.interpolate import CubicSpline

        fitted = [CubicSpline(np.array(s.knots), np.array(s.values), bc_type='clamped')
                  for s in splines]
        self._groups: list[tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64]]]
        self._groups = []
        by_knots: dict[tuple[float, ...], list[int]] = {}
        for i, s in enumerate(splines):
            by_knots.setdefault(tuple(s.knots), []).append(i)
        for knots, rows in by_knots.items():
            # c[k, m, i]: coefficient of (t - t_m)^(3-k) on interval m for agent i.
            c = np.stack([fitted[i].c for i in rows], axis=-1)
            self._groups.append((np.array(rows, dtype=np.intp), np.array(knots), c))
        self.n = len(splines)

    def _eval(self, t: float, derivative: bool) -> NDArray[np.float64]:
        out = np.zeros(self.n)
        for rows, knots, c in self._groups:
            tc = min(max(t, knots[0]), knots[-1])   # held outside the knots
            m = min(max(int(np.searchsorted(knots, tc, side='right')) - 1, 0), len(knots) - 2)
            s = tc - knots[m]
            a3, a2, a1, a0 = c[0, m], c[1, m], c[2, m], c[3, m]
            if derivative:
                inside = knots[0] <= t <= knots[-1]
                out[rows] = (3.0 * a3 * s + 2.0 * a2) * s + a1 if inside else 0.0
            else:
                out[rows] = ((a3 * s + a2) * s + a1) * s + a0
        return out

    def __call__(self, t: float) -> NDArray[np.float64]:
        """``ψ_i(t)`` [rad]."""
        return self._eval(t, derivative=False)

    def rate(self, t: float) -> NDArray[np.float64]:
        """``ψ̇_i(t)`` [rad/s] (0 outside the knots)."""
        return self._eval(t, derivative=True)

    def increment(self, t: float, h: float) -> NDArray[np.float64]:
        """``R_z(ψ(t+h) - ψ(t))`` ``(N, 3, 3)``: exact, no integration."""
        return rot_z(self(t + h) - self(t))

    def held_displacement(self, t: float, h: float, v_body: NDArray[np.float64]
                          ) -> NDArray[np.float64]:
        """``∫_0^h R_z(ψ(t+τ) - ψ(t)) dτ · v`` ``(N, 3)``, with a held body-frame ``v``
        (3-point Gauss-Legendre: exact to rounding at millisecond steps)."""
        psi0 = self(t)
        out = np.zeros_like(v_body)
        for node, weight in zip(_GL3_NODES, _GL3_WEIGHTS):
            out += (weight * h) * np.einsum('nab,nb->na', rot_z(self(t + node * h) - psi0),
                                            v_body)
        return out


def in_anchor_frame(R: NDArray[np.float64], p: NDArray[np.float64], anchor: int
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Poses ``R`` ``(N, 3, 3)`` (body → world), ``p`` ``(N, 3)`` in the body frame of agent
    ``anchor``: ``(R_aᵀ R_i, R_aᵀ (p_i - p_a))``."""
    Ra = R[anchor]
    return np.einsum('ba,nbc->nac', Ra, R), (p - p[anchor]) @ Ra


def yaw_of(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """The yaw of rotations ``(..., 3, 3)`` (exact for rotations about z)."""
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def rot_z(psi: NDArray[np.float64]) -> NDArray[np.float64]:
    """``R_z(ψ)`` for each angle, ``(..., 3, 3)``."""
    c, s = np.cos(psi), np.sin(psi)
    out = np.zeros(np.shape(psi) + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = c, -s, s, c
    out[..., 2, 2] = 1.0
    return out
