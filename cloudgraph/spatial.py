"""The spatial index of the graph's nodes: a uniform grid of node lists (numpy to build, Dr.Jit to
query), used by the field bake and by the graph integrator alike."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np
import scipy.sparse as sp

from .tracing import to_jit


def node_bins(positions: np.ndarray, search_radius: np.ndarray, max_cells: int = 1 << 22) -> tuple:
    """N nodes ((N, 3) positions, (N,) ranges) binned into a uniform grid, in numpy: (cell_start
    (cells + 1,), entries (node ids by cell), (origin x y z, cell side, dims x y z))."""
    lo = (positions - search_radius[:, None]).min(axis=0)
    hi = (positions + search_radius[:, None]).max(axis=0)
    cell = float(np.median(search_radius))
    while np.prod(np.ceil((hi - lo) / cell) + 1) > max_cells:
        cell *= 1.25
    dims = (np.floor((hi - lo) / cell) + 1).astype(np.int64)
    # int32 throughout (cells < 2^22, entries < 2^31): half the memory traffic of int64
    c0 = np.clip(np.floor((positions - search_radius[:, None] - lo) / cell), 0, dims - 1).astype(np.int32)
    c1 = np.clip(np.floor((positions + search_radius[:, None] - lo) / cell), 0, dims - 1).astype(np.int32)
    span = c1 - c0 + 1
    per_node = span.prod(axis=1)
    node = np.repeat(np.arange(len(positions), dtype=np.int32), per_node)
    first = np.cumsum(per_node, dtype=np.int32) - per_node
    k = np.arange(per_node.sum(), dtype=np.int32) - np.repeat(first, per_node)
    sx, sy = span[node, 0], span[node, 1]
    ix = c0[node, 0] + k % sx
    iy = c0[node, 1] + (k // sx) % sy
    iz = c0[node, 2] + k // (sx * sy)
    cell_id = ix + np.int32(dims[0]) * (iy + np.int32(dims[1]) * iz)
    # The entries by cell, in the order made within a cell: a counting sort (a sparse matrix's
    # rows, each entry its own column; a stable argsort took twice as long on blender's 6 M)
    by_cell = sp.csr_matrix(
        (node.astype(np.uint32), (cell_id, np.arange(len(cell_id), dtype=np.int32))),
        shape=(int(dims.prod()), len(cell_id)),
    )
    return (
        by_cell.indptr.astype(np.uint32),
        by_cell.data.astype(np.uint32),
        np.concatenate([lo, [cell], dims]).astype(float),
    )


@dataclass
class NodeGrid:
    """Nodes binned into a uniform grid: cell c lists the nodes whose search ball meets it.

    Attributes (Dr.Jit arrays):
        positions, radius2, radiance: per node; radius2 is R_a^2; gradient: per node its
            radiance's gradient, one Color3f per axis (None: each node read as its mean).
        cell_start: (cells + 1,) offsets into ``entries``; entries: node ids.
        origin, cell, dims: the grid (scalars).
    """

    positions: object
    radius2: object
    radiance: object
    cell_start: object
    entries: object
    origin: tuple
    cell: float
    dims: tuple
    gradient: tuple | None = None

    @classmethod
    def build(
        cls,
        positions: np.ndarray,
        search_radius: np.ndarray,
        radiance: np.ndarray,
        bins=None,
        gradient: np.ndarray | None = None,
    ) -> NodeGrid:
        """N nodes ((N, 3) positions, (N,) ranges, (N, 3) radiance, (N, 3 axes, 3) its gradient
        or None) binned (:func:`node_bins`, unless given), then uploaded."""
        start, entries, grid = bins if bins is not None else node_bins(positions, search_radius)
        return cls(
            positions=to_jit(mi.Point3f, positions),
            radius2=to_jit(mi.Float, search_radius.astype(np.float32) ** 2),
            radiance=to_jit(mi.Color3f, radiance),
            cell_start=to_jit(mi.UInt32, start, np.uint32),
            entries=to_jit(mi.UInt32, entries, np.uint32),
            origin=tuple(float(v) for v in grid[:3]),
            cell=float(grid[3]),
            dims=tuple(int(v) for v in grid[4:]),
            gradient=None if gradient is None else per_axis(gradient),
        )

    @dr.syntax
    def lookup(self, p: mi.Point3f, eps2: float, active: mi.Bool) -> mi.Color3f:
        """L'_search(p): inverse-squared-distance weighted mean over nodes in range (Eq. 4.25),
        each node a read by its plane at p, L_a + grad L_a . (p - x_a), where the grid has the
        gradients (a first-order Shepard interpolation; linear in the radiance, so that a re-mix
        of the lights' radiance reads as their mix)."""
        g = (p - mi.Point3f(*self.origin)) / self.cell
        inside = active & dr.all((g >= 0) & (g < mi.Point3f(*self.dims)))
        gi = mi.Vector3u(dr.clip(mi.Vector3i(g), 0, mi.Vector3i(*self.dims) - 1))
        c = gi.x + self.dims[0] * (gi.y + self.dims[1] * gi.z)
        i = dr.gather(mi.UInt32, self.cell_start, c, inside)
        end = dr.gather(mi.UInt32, self.cell_start, c + 1, inside)
        L = mi.Color3f(0.0)  # Weighted radiance sum
        W = mi.Float(0.0)  # Weight sum
        loop = inside & (i < end)  # an empty cell has nothing to read
        while dr.hint(loop, label="node_gather"):
            a = dr.gather(mi.UInt32, self.entries, i, loop)
            delta = p - dr.gather(mi.Point3f, self.positions, a, loop)
            d2 = dr.squared_norm(delta)
            near = loop & (d2 < dr.gather(mi.Float, self.radius2, a, loop))
            w = dr.rcp(dr.maximum(d2, eps2))  # Eq. 4.25: inverse squared distance
            W[near] += w
            L_a = dr.gather(mi.Color3f, self.radiance, a, near)
            if dr.hint(self.gradient is not None, mode="scalar"):  # (Python-level: never in a kernel)
                for axis, grad in enumerate(self.gradient):
                    L_a += delta[axis] * dr.gather(mi.Color3f, grad, a, near)
            L[near] += w * L_a
            i += 1
            loop &= i < end
        return dr.select(W > 0, L / W, 0.0)

    def set_radiance(self, radiance: np.ndarray, gradient: np.ndarray | None = None) -> None:
        """New node radiance (N, 3) and its gradient (N, 3, 3; None: none) in place (a re-mix)."""
        self.radiance = to_jit(mi.Color3f, radiance)
        self.gradient = None if gradient is None else per_axis(gradient)


def per_axis(gradient: np.ndarray) -> tuple:
    """(N, 3 axes, 3) gradients as one Dr.Jit Color3f per axis."""
    return tuple(to_jit(mi.Color3f, gradient[:, axis, :]) for axis in range(3))
