"""``python -m worker``: a supervisor that keeps one worker process running, holds every job to
its budget, and puts back the jobs of dead workers.

The worker process runs jobs in-process, so its caches and compiled kernels stay warm. Native
code (a Dr.Jit kernel, a long sparse product) cannot be interrupted from inside, so this
supervisor watches from outside: a job still running ``KILL_GRACE_S`` past its budget has its
worker process killed, and is failed for good (no restart brings it back); so has a job whose
function still runs ``CANCEL_KILL_S`` after the supervisor saw a client's cancel (it ends
canceled). A worker process that dies on its own has its job put back, up to ``JOB_RETRIES``
times. Either way the temporary files the dead process was writing are removed (those open at
the supervisor's last look, ``POLL_S`` before), and a fresh worker process takes the next job.
SIGTERM or SIGINT stops both.

Two faults leave a job held by a worker that no longer exists: a worker process killed with its
supervisor (SIGKILL, or its container), and one that died while Redis was away. Every
supervisor looks for such workers on its own host (same boot and PID namespace, their process
gone) when it starts, when Redis comes back and every ``SWEEP_S``, and puts their jobs back at
once (RQ would only once their heartbeat expired, ``HEARTBEAT_S`` + 15 s later).

While Redis is away the supervisor keeps watching its worker process (budgets need no Redis),
logs the outage once and its end once, and does what needed Redis when it is back; the worker
process waits for Redis with the job it holds (worker/process.py).
"""

from __future__ import annotations

import faulthandler
import logging
import multiprocessing as mp
import os
import signal
import socket
import time
import uuid
from collections.abc import Callable
from datetime import UTC
from pathlib import Path

from redis import Redis
from redis.backoff import NoBackoff
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import TimeoutError as RedisTimeoutError
from redis.retry import Retry
from rq import Queue, Worker
from rq.job import JobStatus

