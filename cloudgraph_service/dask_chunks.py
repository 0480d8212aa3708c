"""One precompute over a Dask cluster (docs/service.md, "One precompute over many workers"): the
``chunks`` of :func:`cloudgraph.precompute.precompute` as Dask tasks.

``CLOUDGRAPH_DASK_SCHEDULER=tcp://HOST:8786`` sends every precompute there, from the RQ worker
and from ``cloudgraph precompute`` alike (:func:`precompute_chunks`); unset, the chunks run in
this process (:func:`cloudgraph.stages.local_chunks`). Each stage's chunks go out as tasks when
the engine asks (``client.map``, after one task that holds the stage's inputs) and come back as
they complete; the merges commute, so the bytes are the same however the work is cut. A Dask
worker makes the run's :class:`~cloudgraph.build.GraphBuilder` once, from the volume sent with
the run's first stage. Dask computes again what a lost worker held, inputs and volume too. A
lost scheduler (or none to reach) does not fail the job: what is left of the precompute runs in
this process, the same bytes, with a warning.
"""

from __future__ import annotations

import logging
import uuid
from concurrent.futures import CancelledError
from contextlib import contextmanager
from functools import lru_cache

import dask
import mitsuba as mi
from distributed import Client, WorkerPlugin, as_completed

from cloudgraph import stages
from cloudgraph.build import GraphBuilder
from cloudgraph.tracing import new_scope

log = logging.getLogger("cloudgraph.dask")

#: How long a client tries to reach the scheduler before the precompute runs here instead.
CONNECT_S = 10.0
#: What a lost scheduler (or none to reach) looks like to a client.
LOST = (CancelledError, OSError, TimeoutError)
#: Dask runs higher first: stages wanted late (stages.LATE_STAGES) fill the gaps, the last last.
PRIORITY = {**dict.fromkeys(stages.LATE_STAGES, -1), **dict.fromkeys(stages.LAST_STAGES, -2)}


class CloudgraphVariant(WorkerPlugin):
    """Sets the client's Mitsuba variant on every Dask worker, those that join later too (the same
    variant computes the same bytes), Dr.Jit's threads (``CLOUDGRAPH_WORKER_THREADS``) and the
    heap (cloudgraph/heap.py)."""

    name = "cloudgraph-variant"

    def __init__(self, variant: str):
        self.variant = variant

    def setup(self, worker) -> None:
        from cloudgraph.heap import keep_freed_memory
        from cloudgraph.mitsuba_scene import set_threads, set_variant
        from cloudgraph_service.settings import Settings

        keep_freed_memory()  # (the chunks' arrays reuse each other's pages)
        set_variant(self.variant)
        set_threads(Settings.from_env().WORKER_THREADS)


#: A run's builder on a Dask worker, made by the first of its chunks there: by the run's volume
#: (the object the worker holds, one per run), density scale and parameters.
_builder = lru_cache(maxsize=2)(GraphBuilder)


def _chunk(index: int, volume, density_scale: float, params, stage: str, inputs):
    """Chunk ``index`` of ``stage``, on a Dask worker: in a Dr.Jit scope of its own, since the
    builder's arrays may come from another of the worker's threads (tracing.new_scope)."""
    builder = _builder(volume, density_scale, params)
    new_scope()
    return stages.run_chunk(builder, stage, index, inputs)


def _given(value):
    """``value``, as a task: one that Dask can run again where the worker that held it is lost."""
    return value


class DaskChunks:
    """``chunks(builder, stage, inputs)`` on the cluster of ``client``, for one precompute."""

    def __init__(self, client: Client):
        self.client, self.run, self.lost = client, uuid.uuid4().hex, False
        self.out, self.spec = set(), None  # futures not yet merged; what every chunk is given

    def __call__(self, builder, stage: str, inputs: dict | None = None):
        if not self.lost:
            try:
                return self._results(*self._put(builder, stage, inputs), builder, stage, inputs)
            except LOST as err:
                self._lose(err)
        return stages.local_chunks(builder, stage, inputs)

    def _put(self, builder, stage: str, inputs: dict | None) -> tuple:
        """(tasks, their inputs' future): the stage's chunks as tasks, after a task that holds its
        inputs (and, once per run, one that holds the volume). Not scattered: what a lost worker
        held, inputs too, is computed again from what the scheduler holds."""
        n, c, b = stages.n_chunks(builder, stage, inputs), self.client, builder
        if self.spec is None:  # the run's one builder (precompute makes one)
            volume = c.submit(_given, b.volume, key=f"volume-{self.run}")
            self.spec = dict(volume=volume, density_scale=b.density_scale, params=b.params)
        name = f"{self.run}-{uuid.uuid4().hex[:8]}"  # this stage's
        data = c.submit(_given, inputs, key=f"inputs-{name}") if inputs else None
        keys, priority = [f"{stage}-{name}-{i}" for i in range(n)], PRIORITY.get(stage, 0)
        futures = c.map(_chunk, range(n), **self.spec, stage=stage, inputs=data, key=keys, priority=priority)
        self.out.update(futures)
        return futures, data

    def _lose(self, err: BaseException) -> None:
        if not self.lost:  # the first line of what Dask says, or the error's type
            why = str(err).partition("\n")[0] or type(err).__name__
            log.warning("precompute %s lost the Dask cluster (%s): the rest runs here", self.run, why)
        self.lost = True

    def _results(self, futures, data, builder, stage: str, inputs):
        """The stage's results as they complete; ``data`` (its inputs' future) is held until then."""
        left = {f.key: i for i, f in enumerate(futures)}
        try:
            for f in as_completed(futures, loop=self.client.loop):
                result, _ = f.result(), left.pop(f.key)
                self.out.discard(f)
                f.release()  # its result leaves the cluster
                yield result
        except LOST as err:
            if self.client.status == "running" and "connection-lost" not in str(err):
                raise
            self._lose(err)
        for i in sorted(left.values()):  # only when the scheduler was lost
            yield stages.run_chunk(builder, stage, i, inputs)

    def close(self) -> None:
        """Cancels what is still out (a precompute that failed or was cancelled)."""
        if self.out and self.client.status == "running":
            self.client.cancel(list(self.out))


_clients: dict[str, Client] = {}


def client(address: str, connect_s: float = CONNECT_S) -> Client:
    """This process's client of the scheduler at ``address``: made again once it has lost its
    scheduler (it closes itself when it cannot reach it again within its timeout).

    Raises:
        OSError: no scheduler answered within ``connect_s`` seconds.
    """
    c = _clients.get(address)
    if c is None or c.status != "running":
        # A stage's inputs go with its tasks, so that Dask can compute them again (tens of MB)
        dask.config.set({"distributed.admin.large-graph-warning-threshold": "1GiB"})
        c = _clients[address] = Client(address, timeout=connect_s, set_as_default=False)
        c.register_plugin(CloudgraphVariant(mi.variant()))
    return c


@contextmanager
def precompute_chunks(address: str | None, connect_s: float = CONNECT_S):
    """The ``chunks`` of one precompute: on the Dask cluster at ``address``, else (None, or no
    scheduler answers) in this process. A variant must be set."""
    chunks = stages.local_chunks
    if address:
        try:
            chunks = DaskChunks(client(address, connect_s))
        except LOST as err:
            log.warning("no Dask scheduler at %s (%s): this precompute runs here", address, err)
    try:
        yield chunks
    finally:
        if isinstance(chunks, DaskChunks):
            chunks.close()
