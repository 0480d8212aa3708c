"""Enqueueing and describing jobs: ids, limits, retries, cancellation, status for clients."""

from __future__ import annotations

import hashlib
import json
import time
from datetime import UTC, datetime
from pathlib import Path

from fastapi import HTTPException
from redis import Redis
from rq import Queue, Retry, Worker
from rq.job import Job
from rq.job import JobStatus as RQStatus

from cloudgraph_service.protocol import (
    CANCEL_TTL_S,
    FRAME_GLOB,
    HEARTBEAT_GRACE_S,
    RESULT_TTL_S,
    JobPayload,
    cancel_key,
    end_dependents,
    end_if_orphaned,
    enqueue_payload,
)
from cloudgraph_service.protocol import fetch as fetch  # re-exported for the routes
from cloudgraph_service.settings import Settings

from .schemas import JobPublic, JobStatus

_STATUS = {
    RQStatus.QUEUED: JobStatus.queued,
    RQStatus.SCHEDULED: JobStatus.queued,
    RQStatus.DEFERRED: JobStatus.waiting,
    RQStatus.STARTED: JobStatus.running,
    RQStatus.FINISHED: JobStatus.finished,
    RQStatus.FAILED: JobStatus.failed,
    RQStatus.STOPPED: JobStatus.canceled,
    RQStatus.CANCELED: JobStatus.canceled,
}


