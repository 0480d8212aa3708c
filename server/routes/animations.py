"""/v1/animations: camera keyframes or an orbit -> frames rendered across workers -> MP4."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import ValidationError

from cloudgraph.scene import CameraSpec, format_validation_error
from cloudgraph_service.errors import shown
from cloudgraph_service.protocol import (
    FRAME_FILE,
    FRAME_GLOB,
    VIDEO_FILE,
    EncodeJob,
    FramesJob,
    animation_dir,
)

from ..deps import QueueDep, RedisDep, SettingsDep, VolumesDep
from ..errors import InputError, error_responses
from ..jobs import check_capacity, describe, enqueue, fetch, radiance_key_of, status_of
from ..schemas import AnimationCreate, AnimationPublic, JobPublic, JobStatus, binary
from ..validation import MAX_COORD, MIN_RADIUS, check_camera, check_scene
from .renders import precompute_for

router = APIRouter(prefix="/animations", tags=["animations"])
FRAMES_PER_JOB = 4


def camera_path(body: AnimationCreate) -> list[CameraSpec]:
    """One camera per frame: keyframes interpolated linearly and evenly, or an orbit."""
    base = body.scene.camera
    n = body.frames
    s = np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)
    if body.keyframes is not None:
        keys = body.keyframes
        seg = s * (len(keys) - 1)
        i = np.minimum(np.floor(seg).astype(int), len(keys) - 2)
        f = seg - i
        out = []
        for k, t in zip(i, f, strict=True):  # a loop over frames, not pixels
            a, b = keys[k], keys[k + 1]

            def lerp(x, y, t=t):
                return tuple(float(v) for v in (1 - t) * np.asarray(x) + t * np.asarray(y))

            between = {
                "eye": lerp(a.eye, b.eye),
                "target": lerp(a.target, b.target),
                "up": lerp(a.up, b.up),
                "fov": (1 - t) * a.fov + t * b.fov,
            }
            try:  # (each keyframe is valid; a camera between two need not be: an up that turns over)
                out.append(CameraSpec.model_validate(a.model_dump() | between))
            except ValidationError as err:
                raise InputError(
                    f"keyframes[{k + 1}]",
                    f"frame {len(out)}, between keyframes[{k}] and [{k + 1}], has no valid camera: "
                    f"{format_validation_error(err)}",
                ) from None
        return out
    target, up = np.asarray(base.target), np.asarray(base.up) / np.linalg.norm(base.up)
    offset = np.asarray(base.eye) - target
    radius = body.orbit.radius or float(np.linalg.norm(offset))
    u = offset - up * offset.dot(up)
    u = u / np.linalg.norm(u) if np.linalg.norm(u) > 1e-9 else np.cross(up, [1.0, 0, 0])
    v = np.cross(up, u)
    el = np.radians(body.orbit.elevation)
    steps = np.arange(n) / n * 2 * np.pi * body.orbit.turns
    return [
        base.model_copy(
            update={
                "eye": tuple(
                    float(c)
                    for c in target
                    + radius * (np.cos(el) * (np.cos(a) * u + np.sin(a) * v) + np.sin(el) * up)
                )
            }
        )
        for a in steps
    ]


def check_animation(body: AnimationCreate, settings, volumes) -> None:
    """The scene, the frame count, and every keyframe under the scene camera's limits (all of
    one image size: the frames make one video), or an orbit of bounded radius."""
    if body.frames > settings.MAX_FRAMES:
        raise InputError("frames", f"{body.frames} is over the limit of {settings.MAX_FRAMES}")
    check_scene(body.scene, settings, volumes)
    for i, cam in enumerate(body.keyframes or []):
        check_camera(cam, settings, f"keyframes[{i}]")
        first = body.keyframes[0]
        if (cam.width, cam.height) != (first.width, first.height):
            raise InputError(
                f"keyframes[{i}]",
                f"image {cam.width}x{cam.height} differs from keyframes[0]'s {first.width}x{first.height}; "
                "the frames of one video share a size",
            )
    radius = body.orbit.radius if body.orbit is not None else None
    if radius is not None and not MIN_RADIUS <= radius <= MAX_COORD:
        raise InputError("orbit.radius", f"must be within [{MIN_RADIUS:g}, {MAX_COORD:g}], got {radius:g}")


@router.post(
    "",
    status_code=202,
    response_model=JobPublic,
    response_description="The animation's job, queued",
    responses={
        202: {"headers": {"Location": {"description": "the job's URL", "schema": {"type": "string"}}}},
        **error_responses(400, 404, 413, 415, 422, 429, 503, about={404: "No volume with that id"}),
    },
)
def create_animation(
    body: AnimationCreate, redis: RedisDep, queue: QueueDep, settings: SettingsDep, volumes: VolumesDep
):
    """Renders the frames as batch jobs across the workers, then encodes an MP4."""
    scene = body.scene
    check_animation(body, settings, volumes)
    n_jobs = -(-body.frames // FRAMES_PER_JOB)
    check_capacity(queue, settings, extra=n_jobs + 1)
    pre = (
        precompute_for(scene, body.quality, redis, queue, settings, volumes)
        if body.integrator == "graph"
        else None
    )
    ready = pre is not None and status_of(pre) == JobStatus.finished
    depends = pre if pre is not None and not ready else None
    anim_id = f"anim-{uuid.uuid4().hex}"
    out_dir = animation_dir(settings.outputs_dir, anim_id)
    # The frames share the scene but for its camera: one radiance key serves them all
    cameras = [c.model_dump(mode="json") for c in camera_path(body)]
    shared = {
        "scene": scene.model_dump(mode="json"),
        "integrator": body.integrator,
        "estimator": body.estimator,
        "quality": body.quality,
        "exposure": body.exposure,
        "out_dir": str(out_dir),
        "radiance_key": radiance_key_of(pre) if ready else None,
    }
    children = []
    for first in range(0, body.frames, FRAMES_PER_JOB):
        j = enqueue(
            queue,
            settings,
            FramesJob(cameras=cameras[first : first + FRAMES_PER_JOB], first=first, **shared),
            kind="frames",
            depends_on=depends,
            meta={"animation": anim_id},
        )
        children.append(j)
    job = enqueue(
        queue,
        settings,
        EncodeJob(out_dir=str(out_dir), fps=body.fps, frames=body.frames),
        job_id=anim_id,
        kind="animation",
        depends_on=children,
        meta={
            "result_url": f"/v1/animations/{anim_id}/video",
            "frames": body.frames,
            "out_dir": str(out_dir),
            "children": [c.id for c in children],
        },
    )
    return JSONResponse(
        describe(job).model_dump(mode="json"), status_code=202, headers={"Location": f"/v1/jobs/{anim_id}"}
    )


def _anim(redis, anim_id: str):
    job = fetch(redis, anim_id)
    if job is None or job.meta.get("kind") != "animation":
        raise HTTPException(404, f"no animation {shown(anim_id)}")
    return job


@router.get("/{anim_id}", response_model=AnimationPublic, responses=error_responses(404, 422, 503))
def get_animation(anim_id: str, redis: RedisDep) -> dict:
    job = _anim(redis, anim_id)
    d = describe(job).model_dump(mode="json")

    out = Path(job.meta["out_dir"])
    d["frames_done"] = sorted(int(p.stem.split("_")[1]) for p in out.glob(FRAME_GLOB)) if out.is_dir() else []
    d["frames"] = job.meta["frames"]
    return d


@router.get(
    "/{anim_id}/video",
    response_class=Response,
    responses={
        200: {"description": "The MP4", "content": binary("video/mp4")},
        **error_responses(
            404,
            409,
            410,
            422,
            503,
            about={
                409: "The animation has not finished",
                410: "The video was removed: POST the animation again",
            },
        ),
    },
)
def get_video(anim_id: str, redis: RedisDep):
    job = _anim(redis, anim_id)
    if status_of(job) != JobStatus.finished:
        raise HTTPException(409, f"animation {anim_id} is {status_of(job).value}, not finished")
    video = Path(job.meta["out_dir"]) / VIDEO_FILE
    if not video.is_file():
        raise HTTPException(410, f"the video of animation {anim_id} is gone; start the animation again")
    return FileResponse(video, media_type="video/mp4", filename=f"{anim_id}.mp4")


@router.get(
    "/{anim_id}/frames/{index}",
    response_class=Response,
    responses={
        200: {"description": "The frame", "content": binary("image/png")},
        **error_responses(
            404,
            409,
            410,
            422,
            503,
            about={
                404: "No such animation, or no such frame",
                409: "Not rendered yet",
                410: "The frame was removed: POST the animation again",
            },
        ),
    },
)
def get_frame(anim_id: str, index: int, redis: RedisDep):
    job = _anim(redis, anim_id)

    p = Path(job.meta["out_dir"]) / FRAME_FILE.format(index)
    if not 0 <= index < job.meta["frames"]:
        raise HTTPException(404, f"frame {index} is outside 0..{job.meta['frames'] - 1}")
    if not p.is_file():
        if status_of(job) == JobStatus.finished:
            gone = f"frame {index} of animation {anim_id} is gone; start the animation again"
            raise HTTPException(410, gone)
        raise HTTPException(409, f"frame {index} is not rendered yet")
    return FileResponse(p, media_type="image/png")
