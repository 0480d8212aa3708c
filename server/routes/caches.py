"""/v1/caches: start or find the precompute of a radiance cache (idempotent); its radiance field."""

from __future__ import annotations

import re

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import FileResponse, JSONResponse, Response
from rq.job import Job

from cloudgraph.cache import CacheStore
from cloudgraph_service.errors import shown
from cloudgraph_service.protocol import LOCK_S, PrecomputeJob, cancel_key, lock_key

from ..deps import QueueDep, RedisDep, SettingsDep, VolumesDep
from ..errors import error_responses
from ..jobs import cache_id, check_capacity, describe, enqueue, fetch, status_of
from ..schemas import CacheCreate, CachePublic, JobStatus, binary
from ..validation import check_cache_parts

router = APIRouter(prefix="/caches", tags=["caches"])
CACHE_ID = re.compile(r"[0-9a-f]{32}")
#: A field is content-addressed by its radiance key: it never changes under its URL.
IMMUTABLE = "public, max-age=31536000, immutable"
FIELD_HEADERS = {
    "ETag": {"description": "the radiance key, quoted", "schema": {"type": "string"}},
    "Cache-Control": {"description": IMMUTABLE, "schema": {"type": "string"}},
}


def missing_files(job: Job, settings) -> list[str]:
    """The files that a finished precompute's cache lacks now (evicted or removed): some of
    ``graph``, ``radiance``, ``field``. A cache without them all is not finished."""
    keys = (job.return_value() or {}).get("keys") or {}
    if not keys.get("graph_key") or not keys.get("radiance_key"):
        return []
    store = CacheStore(settings.cache_dir)
    paths = {
        "graph": store.graph_path(keys["graph_key"]),
        "radiance": store.radiance_path(keys["radiance_key"]),
        "field": store.field_path(keys["radiance_key"]),
    }
    return [name for name, p in paths.items() if not p.is_file()]


def ensure_cache(body: CacheCreate, redis, queue, settings, volumes, prefix: str = "") -> tuple[str, Job]:
    """The precompute job of a cache, enqueued once: an existing live or finished job is reused,
    unless its cache has lost files since (then the precompute runs again, and makes only what
    is missing: a lost field is baked again from the graph and the radiance). ``prefix`` names
    the fields as the request has them (``scene.`` for renders)."""
    check_cache_parts(
        body.volume, body.medium, body.light, body.lights, body.max_depth, settings, volumes, prefix
    )
    cid = cache_id(
        body.volume.model_dump(), body.medium.model_dump(), body.light_id(), body.max_depth, body.quality
    )
    job_id = f"cache-{cid}"
    # One request at a time per cache: two at once would both enqueue it, and it would run twice.
    with redis.lock(lock_key(job_id), timeout=LOCK_S, blocking_timeout=LOCK_S):
        job = fetch(redis, job_id)
        st = status_of(job) if job is not None else None
        lost = missing_files(job, settings) if st == JobStatus.finished else []
        if job is not None and st not in (JobStatus.failed, JobStatus.canceled) and not lost:
            return cid, job
        if job is not None:  # failed, cancelled or incomplete: start afresh, no old cancel flag
            job.delete()
            redis.delete(cancel_key(job.id))
        check_capacity(queue, settings)
        scene = {
            "volume": body.volume.model_dump(mode="json"),
            "medium": body.medium.model_dump(mode="json"),
            **body.light_part(),
            "camera": {"eye": [0, 0, 1], "target": [0, 0, 0]},
            "render": {"max_depth": body.max_depth},
        }
        job = enqueue(
            queue,
            settings,
            PrecomputeJob(scene=scene, quality=body.quality),
            job_id=job_id,
            kind="precompute",
            meta={"result_url": f"/v1/caches/{cid}"},
        )
    return cid, job