def cache_id(volume: dict, medium: dict, light: dict, max_depth: int, quality: str) -> str:
    """Id of a radiance cache request: what the cache depends on, canonically hashed."""
    text = json.dumps(
        {
            "v": 1,
            "volume": volume,
            "medium": medium,
            "light": light,
            "max_depth": max_depth,
            "quality": quality,
        },
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def check_capacity(queue: Queue, settings: Settings, extra: int = 1) -> None:
    """429 with Retry-After when the queue is full."""
    waiting = queue.count + queue.deferred_job_registry.count
    if waiting + extra > settings.MAX_QUEUED:
        raise HTTPException(
            429,
            f"the render queue is full ({waiting} jobs waiting); try again shortly",
            headers={"Retry-After": "10"},
        )


def enqueue(
    queue: Queue,
    settings: Settings,
    payload: JobPayload,
    *,
    job_id: str | None = None,
    kind: str,
    depends_on=None,
    meta: dict | None = None,
    at_front: bool = False,
) -> Job:
    """Enqueues ``payload``'s job function (its arguments by name) with the service's budget;
    ``meta`` describes the job to clients.

    ``retry`` counts the reruns a job gets when its worker dies under it; a job that fails with
    an error is never rerun (the worker sets its retries to 0: the error would repeat). A job
    enqueued after what it waits on has already failed is ended at once.
    """
    job = enqueue_payload(
        queue,
        payload,
        job_id=job_id,
        depends_on=depends_on,
        at_front=at_front,
        job_timeout=settings.JOB_TIMEOUT_S,
        retry=Retry(max=settings.JOB_RETRIES) if settings.JOB_RETRIES > 0 else None,
        result_ttl=RESULT_TTL_S,
        failure_ttl=RESULT_TTL_S,
        meta={"kind": kind, "stage": "queued", "fraction": 0.0, **(meta or {})},
    )
    if depends_on is not None:
        end_if_orphaned(job)
    return job


def radiance_key_of(job: Job) -> str | None:
    """The radiance cache key a finished precompute job found or built (None if it has none)."""
    return ((job.return_value() or {}).get("keys") or {}).get("radiance_key")


def status_of(job: Job) -> JobStatus:
    if job.meta.get("canceled"):
        return JobStatus.canceled
    if job.meta.get("failed"):  # what it waited on failed (protocol.end_dependents)
        return JobStatus.failed
    return _STATUS.get(job.get_status(refresh=False), JobStatus.queued)


def describe(job: Job) -> JobPublic:
    """What a client sees of a job (``result_url`` when finished). Errors come from the job's
    meta, written for people; never from RQ's traceback."""
    job.refresh()
    if job.get_status(refresh=False) == RQStatus.DEFERRED and end_if_orphaned(job):
        job.refresh()
    st = status_of(job)
    meta = job.meta
    error = meta.get("error")
    if st == JobStatus.canceled and not error:  # cancelled while queued: no worker said so
        error = "cancelled by a client"
    if st == JobStatus.failed and not error:  # e.g. found abandoned by RQ: no message of ours
        error = f"job {job.id} failed; the service log has the details under that id"
    fraction = float(meta.get("fraction", 0.0))
    result = job.return_value() if st == JobStatus.finished else None
    if st == JobStatus.finished:
        fraction = 1.0
    elif meta.get("kind") == "animation":
        fraction = max(fraction, animation_fraction(job))
    created = job.created_at.timestamp() if job.created_at else None
    return JobPublic(
        id=job.id,
        kind=meta.get("kind", "job"),
        status=st,
        stage=meta.get("stage"),
        fraction=fraction,
        result_url=meta.get("result_url") if st == JobStatus.finished else None,
        result=_public_result(result),
        error=error if st in (JobStatus.failed, JobStatus.canceled) else None,
        created_at=created,
    )


def animation_fraction(job: Job) -> float:
    """Frames done over frames asked for, 90 % of the job; encoding is the rest."""
    out, n = Path(job.meta.get("out_dir", "")), int(job.meta.get("frames", 1))
    done = len(list(out.glob(FRAME_GLOB))) if out.is_dir() else 0
    return 0.9 * done / max(n, 1)


def _public_result(result):
    if not isinstance(result, dict):
        return None
    return {k: v for k, v in result.items() if k not in ("path", "video")}


def cancel(redis: Redis, job: Job) -> None:
    """Cancels a job and its children: queued ones leave the queue, running ones stop at their
    next progress report (the flag is checked there)."""
    ids = [job.id, *job.meta.get("children", [])]
    for jid in ids:
        j = fetch(redis, jid)
        if j is None:
            continue
        redis.set(cancel_key(jid), 1, ex=CANCEL_TTL_S)
        j.meta["canceled"] = True
        j.save_meta()
        if j.get_status() in (RQStatus.QUEUED, RQStatus.DEFERRED, RQStatus.SCHEDULED):
            try:
                j.cancel()
            except Exception:  # already picked up: the flag stops it
                pass
            else:  # a running one's are ended by its worker
                end_dependents(j, f"it waited on job {jid}, which was cancelled", failed=False)


def worker_health(queue: Queue, settings: Settings) -> tuple[int, int]:
    """(live, stuck): workers that have beaten within HEARTBEAT_S + grace, and those of them
    whose job has run past its budget (its supervisor kills it KILL_GRACE_S later).

    RQ's worker registry keeps a killed worker until another worker's maintenance removes it, so
    liveness is judged by the heartbeat's age, not by registration.
    """
    limit = settings.HEARTBEAT_S + HEARTBEAT_GRACE_S
    now = datetime.now(UTC)
    live = [
        w
        for w in Worker.all(queue=queue)
        if w.last_heartbeat is not None and (now - w.last_heartbeat).total_seconds() < limit
    ]
    stuck = set()
    for jid in queue.started_job_registry.get_job_ids(cleanup=False):
        job = fetch(queue.connection, jid)
        if job is None or job.started_at is None:
            continue
        ran = (now - job.started_at.replace(tzinfo=UTC)).total_seconds()
        if ran > (job.timeout or settings.JOB_TIMEOUT_S):
            stuck.add(job.worker_name)
    return len(live), sum(1 for w in live if w.name in stuck)


#: await_job waits on the job's result stream, where RQ writes a job's result (or its failure) as
#: it ends, at most WAIT_SLICE_MS at a time before it looks at the job again (a job cancelled or
#: lost writes none) and at the client. It polled before, every 5 ms growing to 50: a warm re-mix
#: (the worker's render 31 ms) was seen ending up to 12 ms late.
WAIT_SLICE_MS = 100
#: The statuses a job ends in.
TERMINAL = (JobStatus.finished, JobStatus.failed, JobStatus.canceled)


async def await_job(job: Job, timeout: float, request) -> JobStatus:
    """Waits until a job ends or ``timeout`` passes. If the client goes away meanwhile, the job
    is cancelled: a viewer that moved on does not leave stale renders in the queue."""
    from fastapi.concurrency import run_in_threadpool
    from rq.results import Result

    end = time.monotonic() + timeout
    stream, seen = Result.get_key(job.id), "0-0"  # (results after ``seen``: a retry writes more)
    while True:
        await run_in_threadpool(job.refresh)
        st = status_of(job)
        if st in TERMINAL or time.monotonic() > end:
            return st
        if await request.is_disconnected():
            await run_in_threadpool(cancel, job.connection, job)
            return JobStatus.canceled
        block = max(1, min(WAIT_SLICE_MS, int(1000 * (end - time.monotonic()))))
        entries = await run_in_threadpool(job.connection.xread, {stream: seen}, count=1, block=block)
        if entries:  # a result, written with the job's status in one transaction (or a retry's)
            seen = entries[0][1][-1][0]
