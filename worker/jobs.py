"""Job functions. Thin: resolve the scene, call the engine, report progress, write results."""

from __future__ import annotations

import logging
import subprocess
import time
import uuid
from contextlib import nullcontext
from functools import partial
from pathlib import Path

import numpy as np
from rq import Queue, Worker, get_current_job

from cloudgraph.image import png_bytes, write_exr
from cloudgraph.scene import parse_scene
from cloudgraph_service.protocol import (
    CHUNK_JOB,
    FRAME_FFMPEG,
    FRAME_FILE,
    RESULT_TTL_S,
    VIDEO_FILE,
    cancel_key,
)

from .chunks import MAX_HELPERS, SharedChunks, help_run
from .state import state

log = logging.getLogger(__name__)


class JobCancelled(Exception):
    """The job was cancelled by a client (checked at every progress report)."""


def report(stage: str, fraction: float) -> None:
    """Progress into the current job's meta; raises JobCancelled when a cancel was asked for."""
    job = get_current_job()
    if job is None:
        return
    if job.connection.exists(cancel_key(job.id)):
        raise JobCancelled(f"job {job.id} was cancelled")
    # Re-read the meta first: the API writes to it too (the cancel flag), and save_meta() writes
    # the whole of it back.
    job.get_meta(refresh=True).update(stage=stage, fraction=round(float(fraction), 4))
    job.save_meta()


def _precompute(scene, volume, quality: str, progress):
    """The scene's radiance cache, its chunks run by every free worker (worker/chunks.py); the
    store is then trimmed to its size limit (LRU)."""
    from cloudgraph.graph import build_params, local_chunks
    from cloudgraph.precompute import cache_keys, precompute
    from cloudgraph.store import evict_lru

    s, job = state(), get_current_job()
    params = build_params(volume, scene.medium.density_scale, quality)
    keys = cache_keys(scene, volume, params)
    rkey = keys["radiance_key"]
    if job is None or (s.caches.radiance_path(rkey).is_file() and s.caches.field_path(rkey).is_file()):
        shared = nullcontext(local_chunks)  # outside a job, or nothing to compute: here
    else:  # helpers are asked for at once, so that they load the volume while this worker does
        run = f"{job.id}.{uuid.uuid4().hex[:8]}"
        shared = SharedChunks(
            job.connection,
            run,
            {
                "scene": scene.model_dump(mode="json"),
                "quality": quality,
                "params": params.to_dict(),
                "graph": not s.caches.graph_path(keys["graph_key"]).is_file(),  # to be built
            },
            s.caches.root / "runs" / run,
            partial(_ask_helpers, job.connection, run),
        )
    with shared as chunks:
        cache = precompute(scene, volume, quality, s.caches, progress, chunks)
    evict_lru(s.caches.root, int(s.settings.CACHE_MAX_GB * 2**30))
    return cache


def _ask_helpers(connection, run: str) -> int:
    """One helper job per other worker, at the front of the queue; returns how many."""
    settings = state().settings
    queue = Queue(settings.QUEUE, connection=connection)
    n = max(0, min(Worker.count(connection=connection, queue=queue) - 1, MAX_HELPERS))
    for _ in range(n):
        queue.enqueue(
            CHUNK_JOB,
            run,
            at_front=True,
            job_timeout=settings.JOB_TIMEOUT_S,
            result_ttl=RESULT_TTL_S,
            failure_ttl=RESULT_TTL_S,
            meta={"kind": "helper", "stage": "queued", "fraction": 0.0},
        )
    return n


def _builder(spec: dict):
    """The graph builder of a shared run's spec (worker/chunks.py), with its node cells where the
    run builds a graph: a helper makes it while the coordinator puts out the first stage."""
    from cloudgraph.graph import BuildParams, GraphBuilder

    sc = parse_scene(spec["scene"])
    builder = GraphBuilder(state().volume(sc), sc.medium.density_scale, BuildParams(**spec["params"]))
    if spec.get("graph"):
        builder.cells  # noqa: B018 (made now, not in the first chunk)
    return builder


def chunk_job(run: str) -> dict:
    """Helps with another job's graph build (worker/chunks.py) until it ends."""
    report("helping", 0.0)
    n = help_run(get_current_job().connection, run, _builder)
    return {"run": run, "chunks": n}


