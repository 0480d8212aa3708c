"""``python -m worker``: a supervisor that keeps one worker process running and holds every job
to its budget.

The worker process runs jobs in-process, so its caches and compiled kernels stay warm. Native
code (a Dr.Jit kernel, a long sparse product) cannot be interrupted from inside, so this
supervisor watches from outside: a job still running ``KILL_GRACE_S`` past its budget has its
worker process killed, and is failed for good (no restart brings it back); so has a job still
running ``CANCEL_GRACE_S`` after a client cancelled it (it ends canceled); a worker process that
dies on its own has its job put back, up to ``JOB_RETRIES`` times. Either way a fresh worker
process then takes the next job. SIGTERM or SIGINT stops both.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import socket
import time
import uuid

from redis import Redis
from rq import Queue, Worker

from cloudgraph_service.protocol import (
    CANCEL_GRACE_S,
    KILL_GRACE_S,
    cancel_key,
    fail_for_good,
    fetch,
    requeue_after_death,
    sweep_deferred,
)
from cloudgraph_service.settings import Settings

from .process import Running, run

log = logging.getLogger("cloudgraph.supervisor")
POLL_S = 0.25
SWEEP_S = 5.0


class Supervisor:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.ctx = mp.get_context("spawn")  # a fresh interpreter: Mitsuba is loaded there only
        self.redis = Redis.from_url(settings.REDIS_URL)
        self.queue = Queue(settings.QUEUE, connection=self.redis)
        self.running = Running(self.ctx)
        self.child = None
        self.name = ""
        self.stopping = False
        self.cancelled: tuple[str, float] | None = None  # (job id, when its cancel was first seen)

    def start_child(self) -> None:
        self.running.clear()
        self.name = name = f"{socket.gethostname()}.{os.getpid()}.{uuid.uuid4().hex[:6]}"
        self.child = self.ctx.Process(target=run, args=(self.running, name), name="cloudgraph-worker")
        self.child.start()
        log.info("worker process %s started (%s)", self.child.pid, name)

    def stop(self, *_):
        self.stopping = True

    def kill_child(self) -> None:
        self.child.kill()
        self.child.join(10)
        self.forget_child()

    def forget_child(self) -> None:
        """Takes a dead worker process out of RQ's registry at once (else it would look alive
        until its heartbeat expired)."""
        try:
            worker = Worker.find_by_key(
                Worker.redis_worker_namespace_prefix + self.name, connection=self.redis
            )
            if worker is not None:
                worker.register_death()
        except Exception:
            log.exception("could not unregister worker %s", self.name)

    def check(self) -> None:
        """One look at the worker process: past its budget, or dead."""
        job_id, deadline, budget = self.running.current()
        if not self.child.is_alive():
            code = self.child.exitcode
            if job_id:
                log.error("worker process %s died (exit %s) running job %s", self.child.pid, code, job_id)
                job = fetch(self.redis, job_id)
                if job is not None and requeue_after_death(job):
                    log.info("job %s put back in the queue (%s retries left)", job_id, job.retries_left)
            else:
                log.error("worker process %s ended (exit %s)", self.child.pid, code)
            self.forget_child()
            self.start_child()
            return
        if job_id and self.redis.exists(cancel_key(job_id)):
            if self.cancelled is None or self.cancelled[0] != job_id:
                self.cancelled = (job_id, time.monotonic())
            elif time.monotonic() - self.cancelled[1] > CANCEL_GRACE_S:
                log.error("job %s was cancelled %d s ago and still runs: killing worker process %s",
                          job_id, CANCEL_GRACE_S, self.child.pid)  # fmt: skip
                self.kill_child()
                job = fetch(self.redis, job_id)
                if job is not None:
                    fail_for_good(job, "cancelled by a client", cancelled=True)
                self.start_child()
                return
        if job_id and deadline and time.time() > deadline + KILL_GRACE_S:
            log.error(
                "job %s ran past its budget of %.0f s: killing worker process %s",
                job_id,
                budget,
                self.child.pid,
            )
            self.kill_child()
            job = fetch(self.redis, job_id)
            if job is not None:
                fail_for_good(job, f"stopped: it ran past its time budget of {budget:.0f} s")
            self.start_child()

    def loop(self) -> None:
        signal.signal(signal.SIGTERM, self.stop)
        signal.signal(signal.SIGINT, self.stop)
        self.start_child()
        last_sweep = 0.0
        try:
            while not self.stopping:
                try:
                    self.check()
                    if time.monotonic() - last_sweep > SWEEP_S:
                        last_sweep = time.monotonic()
                        sweep_deferred(self.queue)
                except Exception:  # Redis away for a moment: look again at the next poll
                    log.exception("supervisor check failed")
                time.sleep(POLL_S)
        finally:
            if self.child is not None and self.child.is_alive():
                self.child.terminate()  # RQ's warm shutdown: the current job is put back
                self.child.join(10)
                if self.child.is_alive():
                    self.kill_child()


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        settings = Settings.from_env()
    except ValueError as err:  # one line, not a traceback: what to set, and why
        raise SystemExit(f"cloudgraph worker: {err}") from None
    Supervisor(settings).loop()


if __name__ == "__main__":
    main()
