"""/v1/caches: start or find the precompute of a radiance cache (idempotent)."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException
from fastapi.responses import JSONResponse
from rq.job import Job

from worker.jobs import cancel_key

from ..deps import QueueDep, RedisDep, SettingsDep, VolumesDep
from ..jobs import cache_id, check_capacity, describe, enqueue, fetch, status_of
from ..schemas import CacheCreate, JobStatus

router = APIRouter(prefix="/caches", tags=["caches"])


def ensure_cache(body: CacheCreate, redis, queue, settings, volumes) -> tuple[str, Job]:
    """The precompute job of a cache, enqueued once: an existing live or finished job is reused."""
    if body.volume.id is None:
        raise HTTPException(422, "volume.id is required: upload the volume with POST /v1/volumes first")
    if volumes.info(body.volume.id) is None:
        raise HTTPException(404, f"no volume with id {body.volume.id!r}; upload it with POST /v1/volumes")
    cid = cache_id(
        body.volume.model_dump(),
        body.medium.model_dump(),
        body.light.model_dump(),
        body.max_depth,
        body.quality,
    )
    job_id = f"cache-{cid}"
    # One request at a time per cache: two at once would both enqueue it, and it would run twice.
    with redis.lock(f"cloudgraph:lock:{job_id}", timeout=30, blocking_timeout=30):
        job = fetch(redis, job_id)
        if job is not None and status_of(job) not in (JobStatus.failed, JobStatus.canceled):
            return cid, job
        if job is not None:  # failed or cancelled: start afresh, without the old cancel flag
            job.delete()
            redis.delete(cancel_key(job.id))
        check_capacity(queue, settings)
        scene = {
            "volume": body.volume.model_dump(),
            "medium": body.medium.model_dump(),
            "light": body.light.model_dump(),
            "camera": {"eye": [0, 0, 1], "target": [0, 0, 0]},
            "render": {"max_depth": body.max_depth},
        }
        job = enqueue(
            queue,
            settings,
            "worker.jobs.precompute_job",
            scene,
            body.quality,
            job_id=job_id,
            kind="precompute",
            meta={"result_url": f"/v1/caches/{cid}"},
        )
    return cid, job


def cache_body(cid: str, job: Job) -> dict:
    d = describe(job)
    return {
        "id": cid,
        "status": d.status,
        "stage": d.stage,
        "fraction": d.fraction,
        "job": f"/v1/jobs/{job.id}",
        "keys": (d.result or {}).get("keys"),
        "stats": (d.result or {}).get("stats"),
        "error": d.error,
    }


@router.post("")
def create_cache(
    body: CacheCreate, redis: RedisDep, queue: QueueDep, settings: SettingsDep, volumes: VolumesDep
):
    """Starts, or finds, the precompute for this (volume, medium, light, depth, quality)."""
    cid, job = ensure_cache(body, redis, queue, settings, volumes)
    out = cache_body(cid, job)
    if out["status"] == JobStatus.finished:
        return JSONResponse(out, status_code=200)
    return JSONResponse(out, status_code=202, headers={"Location": f"/v1/jobs/{job.id}"})


@router.get("/{cid}")
def get_cache(cid: str, redis: RedisDep) -> dict:
    job = fetch(redis, f"cache-{cid}")
    if job is None:
        raise HTTPException(404, f"no cache with id {cid!r}; start one with POST /v1/caches")
    return cache_body(cid, job)
