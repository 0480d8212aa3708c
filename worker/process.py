"""One worker process: an RQ worker that runs jobs in-process (warm caches and compiled kernels
stay between jobs) and tells its supervisor which job it runs, until when, and when its job
function has returned.

Redis may go away under it (restarted, killed): every Redis command of this process then waits
for Redis to answer again (:class:`WaitForRedis`), so a job in hand is neither failed nor
dropped, and its result is stored once Redis is back. Started, watched and restarted by the
supervisor (``python -m worker``, see ``__main__.py``).
"""

from __future__ import annotations

import contextlib
import ctypes
import faulthandler
import logging
import multiprocessing
import os
import signal
import threading
import time
from pathlib import Path

from redis import Redis
from redis.backoff import AbstractBackoff
from redis.retry import Retry
from rq import Queue, SimpleWorker
from rq.job import JobStatus
from rq.timeouts import JobTimeoutException, UnixSignalDeathPenalty

from cloudgraph.heap import keep_freed_memory, release_freed_memory
from cloudgraph_service.errors import public_message
from cloudgraph_service.protocol import HEARTBEAT_GRACE_S, cancel_key, end_dependents
from cloudgraph_service.settings import Settings

log = logging.getLogger("cloudgraph.worker")
#: Longest wait between two tries to reach Redis: a Redis that is back is used within this.
REDIS_RETRY_MAX_S = 1.0


class Running:
    """What the worker process runs, shared with its supervisor: the job id, its deadline (Unix
    time; 0 when idle) and whether its job function has returned (what is left is storing the
    result or the error). Plain shared memory, so the supervisor reads it even while the job
    holds this process's interpreter in native code."""

    def __init__(self, ctx):
        self.job_id = ctx.Array("c", 128, lock=False)
        self.deadline = ctx.Value("d", 0.0, lock=False)
        self.budget = ctx.Value("d", 0.0, lock=False)
        self.returned = ctx.Value("b", 0, lock=False)

    def start(self, job_id: str, budget: float) -> None:
        self.returned.value = 0
        self.job_id.value = job_id.encode()[:127]
        self.budget.value = budget
        self.deadline.value = time.time() + budget

    def clear(self) -> None:
        self.deadline.value = 0.0
        self.job_id.value = b""
        self.returned.value = 0

    def current(self) -> tuple[str, float, float]:
        """(job id, deadline, budget); the id is empty when idle."""
        return self.job_id.value.decode(), self.deadline.value, self.budget.value


class WaitForRedis(AbstractBackoff):
    """The worker process's way through a Redis outage: every command is tried again until Redis
    answers, waiting twice as long each time up to ``REDIS_RETRY_MAX_S``. An outage is logged
    once when it starts and once when it ends; meanwhile :attr:`away` is true (a job's progress
    reports are skipped: nothing could read them). One state for every connection of the
    process (connections copy their retry policy: this object is shared, not copied)."""

    def __init__(self):
        self.since: float | None = None  # monotonic time of the outage's first failure
        self._lock = threading.Lock()

    def __deepcopy__(self, memo):
        return self

    @property
    def away(self) -> bool:
        return self.since is not None

    def reset(self) -> None:
        pass

    def compute(self, failures: int) -> float:
        with self._lock:
            if self.since is None:
                self.since = time.monotonic()
                log.warning("redis is not reachable: waiting for it (a job in hand is kept)")
        return min(REDIS_RETRY_MAX_S, 0.05 * 2**failures)

    def answered(self) -> None:
        """Redis answered a command: the end of an outage, if there was one."""
        if self.since is not None:
            with self._lock:
                if self.since is not None:
                    log.info("redis is back after %.1f s", time.monotonic() - self.since)
                    self.since = None


class PatientRedis(Redis):
    """A Redis client whose commands wait for Redis through an outage (:class:`WaitForRedis`)."""

    wait: WaitForRedis

    @classmethod
    def connect(cls, url: str) -> PatientRedis:
        wait = WaitForRedis()
        client = cls.from_url(url, retry=Retry(wait, -1))  # -1: tried until Redis answers
        client.wait = wait
        return client

    @property
    def away(self) -> bool:
        """Redis did not answer the last try (a job skips its progress reports meanwhile)."""
        return self.wait.away

    def execute_command(self, *args, **options):
        result = super().execute_command(*args, **options)
        self.wait.answered()
        return result


class JobFunctionBudget(UnixSignalDeathPenalty):
    """RQ's time budget around the job function, which also tells the supervisor when the
    function has returned or raised: storing its result or error is not to be cut short by a
    cancel (the supervisor's ``CANCEL_KILL_S``)."""

    running: Running | None = None

    def __exit__(self, *exc_info):
        if self.running is not None and self.running.job_id.value:
            self.running.returned.value = 1
        return super().__exit__(*exc_info)


