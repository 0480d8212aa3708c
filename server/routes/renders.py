"""/v1/renders: one image, graph or volpath. Small renders on a ready cache come back directly."""

from __future__ import annotations

import uuid

from fastapi import APIRouter, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, JSONResponse, Response

from cloudgraph_service.errors import shown
from cloudgraph_service.protocol import RenderJob, is_job_id, render_path

from ..deps import QueueDep, RedisDep, SettingsDep, VolumesDep
from ..errors import error_responses
from ..jobs import (
    await_job,
    check_capacity,
    describe,
    enqueue,
    fetch,
    radiance_key_of,
    status_of,
    worker_health,
)
from ..schemas import CacheCreate, JobPublic, JobStatus, RenderCreate, binary
from ..validation import check_scene
from .caches import ensure_cache

router = APIRouter(prefix="/renders", tags=["renders"])
MEDIA = {"png": "image/png", "exr": "image/x-exr"}
IMAGE = binary(*MEDIA.values())
JOB_ID = {"X-Job-Id": {"description": "the render's job", "schema": {"type": "string"}}}


def precompute_for(scene, quality, redis, queue, settings, volumes):
    """The scene's cache job (started if needed), for renders to wait on."""
    body = CacheCreate(
        volume=scene.volume,
        medium=scene.medium,
        **({"light": scene.light} if scene.lights is None else {"lights": scene.lights}),
        max_depth=scene.render.max_depth,
        quality=quality,
    )
    return ensure_cache(body, redis, queue, settings, volumes, prefix="scene.")[1]


def _free_workers(queue, settings) -> int:
    """Workers alive and not stuck past a job's budget."""
    live, stuck = worker_health(queue, settings)
    return live - stuck


def _render(body: RenderCreate, redis, queue, settings, volumes):
    """Validates, then enqueues the render (after its cache's precompute when that is not ready).

    Returns:
        (job, ready): ready when the job will run without waiting on another.
    """
    scene = body.scene
    check_scene(scene, settings, volumes)
    check_capacity(queue, settings)
    depends, ready, radiance_key = None, True, None
    if body.integrator == "graph":
        pre = precompute_for(scene, body.quality, redis, queue, settings, volumes)
        ready = status_of(pre) == JobStatus.finished
        depends = None if ready else pre
        radiance_key = radiance_key_of(pre) if ready else None  # handed down: found once
    small = scene.camera.width * scene.camera.height <= settings.SYNC_MAX_PIXELS
    if ready and small and _free_workers(queue, settings) < 1:
        raise HTTPException(
            503, "no worker is running to render this now; try again shortly", headers={"Retry-After": "10"}
        )
    job_id = f"render-{uuid.uuid4().hex}"
    out = render_path(settings.outputs_dir, job_id, body.format)
    payload = RenderJob(
        scene=scene.model_dump(mode="json"),
        integrator=body.integrator,
        estimator=body.estimator,
        quality=body.quality,
        format=body.format,
        exposure=body.exposure,
        out=str(out),
        radiance_key=radiance_key,
    )
    job = enqueue(
        queue,
        settings,
        payload,
        job_id=job_id,
        kind="render",
        depends_on=depends,
        at_front=ready,
        meta={"result_url": f"/v1/renders/{job_id}/image"},
    )
    return job, ready and small


@router.post(
    "",
    response_class=Response,
    responses={
        200: {
            "description": "The image (format png or exr), rendered at once",
            "content": IMAGE,
            "headers": {
                **JOB_ID,
                "X-Render-Seconds": {"description": "seconds the render took", "schema": {"type": "number"}},
            },
        },
        202: {
            "model": JobPublic,
            "description": "The render is queued (after its cache's precompute, if that is not ready)",
            "headers": {"Location": {"description": "the job's URL", "schema": {"type": "string"}}},
        },
        **error_responses(
            400,
            404,
            413,
            415,
            422,
            429,
            503,
            about={
                404: "No volume with that id",
                422: "A field out of its range, or a render that failed (X-Job-Id names it)",
                503: "No worker is free to render it now, or the job store (Redis) is not reachable",
            },
        ),
    },
)
async def create_render(
    request: Request,
    body: RenderCreate,
    redis: RedisDep,
    queue: QueueDep,
    settings: SettingsDep,
    volumes: VolumesDep,
):
    """Renders a scene. 200 with the image when it is small and its cache ready (or volpath and
    quick); else 202 with a job, which waits on the cache's precompute if that is still running.
    With no worker alive (or all stuck), a render that would come back directly is 503 at once."""
    job, sync = await run_in_threadpool(_render, body, redis, queue, settings, volumes)
    if sync:
        st = await await_job(job, settings.SYNC_WAIT_S, request)
        if st == JobStatus.finished:
            result = job.return_value()
            out = render_path(settings.outputs_dir, job.id, body.format)
            return Response(
                await run_in_threadpool(out.read_bytes),
                media_type=MEDIA[body.format],
                headers={"X-Job-Id": job.id, "X-Render-Seconds": str(result["render_s"])},
            )
        if st == JobStatus.failed:
            d = await run_in_threadpool(describe, job)
            raise HTTPException(422, f"render failed: {d.error}", headers={"X-Job-Id": job.id})
    d = await run_in_threadpool(describe, job)
    return JSONResponse(
        d.model_dump(mode="json"), status_code=202, headers={"Location": f"/v1/jobs/{job.id}"}
    )


@router.get(
    "/{job_id}/image",
    response_class=Response,
    responses={
        200: {"description": "The image, png or exr as the render asked", "content": IMAGE},
        **error_responses(
            404, 409, 410, 422, 503, about={409: "The render has not finished", 410: "The image was evicted"}
        ),
    },
)
def render_image(job_id: str, redis: RedisDep, settings: SettingsDep):
    job = fetch(redis, job_id) if is_job_id(job_id) else None
    if job is None or job.meta.get("kind") != "render":
        raise HTTPException(404, f"no render job {shown(job_id)}")
    if status_of(job) != JobStatus.finished:
        raise HTTPException(409, f"render {job_id} is {status_of(job).value}, not finished")
    for fmt, media in MEDIA.items():
        p = render_path(settings.outputs_dir, job_id, fmt)
        if p.is_file():
            return FileResponse(p, media_type=media)
    raise HTTPException(410, f"the image of {job_id} is gone; render it again")
