"""One precompute over many workers (docs/service.md, "One precompute over many workers"): the
graph build's chunks (:func:`cloudgraph.stages.run_chunk`) shared through Redis.

The worker that runs a precompute job coordinates it (:class:`SharedChunks`). For each stage of
the build it writes the stage's inputs to a run folder on the shared cache volume, pushes one
task per chunk to a Redis list and works through the list itself (after work of its own that
does not need the stage's results, so that helpers start first), while helper jobs (put at the
front of the queue, one per other worker) take tasks from the same list and leave their results
in the run folder (:func:`help_run`). A task is claimed atomically with a lease that its holder
renews every LEASE_S / 3 seconds; the task of a killed worker (its lease lapsed) goes back on the
list. The coordinator merges results as they come: :class:`~cloudgraph.nodes.NodeTable` merges
commute, so the graph is the same bytes whoever ran which chunk.

Keys, under ``cloudgraph:run:<run>:``:

| key           | what                                                                      |
|---------------|---------------------------------------------------------------------------|
| spec          | JSON {scene, quality, dir}: what a helper needs; expires unless the       |
|               | coordinator renews it, so helpers of a dead coordinator stop              |
| stage:<gen>   | JSON {stage, inputs} of the gen-th stage put out (inputs in               |
|               | ``<dir>/<gen>-<name>.npy``); several can be out at once                   |
| todo          | tasks ``<gen>:<chunk>`` not yet claimed, oldest stage first               |
| later         | the same, of stages needed late (stages.LATE_STAGES), newest stage  |
|               | first (it is wanted soonest) but those wanted only at the end last        |
|               | (stages.LAST_STAGES): claimed when todo is empty, so that they fill |
|               | the gaps the other stages leave                                           |
| lease:<task>  | the holder of a claimed task; expires LEASE_S after its last renewal      |
| done:<gen>    | tasks of that stage finished by helpers (``<dir>/<gen>-<chunk>.npz``)     |
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from redis import Redis

from cloudgraph import stages
from cloudgraph.files import atomic_writer

log = logging.getLogger("cloudgraph.chunks")

#: A claimed task goes back on the list when its holder has not renewed its lease for this long.
LEASE_S = 10.0
#: How often an idle helper or a waiting coordinator looks again.
POLL_S = 0.05
#: Most helpers asked for one precompute.
MAX_HELPERS = 16

# LPOP a task (from todo, else from later where ARGV[3] is 1) and lease it to ARGV[1] for ARGV[2]
# ms, in one step (no task is ever held unleased)
_CLAIM = """
local t = redis.call('LPOP', KEYS[1])
if not t and ARGV[3] == '1' then t = redis.call('LPOP', KEYS[2]) end
if t then redis.call('SET', KEYS[3] .. t, ARGV[1], 'PX', ARGV[2]) end
return t
"""


# LREM the first of the tasks ARGV[3..] still in the list KEYS[1] and lease it to ARGV[1] for
# ARGV[2] ms, in one step
_CLAIM_LATE = """
for i = 3, #ARGV do
  if redis.call('LREM', KEYS[1], 1, ARGV[i]) == 1 then
    redis.call('SET', KEYS[2] .. ARGV[i], ARGV[1], 'PX', ARGV[2])
    return ARGV[i]
  end