def cache_body(cid: str, job: Job, settings) -> dict:
    d = describe(job)
    status, error = d.status, d.error
    lost = missing_files(job, settings) if status == JobStatus.finished else []
    if lost:  # not finished any more: asking for it again (POST) rebuilds what is missing
        status = JobStatus.failed
        error = (
            f"the {' and '.join(lost)} of cache {cid} {'is' if len(lost) == 1 else 'are'} gone "
            "(evicted or removed); ask for the cache again (POST /v1/caches) to rebuild"
        )
    return {
        "id": cid,
        "status": status,
        "stage": d.stage,
        "fraction": d.fraction,
        "job": f"/v1/jobs/{job.id}",
        "keys": (d.result or {}).get("keys"),
        "stats": (d.result or {}).get("stats"),
        "error": error,
    }


def _cache_job(redis, cid: str) -> Job:
    job = fetch(redis, f"cache-{cid}") if CACHE_ID.fullmatch(cid) else None
    if job is None:
        raise HTTPException(404, f"no cache with id {shown(cid)}; start one with POST /v1/caches")
    return job


@router.post(
    "",
    response_model=CachePublic,
    response_description="The cache is ready",
    responses={
        202: {
            "model": CachePublic,
            "description": "The precompute is queued or running",
            "headers": {"Location": {"description": "the precompute's URL", "schema": {"type": "string"}}},
        },
        **error_responses(400, 404, 413, 415, 422, 429, 503, about={404: "No volume with that id"}),
    },
)
def create_cache(
    body: CacheCreate, redis: RedisDep, queue: QueueDep, settings: SettingsDep, volumes: VolumesDep
):
    """Starts, or finds, the precompute for this (volume, medium, light, depth, quality)."""
    cid, job = ensure_cache(body, redis, queue, settings, volumes)
    out = cache_body(cid, job, settings)
    if out["status"] == JobStatus.finished:
        return JSONResponse(out, status_code=200)
    return JSONResponse(out, status_code=202, headers={"Location": f"/v1/jobs/{job.id}"})


@router.get("/{cid}", response_model=CachePublic, responses=error_responses(404, 422, 503))
def get_cache(cid: str, redis: RedisDep, settings: SettingsDep) -> dict:
    """The cache and its precompute; a finished one whose files have been lost since is failed,
    with what is missing (POST it again to rebuild that)."""
    return cache_body(cid, _cache_job(redis, cid), settings)


@router.get(
    "/{cid}/field",
    response_class=Response,
    responses={
        200: {
            "description": "The radiance field, gzip-compressed (Content-Encoding: gzip)",
            "content": binary("application/octet-stream"),
            "headers": FIELD_HEADERS,
        },
        304: {"description": "The client's copy (If-None-Match) is the field", "headers": FIELD_HEADERS},
        **error_responses(
            404,
            409,
            410,
            422,
            503,
            about={409: "The precompute has not finished", 410: "The field was evicted: POST it again"},
        ),
    },
)
def get_field(cid: str, request: Request, redis: RedisDep, settings: SettingsDep):
    """The cache's radiance field (api.md, "The radiance field"): gzip-compressed bytes sent as
    they are stored, with ``Content-Encoding: gzip``; ETag is the radiance key, cached for ever."""
    job = _cache_job(redis, cid)
    st = status_of(job)
    if st != JobStatus.finished:
        raise HTTPException(409, f"cache {cid} is {st.value}, not finished; its field comes with it")
    key = ((job.return_value() or {}).get("keys") or {}).get("radiance_key")
    path = CacheStore(settings.cache_dir).field_path(key) if key else None
    if path is None or not path.is_file():
        raise HTTPException(
            410, f"the field of cache {cid} is gone; ask for the cache again (POST /v1/caches)"
        )
    headers = {"ETag": f'"{key}"', "Cache-Control": IMMUTABLE}
    wanted = {t.strip().removeprefix("W/") for t in request.headers.get("if-none-match", "").split(",")}
    if headers["ETag"] in wanted or "*" in wanted:
        return Response(status_code=304, headers=headers)
    return FileResponse(
        path,
        media_type="application/octet-stream",
        headers={**headers, "Content-Encoding": "gzip"},
    )
