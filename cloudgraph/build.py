"""Building the graph (thesis §4.3): light tracing, node grouping, edge counts, reinforcement,
search ranges.

Light paths are traced from directional lights through the medium by free-flight sampling
(delta tracking, in Dr.Jit: the walks are in tracing.py): from six axis directions rather than
the scene's light, so that the graph depends only on its key (see GRAPH_LIGHTS). Every
*collision* (docs/method.md's generalisation: not only scattering events) joins a node; per node
we count every outgoing free-flight sample, escapes included, and per edge a -> b the samples from
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
light paths, and the graph is the same bytes however the chunks are cut or ordered. The stages'
chunks are run by whoever calls :func:`build_graph` (stages.py dispatches them by name).
"""

from __future__ import annotations

import logging
import time
from functools import cached_property
from itertools import chain

import numpy as np
from scipy.spatial import cKDTree

from .chunks import placed
from .graph import Graph
from .nodes import MEMBERS_KEPT, NodeCells, NodeTable, reduce_chunk, uniform_hash
from .params import BuildParams
from .tracing import DensityField, cpu_threads, trace_flights, trace_light_paths
from .volume import Volume, voxel_points

log = logging.getLogger(__name__)


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
#: first asked for it, as its key says (docs/method.md: a new light reuses the graph). Transitions do
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


class GraphBuilder:
    """What every chunk of one graph's build needs (the medium, the parameters, the cell origin).
    A chunk is a pure function of (stage, index, inputs), so any process that makes a builder
    from the same (volume, density_scale, params) computes the same chunk (stages.py), and the
    chunks merge into the same graph, since a :class:`NodeTable` is the same whatever the order
    of its merges.

    Stages of the build: ``trace``, light paths from index * CHUNK_PATHS on; ``seeds``, coverage
    seeds from index * CHUNK_SEEDS on; ``flights``, reinforcement flights of one round in chunks
    of at most CHUNK_FLIGHTS (:func:`_flight_chunk`), with inputs per node short of samples
    (``cells`` keys, ``ends`` running total of flights, ``kept`` collisions and how many
    ``members``) and the ``round``: a few bytes per node, not per flight; ``search``, the nodes'
    search ranges from their ``positions`` (float64, in key order), in SEARCH_CHUNKS chunks.
    """

    def __init__(self, volume: Volume, density_scale: float, params: BuildParams):
        self.volume, self.params, self.density_scale = volume, params, density_scale
        self.field = DensityField.from_volume(volume, density_scale)
        self.origin = volume.world_bbox()[0] - params.radius

    @cached_property
    def cells(self) -> NodeCells:
        """The node cells, made when a stage first needs them: a relight's lighting and field
        stages, here or on a helper, never do (their levels read every voxel)."""
        return NodeCells(self.volume, self.density_scale, self.params, self.origin)

    def trace(self, first: int) -> tuple[np.ndarray, ...]:
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

    def seeds(self, first: int) -> tuple[np.ndarray, ...]:
        # Coverage seeds first .. first + CHUNK_SEEDS - 1: collisions without samples
        p, none = self.params, np.zeros(0, np.int64)
        index = np.arange(first, min(first + CHUNK_SEEDS, p.coverage_seeds))
        seeds = density_points(self.volume, index, p.seed, self._density_cdf)
        priority = uniform_hash(p.seed, 1, index)
        return reduce_chunk(self.cells.keys(seeds), seeds, priority, none, none, self.origin, p.radius)

    @cached_property
    def _density_cdf(self) -> np.ndarray:
        return np.cumsum(self.volume.density.ravel(), dtype=np.float64)

    def search(self, index: int, inputs: dict) -> tuple[np.ndarray, np.ndarray]:
        # Search ranges (Eq. 4.21): R_a = max(d_k(a), r), d_k from the k nearest other nodes
        nodes, p = np.asarray(inputs["positions"]), self.params
        size = _search_chunk(len(nodes))
        q = nodes[index * size : (index + 1) * size]
        k = min(p.search_k + 1, len(nodes))
        dk, _ = cKDTree(nodes).query(q, k=k, workers=cpu_threads())
        kth = dk[:, -1] if k > 1 else np.full(len(q), p.radius)
        return np.array([index * size]), np.maximum(kth, p.radius).astype(np.float32)[:, None]

    def flights(self, index: int, inputs: dict) -> tuple[np.ndarray, ...]:
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


# The build's stages (stages.py): how many chunks each has, and one chunk's results, reduced
# (:func:`reduce_chunk`) or placed (search ranges: first node, values).


def trace_chunks(builder: GraphBuilder, inputs: dict | None = None) -> int:
    return -(-builder.params.n_paths // CHUNK_PATHS)


def trace_chunk(builder: GraphBuilder, index: int, inputs: dict | None = None) -> tuple[np.ndarray, ...]:
    return builder.trace(index * CHUNK_PATHS)


def seed_chunks(builder: GraphBuilder, inputs: dict | None = None) -> int:
    return -(-builder.params.coverage_seeds // CHUNK_SEEDS)


def seed_chunk(builder: GraphBuilder, index: int, inputs: dict | None = None) -> tuple[np.ndarray, ...]:
    return builder.seeds(index * CHUNK_SEEDS)


def flight_chunks(builder: GraphBuilder, inputs: dict) -> int:
    return -(-int(inputs["ends"][-1]) // _flight_chunk(inputs))


def flight_chunk(builder: GraphBuilder, index: int, inputs: dict) -> tuple[np.ndarray, ...]:
    return builder.flights(index, inputs)


def search_chunks(builder: GraphBuilder, inputs: dict) -> int:
    return -(-len(inputs["positions"]) // _search_chunk(len(inputs["positions"])))


def search_chunk(builder: GraphBuilder, index: int, inputs: dict) -> tuple[np.ndarray, np.ndarray]:
    return builder.search(index, inputs)


def build_graph(
    volume: Volume,
    density_scale: float,
    params: BuildParams,
    chunks,
    progress=None,
    builder: GraphBuilder | None = None,
    nodes_found=None,
    started=None,
) -> Graph:
    """Builds the graph of a volume and density scale (a variant must be set).

    ``progress(stage, fraction)`` is called as the build goes. ``chunks(builder, stage, inputs)``
    puts a stage's chunks (stages.py) out and returns an iterator of their
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
    n = trace_chunks(builder) + seed_chunks(builder)
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
        # flight starts at a random one of them (GraphBuilder.flights). Collisions in cells
        # without a node make new nodes (filled in the next round).
        short = table.order[deficit[table.order] > 0]
        inputs = {
            "cells": table.keys[short],
            "ends": np.cumsum(deficit[short]),
            "kept": table.kept[short],
            "members": np.minimum(table.count[short], MEMBERS_KEPT),
            "round": np.array([rnd]),
        }
        n = flight_chunks(builder, inputs)
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
    # where each edge's samples collided, from its end node's position (Graph.landing)
    landing = (table.landed_by_key(counts) - nodes[counts.indices]).astype(np.float32)
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
    return Graph(positions, search, out_samples, counts, stats, landing)
