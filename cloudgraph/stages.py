"""The precompute's stages by name: stage name -> (how many chunks, one chunk), and the executor
that runs them in this process.

A chunk is a pure function of (stage, index, inputs) and of what its builder holds (the volume,
the medium and the build parameters: :class:`~cloudgraph.build.GraphBuilder`), so any process
that makes a builder from the same (volume, density_scale, params) computes the same chunk: a
precompute can be spread over workers and merged into the same bytes.

| stage          | module        | what one chunk computes                                    |
|----------------|---------------|------------------------------------------------------------|
| ``trace``      | build.py      | light paths, reduced into per-node sums                    |
| ``seeds``      | build.py      | coverage seeds                                             |
| ``flights``    | build.py      | reinforcement flights of one round                         |
| ``search``     | build.py      | search ranges (Eq. 4.21)                                   |
| ``lighting``   | lighting.py   | direct radiance of nodes (Eq. 4.22 at a point)             |
| ``bins``       | spatial.py    | the nodes binned for the field's lookups (one chunk)       |
| ``graph_file`` | graph_file.py | the graph file's bytes (one chunk)                         |
| ``field_tau``, ``field_lookup``, ``field_ms`` | field.py | the field bake's marches and lookups |
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from . import build, field, lighting
from .build import GraphBuilder
from .graph import Graph
from .graph_file import graph_file
from .spatial import node_bins
from .tracing import new_scope


class Stage(NamedTuple):
    """How many chunks a stage has for its inputs, and one chunk's results."""

    n_chunks: Callable[[GraphBuilder, dict | None], int]
    chunk: Callable[[GraphBuilder, int, dict | None], tuple[np.ndarray, ...]]


def _one(builder, inputs) -> int:
    return 1


def _graph_file(builder, index, inputs):
    return (np.frombuffer(graph_file(Graph.from_arrays(inputs)), np.uint8),)


def _bins(builder, index, inputs):
    return node_bins(np.asarray(inputs["positions"]), np.asarray(inputs["search_radius"]))


def _lighting(builder, index, inputs):
    return lighting.lighting_chunk(builder.field, index, inputs)


def _lighting_chunks(builder, inputs) -> int:
    return -(-len(inputs["positions"]) // lighting.LIGHTING_CHUNK)


def _field_stage(name: str) -> Stage:
    return Stage(
        lambda builder, inputs: field.field_chunks(name, inputs),
        lambda builder, index, inputs: field.field_chunk(builder, name, index, inputs),
    )


STAGES: dict[str, Stage] = {
    "trace": Stage(build.trace_chunks, build.trace_chunk),
    "seeds": Stage(build.seed_chunks, build.seed_chunk),
    "flights": Stage(build.flight_chunks, build.flight_chunk),
    "search": Stage(build.search_chunks, build.search_chunk),
    "lighting": Stage(_lighting_chunks, _lighting),
    "bins": Stage(_one, _bins),
    "graph_file": Stage(_one, _graph_file),
    **{name: _field_stage(name) for name in ("field_tau", "field_lookup", "field_ms")},
}

#: Stages put out long before their results are needed (the field's light march, at the start
#: of a precompute; the node bins and the graph file's bytes, before the transport): workers
#: that share a precompute run them when no other stage has work.
LATE_STAGES = frozenset({"field_tau", "bins", "graph_file"})
#: Late stages whose results are wanted only at the end of a precompute (the graph file is
#: written last): they wait behind every other late stage, whenever that was put out.
LAST_STAGES = frozenset({"graph_file"})

#: Chunks run ahead on threads while the last is merged (local_chunks)
LOCAL_THREADS = 2


def _stage(stage: str) -> Stage:
    if stage not in STAGES:
        raise ValueError(f"unknown precompute stage {stage!r}")
    return STAGES[stage]


def n_chunks(builder: GraphBuilder, stage: str, inputs: dict | None = None) -> int:
    """How many chunks ``stage`` has for ``inputs``."""
    return _stage(stage).n_chunks(builder, inputs)


def run_chunk(builder: GraphBuilder, stage: str, index: int, inputs: dict | None = None) -> tuple:
    """Chunk ``index`` of ``stage``: its results (arrays), the same wherever it runs."""
    return _stage(stage).chunk(builder, index, inputs)


def local_chunks(builder: GraphBuilder, stage: str, inputs: dict | None = None):
    """Runs a stage's chunks in this process (the default ``chunks`` of a precompute), in order,
    on threads while the caller merges the ones before: tracing and reducing chunks (Dr.Jit,
    numpy sorts) overlaps merging. A late stage's chunks (:data:`LATE_STAGES`) start at once, on
    threads of their own, in the order they were put out: the field's light march runs while
    the graph is read or built and the transport solved, as a worker that shares a precompute
    runs it (smoke1: a first precompute 7.1 -> 5.8 s)."""
    if stage in LATE_STAGES:
        return _Ahead(builder, stage, inputs)
    return _in_order(builder, stage, inputs)


def _in_order(builder: GraphBuilder, stage: str, inputs: dict | None):
    n = n_chunks(builder, stage, inputs)
    with ThreadPoolExecutor(LOCAL_THREADS) as pool:
        ahead = deque(pool.submit(run_chunk, builder, stage, i, inputs) for i in range(min(n, LOCAL_THREADS)))
        for i in range(n):
            result = ahead.popleft().result()
            if i + LOCAL_THREADS < n:
                ahead.append(pool.submit(run_chunk, builder, stage, i + LOCAL_THREADS, inputs))
            yield result


#: The late stages' threads (started at their first chunk)
_LATE_POOL = ThreadPoolExecutor(LOCAL_THREADS, thread_name_prefix="late-chunks")


def _late_chunk(builder: GraphBuilder, stage: str, index: int, inputs: dict | None) -> tuple:
    new_scope()  # (the late threads live on: the builder's arrays may be newer than they are)
    return run_chunk(builder, stage, index, inputs)


class _Ahead:
    """A late stage's chunks, all put out on the process's late threads when made; iterated, their
    results in order. Dropped before the end (a cancelled precompute), the chunks not yet started
    are taken back."""

    def __init__(self, builder: GraphBuilder, stage: str, inputs: dict | None):
        n = n_chunks(builder, stage, inputs)
        self._futures = deque(_LATE_POOL.submit(_late_chunk, builder, stage, i, inputs) for i in range(n))

    def __iter__(self):
        return self

    def __next__(self) -> tuple:
        if not self._futures:
            raise StopIteration
        return self._futures.popleft().result()

    def __del__(self):
        for future in self._futures:
            future.cancel()
