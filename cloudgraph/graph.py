"""Building the graph (thesis §4.3): light tracing, node grouping, edge counts, reinforcement,
search ranges.

Light paths are traced from directional lights through the medium by free-flight sampling
(delta tracking, in Dr.Jit: the walks are in tracing.py): from six axis directions rather than
the scene's light, so that the graph depends only on its key (see GRAPH_LIGHTS). Every
*collision* (DESIGN.md's generalisation: not only scattering events) joins a node; per node we
count every outgoing free-flight sample, escapes included, and per edge a -> b the samples from
a that collide in b. Then

    C[a, b] = count(a -> b) / out_samples(a)        (collision probabilities)
    T       = C . diag(albedo)                       (formed in transport.py)

so the graph depends on sigma_t only, never on albedo or light colour.

Nodes (§4.3.1, pseudo-Voronoi cells): space is cut into cubes of side 2r/sqrt(3), so every
point of a cube is within r of its centre; every collision joins the node of its cube, and a
node sits at the mean of its collisions. This is the order-independent, vectorised form of
"closest node within r, else a new node": it gives the same kind of cells and the same result
for the same seed on any machine, and new collisions (reinforcement) find their node by key.
Cells grow where the medium is thin (node levels); both live in nodes.py.

The build runs in fixed chunks of light paths and flights, each reduced into a
:class:`~cloudgraph.nodes.NodeTable` and dropped: memory grows with the nodes, not with the
light paths, and the graph is the same bytes however the chunks are cut or ordered.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from functools import cached_property
from itertools import chain

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .cache import compact_uint
from .nodes import MEMBERS_KEPT, NodeCells, NodeTable, reduce_chunk, uniform_hash
from .tracing import DensityField, cpu_threads, trace_flights, trace_light_paths
from .volume import Volume, voxel_points

log = logging.getLogger(__name__)

#: Quality presets. The node radius is a fraction of the typical mean free path, since the
#: method's bias grows with node size measured in free paths (§5.4). Measured on the bench
#: sphere (optical radius 10, albedo 1), ratio of graph to volpath image means, side-lit /
#: back-lit: radius 0.6 free paths 1.13 / 1.39, 0.4: 1.05 / 1.13, 0.25: 1.03 / 1.07. The radius
#: is clamped to a range of voxels: far below a voxel nodes resolve nothing more, and the node
#: count grows as 1 / r^3. Where the medium is thinner than typical, nodes grow by up to
#: 2^max_level to the same size in local free paths (:class:`NodeCells`): on smoke1 that is 36 %
#: of the nodes at the same converged accuracy (README, "Scale").
PRESETS: dict[str, dict] = {
    "draft": {
        "radius_mfp": 0.6,
        "radius_voxels": (1.0, 4.0),
        "n_paths": 1 << 15,
        "max_collisions": 32,
        "min_out_samples": 16,
        "max_level": 3,
    },
    # default's sampling with larger nodes (0.45 free paths, at least a voxel): a fifth to a half
    # of default's nodes, under a quarter of those of the code issue 11 was filed against and
    # more accurate than that code, less accurate than default (README, "Scale")
    "compact": {
        "radius_mfp": 0.45,
        "radius_voxels": (1.0, 3.0),
        "n_paths": 1 << 17,
        "max_collisions": 48,
        "min_out_samples": 32,
        "max_level": 3,
    },
    "default": {
        "radius_mfp": 0.35,
        "radius_voxels": (0.6, 3.0),
        "n_paths": 1 << 17,
        "max_collisions": 48,
        "min_out_samples": 32,
        "max_level": 3,
    },
    "high": {
        "radius_mfp": 0.25,
        "radius_voxels": (0.5, 2.0),
        "n_paths": 1 << 18,
        "max_collisions": 64,
        "min_out_samples": 64,
        "max_level": 3,
    },
}


@dataclass(frozen=True)
class BuildParams:
    """Graph build parameters (names after the thesis's App. B where it names them).

    Attributes:
        radius: node radius r, world units (§4.3.1), where the medium is densest.
        radius_mfp, max_level: where the medium is thinner, nodes grow to radius_mfp free paths,
            at most 2^max_level r (:class:`NodeCells`).
        n_paths: light paths traced from the directional light.
        max_collisions: collisions kept per light path; the walk is Markov, so cutting a path
            short drops samples but biases no transition estimate.
        min_out_samples: reinforcement tops every node up to this many outgoing samples (§4.3).
        min_out_edges: nodes with fewer distinct out-edges get min_out_samples more.
        reinforce_rounds: reinforcement passes (new nodes found in one are filled in the next).
        coverage_seeds: points drawn in proportion to density that seed nodes where cut light
            paths do not reach (0: from the volume, about two per node cell).
        search_k: the k of Eq. 4.21 (search range from the k-th nearest node).
        seed: random seed; the same seed gives the same graph.
    """

    radius: float
    radius_mfp: float = 0.35
    max_level: int = 0
    n_paths: int = 1 << 17
    max_collisions: int = 48
    min_out_samples: int = 32
    min_out_edges: int = 6
    reinforce_rounds: int = 3
    coverage_seeds: int = 0
    search_k: int = 8
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def typical_free_path(volume: Volume, density_scale: float) -> float:
    """1 / sigma_t averaged where collisions happen (density-weighted), world units."""
    rho = volume.density[volume.density > 0].astype(np.float64)
    if rho.size == 0 or density_scale <= 0:
        return np.inf
    return 1.0 / (density_scale * float((rho * rho).sum() / rho.sum()))


def build_params(volume: Volume, density_scale: float, quality: str = "default", **overrides) -> BuildParams:
    """Preset parameters for a volume and density scale (see :data:`PRESETS`)."""
    if quality not in PRESETS:
        raise ValueError(f"unknown quality {quality!r}; choose one of {', '.join(PRESETS)}")
    p = dict(PRESETS[quality])
    voxel = float(np.mean(volume.voxel_size))
    lo, hi = p.pop("radius_voxels")
    mfp = typical_free_path(volume, density_scale)
    radius = float(np.clip(p["radius_mfp"] * mfp, lo * voxel, hi * voxel))
    p.update(overrides)
    radius = p.pop("radius", radius)
    if not p.get("coverage_seeds"):
        cell = (2.0 * radius / np.sqrt(3.0)) ** 3
        p["coverage_seeds"] = (
            int(2 * np.count_nonzero(volume.density) * float(np.prod(volume.voxel_size)) / cell) + 1
        )
    return BuildParams(radius=radius, **p)


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


# ------------------------------------------------------------------ coverage seeds


def density_points(volume: Volume, index: np.ndarray, seed: int, cdf: np.ndarray | None = None) -> np.ndarray:
    """(n, 3) world points drawn with probability proportional to density (voxel, then jitter),
    point i from numbers of its own (:func:`uniform_hash` of its index): the same whichever chunk
    draws it. ``cdf``: the running sum of the density (float64), if at hand."""
    index = np.asarray(index)
    if not len(index):
        return np.zeros((0, 3))
    cdf = np.cumsum(volume.density.ravel(), dtype=np.float64) if cdf is None else cdf
    voxel = np.searchsorted(cdf, uniform_hash(seed, 7919, index) * cdf[-1], side="right")  # inverse CDF
    jitter = np.stack([uniform_hash(seed, 7920 + axis, index) for axis in range(3)], axis=1)
    return voxel_points(volume, np.stack(np.unravel_index(voxel, volume.shape), axis=1) + jitter - 0.5)


#: Light paths enter from the six axis directions: the graph is then the same whatever light
#: first asked for it, as its key says (DESIGN.md: a new light reuses the graph). Transitions do
#: not depend on the light; only where nodes fall does, and coverage seeds fill the rest.
GRAPH_LIGHTS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


#: Light paths per tracing chunk, and flights per reinforcement chunk: collisions are reduced to
#: per-node sums chunk by chunk, so memory does not grow with the number of light paths. Fixed
#: sizes: the graph does not depend on how the work is cut. Each chunk is merged on the
#: coordinator of a shared build: 2^15 light paths a chunk, not 2^14, took smoke1's merges from
#: 1.3 to 0.8 s, with the same graph.
CHUNK_PATHS = 1 << 15
CHUNK_SEEDS = 1 << 18
CHUNK_FLIGHTS = 1 << 18
#: A round of reinforcement is cut into at least this many chunks (of 2^12 flights or more), so
#: that the workers sharing a build share its last, small rounds too
ROUND_CHUNKS = 8
#: The search ranges are found in this many chunks: on a shared build, by other workers while the
#: edge counts are put in order (0.8 s of k-nearest-node queries on blender)
SEARCH_CHUNKS = 2
#: Chunks run ahead on threads while the last is merged (local_chunks)
LOCAL_THREADS = 2


class GraphBuilder:
    """What every chunk of one graph's build needs (the medium, the parameters, the cell origin),
    and the chunks themselves. A chunk is a pure function of (stage, index, inputs), so any
    process that makes a builder from the same (volume, density_scale, params) computes the same
    chunk: the build can be spread over workers (worker/chunks.py) and merged into the same
    graph, since a :class:`NodeTable` is the same whatever the order of its merges.

    Stages: ``trace``, light paths from index * CHUNK_PATHS on; ``seeds``, coverage seeds from
    index * CHUNK_SEEDS on; ``flights``, reinforcement flights of one round in chunks of at most
    CHUNK_FLIGHTS (:func:`_flight_chunk`), with inputs per node short of samples (``cells``
    keys, ``ends`` running total of flights, ``kept`` collisions and how many ``members``) and
    the ``round``: a few bytes per node, not per flight; ``search``, the nodes' search ranges
    from their ``positions`` (float64, in key order), in SEARCH_CHUNKS chunks; and the later
    stages: the direct lighting of the nodes (``lighting``); the graph file's bytes
    (``graph_file``, one chunk, :func:`~cloudgraph.cache.graph_file` of
    :meth:`Graph.to_arrays`); the nodes binned for the field's lookups (``bins``, one chunk,
    :func:`~cloudgraph.integrators.graph.node_bins`); and the field bake's light march, node
    lookups and gathers (``field_tau``, ``field_lookup``, ``field_ms``).
    """

    #: Stages put out long before their results are needed (the field's light march, at the start
    #: of a precompute; the node bins and the graph file's bytes, before the transport): workers
    #: that share a precompute run them when no other stage has work.
    late_stages = frozenset({"field_tau", "bins", "graph_file"})
    #: Late stages whose results are wanted only at the end of a precompute (the graph file is
    #: written last): they wait behind every other late stage, whenever that was put out.
    last_stages = frozenset({"graph_file"})

    def __init__(self, volume: Volume, density_scale: float, params: BuildParams):
        self.volume, self.params, self.density_scale = volume, params, density_scale
        self.field = DensityField.from_volume(volume, density_scale)
        self.origin = volume.world_bbox()[0] - params.radius

    @cached_property
    def field_points(self):
        """The radiance field's grid points (:class:`~cloudgraph.field.FieldPoints`), made when a
        field stage first needs them."""
        from .field import FieldPoints

        return FieldPoints.of(self.volume, self.field)

    @cached_property
    def cells(self) -> NodeCells:
        """The node cells, made when a stage first needs them: a relight's lighting and field
        stages, here or on a helper, never do (their levels read every voxel)."""
        return NodeCells(self.volume, self.density_scale, self.params, self.origin)

    def n_chunks(self, stage: str, inputs: dict | None = None) -> int:
        if stage == "trace":
            return -(-self.params.n_paths // CHUNK_PATHS)
        if stage == "seeds":
            return -(-self.params.coverage_seeds // CHUNK_SEEDS)
        if stage == "flights":
            return -(-int(inputs["ends"][-1]) // _flight_chunk(inputs))
        if stage in ("bins", "graph_file"):
            return 1
        if stage == "search":
            return -(-len(inputs["positions"]) // _search_chunk(len(inputs["positions"])))
        if stage == "lighting":
            from .lighting import LIGHTING_CHUNK

            return -(-len(inputs["positions"]) // LIGHTING_CHUNK)
        from .field import field_chunks

        return field_chunks(stage, inputs)

    def chunk(self, stage: str, index: int, inputs: dict | None = None) -> tuple[np.ndarray, ...]:
        """One chunk's results: collisions and samples reduced (:func:`reduce_chunk`), or the
        later stages' (the field bake's: :func:`~cloudgraph.field.field_chunk`)."""
        if stage == "trace":
            return self._trace(index * CHUNK_PATHS)
        if stage == "seeds":
            return self._seeds(index * CHUNK_SEEDS)
        if stage == "flights":
            return self._flights(index, inputs)
        if stage == "search":
            return self._search(index, inputs)
        if stage == "lighting":
            from .lighting import lighting_chunk

            return lighting_chunk(self.field, index, inputs)
        if stage in ("field_tau", "field_lookup", "field_ms"):
            from .field import field_chunk

            return field_chunk(self, stage, index, inputs)
        if stage == "graph_file":
            from .cache import graph_file

            return (np.frombuffer(graph_file(Graph.from_arrays(inputs)), np.uint8),)
        if stage == "bins":
            from .integrators.graph import node_bins

            return node_bins(np.asarray(inputs["positions"]), np.asarray(inputs["search_radius"]))
        raise ValueError(f"unknown precompute stage {stage!r}")

    def _trace(self, first: int) -> tuple[np.ndarray, ...]:
        # Light paths (§4.3): every collision joins the node of its cell (§4.3.1) and has an
        # outgoing sample unless it was the last one kept on a cut path: its successor is the
        # next collision, or an escape when the path ended early.
        p = self.params
        n = min(CHUNK_PATHS, p.n_paths - first)
        pos, n_col = trace_light_paths(
            self.field, GRAPH_LIGHTS, self.volume.world_bbox(), n, p.max_collisions, p.seed, first
        )
        k = np.arange(p.max_collisions)[None, :]
        valid = k < n_col[:, None]
        keys = np.full(valid.shape, -1, np.int64)
        points = pos[valid].astype(np.float64)
        keys[valid] = self.cells.keys(points)
        has_next = k + 1 < n_col[:, None]
        escaped = (k + 1 == n_col[:, None]) & (n_col[:, None] < p.max_collisions)
        has_out = has_next | escaped
        priority = uniform_hash(p.seed, 0, ((first + np.arange(n))[:, None] * p.max_collisions + k)[valid])
        # a path's collisions are consecutive among the valid ones: the next is one on
        succ = np.cumsum(valid.ravel()).reshape(valid.shape)
        src, dst = keys[has_out], np.where(has_next, succ, -1)[has_out]
        return reduce_chunk(keys[valid], points, priority, src, dst, self.origin, p.radius)

    def _seeds(self, first: int) -> tuple[np.ndarray, ...]:
        # Coverage seeds first .. first + CHUNK_SEEDS - 1: collisions without samples
        p, none = self.params, np.zeros(0, np.int64)
        index = np.arange(first, min(first + CHUNK_SEEDS, p.coverage_seeds))
        seeds = density_points(self.volume, index, p.seed, self._density_cdf)
        priority = uniform_hash(p.seed, 1, index)
        return reduce_chunk(self.cells.keys(seeds), seeds, priority, none, none, self.origin, p.radius)

    @cached_property
    def _density_cdf(self) -> np.ndarray:
        return np.cumsum(self.volume.density.ravel(), dtype=np.float64)

    def _search(self, index: int, inputs: dict) -> tuple[np.ndarray, np.ndarray]:
        # Search ranges (Eq. 4.21): R_a = max(d_k(a), r), d_k from the k nearest other nodes
        nodes, p = np.asarray(inputs["positions"]), self.params
        size = _search_chunk(len(nodes))
        q = nodes[index * size : (index + 1) * size]
        k = min(p.search_k + 1, len(nodes))
        dk, _ = cKDTree(nodes).query(q, k=k, workers=cpu_threads())
        kth = dk[:, -1] if k > 1 else np.full(len(q), p.radius)
        return np.array([index * size]), np.maximum(kth, p.radius).astype(np.float32)[:, None]

    def _flights(self, index: int, inputs: dict) -> tuple[np.ndarray, ...]:
        # Flights a .. a + size - 1 of the round: flight f belongs to the first node
        # whose running total of flights (``ends``) exceeds f, and starts at one of its kept
        # collisions picked by f's own random number. Each flight is a sample of its node;
        # where it collides is a collision too.
        p, rnd = self.params, int(inputs["round"][0])
        ends, size = np.asarray(inputs["ends"]), _flight_chunk(inputs)
        a = index * size
        f = np.arange(a, min(a + size, int(ends[-1])))
        node = np.searchsorted(ends, f, side="right")
        members = np.asarray(inputs["members"])[node]
        pick = np.floor(uniform_hash(p.seed, 1000 + rnd, f) * members).astype(np.int64)
        starts = np.asarray(inputs["kept"])[node, pick].astype(np.float64)
        hits, collided = trace_flights(self.field, starts, p.seed + 1 + rnd, a)
        hits = hits[collided].astype(np.float64)
        hit_keys = self.cells.keys(hits)
        dst = np.full(len(collided), -1, np.int64)
        dst[collided] = np.arange(len(hits))
        priority = uniform_hash(p.seed, 2 + rnd, a + np.flatnonzero(collided))
        src = np.asarray(inputs["cells"])[node]
        return reduce_chunk(hit_keys, hits, priority, src, dst, self.origin, p.radius)


def _search_chunk(n_nodes: int) -> int:
    """Nodes per chunk of the search ranges: SEARCH_CHUNKS chunks, each with a k-d tree of all the
    nodes (a tenth of the time of its queries on blender)."""
    return max(1, -(-n_nodes // SEARCH_CHUNKS))


def _flight_chunk(inputs: dict) -> int:
    """Flights per chunk of a round of reinforcement."""
    return min(CHUNK_FLIGHTS, max(1 << 12, -(-int(inputs["ends"][-1]) // ROUND_CHUNKS)))


def local_chunks(builder: GraphBuilder, stage: str, inputs: dict | None = None):
    """Runs a stage's chunks in this process (the default ``chunks``), in order, on threads
    while the caller merges the ones before: tracing and reducing chunks (Dr.Jit, numpy sorts)
    overlaps merging."""
    n = builder.n_chunks(stage, inputs)
    with ThreadPoolExecutor(LOCAL_THREADS) as pool:
        ahead = deque(pool.submit(builder.chunk, stage, i, inputs) for i in range(min(n, LOCAL_THREADS)))
        for i in range(n):
            result = ahead.popleft().result()
            if i + LOCAL_THREADS < n:
                ahead.append(pool.submit(builder.chunk, stage, i + LOCAL_THREADS, inputs))
            yield result


def placed(results, n: int, channels: int, dtype=np.float32) -> np.ndarray:
    """(n, channels) values from chunk results (first row, values) that come in any order."""
    out = np.zeros((n, channels), dtype)
    for first, values in results:
        out[int(first[0]) : int(first[0]) + len(values)] = values
    return out


def build_graph(
    volume: Volume,
    density_scale: float,
    params: BuildParams,
    progress=None,
    chunks=local_chunks,
    builder: GraphBuilder | None = None,
    nodes_found=None,
    started=None,
) -> Graph:
    """Builds the graph of a volume and density scale (a variant must be set).

    ``progress(stage, fraction)`` is called as the build goes. ``chunks(builder, stage, inputs)``
    puts a stage's chunks (:meth:`GraphBuilder.chunk`) out and returns an iterator of their
    results in any order: run here as it is iterated by default, or spread over workers (who
    may start before it is iterated); the graph is the same bytes either way. ``builder``:
    one already made for these arguments. ``started()`` is called once the light paths and
    coverage seeds are out, before any is merged: work of the caller's own that other workers
    can start on goes out there, after the build's first. ``nodes_found(positions)`` is called
    with the graph's node positions as soon as they are known, before its search ranges and
    edges are made.
    """
    progress = progress or (lambda stage, fraction: None)
    t_start = time.perf_counter()
    builder = builder or GraphBuilder(volume, density_scale, params)
    origin = builder.origin
    table = NodeTable(origin, params.radius)

    # Light paths (§4.3) and coverage seeds, chunk by chunk, each reduced into the table and
    # dropped (merges commute). Coverage seeds are our addition: light paths are cut at
    # max_collisions, so in thick media they never reach the far side. Points drawn in
    # proportion to density seed nodes there too; reinforcement then gives every node its own
    # outgoing samples.
    stages = [chunks(builder, "trace"), chunks(builder, "seeds")]
    if started is not None:
        started()
    n = builder.n_chunks("trace") + builder.n_chunks("seeds")
    for i, result in enumerate(chain(*stages)):
        table.merge(result)
        progress("trace", 0.3 * (i + 1) / n)
    t_trace = time.perf_counter() - t_start

    # Reinforcement of sparse nodes (§4.3, App. B)
    t0 = time.perf_counter()
    for rnd in range(params.reinforce_rounds):
        n_edges = table.out_edges(params.min_out_edges)
        deficit = np.maximum(params.min_out_samples - table.out, 0)
        deficit[(n_edges < params.min_out_edges) & (deficit == 0)] = params.min_out_samples
        if not deficit.any():
            break
        # The nodes short of samples, in order of keys, with their kept collisions: each new
        # flight starts at a random one of them (GraphBuilder._flights). Collisions in cells
        # without a node make new nodes (filled in the next round).
        short = table.order[deficit[table.order] > 0]
        inputs = {
            "cells": table.keys[short],
            "ends": np.cumsum(deficit[short]),
            "kept": table.kept[short],
            "members": np.minimum(table.count[short], MEMBERS_KEPT),
            "round": np.array([rnd]),
        }
        n = builder.n_chunks("flights", inputs)
        for i, result in enumerate(chunks(builder, "flights", inputs)):
            table.merge(result)
            progress("reinforce", 0.3 + 0.7 * (rnd + (i + 1) / n) / params.reinforce_rounds)
    t_reinforce = time.perf_counter() - t0

    # Node positions (the mean of their collisions), counts, then search ranges from the k
    # nearest nodes (Eq. 4.21, thesis §4.3.2)
    t0 = time.perf_counter()
    n, by_key = len(table), table.order  # nodes in order of their keys: the same however found
    nodes = table.means()[by_key]
    positions = nodes.astype(np.float32)
    if nodes_found is not None:
        nodes_found(positions)
    ranges = chunks(builder, "search", {"positions": nodes})  # other workers start on them
    out_samples = table.out[by_key]
    counts = table.counts_by_key()
    search = placed(ranges, n, 1)[:, 0]
    t_group = time.perf_counter() - t0

    progress("graph", 1.0)
    stats = {
        "nodes": int(n),
        "edges": int(counts.nnz),
        "collisions": int(table.count.sum()),
        "light_paths": int(params.n_paths),
        "samples": int(out_samples.sum()),
        "trace_s": round(t_trace, 3),
        "group_s": round(t_group, 3),
        "reinforce_s": round(t_reinforce, 3),
        "build_s": round(time.perf_counter() - t_start, 3),
    }
    log.info("graph: %s", stats)
    return Graph(positions, search, out_samples, counts, stats)
