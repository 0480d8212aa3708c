"""The graph (thesis §4.3): nodes with their search ranges and the collision counts between them.

Built by build.py; kept on disk by graph_file.py. Per node, every outgoing free-flight sample is
counted (escapes included), and per edge a -> b the samples from a that collide in b:

    C[a, b] = count(a -> b) / out_samples(a)        (collision probabilities)
    T       = C . diag(albedo)                       (formed in transport.py)

so the graph depends on sigma_t only, never on albedo or light colour.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp


@dataclass
class Graph:
    """The graph of a (volume, density_scale, build params).

    Attributes:
        positions: (N, 3) float32 node positions, world units.
        search_radius: (N,) float32 render search ranges (Eq. 4.21), world units.
        out_samples: (N,) int64 outgoing free-flight samples per node, escapes included.
        counts: (N, N) CSR int64, counts[a, b] = samples from a that collided in b.
        stats: sizes and stage times.
    """

    positions: np.ndarray
    search_radius: np.ndarray
    out_samples: np.ndarray
    counts: sp.csr_matrix
    stats: dict = field(default_factory=dict)

    @property
    def n_nodes(self) -> int:
        return len(self.positions)

    def collision_matrix(self) -> sp.csr_matrix:
        """C[a, b] = count(a -> b) / out_samples(a): probability that a flight from a collides in b.

        Rows sum to 1 - P(escape from a); rows of nodes without samples are zero.
        """
        inv = np.divide(1.0, self.out_samples, out=np.zeros(self.n_nodes), where=self.out_samples > 0)
        return sp.csr_matrix(sp.diags(inv) @ self.counts)

    def to_arrays(self) -> dict:
        """The graph as plain arrays (the inputs of a ``graph_file`` chunk, GraphBuilder); the
        counts in the smallest unsigned type that holds them (the file packs them anyway)."""
        c = self.counts
        return {
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
        )

    def escape_samples(self) -> np.ndarray:
        """(N,) outgoing samples that left the medium."""
        return self.out_samples - np.asarray(self.counts.sum(axis=1)).ravel()


def compact_uint(a: np.ndarray) -> np.ndarray:
    """Non-negative integers in the smallest unsigned type that holds them."""
    return a.astype(np.min_scalar_type(int(a.max())) if a.size else np.uint8)
