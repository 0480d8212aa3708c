"""``python -m worker``: an RQ worker that runs jobs in-process and keeps its caches warm."""

from __future__ import annotations

import logging
import threading

from redis import Redis
from rq import Queue, SimpleWorker

from server.settings import Settings

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
