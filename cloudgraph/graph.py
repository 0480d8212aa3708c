"""The graph (thesis §4.3): nodes with their search ranges and the collision counts between them.

Built by build.py; kept on disk by graph_file.py. Per node, every outgoing free-flight sample is
counted (escapes included), and per edge a -> b the samples from a that collide in b:

    C[a, b] = count(a -> b) / out_samples(a)        (collision probabilities)
    T       = C . diag(albedo)                       (formed in transport.py)

so the graph depends on sigma_t only, never on albedo or light colour.

A flight from a lands in b on a's side of b: an edge reads b's radiance at b's position, the
mean of all b's collisions, where its own samples collided nearer to a. Per edge the graph keeps
where they did (``landing``), and transport reads b there, to first order, by b's radiance
gradient (:meth:`Graph.transitions`; docs/method.md, "Where a flight lands"). Where the medium
absorbs, radiance is not linear across a node: it falls as exp(-kappa x) with the diffusion's
kappa^2 = 3 (1 - albedo) sigma_t^2, and a linear read from b's position to the landing point
reads low by its second-order term, about (1 - albedo) sigma_t^2 |offset|^2 / 2 of L_b (the
Laplacian kappa^2 L shared by the three axes). Transport adds that term too.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


@dataclass
class Graph:
    """The graph of a (volume, density_scale, build params).

    Attributes:
        positions: (N, 3) float32 node positions, world units.
        search_radius: (N,) float32 render search ranges (Eq. 4.21), world units.
        out_samples: (N,) int64 outgoing free-flight samples per node, escapes included.
        counts: (N, N) CSR int64, counts[a, b] = samples from a that collided in b.
        stats: sizes and stage times.
        landing: (E, 3) float32, per entry of ``counts`` (CSR order) the mean of where its
            samples collided less b's position, world units (None: unknown, read at b).
    """

    positions: np.ndarray
    search_radius: np.ndarray
    out_samples: np.ndarray
    counts: sp.csr_matrix
    stats: dict = field(default_factory=dict)
    landing: np.ndarray | None = None

    @property
    def n_nodes(self) -> int:
        return len(self.positions)

    def collision_matrix(self) -> sp.csr_matrix:
        """C[a, b] = count(a -> b) / out_samples(a): probability that a flight from a collides in b.

        Rows sum to 1 - P(escape from a); rows of nodes without samples are zero.
        """
        inv = np.divide(1.0, self.out_samples, out=np.zeros(self.n_nodes), where=self.out_samples > 0)
        return sp.csr_matrix(sp.diags(inv) @ self.counts)

    def transitions(self, gradient: dict, workers: int = 1, sigma_t=None, albedo=1.0) -> Transitions:
        """The collision probabilities with each edge read where its flights landed (the module
        docstring): T x = C x + sum_axis S_axis (D_axis x) + (1 - albedo) Q x, S_axis = C times
        the landing offsets on that axis, D_axis the nodes' gradient operator
        (:func:`gradient_operators` of the ``gradient`` parameters, params.GRADIENT; its k-d tree
        queried on ``workers`` threads), Q = C times sigma_t(b)^2 |offset|^2 / 2 (the curvature
        where the medium absorbs; ``sigma_t`` (N,) at the nodes, None: none), ``albedo`` scalar
        or per channel of the x that T is applied to."""
        C = self.collision_matrix()
        C.sort_indices()
        if self.landing is None or not C.nnz:
            return Transitions(C)
        counts = self.counts.tocsr()
        counts.sort_indices()
        assert np.array_equal(counts.indptr, C.indptr) and np.array_equal(counts.indices, C.indices)
        D = gradient_operators(self.positions, self.search_radius, **gradient, workers=workers)
        # S_x, S_y, S_z side by side (N, 3N): column 3 b + axis, against D's rows stacked alike
        n = C.shape[0]
        S = sp.csr_matrix(
            (
                (C.data[:, None] * self.landing).ravel(),
                (3 * C.indices[:, None] + np.arange(3)[None, :]).ravel(),
                3 * C.indptr,
            ),
            shape=(n, 3 * n),
        )
        Q = None
        if sigma_t is not None:
            half = (
                0.5
                * np.asarray(sigma_t, np.float64)[C.indices] ** 2
                * np.sum(self.landing.astype(np.float64) ** 2, axis=1)
            )
            Q = sp.csr_matrix((C.data * half, C.indices, C.indptr), shape=C.shape)
        return Transitions(C, S, D, Q, 1.0 - np.asarray(albedo, np.float64))

    def to_arrays(self) -> dict:
        """The graph as plain arrays (the inputs of a ``graph_file`` chunk, GraphBuilder); the
        counts in the smallest unsigned type that holds them (the file packs them anyway)."""
        c = self.counts
        landing = {} if self.landing is None else {"landing": self.landing}
        return {
            **landing,
            "positions": self.positions,
            "search_radius": self.search_radius,
            "out_samples": self.out_samples,
            "indptr": c.indptr,
            "indices": c.indices,
            "counts": compact_uint(c.data),
            "stats": np.frombuffer(json.dumps(self.stats).encode(), np.uint8),
        }

    @classmethod
    def from_arrays(cls, a: dict) -> Graph:
        """The graph of :meth:`to_arrays`."""
        n = len(a["positions"])
        data = np.asarray(a["counts"]).astype(np.int64)
        counts = sp.csr_matrix((data, np.asarray(a["indices"]), np.asarray(a["indptr"])), shape=(n, n))
        stats = json.loads(np.asarray(a["stats"]).tobytes())
        return cls(
            np.asarray(a["positions"]),
            np.asarray(a["search_radius"]),
            np.asarray(a["out_samples"]),
            counts,
            stats,
            np.asarray(a["landing"]) if "landing" in a else None,
        )

    def escape_samples(self) -> np.ndarray:
        """(N,) outgoing samples that left the medium."""
        return self.out_samples - np.asarray(self.counts.sum(axis=1)).ravel()


def compact_uint(a: np.ndarray) -> np.ndarray:
    """Non-negative integers in the smallest unsigned type that holds them."""
    return a.astype(np.min_scalar_type(int(a.max())) if a.size else np.uint8)


class Transitions:
    """The graph's transition operator for transport (:meth:`Graph.transitions`): ``T @ x`` for
    (N,) or (N, K) x, and ``correction(x)``, (T - C) x. ``S`` (N, 3N) and ``D`` (3N, N): the
    landing offsets and the gradients, axes interleaved (None: C alone); ``Q`` (N, N): the
    curvature's term per unit of ``absorption`` (1 - albedo: scalar, or (K,) per column of x;
    None: none)."""

    def __init__(self, C: sp.csr_matrix, S=None, D=None, Q=None, absorption=0.0):
        self.C, self.S, self.D, self.Q, self.shape = C, S, D, Q, C.shape
        self.absorption = absorption

    def with_albedo(self, albedo) -> Transitions:
        """The same operator for x of ``albedo`` (scalar or per column; the matrices shared)."""
        return Transitions(self.C, self.S, self.D, self.Q, 1.0 - np.asarray(albedo, np.float64))

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        return self.C @ x + self.correction(x)

    def correction(self, x: np.ndarray) -> np.ndarray:
        """(T - C) x: what reading the edges where their flights landed adds."""
        if self.S is None:
            return np.zeros_like(x)
        out = self.S @ (self.D @ x)
        if self.Q is not None:
            out += (self.Q @ x) * self.absorption
        return out


def node_gradients(D: sp.csr_matrix, values: np.ndarray) -> np.ndarray:
    """(N, 3, C) float32: each node's gradient of ``values`` (N, C) by the (3N, N) operator D of
    :func:`gradient_operators`, read where a lookup falls (spatial.NodeGrid.lookup)."""
    values = np.asarray(values, np.float64)
    return (D @ values).reshape(len(values), 3, -1).astype(np.float32)


def gradient_operators(
    positions: np.ndarray, search_radius: np.ndarray, nodes: int, width: float, ridge: float, workers: int = 1
) -> sp.csr_matrix:
    """(3N, N) sparse: row 3 a + axis of (D L) is node a's radiance gradient on that axis, the
    weighted least-squares plane through its ``nodes`` nearest nodes b, minimising
    sum_b w_b (L_b - L_a - G . (c_b - c_a))^2 + ridge R_a^2 |G|^2, w_b a Gaussian of ``width``
    search ranges R (c: the positions, (N, 3); ``search_radius`` (N,)). A linear L's gradient, to
    within the ridge's shrinkage (1-5 %). Computed in float64 whatever the inputs' type."""
    positions, search_radius = np.asarray(positions, np.float64), np.asarray(search_radius, np.float64)
    n = len(positions)
    k = min(nodes, n - 1)
    if k < 3:
        return sp.csr_matrix((3 * n, n))
    _, j = cKDTree(positions).query(positions, k + 1, workers=workers)
    j = j[:, 1:]
    d = positions[j] - positions[:, None, :]  # (N, k, 3)
    h = width * search_radius[:, None]
    w = np.exp(-np.sum(d * d, axis=-1) / (2.0 * h * h))  # (N, k)
    wd = [w * d[:, :, axis] for axis in range(3)]
    ridge = ridge * search_radius**2
    # m = sum_b w_b d_b d_b^T + ridge I (symmetric 3 x 3 per node), inverted by its adjugate:
    # elementwise over the nodes, where a batched matrix product and solve took a second
    m = [[(wd[r] * d[:, :, c]).sum(axis=1) + (ridge if r == c else 0.0) for c in range(3)] for r in range(3)]
    adj = [
        [
            m[(c + 1) % 3][(r + 1) % 3] * m[(c + 2) % 3][(r + 2) % 3]
            - m[(c + 1) % 3][(r + 2) % 3] * m[(c + 2) % 3][(r + 1) % 3]
            for c in range(3)
        ]
        for r in range(3)
    ]
    det = m[0][0] * adj[0][0] + m[0][1] * adj[1][0] + m[0][2] * adj[2][0]
    # coef[a, axis, b]: G_axis = sum_b coef (L_b - L_a), (m^-1 (w d)^T)
    coef = (
        np.stack([sum(adj[r][c][:, None] * wd[c] for c in range(3)) for r in range(3)], axis=1)
        / det[:, None, None]
    )
    # row 3 a + axis: coef at a's k neighbours, then minus their sum at a itself
    cols = np.concatenate(
        [np.broadcast_to(j[:, None, :], (n, 3, k)), np.broadcast_to(np.arange(n)[:, None, None], (n, 3, 1))],
        axis=2,
    )
    data = np.concatenate([coef, -coef.sum(axis=2, keepdims=True)], axis=2)
    D = sp.csr_matrix(
        (data.ravel(), cols.ravel(), np.arange(0, 3 * n * (k + 1) + 1, k + 1)), shape=(3 * n, n)
    )
    D.sum_duplicates()  # (sorted; a node at another's very position may be its own neighbour)
    return D
