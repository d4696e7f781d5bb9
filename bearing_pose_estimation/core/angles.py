"""Angle rigidity (Presenza et al. 2026, Sec. II; ``presenza-2026.md`` §2, §4.1): the angle
set of a directed sensing graph, its rigidity matrix, the cost's Hessian and the margins.
Robot i measures the body bearings ``β_ij`` of its out-neighbours ``j ∈ O_i``; the
angles are the cosines ``α_ijk = β_ijᵀ β_ik`` for every pair ``{j, k} ⊆ O_i``, ``j < k``. With
``𝔮_ij = q_ij/‖q_ij‖`` and ``χ_ijk = Π(𝔮_ij) 𝔮_ik / ‖q_ij‖``, the row of ``α_ijk`` in the
rigidity matrix ``A = ∂α/∂q`` has the blocks ``-(χ_ijk + χ_ikj)ᵀ`` at i, ``χ_ijkᵀ`` at j and
``χ_ikjᵀ`` at k (3)."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
Index = NDArray[np.intp]

# Infinitesimal angle rigidity on normalised positions: σ_{3N-7}(A)/σ_1(A) above this (§2).
IAR_TOLERANCE = 1e-8


def angle_triples(out_neighbours: Sequence[Sequence[int]]) -> Index:
    """Every angle ``(i, j, k)`` ``(|𝒜|, 3)``: i's out-neighbours ``j < k`` in its list order."""
    rows = [(i, o[a], o[b]) for i, o in enumerate(out_neighbours)
            for a in range(len(o)) for b in range(a + 1, len(o))]
    return np.array(rows, dtype=np.intp).reshape(-1, 3)


def chi(q: Array, triples: Index) -> tuple[Array, Array]:
    """``(χ_ijk, χ_ikj)`` ``(|𝒜|, 3)`` each, at the positions ``q`` ``(N, 3)``."""
    i, j, k = triples.T
    dj, dk = q[j] - q[i], q[k] - q[i]
    rj = np.linalg.norm(dj, axis=1, keepdims=True)
    rk = np.linalg.norm(dk, axis=1, keepdims=True)
    uj, uk = dj / rj, dk / rk
    c = np.sum(uj * uk, axis=1, keepdims=True)
    return (uk - c * uj) / rj, (uj - c * uk) / rk


def rigidity_matrix(q: Array, triples: Index) -> Array:
    """``A(q) = ∂α/∂q`` ``(|𝒜|, 3N)`` (3)."""
    n = q.shape[0]
    a = np.zeros((len(triples), n, 3))
    c_jk, c_kj = chi(q, triples)
    rows = np.arange(len(triples))
    i, j, k = triples.T
    a[rows, i] -= c_jk + c_kj
    a[rows, j] += c_jk
    a[rows, k] += c_kj
    return a.reshape(len(triples), 3 * n)


def normalised(q: Array) -> Array:
    """``q`` minus its centroid, divided by its RMS radius: ``A`` scales like 1/length, so a
    relative tolerance on its singular values needs one scale (§2, step 2)."""
    c = q - q.mean(axis=0)
    return c / max(float(np.sqrt(np.mean(np.sum(c * c, axis=1)))), 1e-300)


def iar_margin(q: Array, triples: Index) -> float:
    """``σ_{3N-7}(A)/σ_1(A)`` on the normalised positions, above :data:`IAR_TOLERANCE` iff
    infinitesimally angle rigid (Definition 1); 0 with fewer than ``3N - 7`` angles."""
    n = q.shape[0]
    if len(triples) < 3 * n - 7 or not len(triples):
        return 0.0
    s = np.linalg.svd(rigidity_matrix(normalised(q), triples), compute_uv=False)
    return float(s[3 * n - 8] / s[0]) if s[0] > 0 else 0.0


def hessian(q: Array, triples: Index, kappa_s: float, anchor: int,
            ranged: Sequence[int]) -> Array:
    """``H = AᵀA + κ_s (𝔢_a𝔢_aᵀ + 𝔢_b𝔢_bᵀ + 𝔢_c𝔢_cᵀ) ⊗ I_3`` ``(3N, 3N)`` [1/m²]: the cost's
    Hessian at the true positions (Lemma 1, with the paper's ``I_N`` read as ``I_{3N}``)."""
    a = rigidity_matrix(q, triples)
    h = a.T @ a
    for r in (anchor, *ranged):
        h[3 * r:3 * r + 3, 3 * r:3 * r + 3] += kappa_s * np.eye(3)
    return h


def projector_sum(bearings: Array) -> Array:
    """``Σ_m Π(β_m)`` ``(3, 3)`` of unit vectors ``(M, 3)`` (A3, A5 and P_i of (15))."""
    return len(bearings) * np.eye(3) - bearings.T @ bearings
