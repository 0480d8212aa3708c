"""Node grouping (thesis §4.3.1): the node cell a collision joins (:class:`NodeCells`), and the
nodes as a build finds them (:class:`NodeTable`), fed by chunk reductions (:func:`reduce_chunk`).
Everything kept is a sum or a minimum, so a graph is the same bytes however its work is cut or
spread over workers (``GraphBuilder`` in graph.py)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.ndimage import maximum_filter

from .errors import VolumeError
from .volume import Volume, voxel_points

if TYPE_CHECKING:
    from .params import BuildParams


class NodeCells:
    """Node cells (§4.3.1): cubes of side 2r/sqrt(3) from ``origin`` (a corner below every point),
    so that every point of a cube is within r of its centre, grown where the medium is thin.

    The node radius is a fraction of the free path (graph.PRESETS), and the free path varies
    through a cloud: cubes of ``2^max_level`` cells a side (blocks) take cells 2^l times as
    large, with l the largest level whose radius r 2^l is still at most ``radius_mfp`` free
    paths at the block's densest point (σ_t dilated by a voxel, as trilinear interpolation reads
    it). Dense blocks keep r; thin smoke gets nodes of the same size in free paths as the rest.
    Levels are whole blocks, so cells of different levels never overlap, and a cell's key is the
    lowest base cell it covers.
    """

    def __init__(self, volume: Volume, density_scale: float, params: BuildParams, origin: np.ndarray):
        self.origin, self.side = np.asarray(origin, float), 2.0 * params.radius / np.sqrt(3.0)
        self.top = params.max_level
        self.levels = np.zeros((1, 1, 1), np.int64)
        if self.top == 0:
            return
        block = self.side * 2**self.top
        dims = np.floor((volume.world_bbox()[1] + params.radius - self.origin) / block).astype(np.int64) + 1
        sigma = maximum_filter(volume.density, size=3, mode="constant").ravel() * float(density_scale)
        with np.errstate(divide="ignore"):  # each voxel's own level (empty: the top one)
            own = np.floor(np.log2(np.maximum(params.radius_mfp / sigma / params.radius, 1.0)) + 1e-9)
        own = np.minimum(own, self.top).astype(np.int64)
        n, (nx, ny, nz) = int(np.prod(dims)), volume.shape
        below = np.zeros((self.top, n), bool)  # below[l]: the block holds a voxel of level <= l
        m = volume.index_to_world[:3, :3] / block  # voxel steps in blocks
        first = (voxel_points(volume, np.zeros((1, 3)))[0] - self.origin) / block  # voxel (0, 0, 0)
        j, k = np.arange(ny)[None, :, None], np.arange(nz)[None, None, :]
        step = max(1, (1 << 22) // (ny * nz))  # slabs of i: memory stays small for large volumes
        for a in range(0, nx, step):
            i = np.arange(a, min(a + step, nx))[:, None, None]
            ids = 0  # the block of each voxel, axis by axis
            for axis in range(3):
                b = np.floor(first[axis] + m[axis, 0] * i + m[axis, 1] * j + m[axis, 2] * k).astype(np.int64)
                ids = ids * dims[axis] + np.clip(b, 0, dims[axis] - 1)
            ids, lv = ids.ravel(), own[a * ny * nz : (a + len(i)) * ny * nz]
            for level in range(self.top):
                below[level] |= np.bincount(ids[lv <= level], minlength=n) > 0
        # a block's level is its densest voxel's: the lowest level any of its voxels has
        self.levels = np.where(below.any(axis=0), below.argmax(axis=0), self.top).reshape(dims)

    def keys(self, points: np.ndarray) -> np.ndarray:
        """(M,) int64 cell keys of (M, 3) world points: the lowest base cell of their cell."""
        cell = np.floor((points - self.origin) / self.side).astype(np.int64)
        if cell.size and (cell.min() < 0 or cell.max() >= 1 << 21):
            raise VolumeError(
                "the medium spans more than 2^21 node cells along an axis; resample the volume coarser"
            )
        block = np.minimum(cell >> self.top, np.array(self.levels.shape) - 1)
        level = self.levels[block[:, 0], block[:, 1], block[:, 2]][:, None]
        cell = (cell >> level) << level
        return (cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2]


#: Collisions kept per node (a uniform sample of all of them, by random priority) as the starting
#: points of its reinforcement flights.
MEMBERS_KEPT = 8


def uniform_hash(seed: int, stream: int, index: np.ndarray) -> np.ndarray:
    """Numbers uniform in [0, 1) from (seed, stream, index) by splitmix64: each collision's own,
    whichever chunk it was traced in."""
    mix = (int(seed) * 0x9E3779B97F4A7C15 + int(stream) * 0xD1B54A32D192ED03 + 1) % 2**64
    x = np.asarray(index).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(mix)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    x = x ^ (x >> np.uint64(31))
    return (x >> np.uint64(11)).astype(np.float64) / 2.0**53


#: Collision positions are summed in fixed point, 2^-20 node radii, so that sums in any order are
#: equal (exact in float64 up to 2^53: 2^21 cells a side times 2^12 collisions a node).
FIXED_POINT = 2.0**20


#: A NodeTable's per-node arrays: (shape of a node's row, type, value of a new node)
_COLUMNS = {
    "keys": ((), np.int64, 0),
    "count": ((), np.int64, 0),
    "sum": ((3,), np.int64, 0),
    "kept": ((MEMBERS_KEPT, 3), np.float32, 0),
    "priority": ((MEMBERS_KEPT,), np.float64, np.inf),
    "out": ((), np.int64, 0),
}


class NodeTable:
    """The nodes as they are being found, in the order found: per node its cell key, the number
    and sum of its collisions, a uniform sample of MEMBERS_KEPT of them (the lowest random
    priorities), its outgoing samples, and per edge its count and the sum of where its samples
    collided. Collisions and samples are merged in (:meth:`merge`) and then dropped, so memory
    grows with the nodes, not with the samples.
    Everything kept is a sum or a minimum, so the table is the same whatever the order and the
    cut of the merges."""

    def __init__(self, origin: np.ndarray, radius: float):
        self.origin, self.unit = np.asarray(origin, float), float(radius) / FIXED_POINT
        self.order = np.zeros(0, np.int64)  # node indices sorted by key
        self.sorted_keys = np.zeros(0, np.int64)  # keys[order]
        # The per-node arrays (self.keys, ...) are views of the first len(self) rows of stores
        # that grow by half when full: adding nodes does not copy the table at every merge
        self._store: dict[str, np.ndarray] = {}
        self._grow(0, 0)
        self._counts = sp.csr_matrix((0, 0), dtype=np.int64)
        # per edge, the fixed-point sums of where its samples collided, one matrix an axis (the
        # counts' pattern: every sum is positive, the origin lies below every point)
        self._landed = [sp.csr_matrix((0, 0), dtype=np.int64) for _ in range(3)]
        self._edges: list[tuple[np.ndarray, ...]] = []  # (rows, cols, counts, sums) merged, not yet summed
        self._pending = 0

    def counts_by_key(self) -> sp.csr_matrix:
        """(N, N) edge counts of everything merged so far, node i numbered by its place in key
        order (:attr:`order`), indices sorted: the summed and the waiting edges renumbered and
        summed in one conversion (0.45 s on blender, where summing and then permuting rows and
        columns took 0.9 s)."""
        return self._by_key(0)

    def landed_by_key(self, counts: sp.csr_matrix) -> np.ndarray:
        """(E, 3) the mean of where each edge's samples collided, world units, in the order of
        the entries of ``counts``, :meth:`counts_by_key` (made once: a conversion of every edge)."""
        sums = np.stack([self._by_key(1 + axis).data for axis in range(3)], axis=1)
        return self.origin + sums * self.unit / counts.data[:, None]

    def _by_key(self, column: int) -> sp.csr_matrix:
        """The edges' counts (column 0) or landing sums on an axis (1 + axis), by key."""
        n = len(self)
        rank = np.empty(n, np.int64)
        rank[self.order] = np.arange(n)
        summed = ([self._counts] + self._landed)[column].tocoo()
        rows = np.concatenate([summed.row] + [e[0] for e in self._edges])
        cols = np.concatenate([summed.col] + [e[1] for e in self._edges])
        values = np.concatenate(
            [summed.data] + [e[2] if column == 0 else e[3][:, column - 1] for e in self._edges]
        )
        out = sp.csr_matrix((values, (rank[rows], rank[cols])), shape=(n, n))
        out.sort_indices()
        return out

    def _sum_edges(self) -> None:
        # Merged edges wait in a list and are summed when as many wait as are summed and at least
        # 2^23 (memory stays within twice the edges, or 200 MB more): adding each chunk's to the
        # sum would copy every edge at every merge, and a sum during a shared build is serial
        # work that its helpers wait on (0.5 s on blender, which now sums once, when the graph is
        # made: counts_by_key).
        n = len(self)
        waiting = [np.concatenate(a) for a in zip(*self._edges, strict=True)] if self._edges else []
        self._counts.resize((n, n))
        for m in self._landed:
            m.resize((n, n))
        if waiting:
            rows, cols, values, sums = waiting
            self._counts = self._counts + sp.csr_matrix((values, (rows, cols)), shape=(n, n))
            self._landed = [
                m + sp.csr_matrix((sums[:, axis], (rows, cols)), shape=(n, n))
                for axis, m in enumerate(self._landed)
            ]
        self._edges, self._pending = [], 0

    def out_edges(self, below: int) -> np.ndarray:
        """(N,) distinct edges from each node, exact where fewer than ``below`` (``below`` or
        more elsewhere), without summing the edges still waiting: between reinforcement rounds
        that would stop every worker that shares the build while one does it. A merge's edges
        are distinct, so a node with ``below`` of them in one merge has enough; only the others
        are counted exactly."""
        n = len(self)
        self._counts.resize((n, n))
        known = np.diff(self._counts.indptr)  # distinct edges: at least this many
        for rows, *_ in self._edges:
            known = np.maximum(known, np.bincount(rows, minlength=n))
        few = known < below
        if not self._edges or not few.any():
            return known
        rows, cols = (np.concatenate(a) for a in list(zip(*self._edges, strict=True))[:2])
        wait = few[rows]
        summed = self._counts[few].tocoo()  # the few's summed rows, numbered from 0
        keys = np.concatenate([np.flatnonzero(few)[summed.row] * n + summed.col, rows[wait] * n + cols[wait]])
        known[few] = np.bincount(np.unique(keys) // n, minlength=n)[few]
        return known

    def __len__(self) -> int:
        return len(self.keys)

    def means(self) -> np.ndarray:
        """(N, 3) the mean of each node's collisions, world units (from the fixed-point sums)."""
        return self.origin + self.sum * self.unit / self.count[:, None]

    def index(self, keys: np.ndarray) -> np.ndarray:
        """Node indices of cell keys; cells without a node become new nodes."""
        pos = np.searchsorted(self.sorted_keys, keys)
        found = np.zeros(len(keys), bool)
        inside = pos < len(self.order)
        found[inside] = self.sorted_keys[pos[inside]] == keys[inside]
        new = np.unique(keys[~found])
        if len(new):
            n, m = len(self), len(new)
            self._grow(n, m)
            self.keys[n:] = new
            at = np.searchsorted(self.sorted_keys, new)  # both sorted: insert, no new sort
            self.order = np.insert(self.order, at, np.arange(n, n + m))
            self.sorted_keys = np.insert(self.sorted_keys, at, new)
        return self.order[np.searchsorted(self.sorted_keys, keys)]

    def _grow(self, n: int, m: int) -> None:
        """From n nodes to n + m, the new ones as _COLUMNS makes them."""
        if not self._store or n + m > len(self._store["keys"]):
            size = max(n + m + (n + m) // 2, 1024)
            for name, (shape, dtype, fill) in _COLUMNS.items():
                store = np.full((size, *shape), fill, dtype)
                if n:
                    store[:n] = self._store[name][:n]
                self._store[name] = store
        for name in _COLUMNS:
            setattr(self, name, self._store[name][: n + m])

    def merge(self, part: tuple[np.ndarray, ...]) -> None:
        """Adds a chunk's :func:`reduce_chunk` (per cell: collisions, their fixed-point sum and
        lowest priorities; outgoing samples per start cell; edge counts and landing sums)."""
        (
            cells,
            count,
            sums,
            kept_cell,
            kept_points,
            kept_pri,
            src,
            src_count,
            e_src,
            e_dst,
            e_count,
            e_sums,
        ) = part
        node, src_node = self.index(cells), self.index(src)
        self.count[node] += count
        self.sum[node] += sums
        # The kept sample of each node touched: its MEMBERS_KEPT lowest priorities so far. Kept
        # priorities are in ascending order, so a collision above a node's last cannot enter. A
        # chunk brings at most MEMBERS_KEPT a cell, grouped by cell (:func:`reduce_chunk`).
        cand = node[kept_cell]
        enter = kept_pri < self.priority[cand, -1]
        cand, priority, points = cand[enter], kept_pri[enter], kept_points[enter]
        if len(cand):
            self._keep(cand, priority, points)
        # Samples and edge counts
        self.out[src_node] += src_count
        self._edges.append((src_node[e_src], node[e_dst], e_count, e_sums))
        self._pending += len(e_count)
        if self._pending > max(1 << 23, self._counts.nnz):
            self._sum_edges()

    def _keep(self, cand: np.ndarray, priority: np.ndarray, points: np.ndarray) -> None:
        # Each touched node's row of kept and entering collisions (2 x MEMBERS_KEPT, padded with
        # inf) is sorted on its own; entering ones come grouped by node. The MEMBERS_KEPT lowest
        # are gathered from one pool (the touched nodes' kept ones, then the entering ones),
        # each node's row moved as one record.
        first = np.flatnonzero(np.diff(cand, prepend=-1))  # each touched node's first one
        touched, m, n, M = cand[first], len(cand), len(first), MEMBERS_KEPT
        row = np.repeat(np.arange(n), np.diff(np.append(first, m)))
        pri = np.full((n, 2 * M), np.inf)
        pri[:, :M] = _records(self.priority)[touched].view(np.float64).reshape(n, M)
        pri[row, M + np.arange(m) - first[row]] = priority
        low = np.argsort(pri, axis=1, kind="stable")[:, :M]
        # slot j < M: the node's kept one j stays (pool row i M + j); else entering one first + j - M
        i = np.arange(n)[:, None]
        take = np.where(low < M, i * M + low, n * M + first[:, None] + low - M).ravel()
        pool = np.concatenate([_records(self.kept)[touched].view(np.float32).reshape(-1, 3), points])
        _records(self.kept)[touched] = _records(_records(pool)[take].view(np.float32).reshape(n, M, 3))
        _records(self.priority)[touched] = _records(pri[i, low])


def _records(a: np.ndarray) -> np.ndarray:
    """A non-empty C-contiguous (N, ...) array as a view of N records: gathering or scattering
    rows of it moves each row as one copy, several times faster than fancy indexing of the last
    axes. Writes to the view are writes to ``a``."""
    assert a.flags.c_contiguous and len(a), "records of a contiguous, non-empty array only"
    return a.reshape(len(a), -1).view(np.dtype((np.void, a.strides[0])))[:, 0]


def _lowest(group: np.ndarray, priority: np.ndarray) -> np.ndarray:
    """The entries of the MEMBERS_KEPT lowest priorities of each group (non-negative integers)."""
    # A group of at most MEMBERS_KEPT keeps all; of a larger one, only entries below its
    # threshold (4 x MEMBERS_KEPT / its size) are sorted where at least MEMBERS_KEPT are below
    # it, which then holds its lowest; the whole group elsewhere. The same entries as sorting
    # all, in a fraction of the time.
    size = np.bincount(group)
    small = size[group] <= MEMBERS_KEPT
    below = priority < np.minimum(1.0, 4.0 * MEMBERS_KEPT / np.maximum(size, 1))[group]
    enough = np.bincount(group[below], minlength=len(size)) >= MEMBERS_KEPT
    cand = np.flatnonzero(~small & (below | ~enough[group]))
    by_priority = cand[np.argsort(priority[cand], kind="stable")]
    order = by_priority[np.argsort(group[by_priority], kind="stable")]  # as np.lexsort, faster
    starts = np.flatnonzero(np.diff(group[order], prepend=-1))
    rank = np.arange(len(order)) - np.repeat(starts, np.diff(np.append(starts, len(order))))
    return np.sort(np.concatenate([np.flatnonzero(small), order[rank < MEMBERS_KEPT]]))


def reduce_chunk(keys, points, priority, src, dst, origin, radius) -> tuple[np.ndarray, ...]:
    """A chunk's collisions ((M,) cell keys, (M, 3) world points, (M,) priorities in [0, 1)) and
    outgoing samples ((S,) cell keys of their start, (S,) the index of their collision among the
    chunk's or -1: escaped),
    reduced per cell and per edge where they were traced, so that what is sent and merged grows
    with the cells a chunk touches, not with its samples. Merging the reductions gives the table
    that merging the samples would (sums of integers, lowest priorities). Kept collisions and
    edges refer to cells by their index in ``cells`` (edge starts: in ``src``)."""
    cells, inv, count = np.unique(keys, return_inverse=True, return_counts=True)
    fixed = np.round((points - origin) / (radius / FIXED_POINT))
    sums = np.stack([np.bincount(inv, fixed[:, i], len(cells)) for i in range(3)], axis=1).astype(np.int64)
    keep = _lowest(inv, priority)
    keep = keep[np.argsort(inv[keep], kind="stable")]  # grouped by cell, as NodeTable.merge reads them
    src_cells, src_inv, src_count = np.unique(src, return_inverse=True, return_counts=True)
    # Edges as (start cell, collision cell) indices into src_cells and cells, counted once each
    hit = dst >= 0
    a, b = src_inv[hit], inv[dst[hit]]
    edge = a * len(cells) + b
    edges, e_at, e_count = np.unique(edge, return_inverse=True, return_counts=True)
    # and per edge the fixed-point sum of where its samples collided (Graph.landing)
    landed = fixed[dst[hit]]
    e_sums = np.stack([np.bincount(e_at, landed[:, i], len(edges)) for i in range(3)], axis=1).astype(
        np.int64
    )
    return (
        cells,
        count.astype(np.int64),
        sums,
        inv[keep],
        points[keep].astype(np.float32),
        priority[keep],
        src_cells,
        src_count.astype(np.int64),
        edges // len(cells),
        edges % len(cells),
        e_count.astype(np.int64),
        e_sums,
    )
