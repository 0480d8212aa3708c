"""One worker process: an RQ worker that runs jobs in-process (warm caches and compiled kernels
stay between jobs) and tells its supervisor which job it runs and until when.

Started, watched and restarted by the supervisor (``python -m worker``, see ``__main__.py``).
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import signal
import threading
import time

from redis import Redis
from rq import Queue, SimpleWorker
from rq.job import JobStatus
from rq.timeouts import JobTimeoutException

from cloudgraph_service.errors import public_message
from cloudgraph_service.protocol import HEARTBEAT_GRACE_S, cancel_key, end_dependents
from cloudgraph_service.settings import Settings

log = logging.getLogger("cloudgraph.worker")


class Running:
    """What the worker process runs, shared with its supervisor: the job id and its deadline
    (Unix time; 0 when idle). Plain shared memory, so the supervisor reads it even while the
    job holds this process's interpreter in native code."""

    def __init__(self, ctx):
        self.job_id = ctx.Array("c", 128, lock=False)
        self.deadline = ctx.Value("d", 0.0, lock=False)
        self.budget = ctx.Value("d", 0.0, lock=False)

    def start(self, job_id: str, budget: float) -> None:
        self.job_id.value = job_id.encode()[:127]
        self.budget.value = budget
        self.deadline.value = time.time() + budget

    def clear(self) -> None:
        self.deadline.value = 0.0
        self.job_id.value = b""

    def current(self) -> tuple[str, float, float]:
        """(job id, deadline, budget); the id is empty when idle."""
        return self.job_id.value.decode(), self.deadline.value, self.budget.value


class CloudgraphWorker(SimpleWorker):
    """Runs jobs in this process and keeps a short heartbeat from a thread while a job runs, so
    that a killed worker's job is found abandoned within seconds. Errors become public messages
    in the job's meta and are never retried: they would repeat."""

    heartbeat_s = 30
    running: Running | None = None

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
        self.set_state("idle")

    def handle_exception(self, job, *exc_info):
        """Logs the whole error under the job id; the job's meta gets what a client may read."""
        err = exc_info[1]
        if self.connection.exists(cancel_key(job.id)):
            message = "cancelled by a client"
        elif isinstance(err, JobTimeoutException):
            message = f"stopped: it ran past its time budget of {job.timeout} s"
        else:
            message = public_message(err, job.id)
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
    """Linux: this process gets SIGKILL when its supervisor dies, so no worker is left orphaned."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def run(running: Running, name: str) -> None:
    """The worker process's entry point: sets the Mitsuba variant, then works the queue."""
    _die_with_parent()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    settings = Settings.from_env()
    from cloudgraph.mitsuba_scene import set_variant

    variant = set_variant()
    if settings.WORKER_THREADS > 0:
        import drjit as dr

        dr.set_thread_count(settings.WORKER_THREADS)
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
    conn = Redis.from_url(settings.REDIS_URL)
    CloudgraphWorker.heartbeat_s = settings.HEARTBEAT_S
    CloudgraphWorker.running = running
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
