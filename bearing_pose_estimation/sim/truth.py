"""The truth of a scenario, the one model behind the batch simulator and the simulator node.

Positions are static; every attitude follows ``dR_i/dt = R_i [ω_i(t)]x``, advanced by the
4th-order Magnus increment (:func:`core.motion.magnus_increment`) over steps of ``dt``: the
estimator step in the batch simulator, ``simulation.internal_step`` (1 ms) in the simulator
node. Bearings are measured from it: ``b^i_ij = R_iᵀ (p_j - p_i)/‖p_j - p_i‖``.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from ..core.motion import OmegaProfile, magnus_increment
from ..scenario.model import Scenario

Array = NDArray[np.float64]
Index = NDArray[np.intp]

# Products of rotations drift off SO(3) by about one rounding error per step; re-orthonormalising
# every 16 steps keeps ‖RᵀR - I‖ below 1e-14 at a sixteenth of the cost.
REORTHONORMALIZE_EVERY = 16


class Truth:
    """True poses of every agent on the grid ``t = k · dt``."""

    def __init__(self, scenario: Scenario, dt: float) -> None:
        self.scenario = scenario
        self.dt = float(dt)
        self.omega = OmegaProfile([a.angular_velocity for a in scenario.agents])
        self.p = np.stack([a.position for a in scenario.agents])
        # Constant rates (common in generated fleets): the increment never changes.
        self._constant = (magnus_increment(self.omega, 0.0, self.dt)
                          if self.omega.is_constant else None)
        self.reset()

    def reset(self) -> None:
        """Back to t = 0 and the scenario's attitudes."""
        self.k = 0
        self.R = np.stack([a.attitude for a in self.scenario.agents])
        self._next: tuple[int, Array] | None = None  # the increment from step k, once computed

    @property
    def t(self) -> float:
        return self.k * self.dt

    @property
    def reorthonormalizes(self) -> bool:
        """The step just taken pulled the attitudes back onto SO(3) (every
        :data:`REORTHONORMALIZE_EVERY` steps); an estimator stepped alongside can do the same."""
        return self.k % REORTHONORMALIZE_EVERY == 0

    def increment(self) -> Array:
        """``ΔR_i = R_i(t)ᵀ R_i(t + dt)`` of every agent, ``(N, 3, 3)`` (body frame)."""
        if self._constant is not None:
            return self._constant
        if self._next is None or self._next[0] != self.k:  # measured, then stepped: once
            self._next = (self.k, magnus_increment(self.omega, self.t, self.dt))
        return self._next[1]

    def advance(self) -> Array:
        """Advance by ``dt``; return the increment used."""
        delta_R = self.increment()
        self.R = so3.matmul(self.R, delta_R)
        self.k += 1
        if self.reorthonormalizes:
            self.R = so3.reorthonormalize(self.R)
        return delta_R

    def world_bearings(self, owner: Index, target: Index) -> Array:
        """Unit world bearings ``b_ij = (p_j - p_i)/‖p_j - p_i‖`` from ``owner[m]`` to
        ``target[m]``, ``(M, 3)``."""
        d = self.p[target] - self.p[owner]
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def body_bearings(self, owner: Index, b_world: Array) -> Array:
        """What ``owner[m]`` measures of the world bearing ``b_world[m]``: ``R_iᵀ b``,
        ``(M, 3)``."""
        return np.einsum('eba,eb->ea', np.take(self.R, owner, axis=0), b_world)


class OnTruth:
    """What a simulator built on a :class:`Truth` shows of it: true attitudes ``R``
    ``(N, 3, 3)``, positions ``p`` ``(N, 3)`` [m] and the time ``t`` [s]."""

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