from cloudgraph.store import host_id, process_alive
from cloudgraph_service.protocol import (
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
POLL_S = 0.1
SWEEP_S = 5.0
#: A cancelled job whose function still runs this long after the supervisor saw the cancel is
#: stopped by force: cancels stop a job within a second, even in native code.
CANCEL_KILL_S = 0.5
#: Longest wait between two tries to reach Redis while it is away.
REDIS_RETRY_MAX_S = 1.0
#: A dead worker's jobs are put back once: the first supervisor to claim it does (a key that
#: expires, as every key of the service does).
REAPED_KEY = "cloudgraph:reaped:{}"
REAPED_TTL_S = 3600
REDIS_DOWN = (RedisConnectionError, RedisTimeoutError)


def open_temporaries(pid: int) -> list[Path]:
    """The temporary files (``*.tmp``, as files.py and the stores name them) that process
    ``pid`` has open: what it leaves behind if it is killed mid-write."""
    out = []
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return out
    for fd in fds:
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.endswith(".tmp") and target.startswith("/"):
            out.append(Path(target))
    return out


class Supervisor:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.ctx = mp.get_context("spawn")  # a fresh interpreter: Mitsuba is loaded there only
        # One try per command: an outage is handled here (catch_up), not by waiting in a command
        self.redis = Redis.from_url(
            settings.REDIS_URL, socket_timeout=5, socket_connect_timeout=2, retry=Retry(NoBackoff(), 0)
        )
        self.queue = Queue(settings.QUEUE, connection=self.redis)
        self.running = Running(self.ctx)
        self.child = None
        self.name = ""
        self.host = host_id()
        self.stopping = False
        self.cancelled: tuple[str, float] | None = None  # (job id, when its cancel was first seen)
        self.pending: list[tuple[str, Callable[[], None]]] = []  # what waits for Redis, in order
        self.away_since: float | None = None  # Redis did not answer since then
        self.retry_at, self.retry_s = 0.0, POLL_S
        self.last_sweep = float("-inf")
        self.writing: list[Path] = []  # temporary files the worker process had open at the last look

    # ------------------------------------------------------------------ the worker process
    def start_child(self) -> None:
        self.running.clear()
        self.writing = []
        self.name = name = f"{socket.gethostname()}.{self.host}.{os.getpid()}.{uuid.uuid4().hex[:6]}"
        self.child = self.ctx.Process(target=run, args=(self.running, name), name="cloudgraph-worker")
        self.child.start()
        log.info("worker process %s started (%s)", self.child.pid, name)

    def stop(self, *_):
        self.stopping = True

    def kill_child(self) -> str:
        """Kills the worker process, removes the temporary files it had open, and returns its
        worker name (to be reaped: :meth:`reap`)."""
        left = open_temporaries(self.child.pid)
        self.child.kill()
        self.child.join(10)
        for p in left:
            p.unlink(missing_ok=True)
        return self.name

    def check(self) -> None:
        """One look at the worker process: dead, past its budget, or cancelled and still running.
        Only the cancel needs Redis; what must be recorded there waits in ``pending``."""
        job_id, deadline, budget = self.running.current()
        if not self.child.is_alive():
            code, dead = self.child.exitcode, self.name
            if job_id:
                log.error("worker process %s died (exit %s) running job %s", self.child.pid, code, job_id)
            else:
                log.error("worker process %s ended (exit %s)", self.child.pid, code)
            for p in self.writing:  # what it was writing when last looked at, if not renamed since
                p.unlink(missing_ok=True)
            self.later(f"reap {dead}", lambda: self.reap(dead))
            self.start_child()
            return
        self.writing = open_temporaries(self.child.pid) if job_id else []
        if job_id and deadline and time.time() > deadline + KILL_GRACE_S:
            log.error("job %s ran past its budget of %.0f s: killing worker process %s",
                      job_id, budget, self.child.pid)  # fmt: skip
            dead = self.kill_child()
            why = f"stopped: it ran past its time budget of {budget:.0f} s"
            self.later(f"fail {job_id}", lambda: self.fail(job_id, why))
            self.later(f"reap {dead}", lambda: self.reap(dead))
            self.start_child()
            return
        if not job_id or self.running.returned.value or self.away_since is not None:
            return
        try:
            cancelled = self.redis.exists(cancel_key(job_id))
        except REDIS_DOWN as err:
            self.went_away(err)
            return
        if not cancelled:
            return
        if self.cancelled is None or self.cancelled[0] != job_id:
            self.cancelled = (job_id, time.monotonic())
        elif time.monotonic() - self.cancelled[1] > CANCEL_KILL_S:
            log.warning("job %s was cancelled and still runs: killing worker process %s",
                        job_id, self.child.pid)  # fmt: skip
            dead = self.kill_child()
            self.later(f"fail {job_id}", lambda: self.fail(job_id, "cancelled by a client", cancelled=True))
            self.later(f"reap {dead}", lambda: self.reap(dead))
            self.start_child()

    # ------------------------------------------------------------------------------- Redis
    def later(self, what: str, action: Callable[[], None]) -> None:
        """Does ``action`` (Redis writes) now if Redis answers, else once it is back, in order."""
        self.pending.append((what, action))
        self.catch_up()

    def went_away(self, err: Exception) -> None:
        now = time.monotonic()
        if self.away_since is None:
            log.warning("redis is not reachable (%s): waiting for it; the worker process keeps its job", err)
            self.away_since, self.retry_s = now, POLL_S
        self.retry_at = now + self.retry_s
        self.retry_s = min(REDIS_RETRY_MAX_S, 2 * self.retry_s)

    def catch_up(self) -> None:
        """What waits for Redis, when it answers: the pending actions, then (every ``SWEEP_S``,
        and at once when Redis is back) the dead workers of this host and the orphaned waits."""
        now = time.monotonic()
        if self.away_since is not None and now < self.retry_at:
            return
        try:
            if self.away_since is not None:
                self.redis.ping()
                log.info("redis is back after %.1f s", now - self.away_since)
                self.away_since, self.last_sweep = None, float("-inf")
            while self.pending:
                what, action = self.pending[0]
                try:
                    action()
                except REDIS_DOWN:
                    raise
                except Exception:  # a bug, not an outage: logged, not retried for ever
                    log.exception("supervisor: could not %s", what)
                self.pending.pop(0)
            if now - self.last_sweep > SWEEP_S:
                self.last_sweep = now
                self.reap_host()
                sweep_deferred(self.queue)
        except REDIS_DOWN as err:
            self.went_away(err)

    def fail(self, job_id: str, message: str, cancelled: bool = False) -> None:
        job = fetch(self.redis, job_id)
        if job is not None and job.get_status() == JobStatus.STARTED:
            fail_for_good(job, message, cancelled=cancelled)

    def reap(self, name: str) -> None:
        """Puts back the jobs that the dead worker ``name`` held (or fails them for good, out of
        retries) and takes it out of RQ's registry, so that ``/readyz`` no longer counts it.
        Once, by whichever supervisor claims it first (and again by that one, if Redis went
        away half-way)."""
        me, key = f"{self.host}.{os.getpid()}".encode(), REAPED_KEY.format(name)
        if not self.redis.set(key, me, nx=True, ex=REAPED_TTL_S) and self.redis.get(key) != me:
            return
        for jid in self.queue.started_job_registry.get_job_ids(cleanup=False):
            job = fetch(self.redis, jid)
            if job is None or job.worker_name != name or job.get_status() != JobStatus.STARTED:
                continue
            if requeue_after_death(job):
                log.info("job %s put back in the queue (%s retries left)", jid, job.retries_left)
            else:
                log.error("job %s failed for good: its worker died on every try", jid)
        worker = Worker.find_by_key(Worker.redis_worker_namespace_prefix + name, connection=self.redis)
        if worker is not None:
            worker.register_death()

    def reap_host(self) -> None:
        """Reaps this host's dead workers: their process is gone (a worker registers after its
        process starts, so one started later under the same id is another)."""
        for w in Worker.all(connection=self.redis):
            parts = w.name.rsplit(".", 3)
            if len(parts) != 4 or parts[1] != self.host or w.name == self.name:
                continue
            born = w.birth_date
            if born is not None and born.tzinfo is None:  # RQ's times are UTC
                born = born.replace(tzinfo=UTC)
            if not process_alive(w.pid, born.timestamp() if born else None):
                log.info("worker %s (process %s) is gone", w.name, w.pid)
                self.reap(w.name)

    # -------------------------------------------------------------------------------- loop
    def loop(self) -> None:
        signal.signal(signal.SIGTERM, self.stop)
        signal.signal(signal.SIGINT, self.stop)
        self.start_child()
        self.catch_up()  # the dead workers a killed predecessor left, at once
        try:
            while not self.stopping:
                self.check()
                self.catch_up()
                time.sleep(POLL_S)
        finally:
            if self.child is not None and self.child.is_alive():
                self.child.terminate()  # RQ's warm shutdown: the current job may end first
                self.child.join(10)
                if self.child.is_alive():
                    dead = self.kill_child()
                    self.pending.append((f"reap {dead}", lambda: self.reap(dead)))  # its job, back
            self.away_since, self.last_sweep = None, time.monotonic()  # one last try, no sweep
            self.catch_up()


def main() -> None:
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # every thread's stack into the log
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        settings = Settings.from_env()
    except ValueError as err:  # one line, not a traceback: what to set, and why
        raise SystemExit(f"cloudgraph worker: {err}") from None
    Supervisor(settings).loop()


if __name__ == "__main__":
    main()