def _renderer(scene, volume, quality: str, progress):
    """A loaded renderer for the scene's radiance cache, found by its keys before any file is read."""
    from cloudgraph.graph import build_params
    from cloudgraph.integrators.graph import GraphRenderer
    from cloudgraph.precompute import cache_keys

    keys = cache_keys(scene, volume, build_params(volume, scene.medium.density_scale, quality))
    return state().renderers.get_or_make(
        keys["radiance_key"],
        lambda: GraphRenderer(_precompute(scene, volume, quality, progress), volume, scene),
    )


def precompute_job(scene: dict, quality: str) -> dict:
    """Builds (or finds) the radiance cache of a scene; returns its keys and stats."""
    sc = parse_scene(scene)
    cache = _precompute(sc, state().volume(sc), quality, report)
    return {"keys": cache.keys, "stats": cache.stats}


def render_image(
    scene: dict, integrator: str, quality: str, estimator: str = "gather"
) -> tuple[np.ndarray, float]:
    """(image, seconds) for a scene with the graph or volpath integrator; ``estimator`` is the
    graph integrator's camera stage (one loaded renderer serves them all)."""
    from cloudgraph.render import render_volpath

    sc = parse_scene(scene)
    volume = state().volume(sc)
    if integrator == "graph":
        renderer = _renderer(sc, volume, quality, lambda s, f: report(s, 0.9 * f))
        report("render", 0.9)
        t0 = time.perf_counter()
        image = renderer.render(sc.camera, sc.render.spp, sc.render.seed, estimator=estimator)
    else:
        report("render", 0.0)
        t0 = time.perf_counter()
        image = render_volpath(sc, volume)
    return image, time.perf_counter() - t0


def render_job(
    scene: dict,
    integrator: str,
    fmt: str,
    quality: str,
    exposure: float,
    out: str,
    estimator: str = "gather",
) -> dict:
    """Renders one image to ``out`` (png or exr)."""
    image, seconds = render_image(scene, integrator, quality, estimator)
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp" + path.suffix)
    if fmt == "exr":
        write_exr(image, tmp)
    else:
        tmp.write_bytes(png_bytes(image, exposure))
    tmp.replace(path)
    report("done", 1.0)
    return {"path": str(path), "render_s": round(seconds, 4), "mean": float(image.mean())}


def frames_job(
    scenes: list[dict],
    first: int,
    integrator: str,
    quality: str,
    exposure: float,
    out_dir: str,
    estimator: str = "gather",
) -> dict:
    """Renders a run of animation frames (``FRAME_FILE``), one Python call per frame."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for i, scene in enumerate(scenes):  # a loop over frames, each a whole vectorised render
        image, _ = render_image(scene, integrator, quality, estimator)
        name = FRAME_FILE.format(first + i)
        tmp = out / f".{name}.tmp"
        tmp.write_bytes(png_bytes(image, exposure))
        tmp.replace(out / name)
        report("frames", (i + 1) / len(scenes))
    return {"frames": len(scenes), "first": first}


def encode_job(out_dir: str, fps: float, n_frames: int) -> dict:
    """Encodes frame_%05d.png into an H.264 MP4 that browsers play."""
    import imageio_ffmpeg

    out = Path(out_dir)
    missing = [i for i in range(n_frames) if not (out / FRAME_FILE.format(i)).is_file()]
    if missing:
        raise RuntimeError(f"{len(missing)} frames are missing, first {missing[0]}")
    report("encode", 0.0)
    tmp = out / ".video.tmp.mp4"
    cmd = [
        imageio_ffmpeg.get_ffmpeg_exe(),
        "-y",
        "-loglevel",
        "error",
        "-framerate",
        str(fps),
        "-i",
        str(out / FRAME_FFMPEG),
        "-c:v",
        "libx264",
        "-pix_fmt",
        "yuv420p",
        "-vf",
        "pad=ceil(iw/2)*2:ceil(ih/2)*2",
        "-movflags",
        "+faststart",
        str(tmp),
    ]
    subprocess.run(cmd, check=True, capture_output=True, timeout=600)
    tmp.replace(out / VIDEO_FILE)
    report("done", 1.0)
    return {"video": str(out / VIDEO_FILE), "frames": n_frames, "fps": fps}
