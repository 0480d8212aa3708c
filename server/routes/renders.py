"""/v1/renders: one image, graph or volpath. Small renders on a ready cache come back directly."""

from __future__ import annotations

import uuid

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import FileResponse, JSONResponse, Response

from ..deps import QueueDep, RedisDep, SettingsDep, VolumesDep
from ..jobs import await_job, check_capacity, describe, enqueue, fetch, status_of
from ..schemas import CacheCreate, JobStatus, RenderCreate
from .caches import ensure_cache

router = APIRouter(prefix="/renders", tags=["renders"])
MEDIA = {"png": "image/png", "exr": "image/x-exr"}


def check_scene(scene, settings, volumes) -> None:
    """Size and sample limits (422), then that the scene's volume was uploaded (404)."""
    c = scene.camera
    if max(c.width, c.height) > settings.MAX_IMAGE_SIDE:
        raise HTTPException(
            422, f"image {c.width}x{c.height} is over the limit of {settings.MAX_IMAGE_SIDE} pixels a side"
        )
    if scene.render.spp > settings.MAX_SPP:
        raise HTTPException(422, f"spp {scene.render.spp} is over the limit of {settings.MAX_SPP}")
    if scene.volume.id is None or volumes.info(scene.volume.id) is None:
        raise HTTPException(404, f"no volume with id {scene.volume.id!r}; upload it with POST /v1/volumes")


def precompute_for(scene, quality, redis, queue, settings, volumes):
    """The scene's cache job (started if needed), for renders to wait on."""
    body = CacheCreate(
        volume=scene.volume,
        medium=scene.medium,
        light=scene.light,
        max_depth=scene.render.max_depth,
        quality=quality,
    )
    return ensure_cache(body, redis, queue, settings, volumes)[1]


@router.post("")
async def create_render(
    request: Request,
    body: RenderCreate,
    redis: RedisDep,
    queue: QueueDep,
    settings: SettingsDep,
    volumes: VolumesDep,
):
    """Renders a scene. 200 with the image when it is small and its cache ready (or volpath and
    quick); else 202 with a job, which waits on the cache's precompute if that is still running."""
    scene = body.scene
    check_scene(scene, settings, volumes)
    check_capacity(queue, settings)
    depends, ready = None, True
    if body.integrator == "graph":
        pre = precompute_for(scene, body.quality, redis, queue, settings, volumes)
        ready = status_of(pre) == JobStatus.finished
        depends = None if ready else pre
    job_id = f"render-{uuid.uuid4().hex}"
    out = settings.outputs_dir / "renders" / f"{job_id}.{body.format}"
    job = enqueue(
        queue,
        settings,
        "worker.jobs.render_job",
        scene.model_dump(),
        body.integrator,
        body.format,
        body.quality,
        body.exposure,
        str(out),
        job_id=job_id,
        kind="render",
        depends_on=depends,
        at_front=ready,
        meta={"result_url": f"/v1/renders/{job_id}/image"},
    )
    small = scene.camera.width * scene.camera.height <= settings.SYNC_MAX_PIXELS
    if ready and small:
        st = await await_job(job, settings.SYNC_WAIT_S, request)
        if st == JobStatus.finished:
            return Response(
                out.read_bytes(),
                media_type=MEDIA[body.format],
                headers={"X-Job-Id": job_id, "X-Render-Seconds": str(job.return_value()["render_s"])},
            )
        if st == JobStatus.failed:
            raise HTTPException(422, f"render failed: {describe(job).error}")
    return JSONResponse(
        describe(job).model_dump(mode="json"), status_code=202, headers={"Location": f"/v1/jobs/{job_id}"}
    )


@router.get("/{job_id}/image")
def render_image(job_id: str, redis: RedisDep, settings: SettingsDep):
    job = fetch(redis, job_id)
    if job is None or job.meta.get("kind") != "render":
        raise HTTPException(404, f"no render job {job_id!r}")
    if status_of(job) != JobStatus.finished:
        raise HTTPException(409, f"render {job_id} is {status_of(job).value}, not finished")
    path = settings.outputs_dir / "renders"
    for fmt, media in MEDIA.items():
        p = path / f"{job_id}.{fmt}"
        if p.is_file():
            return FileResponse(p, media_type=media)
    raise HTTPException(410, f"the image of {job_id} is gone; render it again")