end
return nil
"""


# RPUSH ARGV[1] to the done list KEYS[2] while the run's spec KEYS[1] exists: a helper that ends a
# chunk after its run ended leaves no key behind
_DONE = """
if redis.call('EXISTS', KEYS[1]) == 1 then return redis.call('RPUSH', KEYS[2], ARGV[1]) end
return 0
"""


def run_key(run: str, part: str) -> str:
    return f"cloudgraph:run:{run}:{part}"


def holder_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


class _Run:
    """A run's keys and the operations both sides perform."""

    def __init__(self, redis: Redis, run: str, lease_s: float):
        self.redis, self.run, self.lease_ms = redis, run, int(lease_s * 1000)
        self._claim = redis.register_script(_CLAIM)
        self._claim_late = redis.register_script(_CLAIM_LATE)
        self._done = redis.register_script(_DONE)

    def key(self, part: str) -> str:
        return run_key(self.run, part)

    def claim(self, holder: str, late: bool = True) -> str | None:
        """A task for ``holder``: of the stages in order, then (``late``) of the late ones."""
        keys = [self.key("todo"), self.key("later"), self.key("lease:")]
        t = self._claim(keys=keys, args=[holder, self.lease_ms, int(late)])
        return None if t is None else t.decode()

    def claim_late(self, holder: str, tasks: list[str]) -> str | None:
        """The first of ``tasks`` (of a late stage) still unclaimed, for ``holder``."""
        keys = [self.key("later"), self.key("lease:")]
        t = self._claim_late(keys=keys, args=[holder, self.lease_ms, *tasks]) if tasks else None
        return None if t is None else t.decode()

    def put(self, gen: int, n: int, late: bool, last: bool = False) -> None:
        """Puts the n tasks of stage ``gen`` out: at the end of todo, or (``late``) at the head of
        later, in order: of the late stages, the last put out is the first wanted (the field's
        node bins before its light march); or (``last``) at the end of later: wanted only when
        the precompute ends (the graph file's bytes)."""
        tasks = [f"{gen}:{i}" for i in range(n)]
        if last:
            self.redis.rpush(self.key("later"), *tasks)
        elif late:
            self.redis.lpush(self.key("later"), *reversed(tasks))
        else:
            self.redis.rpush(self.key("todo"), *tasks)

    def done(self, gen: int, task: str) -> None:
        """Tells the coordinator that a helper's task is done (unless the run has ended)."""
        self._done(keys=[self.key("spec"), self.key(f"done:{gen}")], args=[task])

    @contextmanager
    def leased(self, task: str, holder: str):
        """Renews the task's lease while the block runs, then drops it."""
        stop = threading.Event()

        def renew():
            while not stop.wait(self.lease_ms / 3000):
                try:
                    self.redis.set(self.key(f"lease:{task}"), holder, px=self.lease_ms)
                except Exception:  # Redis away for a moment: the next renewal tries again
                    log.exception("lease renewal failed")

        t = threading.Thread(target=renew, daemon=True)
        t.start()
        try:
            yield
        finally:
            stop.set()
            t.join()
            self.redis.delete(self.key(f"lease:{task}"))


def _write(path: Path, save, *args, **kwargs) -> None:
    """``save(file, *args, **kwargs)`` written atomically (cloudgraph.files): whole when its task
    is announced. Not synced to disk: a run's files live only as long as the run.

    Raises:
        FileNotFoundError: the run's folder is gone (the run ended); it is not made again.
    """
    if not path.parent.is_dir():
        raise FileNotFoundError(f"the run folder of {path.name} is gone")
    with atomic_writer(path, sync=False) as f:
        save(f, *args, **kwargs)


def _linked(source: Path, path: Path) -> bool:
    """Whether ``path`` could be made a hard link to ``source`` (not on every file system)."""
    try:
        os.link(source, path)
    except OSError:
        return False
    return True


def _inputs(folder: Path, gen: int, names: list[str]) -> dict:
    return {name: np.load(folder / f"{gen}-{name}.npy", mmap_mode="r") for name in names}


