"""Job functions. Thin: resolve the scene, call the engine, report progress, write results.

Each takes its arguments by name, as one payload (``payload``: the JSON of its model in
cloudgraph_service.protocol), and validates it before it does anything else.
"""

from __future__ import annotations

import logging
import subprocess
import time
from pathlib import Path

import numpy as np
from rq import get_current_job

from cloudgraph.errors import SceneError
from cloudgraph.files import write_atomic
from cloudgraph.image import png_bytes, write_exr
from cloudgraph.lights import Lights
from cloudgraph.scene import parse_scene
from cloudgraph_service.protocol import (
    FRAME_FFMPEG,
    FRAME_FILE,
    VIDEO_FILE,
    EncodeJob,
    FramesJob,
    PrecomputeJob,
    RenderJob,
    cancel_key,
)

from .state import state

log = logging.getLogger(__name__)


class JobCancelled(Exception):
    """The job was cancelled by a client (checked at every progress report, every chunk of a
    precompute's stages and before every file a job writes)."""


def _current_job():
    """The job being run, or None outside a job or while Redis is away (the worker process's
    client waits for it: worker/process.py); a job goes on meanwhile, unchecked."""
    job = get_current_job()
    return None if job is None or getattr(job.connection, "away", False) else job


def stop_if_cancelled() -> None:
    """Raises JobCancelled when a client cancelled the current job."""
    job = _current_job()
    if job is not None and job.connection.exists(cancel_key(job.id)):
        raise JobCancelled(f"job {job.id} was cancelled")


def report(stage: str, fraction: float) -> None:
    """Progress into the current job's meta; raises JobCancelled when a cancel was asked for."""
    stop_if_cancelled()
    job = _current_job()
    if job is None:
        return

    # The API writes to the meta too (the cancel flag): read, update and write it back in one
    # transaction (tried again if the job changed meanwhile), so that no write of the API's is lost
    def update(pipe) -> None:
        raw = pipe.hget(job.key, "meta")
        job.meta = job.serializer.loads(raw) if raw else {}
        job.meta.update(stage=stage, fraction=round(float(fraction), 4))
        pipe.multi()
        pipe.hset(job.key, "meta", job.serializer.dumps(job.meta))

    job.connection.transaction(update, job.key)


def _checked(chunks):
    """``chunks`` whose results are checked for a cancel as each arrives, so that a cancelled
    precompute stops at its next chunk, in every stage (the stage's chunks still go out when
    asked for, as ``chunks`` puts them)."""

    def run(builder, stage: str, inputs: dict | None = None):
        results = chunks(builder, stage, inputs)

        def checked():
            try:
                for result in results:
                    stop_if_cancelled()
                    yield result
            finally:
                getattr(results, "close", lambda: None)()

        return checked()

    return run


def _checked_store(caches, graph_key: str):
    """The worker's cache store as a precompute sees it: it writes nothing once the job is
    cancelled, and takes a cache whose graph file is gone for one without a field, so that the
    precompute builds the graph again (the same bytes) rather than finishing without it."""
    from cloudgraph.cache import CacheStore

    class CheckedStore(CacheStore):
        def save_graph(self, key, data):
            stop_if_cancelled()
            return super().save_graph(key, data)

        def save_radiance(self, key, data):
            stop_if_cancelled()
            return super().save_radiance(key, data)

        def save_field(self, key, data):
            stop_if_cancelled()
            return super().save_field(key, data)

        def load_field(self, key):
            return super().load_field(key) if self.graph_path(graph_key).is_file() else None

    return CheckedStore(caches.root)


def with_environment_files(scene, environments_dir):
    """The scene with each uploaded environment map's id (an ``envmap`` light's) as the path of
    its stored file, which the engine reads (the API checked that it exists)."""
    if scene.lights is None or not any(li.type == "envmap" for li in scene.lights):
        return scene
    from cloudgraph.store import EnvironmentStore

    store = EnvironmentStore(environments_dir)

    def resolved(li):
        if li.type != "envmap" or li.id is None:
            return li
        path = store.path(li.id)
        if path is None:
            raise SceneError(
                f"no environment map with id {li.id[:12]}...; upload it with POST /v1/environments"
            )
        return li.model_copy(update={"id": None, "path": str(path)})

    return scene.model_copy(update={"lights": tuple(resolved(li) for li in scene.lights)})


def _parsed(doc: dict):
    """A job's scene, parsed, with its uploaded environment maps as files."""
    return with_environment_files(parse_scene(doc), state().settings.environments_dir)


def _cache(scene, volume, quality: str):
    """(keys, build) of the scene's radiance cache: its keys, worked out once per job (a pass
    over the volume), and ``build(progress)``, which finds or makes the cache under those keys,
    with its chunks on the Dask cluster of ``CLOUDGRAPH_DASK_SCHEDULER`` where one is set, else
    here (cloudgraph_service/dask_chunks.py), then trims the store to its size limit (LRU)."""
    from cloudgraph.cache import cache_keys
    from cloudgraph.params import build_params
    from cloudgraph.precompute import precompute
    from cloudgraph.store import evict_lru
    from cloudgraph_service.dask_chunks import precompute_chunks

    s = state()
    params = build_params(volume, scene.medium.density_scale, quality)
    keys = cache_keys(scene, volume, params)

    def build(progress):
        gkey, rkey = keys["graph_key"], keys["radiance_key"]
        paths = (s.caches.graph_path(gkey), s.caches.radiance_path(rkey), s.caches.field_path(rkey))
        found = all(p.is_file() for p in paths)
        store = _checked_store(s.caches, gkey)
        with precompute_chunks(None if found else s.settings.DASK_SCHEDULER) as chunks:
            cache = precompute(scene, volume, quality, store, progress, _checked(chunks))
        evict_lru(s.caches.root, int(s.settings.CACHE_MAX_GB * 2**30))
        return cache

    return keys, build


