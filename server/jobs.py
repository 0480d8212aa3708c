"""Enqueueing and describing jobs: ids, limits, retries, cancellation, status for clients."""

from __future__ import annotations

import asyncio
import hashlib
import json
import time

from fastapi import HTTPException
from redis import Redis
from rq import Queue, Retry
from rq.exceptions import NoSuchJobError
from rq.job import Job
from rq.job import JobStatus as RQStatus

from worker.jobs import cancel_key, end_dependents

from .schemas import JobPublic, JobStatus
from .settings import Settings

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
    func: str,
    *args,
    job_id: str | None = None,
    kind: str,
    depends_on=None,
    meta: dict | None = None,
    at_front: bool = False,
) -> Job:
    """Enqueues with the service's timeout and retries; ``meta`` describes the job to clients."""
    return queue.enqueue(
        func,
        *args,
        job_id=job_id,
        depends_on=depends_on,
        at_front=at_front,
        job_timeout=settings.JOB_TIMEOUT_S,
        retry=Retry(max=settings.JOB_RETRIES),
        result_ttl=7 * 24 * 3600,
        failure_ttl=7 * 24 * 3600,
        meta={"kind": kind, "stage": "queued", "fraction": 0.0, **(meta or {})},
    )


def fetch(redis: Redis, job_id: str) -> Job | None:
    try:
        return Job.fetch(job_id, connection=redis)
    except NoSuchJobError:
        return None


def status_of(job: Job) -> JobStatus:
    if job.meta.get("canceled"):
        return JobStatus.canceled
    if job.meta.get("failed"):  # what it waited on failed (worker.jobs.end_dependents)
        return JobStatus.failed
    return _STATUS.get(job.get_status(refresh=False), JobStatus.queued)


def describe(job: Job) -> JobPublic:
    """What a client sees of a job (``result_url`` when finished)."""
    job.refresh()
    st = status_of(job)
    meta = job.meta
    error = None
    if meta.get("error"):  # it waited on a job that failed or was cancelled
        error = meta["error"]
    elif st == JobStatus.failed:
        exc = job.latest_result().exc_string if job.latest_result() else (job.exc_info or "")
        error = _last_line(exc or "failed")
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
        error=error,
        created_at=created,
    )


def animation_fraction(job: Job) -> float:
    """Frames done over frames asked for, 90 % of the job; encoding is the rest."""
    from pathlib import Path

    out, n = Path(job.meta.get("out_dir", "")), int(job.meta.get("frames", 1))
    done = len(list(out.glob("frame_*.png"))) if out.is_dir() else 0
    return 0.9 * done / max(n, 1)


def _public_result(result):
    if not isinstance(result, dict):
        return None
    return {k: v for k, v in result.items() if k not in ("path", "video")}


def _last_line(text: str) -> str:
    lines = [ln for ln in str(text).strip().splitlines() if ln.strip()]
    return lines[-1] if lines else "failed"


def cancel(redis: Redis, job: Job) -> None:
    """Cancels a job and its children: queued ones leave the queue, running ones stop at their
    next progress report (the flag is checked there)."""
    ids = [job.id, *job.meta.get("children", [])]
    for jid in ids:
        j = fetch(redis, jid)
        if j is None:
            continue
        redis.set(cancel_key(jid), 1, ex=24 * 3600)
        j.meta["canceled"] = True
        j.save_meta()
        if j.get_status() in (RQStatus.QUEUED, RQStatus.DEFERRED, RQStatus.SCHEDULED):
            try:
                j.cancel()
            except Exception:  # already picked up: the flag stops it
                pass
            else:  # a running one's are ended by its worker
                end_dependents(j, f"it waited on job {jid}, which was cancelled", failed=False)


async def await_job(job: Job, timeout: float, request) -> JobStatus:
    """Polls a job until it ends or ``timeout`` passes. If the client goes away meanwhile, the job
    is cancelled: a viewer that moved on does not leave stale renders in the queue."""
    from fastapi.concurrency import run_in_threadpool

    end = time.monotonic() + timeout
    while True:
        await run_in_threadpool(job.refresh)
        st = status_of(job)
        if st in (JobStatus.finished, JobStatus.failed, JobStatus.canceled) or time.monotonic() > end:
            return st
        if await request.is_disconnected():
            await run_in_threadpool(cancel, job.connection, job)
            return JobStatus.canceled
        await asyncio.sleep(0.05)
