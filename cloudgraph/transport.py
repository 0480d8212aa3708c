"""Radiance transport through the graph (thesis §4.5, Algorithm 1).

L' = sum_{i < k} T^i L_d with T = C . diag(albedo) (DESIGN.md), by iterated sparse
matrix-vector products: with k = max_depth, or until the energy a product adds falls below a
tolerance when the depth is unbounded (max_depth -1).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def transport(
    C: sp.spmatrix,
    L_d: np.ndarray,
    albedo,
    max_depth: int = -1,
    tol: float = 1e-5,
    max_iterations: int = 100_000,
) -> tuple[np.ndarray, int]:
    """Neumann series of the transport matrix applied to the direct radiance (Algorithm 1).

    Args:
        C: (N, N) collision probabilities, C[a, b] = P(a flight from a collides in b).
        L_d: (N, 3) direct radiance per node and channel.
        albedo: scalar or (3,) single-scattering albedo per channel.
        max_depth: most scattering events on a path; node radiance holds paths of up to
            max_depth - 1 further events after the one at the node. -1: unbounded.
        tol: unbounded depth stops when sum(T^i L_d) <= tol * sum(L').

    Returns:
        (L', iterations): (N, 3) total in-scattered radiance per node, and products done.
    """
    L_d = np.asarray(L_d, np.float64).reshape(len(L_d), -1)
    albedo = np.broadcast_to(np.asarray(albedo, np.float64), (L_d.shape[1],))
    if max_depth == 0:
        return np.zeros_like(L_d), 0
    C = sp.csr_matrix(C, dtype=np.float64)
    L = L_d.copy()  # Radiance accumulator, L'
    term = L_d.copy()  # T^i L_d
    limit = max_iterations if max_depth < 0 else max_depth - 1
    i = 0
    while i < limit:  # one sparse product per scattering order, not a loop over nodes
        term = C @ (term * albedo[None, :])  # T = C . diag(albedo)
        L += term
        i += 1
        if max_depth < 0 and term.sum() <= tol * L.sum():
            break
    return L, i