def _renderer(scene, volume, quality: str, progress, radiance_key: str | None = None):
    """A loaded renderer for the scene's radiance cache, found by its radiance key before any
    file is read.

    ``radiance_key`` is the key handed down with the job (the API read it from the finished
    precompute; None where it did not know it). A renderer this worker holds under it serves at
    once: this worker put it there under the key it worked out itself, from the same volume,
    medium, light and depth. Otherwise the key is worked out here, as the cache needs it anyway,
    and a handed key that differs is logged and not used.
    """
    from cloudgraph.render import GraphRenderer

    renderers = state().renderers
    found = renderers.get(radiance_key) if radiance_key else None
    if found is not None:
        return found
    keys, build = _cache(scene, volume, quality)
    rkey = keys["radiance_key"]
    if radiance_key and radiance_key != rkey:
        job = get_current_job()
        log.warning(
            "job %s was handed radiance key %s, but its scene's is %s: rendering with the scene's",
            job.id if job else "-",
            radiance_key,
            rkey,
        )
    return renderers.get_or_make(rkey, lambda: GraphRenderer(build(progress), volume, scene))


def _renderer_for(integrator: str, scene, volume, quality: str, radiance_key: str | None):
    """The graph integrator's renderer (its precompute reported as the job's first 90 %), or
    None for volpath."""
    if integrator != "graph":
        return None
    return _renderer(scene, volume, quality, lambda s, f: report(s, 0.9 * f), radiance_key)


def precompute_job(payload: dict) -> dict:
    """Builds (or finds) the radiance cache of a scene (PrecomputeJob); returns its keys and
    stats."""
    p = PrecomputeJob.received(payload)
    sc = _parsed(p.scene)
    _, build = _cache(sc, state().volume(sc), p.quality)
    cache = build(report)
    return {"keys": cache.keys, "stats": cache.stats}


def render_image(scene, volume, renderer=None, estimator: str = "gather") -> tuple[np.ndarray, float]:
    """(image, seconds) of a parsed scene with the graph ``renderer`` (``estimator``: its camera
    stage; one loaded renderer serves them all), or with volpath where it is None."""
    from cloudgraph.render import render_volpath

    if renderer is not None:
        report("render", 0.9)
        t0 = time.perf_counter()
        # (a cache of v1.1 lights holds each light apart: this scene's intensities mix them)
        lights = Lights.of(scene)
        image = renderer.render(scene.camera, scene.render.spp, scene.render.seed, estimator, lights)
    else:
        report("render", 0.0)
        t0 = time.perf_counter()
        image = render_volpath(scene, volume)
    return image, time.perf_counter() - t0


def render_job(payload: dict) -> dict:
    """Renders one image to the payload's ``out``, png or exr (RenderJob)."""
    p = RenderJob.received(payload)
    sc = _parsed(p.scene)
    volume = state().volume(sc)
    renderer = _renderer_for(p.integrator, sc, volume, p.quality, p.radiance_key)
    image, seconds = render_image(sc, volume, renderer, p.estimator)
    path = Path(p.out)
    stop_if_cancelled()  # nothing is written for a cancelled job
    if p.format == "exr":  # Mitsuba writes an EXR by path: under a temporary name, then renamed
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp" + path.suffix)
        write_exr(image, tmp)
        tmp.replace(path)
    else:
        write_atomic(path, png_bytes(image, p.exposure))
    report("done", 1.0)
    return {"path": str(path), "render_s": round(seconds, 4), "mean": float(image.mean())}


def frames_job(payload: dict) -> dict:
    """Renders a run of animation frames (``FRAME_FILE``; FramesJob): the scene from each of the
    payload's cameras in turn, one Python call per frame, all with one renderer."""
    p = FramesJob.received(payload)
    base = _parsed(p.scene)
    volume = state().volume(base)
    renderer = _renderer_for(p.integrator, base, volume, p.quality, p.radiance_key)
    out = Path(p.out_dir)
    for i, camera in enumerate(p.cameras):  # a loop over frames, each a whole vectorised render
        image, _ = render_image(_parsed({**p.scene, "camera": camera}), volume, renderer, p.estimator)
        stop_if_cancelled()
        write_atomic(out / FRAME_FILE.format(p.first + i), png_bytes(image, p.exposure))
        report("frames", (i + 1) / len(p.cameras))
    return {"frames": len(p.cameras), "first": p.first}


def encode_job(payload: dict) -> dict:
    """Encodes frame_%05d.png into an H.264 MP4 that browsers play (EncodeJob)."""
    import imageio_ffmpeg

    p = EncodeJob.received(payload)
    out, n_frames = Path(p.out_dir), p.frames
    missing = [i for i in range(n_frames) if not (out / FRAME_FILE.format(i)).is_file()]
    if missing:
        raise RuntimeError(f"{len(missing)} frames are missing, first {missing[0]}")
    report("encode", 0.0)
    # ffmpeg writes by path (a faststart MP4 is rewritten in place): under a temporary name, then
    # renamed
    tmp = out / ".video.tmp.mp4"
    cmd = [
        imageio_ffmpeg.get_ffmpeg_exe(),
        "-y",
        "-loglevel",
        "error",
        "-framerate",
        str(p.fps),
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
    return {"video": str(out / VIDEO_FILE), "frames": n_frames, "fps": p.fps}
