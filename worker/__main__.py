"""``python -m worker``: an RQ worker that runs jobs in-process and keeps its caches warm."""

from __future__ import annotations

import logging
import threading

from redis import Redis
from rq import Queue, SimpleWorker
from rq.job import JobStatus

from server.settings import Settings

from .jobs import cancel_key, end_dependents

log = logging.getLogger("cloudgraph.worker")


class CloudgraphWorker(SimpleWorker):
    """Runs jobs in this process (no fork per job: warm caches and compiled kernels stay) and
    keeps a short heartbeat from a thread while a job runs, so that a killed worker's job is
    found abandoned within seconds and retried by another worker."""

    heartbeat_s = 30

    def get_heartbeat_ttl(self, job, working_time: float = 0.0) -> int:
        return self.heartbeat_s + 15

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
        try:
            self.perform_job(job, queue, execution)
        finally:
            stop.set()
            t.join()
        self.set_state("idle")

    def handle_job_failure(self, job, queue, started_job_registry=None, exc_string="", execution=None):
        """A job that a client cancelled ends as stopped (the API says canceled), never retried:
        RQ would otherwise retry its JobCancelled like any other error."""
        cancelled = bool(self.connection.exists(cancel_key(job.id)))
        if cancelled:
            self._stopped_job_id = job.id
        super().handle_job_failure(
            job, queue, started_job_registry=started_job_registry, exc_string=exc_string, execution=execution
        )
        try:
            if job.get_status() in (JobStatus.FAILED, JobStatus.STOPPED):  # not retried: the end
                lines = [ln for ln in exc_string.strip().splitlines() if ln.strip()] or ["an error"]
                why = "was cancelled" if cancelled else f"failed: {lines[-1]}"
                end_dependents(job, f"it waited on job {job.id}, which {why}", failed=not cancelled)
        except Exception:  # never let this end the worker's loop
            log.exception("could not end the jobs waiting on %s", job.id)


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    settings = Settings.from_env()
    from cloudgraph.mitsuba_scene import set_variant

    variant = set_variant()
    import cloudgraph.integrators.graph  # noqa: F401  (registers the integrator for this variant)

    log.info("worker: variant %s, data %s, redis %s", variant, settings.DATA_DIR, settings.REDIS_URL)
    conn = Redis.from_url(settings.REDIS_URL)
    CloudgraphWorker.heartbeat_s = settings.HEARTBEAT_S
    # A short worker_ttl makes the blocking dequeue return often, so that maintenance (which
    # retries the jobs of dead workers) runs every HEARTBEAT_S seconds, not every 7 minutes.
    worker = CloudgraphWorker(
        [Queue(settings.QUEUE, connection=conn)],
        connection=conn,
        worker_ttl=settings.HEARTBEAT_S + 15,
        maintenance_interval=settings.HEARTBEAT_S,
    )
    worker.work(with_scheduler=False)


if __name__ == "__main__":
    main()
