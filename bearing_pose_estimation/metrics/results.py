"""Pose errors, measured as each method's estimate frame requires, and the recording of a run:
the one place (batch simulator, netsim, DDS monitor) that turns estimates into errors. Estimates
are first mapped to the world frame (:func:`to_world`). ``COMMON_YAW_TRANSLATION``
(``p̂_i ≈ R_z(a) p_i + t``) is aligned exactly in closed form: ``a*``, the circular mean of the
yaw offsets ``ψ̂_i - ψ_i``, minimises ``Σ_i |e^{ιψ̂_i} - e^{ι(ψ_i + a)}|²``, and ``t* = mean_i
(p̂_i - R_z(a*) p_i)``; one ``a*`` for attitudes and positions, so a yaw/position inconsistency
is not hidden. ``ANCHOR_BODY`` estimates take the anchor's true pose (it fixes the gauge).

Per agent: the angle of ``R_i R̂_iᵀ`` [rad], ``‖p_i − p̂_i‖`` [m], and Boughellaba & Tayebi's
``|R̃_i|_I`` (Fig. 2) and ``‖p_i − R̃_i p̂_i‖`` (Fig. 3)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..core import so3
from ..core.motion import rot_z, yaw_of
from ..estimators.base import EstimateFrame

Array = NDArray[np.float64]


class PoseErrors(NamedTuple):
    """Errors of some agents at one instant, each ``(n,)``."""

    att_err: Array
    pos_err: Array
    att_dist_I: Array
    pos_err_paper: Array


def to_world(frame: EstimateFrame, R: Array, p: Array, R_hat: Array, p_hat: Array,
             anchor: int | None = None) -> tuple[Array, Array]:
    """The fleet's estimates ``R_hat`` ``(N, 3, 3)``, ``p_hat`` ``(N, 3)`` in the world frame,
    aligned as ``frame`` calls for (``anchor``: the anchor's row, for ``ANCHOR_BODY``)."""
    if frame is EstimateFrame.WORLD:
        return R_hat, p_hat
    if frame is EstimateFrame.COMMON_YAW_TRANSLATION:
        a = float(np.angle(np.sum(np.exp(1j * (yaw_of(R_hat) - yaw_of(R))))))
        Rz = rot_z(np.array(a))
        t = np.mean(p_hat - p @ Rz.T, axis=0)
        return Rz.T @ R_hat, (p_hat - t) @ Rz
    if frame is EstimateFrame.ANCHOR_BODY:
        if anchor is None:
            raise ValueError('ANCHOR_BODY estimates need the anchor')
        return R[anchor] @ R_hat, p[anchor] + p_hat @ R[anchor].T
    raise ValueError(f'unknown estimate frame {frame}')


def pose_errors(frame: EstimateFrame, R: Array, p: Array, R_hat: Array, p_hat: Array,
                rows: Sequence[int] | NDArray[np.intp] | None = None,
                anchor: int | None = None) -> PoseErrors:
    """Errors of the agents ``rows`` (default: all), after the whole fleet's alignment."""
    R_hat, p_hat = to_world(frame, R, p, R_hat, p_hat, anchor)
    if rows is not None:
        R, p, R_hat, p_hat = R[rows], p[rows], R_hat[rows], p_hat[rows]
    R_tilde = R @ np.swapaxes(R_hat, -1, -2)
    p_tilde = p - np.einsum('nab,nb->na', R_tilde, p_hat)
    return PoseErrors(so3.angle(R_tilde), np.linalg.norm(p - p_hat, axis=1),
                      so3.dist_I(R_tilde), np.linalg.norm(p_tilde, axis=1))


@dataclass
class Trajectories:
    """Positions of the whole fleet at a recording's times, ``(K, N, 3)`` [m], rows in the order
    of ``agents``: the truth ``p`` and the estimates ``p_hat`` (world frame, :func:`to_world`)."""

    agents: list[str]
    leaders: list[str]
    p: Array
    p_hat: Array

    @property
    def is_leader(self) -> NDArray[np.bool_]:
        """``(N,)``: which rows are leaders."""
        return np.array([name in self.leaders for name in self.agents], dtype=bool)


@dataclass
class Recording:
    """Errors of every estimating agent (``followers``) at the recorded times, ``(K, F)``; moving
    fleets' :class:`Trajectories`; ``extra`` columns ``(K,)`` by name (``rel_yaw_err_<a>_<b>``)."""

    t: Array
    followers: list[str]
    att_err: Array
    pos_err: Array
    att_dist_I: Array
    pos_err_paper: Array
    trajectories: Trajectories | None = None
    extra: dict[str, Array] = field(default_factory=dict)

    @staticmethod
    def of(t: Sequence[float], followers: list[str], rows: Sequence[PoseErrors], *,
           agents: list[str] | None = None, leaders: Sequence[str] = (),
           p: Sequence[Array] | None = None, p_hat: Sequence[Array] | None = None,
           extra: Mapping[str, Array] | None = None) -> Recording:
        """A recording from the errors at each time; with ``agents`` (all N, in row order),
        ``leaders`` and the positions ``p``, ``p_hat`` ``(N, 3)`` at each, its trajectories."""
        att_err, pos_err, att_dist_I, pos_err_paper = (
            np.array([r[c] for r in rows]) for c in range(len(PoseErrors._fields)))
        times = np.array(t, dtype=float)
        columns = {name: np.asarray(v, dtype=float) for name, v in (extra or {}).items()}
        for name, v in columns.items():
            if v.shape != times.shape:
                raise ValueError(f'extra column {name} must be {times.shape}, got {v.shape}')
        if p is None and p_hat is None and agents is None:
            return Recording(times, followers, att_err, pos_err, att_dist_I, pos_err_paper,
                             extra=columns)
        if p is None or p_hat is None or agents is None:
            raise ValueError('trajectories need agents, p and p_hat together')
        shape = (len(times), len(agents), 3)

        def stacked(x: Sequence[Array]) -> Array:
            return np.array(x, dtype=float) if len(x) else np.empty(shape)

        P, P_hat = stacked(p), stacked(p_hat)
        if P.shape != shape or P_hat.shape != shape:
            raise ValueError(f'trajectories must be {shape}, got p {P.shape}, '
                             f'p_hat {P_hat.shape}')
        unknown = sorted((set(leaders) | set(followers)) - set(agents))
        if unknown:
            raise ValueError(f'not among the agents: {", ".join(unknown)}')
        return Recording(times, followers, att_err, pos_err, att_dist_I, pos_err_paper,
                         Trajectories(list(agents), list(leaders), P, P_hat), extra=columns)

    def mean_errors(self) -> tuple[Array, Array]:
        """Mean attitude [rad] and position [m] error over the agents, per record."""
        return self.att_err.mean(axis=1), self.pos_err.mean(axis=1)