class SharedChunks:
    """The ``chunks`` argument of :func:`cloudgraph.precompute.precompute` that spreads a build
    over the workers: used as a context manager around the precompute (its exit ends the run:
    helpers stop, keys and the run folder go).

    Args:
        redis: the queue's Redis.
        run: a name unique to this precompute attempt.
        spec: ``scene`` (a scene dict), ``quality``, ``graph`` (whether a graph is built) and,
            where known, ``params`` (the build parameters, else added at the first stage): what a
            helper needs to make the builder.
            Helpers are asked for once the spec is whole.
        folder: the run folder, on a volume every worker shares.
        ask_helpers: called once, to enqueue helper jobs; returns how many it asked for.
        lease_s: see :data:`LEASE_S`.
    """

    def __init__(self, redis: Redis, run: str, spec: dict, folder: Path, ask_helpers=None, lease_s=LEASE_S):
        self.r = _Run(redis, run, lease_s)
        self.spec = {**spec, "dir": str(folder)}
        self.folder, self.ask_helpers = Path(folder), ask_helpers
        self.holder = holder_name()
        self.gen, self.helpers, self.redone, self.here = 0, None, 0, {}
        self.stages, self.pending, self.ready = {}, {}, {}  # per stage out: (stage, inputs), chunks
        self.written = {}  # id of an input array -> (the array, its file in the run folder)
        self._stop = threading.Event()
        self._beat = threading.Thread(target=self._renew_spec, daemon=True)

    def __enter__(self) -> SharedChunks:
        # Folders of runs whose coordinator died (their spec expired) go first
        for old in self.folder.parent.glob("*"):
            try:
                stale = time.time() - old.stat().st_mtime > 600
            except OSError:  # removed meanwhile by another coordinator
                continue
            if stale and not self.r.redis.exists(run_key(old.name, "spec")):
                shutil.rmtree(old, ignore_errors=True)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._set_spec()
        self._beat.start()
        if "params" in self.spec:  # the spec is whole: helpers can start on their set-up now
            self.helpers = self.ask_helpers() if self.ask_helpers else 0
        return self

    def __exit__(self, *exc) -> None:
        log.info("run %s: chunks run here per stage %s, redone %d", self.r.run, self.here, self.redone)
        self._stop.set()
        self._beat.join()
        r, key = self.r.redis, self.r.key
        # First the spec and the task lists: no helper takes a task or reports one after this
        # (_DONE); then wait (at most a lease) for chunks still held, whose files may yet come
        r.delete(key("spec"), key("todo"), key("later"))
        end = time.monotonic() + self.r.lease_ms / 1000
        while any(r.scan_iter(match=key("lease:*"), count=1000)) and time.monotonic() < end:
            time.sleep(POLL_S)
        left = list(r.scan_iter(match=key("*"), count=1000))
        if left:
            r.delete(*left)
        shutil.rmtree(self.folder, ignore_errors=True)

    def _set_spec(self) -> None:
        self.r.redis.set(self.r.key("spec"), json.dumps(self.spec), px=3 * self.r.lease_ms)

    def _renew_spec(self) -> None:
        while not self._stop.wait(self.r.lease_ms / 3000):
            try:
                self._set_spec()
            except Exception:
                log.exception("could not renew the run's spec")

    def __call__(self, builder, stage: str, inputs: dict | None = None):
        """Puts one stage's chunks on the list at once, for the helpers to start on, and returns
        an iterator that works on them here too and yields their results as they come. Several
        stages may be out at a time: the caller can do work of its own before it iterates."""
        r, gen = self.r, self.gen + 1
        self.gen = gen
        n = stages.n_chunks(builder, stage, inputs)
        names = sorted(inputs or {})
        for name in names:
            # An array already written for an earlier stage (the field's points, the node
            # positions) is linked, not written again
            a, path = inputs[name], self.folder / f"{gen}-{name}.npy"
            earlier = self.written.get(id(a))
            if earlier is None or earlier[0] is not a or not _linked(earlier[1], path):
                _write(path, np.save, np.asarray(a))
                self.written[id(a)] = (a, path)
        self.stages[gen] = (stage, inputs)
        self.pending[gen], self.ready[gen] = set(range(n)), []
        r.redis.set(r.key(f"stage:{gen}"), json.dumps({"stage": stage, "inputs": names}))
        if n:
            r.put(gen, n, stage in stages.LATE_STAGES, stage in stages.LAST_STAGES)
        if self.helpers is None:  # the first stage: helpers are asked for once the spec is whole
            self.spec["params"] = builder.params.to_dict()
            self._set_spec()
            self.helpers = self.ask_helpers() if self.ask_helpers else 0
        return self._collect(builder, gen)

    def _collect(self, builder, gen: int):
        r, pending, ready = self.r, self.pending[gen], self.ready[gen]
        while pending or ready:
            if ready:
                yield ready.pop()
                continue
            # Results the helpers left
            while (item := r.redis.lpop(r.key(f"done:{gen}"))) is not None:
                self._finished(item.decode())
            if ready:
                continue
            # A chunk of our own: of this stage or an earlier one still out; of a late stage only
            # when its results are wanted (the helpers run them meanwhile), and then only its own:
            # another late stage's chunk (the graph file's, 1 s on blender) would hold up this
            # one's results while the helpers have nothing to do
            task = r.claim(self.holder, late=False)
            if task is None and self.stages[gen][0] in stages.LATE_STAGES:
                task = r.claim_late(self.holder, [f"{gen}:{i}" for i in sorted(pending)])
            if task is not None:
                g, i = (int(x) for x in task.split(":"))
                stage, inputs = self.stages[g]
                with r.leased(task, self.holder):
                    result = stages.run_chunk(builder, stage, i, inputs)
                self.here[stage] = self.here.get(stage, 0) + 1
                if i in self.pending[g]:
                    self.pending[g].discard(i)
                    self.ready[g].append(result)
                continue
            # Every chunk is taken: put back those whose holder died, then wait for the others
            for i in sorted(pending):
                task = f"{gen}:{i}"
                lapsed = not r.redis.exists(r.key(f"lease:{task}"))
                if lapsed and r.redis.lpos(r.key(f"done:{gen}"), task) is None:
                    log.warning("chunk %s of run %s lost its worker: it is redone", task, r.run)
                    self.redone += 1
                    r.redis.rpush(r.key("todo"), task)
            item = r.redis.blpop([r.key(f"done:{gen}")], timeout=POLL_S)
            if item is not None:
                self._finished(item[1].decode())

    def _finished(self, task: str) -> None:
        """A helper's result, read into its stage's ready list (dropped if it came twice)."""
        g, i = (int(x) for x in task.split(":"))
        path = self.folder / f"{g}-{i}.npz"
        if i not in self.pending.get(g, ()):  # a chunk redone twice: its first result counted
            path.unlink(missing_ok=True)
            return
        with np.load(path) as z:
            result = tuple(z[f"a{k}"] for k in range(len(z.files)))
        path.unlink()
        self.pending[g].discard(i)
        self.ready[g].append(result)


