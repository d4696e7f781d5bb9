"""The truth of a scenario, behind the batch simulator, the simulator node and the check, with
the sensors' true values. Rotation and translation advance together over ``dt``
(:mod:`core.motion`); yaw splines give ``R_i = R_z(ψ_i(t))`` exactly. The formation controller
(:mod:`core.formation`) is held between its ticks (a sampled-data plant, the note's §7), in
``paper`` mode on :attr:`Truth.controller_yaws`. ``anchor_estimate`` velocities (Presenza et
al., case 2) hold ``u_i = Q̂_iᵀ v_i(t)`` with :meth:`Truth.command`'s estimate (else the true)."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ..core import formation, so3
from ..core.motion import (ZERO, ProfileSet, YawSplines, body_displacement,
                           held_body_displacement, in_anchor_frame, magnus_increment,
                           rot_z)
from .model import Scenario

Array = NDArray[np.float64]
Index = NDArray[np.intp]

# Products of rotations drift off SO(3) by about one rounding error per step; re-orthonormalising
# every 16 steps keeps ‖RᵀR - I‖ below 1e-14 at a sixteenth of the cost.
REORTHONORMALIZE_EVERY = 16
INCREMENT_CHUNK = 50   # steps whose increments (and body displacements) one call computes


class _Chunk:
    """A function of time alone at :data:`INCREMENT_CHUNK` steps from ``k0``, in one call."""

    def __init__(self, compute: Callable[[Array], Array], dt: float) -> None:
        self.compute = compute   # start times (M,) -> values (M, ...)
        self.dt = dt
        self.k0 = 0
        self.values: Array | None = None

    def at(self, k: int) -> Array:
        if self.values is None or not self.k0 <= k < self.k0 + len(self.values):
            # Start times as Truth.t gives them: bit for bit the numbers of one call per step.
            self.k0 = k
            self.values = self.compute(np.arange(k, k + INCREMENT_CHUNK, dtype=float) * self.dt)
        return self.values[k - self.k0]


class Truth:
    """True poses of every agent on the grid ``t = k · dt``."""

    def __init__(self, scenario: Scenario, dt: float) -> None:
        self.scenario = scenario
        self.dt = float(dt)
        agents = scenario.agents
        self.omega = ProfileSet([a.angular_velocity for a in agents])

        def velocities(frame: str) -> ProfileSet:
            return ProfileSet([a.velocity.value if a.velocity is not None
                               and a.velocity.frame == frame else ZERO for a in agents])

        self.v_world, self.v_body = velocities('world'), velocities('body')
        self.v_anchor = velocities('anchor_estimate')   # u_i = Q̂_iᵀ v_i(t), held per step
        self.anchor = scenario.anchor_index
        self.yaws = (YawSplines([a.yaw for a in agents if a.yaw is not None])
                     if scenario.yaw_only else None)   # the parser: all agents or none
        self.control = scenario.formation
        self._controlled = np.array([a.formation_position is not None for a in agents])
        if self.control is not None and self._controlled.any():
            self._p_star = np.stack([a.formation_position if a.formation_position is not None
                                     else np.zeros(3) for a in agents])
            self._tail, self._head = scenario.sensing_edges()
            self._control_every = max(1, int(round(1.0 / (self.control.rate * self.dt))))
        else:
            self.control = None
        self.moves = (not (self.v_world.is_zero and self.v_body.is_zero and self.v_anchor.is_zero)
                      or self.control is not None)
        # The yaws the controller uses (paper mode: the estimates); None: the true yaws.
        self.controller_yaws: Array | None = None
        # Constant rates (common in generated fleets): the increment never changes.
        self._constant = (magnus_increment(self.omega, 0.0, self.dt)
                          if self.omega.is_constant and self.yaws is None else None)
        self.reset()

    def reset(self) -> None:
        """Back to t = 0 and the scenario's poses."""
        self.k = 0
        self.R = np.stack([a.attitude for a in self.scenario.agents])
        self.p = np.stack([a.position for a in self.scenario.agents])
        self._next: tuple[int, Array] | None = None  # the increment from step k, once computed
        self._increments = _Chunk(lambda t: magnus_increment(self.omega, t, self.dt), self.dt)
        self._body_deltas = _Chunk(
            lambda t: body_displacement(self.omega, self.v_body, t, self.dt), self.dt)
        self._next_delta: tuple[int, Array] | None = None  # the displacement from step k
        self.v_control = np.zeros_like(self.p)   # the controller's held body velocities
        self.controller_yaws = None
        self.u_command = np.zeros_like(self.p)   # anchor_estimate agents' held body commands
        self._commanded_at = -1                  # the step whose commands are set

    @property
    def t(self) -> float:
        return self.k * self.dt

    @property
    def reorthonormalizes(self) -> bool:
        """The step just taken re-orthonormalised the attitudes (an estimator can follow)."""
        return self.k % REORTHONORMALIZE_EVERY == 0

    def increment(self) -> Array:
        """``ΔR_i = R_i(t)ᵀ R_i(t + dt)`` of every agent, ``(N, 3, 3)`` (body frame)."""
        if self._constant is not None:
            return self._constant
        if self.yaws is None:
            # ω is a function of time alone: a chunk of increments in one call, the same
            # numbers for a third of the world's cost per tick (bench/world_cost.py).
            return self._increments.at(self.k)
        if self._next is None or self._next[0] != self.k:  # measured, then stepped: once
            self._next = (self.k, self.yaws.increment(self.t, self.dt))
        return self._next[1]

    def displacement(self) -> Array:
        """``δ_i = R_i(t)ᵀ (p_i(t + dt) - p_i(t))`` ``(N, 3)`` [m], what odometry integrates."""
        if not self.moves:
            return np.zeros_like(self.p)
        if self._next_delta is None or self._next_delta[0] != self.k:
            delta = np.einsum('nba,nb->na', self.R, self.v_world.integral(self.t, self.dt))
            if not self.v_body.is_zero:   # a function of time alone: a chunk at once
                delta += self._body_deltas.at(self.k)
            if not self.v_anchor.is_zero:
                delta += held_body_displacement(self.omega, self.t, self.dt, self.commands())
            if self.control is not None:
                if self.k % self._control_every == 0:
                    self.v_control = self.controller_velocity()
                assert self.yaws is not None   # the parser requires yaw splines
                delta += self.yaws.held_displacement(self.t, self.dt, self.v_control)
            self._next_delta = (self.k, delta)
        return self._next_delta[1]

    def controller_velocity(self) -> Array:
        """The formation controller's body-frame velocities now ``(N, 3)`` [m/s]."""
        assert self.control is not None and self.yaws is not None
        psi = self.yaws(self.t)
        used = (self.controller_yaws if self.control.mode == 'paper'
                and self.controller_yaws is not None else psi)
        return formation.body_velocity(self.p, used, psi, self._p_star, self._tail,
                                       self._head, self.control.k_c, self.control.nu_max,
                                       self._controlled)

    def command(self, Q_hat: Array | None = None) -> None:
        """Hold ``u_i = Q̂_iᵀ v_i(t)`` over the step from now, ``Q_hat`` ``(N, 3, 3)`` the attitude
        estimates in the anchor frame (None: the true ``R_aᵀ R_i``)."""
        if Q_hat is None:
            assert self.anchor is not None
            Q_hat = in_anchor_frame(self.R, self.p, self.anchor)[0]
        self.u_command = np.einsum('nba,nb->na', Q_hat, self.v_anchor(self.t))
        self._commanded_at = self.k

    def commands(self) -> Array:
        """The held body commands ``(N, 3)`` [m/s] now (:meth:`command`'s, else the truth's)."""
        if self._commanded_at != self.k:
            self.command()
        return self.u_command

    @property
    def p_star(self) -> Array | None:
        """The desired formation ``(N, 3)`` [m] (None without formation control)."""
        return self._p_star if self.control is not None else None

    def advance(self) -> Array:
        """Advance by ``dt``; return the rotation increment used."""
        delta_R = self.increment()
        if self.moves:
            self.p = self.p + np.einsum('nab,nb->na', self.R, self.displacement())
        self.k += 1
        if self.yaws is not None:   # exact, nothing accumulates
            self.R = rot_z(self.yaws(self.t))
            return delta_R
        self.R = so3.matmul(self.R, delta_R)
        if self.reorthonormalizes:
            self.R = so3.reorthonormalize(self.R)
        return delta_R

    def angular_rate(self) -> Array:
        """Body angular velocities now, ``(N, 3)`` [rad/s]."""
        if self.yaws is not None:
            out = np.zeros((len(self.p), 3))
            out[:, 2] = self.yaws.rate(self.t)
            return out
        return self.omega(self.t)

    def velocity(self) -> Array:
        """World-frame velocities ``dp_i/dt`` now, ``(N, 3)`` [m/s]."""
        v = self.v_world(self.t)
        if not self.v_body.is_zero:
            v = v + np.einsum('nab,nb->na', self.R, self.v_body(self.t))
        if not self.v_anchor.is_zero:
            v = v + np.einsum('nab,nb->na', self.R, self.commands())
        if self.control is not None:
            if self.k % self._control_every == 0 and (self._next_delta is None
                                                       or self._next_delta[0] != self.k):
                self.displacement()   # evaluates the controller at this instant
            v = v + np.einsum('nab,nb->na', self.R, self.v_control)
        return v

    def relative_positions(self, owner: Index, target: Index) -> Array:
        """``ⁱp_ij = R_iᵀ (p_j - p_i)`` from ``owner[m]`` to ``target[m]``, ``(M, 3)`` [m]."""
        return self.body_bearings(owner, self.p[target] - self.p[owner])

    def ranges(self, owner: Index, target: Index) -> Array:
        """``‖p_j - p_i‖``, ``(M,)`` [m]."""
        return np.linalg.norm(self.p[target] - self.p[owner], axis=1)

    def bearing_rates(self, owner: Index, target: Index) -> Array:
        """``d b^i_ij/dt`` of the body bearings ``b^i_ij = R_iᵀ d/‖d‖``, ``d = p_j - p_i``,
        ``(M, 3)`` [1/s]: ``-ω_i × b^i_ij + R_iᵀ P_{d} ḋ/‖d‖`` (``P_d = I - d dᵀ/‖d‖²``)."""
        d = self.p[target] - self.p[owner]
        rho = np.linalg.norm(d, axis=1, keepdims=True)
        u = d / rho
        v = self.velocity()
        d_dot = v[target] - v[owner]
        u_dot = (d_dot - u * so3.dot(u, d_dot)[:, None]) / rho
        b = self.body_bearings(owner, u)
        w = self.angular_rate()[owner]
        return self.body_bearings(owner, u_dot) - so3.cross(w, b)

    def world_bearings(self, owner: Index, target: Index) -> Array:
        """World bearings ``b_ij = (p_j - p_i)/‖p_j - p_i‖``, ``owner[m]`` to ``target[m]``."""
        d = self.p[target] - self.p[owner]
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def body_bearings(self, owner: Index, b_world: Array) -> Array:
        """What ``owner[m]`` measures of the world bearing ``b_world[m]``: ``R_iᵀ b``."""
        return np.einsum('eba,eb->ea', np.take(self.R, owner, axis=0), b_world)


class OnTruth:
    """A simulator's true attitudes ``R``, positions ``p`` [m] and time ``t`` [s]."""

    truth: Truth

    @property
    def R(self) -> Array:
        return self.truth.R

    @property
    def p(self) -> Array:
        return self.truth.p

    @property
    def t(self) -> float:
        return self.truth.t
