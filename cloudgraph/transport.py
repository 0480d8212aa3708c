"""Radiance transport through the graph (thesis §4.5, Algorithm 1).

L' = sum_{i < k} T^i L_d with T = C . diag(albedo) (docs/method.md). With k = max_depth the series is
summed by iterated sparse matrix-vector products (Algorithm 1). With unbounded depth (-1) the
series is the solution of the linear system

    (I - T) L' = L_d,

which a Krylov method (BiCGSTAB, Jacobi-preconditioned) reaches in far fewer products than the
series, whose terms shrink only as fast as the chance of escaping: slowly in a thick medium of
albedo 1. The series stays as the fallback should the solver not converge.

The graph's edges are read where their flights landed (graph.Graph.transitions: T = C + K, K by
the nodes' radiance gradients, and where the medium absorbs the curvature's term). With
unbounded depth K is taken to first order, by a second solve of C alone: L' = L_0 +
(I - aC)^-1 aK L_0, L_0 = (I - aC)^-1 L_d. Solved with K inside, the system need not converge
at albedo 1 (on the bench's dense cloud lit by a random direct light, BiCGSTAB broke down and
GMRES stalled at a residual of 0.6; its sun's light converged): C's spectral radius is all but 1
there, and K's gradients lift some modes of noise past it.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

log = logging.getLogger(__name__)

#: Methods for unbounded depth.
METHODS = ("krylov", "neumann")


def transport(
    C: sp.spmatrix,
    L_d: np.ndarray,
    albedo,
    max_depth: int = -1,
    tol: float = 1e-5,
    max_iterations: int = 100_000,
    method: str = "krylov",
    cancelled=None,
) -> tuple[np.ndarray, int]:
    """Total in-scattered radiance per node: the Neumann series of T applied to L_d (Algorithm 1).

    Args:
        C: (N, N) collision probabilities, C[a, b] = P(a flight from a collides in b): a sparse
            matrix, or graph.Transitions (``@``, and ``correction`` with C beside it).
        L_d: (N, 3) direct radiance per node and channel.
        albedo: scalar or (3,) single-scattering albedo per channel.
        max_depth: most scattering events on a path; node radiance holds paths of up to
            max_depth - 1 further events after the one at the node. -1: unbounded.
        tol: unbounded depth: the solver's relative residual |L_d - (I - T) L'| / |L_d|, or for
            the series, stop when sum(T^i L_d) <= tol * sum(L').
        max_iterations: most sparse products.
        method: ``krylov`` or ``neumann`` for unbounded depth (bounded depth is always the series).
        cancelled: optional callable, checked every few products; raising from it stops the work.

    Returns:
        (L', products): (N, 3) radiance, and the sparse matrix-vector products done.
    """
    if method not in METHODS:
        raise ValueError(f"unknown transport method {method!r}; choose one of {', '.join(METHODS)}")
    L_d = np.asarray(L_d, np.float64).reshape(len(L_d), -1)
    albedo = np.broadcast_to(np.asarray(albedo, np.float64), (L_d.shape[1],))
    if max_depth == 0:
        return np.zeros_like(L_d), 0
    if sp.issparse(C):  # (else an operator of its own: graph.Transitions)
        C = sp.csr_matrix(C, dtype=np.float64)
    if max_depth >= 0:  # (a few terms: K inside them grows nothing)
        L, products = _series(C, L_d, albedo, max_depth, tol, max_iterations, cancelled)
        return np.maximum(L, 0.0), products
    correction = getattr(C, "correction", None)
    if correction is None:
        return _unbounded(C, L_d, albedo, tol, max_iterations, method, cancelled)
    # T = C + K (graph.Transitions), K to first order (the module docstring)
    L, products = _unbounded(C.C, L_d, albedo, tol, max_iterations, method, cancelled, clamp=False)
    dL, more = _unbounded(
        C.C, albedo[None, :] * correction(L), albedo, tol, max_iterations, method, cancelled, clamp=False
    )
    return np.maximum(L + dL, 0.0), products + more + 1


def _unbounded(C, L_d, albedo, tol, max_iterations, method, cancelled, clamp=True) -> tuple[np.ndarray, int]:
    if method == "krylov":
        return _solve(C, L_d, albedo, tol, max_iterations, cancelled, clamp)
    L, products = _series(C, L_d, albedo, -1, tol, max_iterations, cancelled)
    return (np.maximum(L, 0.0) if clamp else L), products


def _series(C, L_d, albedo, max_depth, tol, max_iterations, cancelled) -> tuple[np.ndarray, int]:
    L = L_d.copy()  # Radiance accumulator, L'
    term = L_d.copy()  # T^i L_d
    limit = max_iterations if max_depth < 0 else min(max_depth - 1, max_iterations)
    i = 0
    while i < limit:  # one sparse product per scattering order, not a loop over nodes
        term = C @ (term * albedo[None, :])  # T = C . diag(albedo)
        L += term
        i += 1
        if cancelled is not None and i % 16 == 0:
            cancelled()
        if max_depth < 0 and np.abs(term).sum() <= tol * np.abs(L).sum():
            break
    return L, i


def _solve(C, L_d, albedo, tol, max_iterations, cancelled, clamp=True) -> tuple[np.ndarray, int]:
    """(I - albedo_c C) L'_c = L_d,c per channel by BiCGSTAB; equal channels are solved once.
    ``clamp``: radiance, clamped at 0 (else a correction, of either sign)."""
    n = C.shape[0]
    L = np.zeros_like(L_d)
    products = 0
    solved: dict[tuple, np.ndarray] = {}
    diag = C.diagonal()
    for c in range(L_d.shape[1]):  # three channels at most
        key = (float(albedo[c]), L_d[:, c].tobytes())
        if key in solved:
            L[:, c] = solved[key]
            continue
        a, b = float(albedo[c]), L_d[:, c]
        if a == 0.0 or not b.any():
            L[:, c] = b
            solved[key] = b
            continue
        count = [0]

        def matvec(x, a=a, count=count):
            count[0] += 1
            if cancelled is not None and count[0] % 16 == 0:
                cancelled()
            return x - a * (C @ x)

        A = spla.LinearOperator((n, n), matvec=matvec, dtype=np.float64)
        M = sp.diags(1.0 / (1.0 - a * diag))  # Jacobi
        x, info = spla.bicgstab(A, b, x0=b.copy(), rtol=tol, atol=0.0, maxiter=max_iterations // 2, M=M)
        products += count[0]
        if info != 0:  # not converged (or broke down): the series always converges for albedo <= 1
            log.warning("BiCGSTAB did not converge (info %s); summing the series instead", info)
            x, k = _series(C, b[:, None], np.array([a]), -1, tol, max_iterations, cancelled)
            x, products = x[:, 0], products + k
        L[:, c] = np.maximum(x, 0.0) if clamp else x  # (the solver's residual may dip below zero)
        solved[key] = L[:, c]
    return L, products