class CloudgraphWorker(SimpleWorker):
    """Runs jobs in this process and keeps a short heartbeat from a thread while a job runs, so
    that a killed worker's job is found abandoned within seconds. Errors become public messages
    in the job's meta and are never retried: they would repeat."""

    heartbeat_s = 30
    running: Running | None = None
    death_penalty_class = JobFunctionBudget
    volumes: dict[str, Path] | None = None  # the folders jobs write, by the name errors give them

    def get_heartbeat_ttl(self, job, working_time: float = 0.0) -> int:
        return self.heartbeat_s + HEARTBEAT_GRACE_S

    def execute_job(self, job, queue):
        execution = self.prepare_execution(job)
        stop = threading.Event()

        def beat():
            while not stop.wait(self.heartbeat_s / 3):
                try:
                    self.maintain_heartbeats(job, execution)
                except Exception:  # a missed beat is retried at the next one
                    log.exception("heartbeat failed")

        t = threading.Thread(target=beat, daemon=True)
        t.start()
        if self.running is not None:
            self.running.start(job.id, float(job.timeout or 0) or 3600.0)
        try:
            self.perform_job(job, queue, execution)
        finally:
            if self.running is not None:
                self.running.clear()
            stop.set()
            t.join()
            release_freed_memory()  # (kept for reuse within the job: cloudgraph/heap.py)
        self.set_state("idle")

    def handle_exception(self, job, *exc_info):
        """Logs the whole error under the job id; the job's meta gets what a client may read."""
        err = exc_info[1]
        if self.connection.exists(cancel_key(job.id)):
            message = "cancelled by a client"
        elif isinstance(err, JobTimeoutException):
            message = f"stopped: it ran past its time budget of {job.timeout} s"
        else:
            message = public_message(err, job.id, self.volumes)
        if message == "cancelled by a client":  # no traceback: nothing went wrong
            log.info("job %s stopped: cancelled by a client", job.id)
        else:
            log.error("job %s failed", job.id, exc_info=exc_info)
        try:
            job.get_meta(refresh=True)
            job.meta["error"] = message
            job.save_meta()
        except Exception:  # the failure itself is still recorded by handle_job_failure
            log.exception("could not record the error of job %s", job.id)
        job.retries_left = 0  # an error is not a worker's death: running it again would repeat it
        return super().handle_exception(job, *exc_info)

    def handle_job_failure(self, job, queue, started_job_registry=None, exc_string="", execution=None):
        """A job that a client cancelled ends as stopped (the API says canceled); a failed one
        ends the jobs that wait on it."""
        cancelled = bool(self.connection.exists(cancel_key(job.id)))
        if cancelled:
            self._stopped_job_id = job.id
        super().handle_job_failure(
            job, queue, started_job_registry=started_job_registry, exc_string=exc_string, execution=execution
        )
        try:
            if job.get_status() in (JobStatus.FAILED, JobStatus.STOPPED):
                why = "was cancelled" if cancelled else f"failed: {job.meta.get('error', 'an error')}"
                end_dependents(job, f"it waited on job {job.id}, which {why}", failed=not cancelled)
        except Exception:  # never let this end the worker's loop
            log.exception("could not end the jobs waiting on %s", job.id)


def _die_with_parent() -> None:
    """Linux: this process gets SIGKILL when its supervisor dies, so no worker is left orphaned
    (and it ends at once if the supervisor died before it could ask for that)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    parent = multiprocessing.parent_process()
    if parent is not None and os.getppid() != parent.pid:
        os._exit(1)


def run(running: Running, name: str) -> None:
    """The worker process's entry point: sets the Mitsuba variant, then works the queue."""
    _die_with_parent()
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # every thread's stack into the log
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    settings = Settings.from_env()
    keep_freed_memory()
    from cloudgraph.mitsuba_scene import set_threads, set_variant

    variant = set_variant()
    set_threads(settings.WORKER_THREADS)
    import cloudgraph.integrators.graph  # noqa: F401  (registers the integrator for this variant)

    # What jobs import (the engine's stages, scipy, OpenVDB, Dask's client where a cluster is
    # set), now: a second or so that every first job of a process would wait for
    import cloudgraph.precompute  # noqa: F401

    if settings.DASK_SCHEDULER:
        import cloudgraph_service.dask_chunks  # noqa: F401

    with contextlib.suppress(ImportError):  # without it, jobs that read .vdb files say so
        import pyopenvdb  # noqa: F401

    log.info("worker %s: variant %s, data %s, redis %s, dask %s", name, variant, settings.DATA_DIR,
             settings.REDIS_URL, settings.DASK_SCHEDULER or "none: precomputes run here")  # fmt: skip
    conn = PatientRedis.connect(settings.REDIS_URL)
    CloudgraphWorker.heartbeat_s = settings.HEARTBEAT_S
    CloudgraphWorker.running = JobFunctionBudget.running = running
    CloudgraphWorker.volumes = {"cache": settings.cache_dir, "outputs": settings.outputs_dir}
    # A short worker_ttl makes the blocking dequeue return often, so that maintenance (which
    # fails the jobs of dead workers) runs every HEARTBEAT_S seconds, not every 7 minutes.
    worker = CloudgraphWorker(
        [Queue(settings.QUEUE, connection=conn)],
        connection=conn,
        name=name,
        worker_ttl=settings.HEARTBEAT_S + HEARTBEAT_GRACE_S,
        maintenance_interval=settings.HEARTBEAT_S,
    )
    worker.work(with_scheduler=False)