def help_run(redis: Redis, run: str, make_builder, lease_s: float = LEASE_S) -> int:
    """A helper's loop: takes the run's tasks until the run ends; returns the chunks it ran.

    ``make_builder(spec)`` makes the :class:`~cloudgraph.build.GraphBuilder` of a run's spec
    (``scene``, ``quality``, ``params``: the coordinator's build parameters; ``graph``: whether
    the run builds a graph).
    """
    r, holder = _Run(redis, run, lease_s), holder_name()
    done, busy, t_start = 0, 0.0, time.perf_counter()
    raw = redis.get(r.key("spec"))
    if raw is None:  # the run ended before this helper started
        return 0
    # The builder is made before the first task: while the coordinator puts out its first stage
    builder = make_builder(json.loads(raw))
    while (raw := redis.get(r.key("spec"))) is not None:
        task = r.claim(holder)
        if task is None:
            time.sleep(POLL_S)
            continue
        spec = json.loads(raw)
        gen, i = (int(x) for x in task.split(":"))
        stage = json.loads(redis.get(r.key(f"stage:{gen}")) or "null")
        if stage is None:  # the run ended between the claim and now
            break
        folder = Path(spec["dir"])
        t0 = time.perf_counter()
        with r.leased(task, holder):
            result = stages.run_chunk(builder, stage["stage"], i, _inputs(folder, gen, stage["inputs"]))
            try:
                _write(folder / f"{gen}-{i}.npz", np.savez, **{f"a{k}": a for k, a in enumerate(result)})
            except FileNotFoundError:  # the run ended (its folder went) while this chunk ran
                break
            r.done(gen, task)
        done, busy = done + 1, busy + time.perf_counter() - t0
    log.info("run %s: ran %d chunks, busy %.1f s of %.1f s", run, done, busy, time.perf_counter() - t_start)
    return done
