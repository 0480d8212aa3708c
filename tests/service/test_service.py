"""The render service against real processes: redis-server, `python -m worker`, uvicorn.

Nothing is mocked. Each fixture starts a whole service (tests/harness.py) on free ports with its
data in a temporary folder; Redis is also read directly to check what really ran.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import struct
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from redis import Redis
from rq import Worker
from rq.job import Job, JobStatus
from rq.results import Result

from ..conftest import DATA
from ..harness import Service, start_service, wait_until

FOG = DATA / "fog_sphere.vdb"  # 78 KB: a draft cache in well under a second
BLENDER = DATA / "blender_smoke_000002.vdb"  # 300 KB: a draft cache in a few seconds, every stage
SMOKE = DATA / "smoke1.vdb"  # 2.5 MB: long precomputes
KEY = "k3y-for-tests-0123456789abcdef"
TERMINAL = ("finished", "failed", "canceled")


# --------------------------------------------------------------------------------- helpers


def fog_scene(
    vid: str, width: int = 32, height: int | None = None, spp: int = 4, density: float = 5.0
) -> dict:
    """The fog sphere (centre (0, 2, 0), radius 1.1), seen from the side."""
    camera = {"eye": [0, 2, 6], "target": [0, 2, 0], "fov": 30, "width": width, "height": height or width}
    return {
        "volume": {"id": vid},
        "medium": {"density_scale": density},
        "light": {"direction": [1, -1, 0]},
        "camera": camera,
        "render": {"spp": spp},
    }


def smoke_scene(vid: str, density: float, width: int = 32) -> dict:
    """smoke1.vdb (a 110 x 220 x 110 plume, y up) from the front."""
    camera = {"eye": [-7, 40, 160], "target": [-7, 40, 0], "fov": 45, "width": width, "height": width}
    return {
        "volume": {"id": vid},
        "medium": {"density_scale": density},
        "light": {"direction": [0.55, -0.25, -0.8]},
        "camera": camera,
        "render": {"spp": 4},
    }


def blender_cache(vid: str, density: float = 6.0) -> dict:
    """A /v1/caches body for the Blender smoke (z up, about 7 x 7 x 10.5 units)."""
    return {
        "volume": {"id": vid},
        "medium": {"density_scale": density},
        "light": {"direction": [0.3, 0.2, -1]},
        "quality": "draft",
    }


def cache_of(scene: dict, quality: str = "draft") -> dict:
    """The /v1/caches body of a scene's cache."""
    return {k: scene[k] for k in ("volume", "medium", "light")} | {"quality": quality}


def upload(client, path, name: str | None = None):
    with open(path, "rb") as f:
        return client.post("/v1/volumes", files={"file": (name or path.name, f)})


def job_of(response) -> str:
    """The job id from a 202's Location header."""
    location = response.headers["location"]
    assert location.startswith("/v1/jobs/"), location
    return location.removeprefix("/v1/jobs/")


def wait_job(client, job_id: str, timeout: float = 180) -> dict:
    def ended():
        r = client.get(f"/v1/jobs/{job_id}")
        assert r.status_code == 200, r.text
        return r.json() if r.json()["status"] in TERMINAL else None

    return wait_until(ended, timeout, f"job {job_id} did not end in {timeout} s", interval=0.1)


def wait_stage(client, job_id: str, timeout: float = 120) -> dict:
    """The job once it runs and has reported a stage of its own."""

    def running():
        j = client.get(f"/v1/jobs/{job_id}").json()
        assert j["status"] not in TERMINAL, j
        return j if j["status"] == "running" and j["stage"] not in (None, "queued") else None

    return wait_until(running, timeout, f"job {job_id} never started", interval=0.05)


def sse(client, job_id: str) -> list[tuple[str, dict]]:
    """(event, data) pairs of a job's event stream, read to its end."""
    out, event = [], None
    with client.stream("GET", f"/v1/jobs/{job_id}/events") as r:
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/event-stream")
        for line in r.iter_lines():
            if line.startswith("event: "):
                event = line.removeprefix("event: ")
            elif line.startswith("data: "):
                out.append((event, json.loads(line.removeprefix("data: "))))
    return out


def png_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n", data[:16]
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def rq(svc: Service) -> Redis:
    return Redis(port=svc.redis_port)


def rq_job(svc: Service, job_id: str) -> Job:
    return Job.fetch(job_id, connection=rq(svc))


def no_server_errors(svc: Service) -> None:
    """No request to this service was answered with a 500 (the API counts every answer; the 503s
    of /readyz and of a Redis outage are meant)."""
    with svc.client() as c:
        metrics = c.get("/metrics").text
    counted = [ln for ln in metrics.splitlines() if ln.startswith("cloudgraph_http_requests_total{")]
    assert counted, metrics
    assert not [ln for ln in counted if 'status="500"' in ln], counted


def cache_files(svc: Service) -> set:
    return {p.relative_to(svc.data_dir) for p in (svc.data_dir / "cache").rglob("*") if p.is_file()}


def detail(r) -> str:
    body = r.json()
    assert isinstance(body.get("detail"), str), body
    return body["detail"]


# ------------------------------------------------------------------- the service with a worker


@pytest.fixture(scope="module")
def svc(tmp_path_factory):
    s = start_service(tmp_path_factory.mktemp("svc"), workers=1)
    yield s
    try:
        no_server_errors(s)
    finally:
        s.stop()


@pytest.fixture(scope="module")
def client(svc):
    with svc.client() as c:
        yield c


@pytest.fixture(scope="module")
def uploads(client) -> dict:
    """The first upload of each test volume (their answers, checked in the first test)."""
    return {p.name: upload(client, p) for p in (FOG, BLENDER)}


@pytest.fixture(scope="module")
def fog(uploads) -> str:
    return uploads[FOG.name].json()["id"]


@pytest.fixture(scope="module")
def blender(uploads) -> str:
    return uploads[BLENDER.name].json()["id"]


def test_an_upload_is_stored_under_the_sha256_of_its_bytes_and_described(client, uploads):
    first = uploads[FOG.name]
    assert first.status_code == 201, first.text
    vid = first.json()["id"]
    assert vid == hashlib.sha256(FOG.read_bytes()).hexdigest()
    assert first.headers["location"] == f"/v1/volumes/{vid}"

    again = upload(client, FOG, name="renamed.vdb")
    assert again.status_code == 200, again.text
    assert again.json()["id"] == vid

    r = client.get(f"/v1/volumes/{vid}")
    assert r.status_code == 200
    info = r.json()
    assert info["grids"] == [{"name": "density", "type": "float"}]
    assert info["index_bbox"] == [[-5, -4, -5], [5, 4, 5]]
    assert info["voxel_size"] == pytest.approx([0.2] * 3, rel=1e-6)
    assert info["bytes"] == FOG.stat().st_size and info["format"] == "vdb"

    r = client.get("/v1/volumes")
    assert r.status_code == 200
    listed = {v["id"]: v for v in r.json()}
    assert set(listed) == {vid, uploads[BLENDER.name].json()["id"]}
    assert uploads[BLENDER.name].status_code == 201


def test_a_precompute_streams_its_stages_then_the_cache_has_a_graph(client, blender):
    r = client.post("/v1/caches", json=blender_cache(blender))
    assert r.status_code == 202, r.text
    body = r.json()
    job = job_of(r)
    assert body["job"] == f"/v1/jobs/{job}" and job == f"cache-{body['id']}"
    assert body["status"] in ("queued", "running")

    events = sse(client, job)
    names = [e for e, _ in events]
    assert names[-1] == "end" and set(names[:-1]) == {"progress"}, names
    progress = [d for e, d in events if e == "progress"]
    fractions = [d["fraction"] for d in progress]
    assert fractions == sorted(fractions), fractions
    stages = [d["stage"] for d in progress if d["status"] == "running"]
    assert {"reinforce", "lighting", "transport"} & set(stages), stages  # several stages seen
    assert len(set(stages)) >= 2, stages
    end = events[-1][1]
    assert end["status"] == "finished" and end["fraction"] == 1.0 and end["stage"] == "done"

    r = client.get(f"/v1/caches/{body['id']}")
    assert r.status_code == 200
    cache = r.json()
    assert cache["status"] == "finished"
    assert cache["stats"]["nodes"] > 1000 and cache["stats"]["edges"] > cache["stats"]["nodes"]
    assert set(cache["keys"]) == {"volume_id", "graph_key", "radiance_key"}

    again = client.post("/v1/caches", json=blender_cache(blender))
    assert again.status_code == 200 and again.json()["id"] == body["id"]
    assert "location" not in again.headers


def test_renders_on_a_ready_cache_come_back_in_the_response(client, fog):
    scene = fog_scene(fog, width=40, height=24)
    r = client.post("/v1/caches", json=cache_of(scene))
    assert r.status_code in (200, 202), r.text
    assert wait_job(client, f"cache-{r.json()['id']}")["status"] == "finished"

    png = client.post("/v1/renders", json={"scene": scene, "quality": "draft"})
    assert png.status_code == 200, png.text
    assert png.headers["content-type"] == "image/png"
    assert png_size(png.content) == (40, 24)
    assert float(png.headers["x-render-seconds"]) >= 0
    job = client.get(f"/v1/jobs/{png.headers['x-job-id']}").json()
    assert job["kind"] == "render" and job["status"] == "finished"
    assert client.get(job["result_url"]).content == png.content

    exr = client.post("/v1/renders", json={"scene": scene, "quality": "draft", "format": "exr"})
    assert exr.status_code == 200, exr.text
    assert exr.headers["content-type"] == "image/x-exr"
    assert exr.content[:4] == b"\x76\x2f\x31\x01"  # the OpenEXR magic number
    assert b"dataWindow" in exr.content[:1024]

    vp = client.post("/v1/renders", json={"scene": fog_scene(fog, 16), "integrator": "volpath"})
    assert vp.status_code == 200, vp.text
    assert png_size(vp.content) == (16, 16)


def test_a_render_before_its_cache_waits_on_the_precompute(svc, client, fog):
    scene = fog_scene(fog, 24, density=4.0)  # a cache nobody has asked for
    r = client.post("/v1/renders", json={"scene": scene, "quality": "draft"})
    assert r.status_code == 202, r.text
    render = job_of(r)
    assert r.json()["kind"] == "render" and r.json()["status"] in ("waiting", "queued", "running")

    cache = client.post("/v1/caches", json=cache_of(scene))  # the render started it
    assert cache.status_code in (200, 202) and cache.json()["status"] != "canceled"
    end = wait_job(client, render)
    assert end["status"] == "finished", end
    assert wait_job(client, f"cache-{cache.json()['id']}")["status"] == "finished"
    assert rq_job(svc, render).started_at >= rq_job(svc, f"cache-{cache.json()['id']}").ended_at
    img = client.get(end["result_url"])
    assert img.status_code == 200 and img.headers["content-type"] == "image/png"
    assert png_size(img.content) == (24, 24)


def test_a_render_waiting_on_a_failing_precompute_fails_and_says_why(svc, client, fog):
    scene = fog_scene(fog, 8)
    scene["volume"]["grid"] = "temperature"  # the fog sphere has only 'density': the build fails
    r = client.post("/v1/renders", json={"scene": scene, "quality": "draft"})
    assert r.status_code == 202, r.text
    end = wait_job(client, job_of(r))
    assert end["status"] == "failed", end
    assert "which failed" in end["error"] and "has no grid named 'temperature'" in end["error"], end
    cache = re.search(r"it waited on job (cache-[0-9a-f]+), which failed", end["error"])
    assert cache, end["error"]
    assert client.get(f"/v1/jobs/{cache[1]}").json()["status"] == "failed"
    assert rq(svc).zcard("rq:deferred:cloudgraph") == 0  # it no longer takes room in the queue


def test_an_orbit_animation_becomes_an_mp4_and_its_frames(client, fog):
    body = {
        "scene": fog_scene(fog, 32),
        "orbit": {"elevation": 10},
        "frames": 5,
        "fps": 10,
        "quality": "draft",
    }
    r = client.post("/v1/animations", json=body)
    assert r.status_code == 202, r.text
    anim = job_of(r)
    assert r.json()["kind"] == "animation"
    end = wait_job(client, anim)
    assert end["status"] == "finished", end

    video = client.get(end["result_url"])
    assert video.status_code == 200 and video.headers["content-type"] == "video/mp4"
    assert video.content[4:8] == b"ftyp"
    info = client.get(f"/v1/animations/{anim}").json()
    assert info["frames"] == 5 and info["frames_done"] == [0, 1, 2, 3, 4]
    frames = [client.get(f"/v1/animations/{anim}/frames/{i}") for i in (0, 4)]
    assert [f.status_code for f in frames] == [200, 200]
    assert png_size(frames[0].content) == (32, 32)
    assert frames[0].content != frames[1].content  # the camera moved
    outside = client.get(f"/v1/animations/{anim}/frames/5")
    assert outside.status_code == 404 and "outside 0..4" in detail(outside)


def test_the_same_cache_asked_for_at_once_is_one_precompute(svc, client, fog):
    body = cache_of(fog_scene(fog, density=6.0))

    def post(_):
        with svc.client() as c:
            return c.post("/v1/caches", json=body)

    with ThreadPoolExecutor(6) as pool:
        answers = list(pool.map(post, range(6)))
    assert {a.status_code for a in answers} <= {200, 202}, [a.text for a in answers]
    assert len({a.json()["id"] for a in answers}) == 1
    assert len({a.json()["job"] for a in answers}) == 1
    job = answers[0].json()["job"].removeprefix("/v1/jobs/")
    assert wait_job(client, job)["status"] == "finished"

    again = client.post("/v1/caches", json=body)
    assert again.status_code == 200 and again.json()["status"] == "finished"
    time.sleep(0.5)  # a duplicate in the queue would have run by now
    assert len(rq_job(svc, job).results()) == 1  # one execution
    assert rq(svc).llen("rq:queue:cloudgraph") == 0


# ------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    "mutate, status, words",
    [
        (
            lambda b: b["scene"]["camera"].update(fov=0),
            422,
            "scene.camera.fov: Input should be greater than 0",
        ),
        (lambda b: b["scene"]["camera"].update(width=0), 422, "scene.camera.width: Input should be greater"),
        (lambda b: b["scene"]["camera"].update(eye=[0, 2, 0]), 422, "eye and target must differ"),
        (lambda b: b["scene"]["camera"].update(width=3000), 422, "image 3000x32 is over the limit of 2048"),
        (lambda b: b["scene"]["render"].update(spp=5000), 422, "spp 5000 is over the limit of 4096"),
        (lambda b: b["scene"]["medium"].update(density_scale=-1), 422, "scene.medium.density_scale"),
        (lambda b: b["scene"]["volume"].update(id="0" * 64), 404, "upload it with POST /v1/volumes"),
        (lambda b: b.update(integrator="photon"), 422, "integrator: Input should be 'graph' or 'volpath'"),
        (lambda b: b.update(colour="red"), 422, "colour: Extra inputs are not permitted"),
        (lambda b: b.pop("scene"), 422, "scene: Field required"),
    ],
)
def test_a_bad_render_body_gets_a_4xx_that_says_what_is_wrong(client, fog, mutate, status, words):
    body = {"scene": fog_scene(fog), "quality": "draft"}
    mutate(body)
    r = client.post("/v1/renders", json=body)
    assert r.status_code == status, r.text
    assert words in detail(r)


def test_other_bad_requests_get_a_4xx_that_says_what_is_wrong(client, fog, tmp_path):
    r = client.post("/v1/renders", content=b'{"scene": ', headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert detail(r) == "the body is not valid JSON: Expecting value at character 10"
    r = client.post("/v1/renders", content=b"[1]", headers={"content-type": "application/json"})
    assert r.status_code == 422 and detail(r).startswith("the request body: Input should be a valid dict")

    for path, words in [
        ("/v1/jobs/no-such-job", "no job 'no-such-job'"),
        ("/v1/volumes/" + "a" * 64, "no volume with id"),
        ("/v1/volumes/" + "g" * 64, "no volume with id"),
        ("/v1/caches/abc", "start one with POST /v1/caches"),
        ("/v1/renders/render-nope/image", "no render job"),
        ("/v1/animations/anim-nope", "no animation"),
    ]:
        r = client.get(path)
        assert r.status_code == 404, (path, r.text)
        assert words in r.text, (path, r.text)

    bad = tmp_path / "notes.vdb"
    bad.write_text("not a volume at all")
    r = upload(client, bad)
    assert r.status_code == 422, r.text
    assert "notes.vdb is neither an OpenVDB" in detail(r)
    empty = tmp_path / "empty.vdb"
    empty.write_bytes(b"")
    r = upload(client, empty)
    assert r.status_code == 422 and "upload is empty" in detail(r)
    r = client.post("/v1/volumes", data={"name": "x"})
    assert r.status_code == 422 and "multipart form field named 'file'" in detail(r)

    r = client.post("/v1/caches", json={"volume": {"id": "f" * 64}, "quality": "draft"})
    assert r.status_code == 404 and "upload it with POST /v1/volumes" in detail(r)
    r = client.post("/v1/caches", json={"volume": {"id": fog}, "quality": "best"})
    assert r.status_code == 422 and "quality: Input should be 'draft', 'default' or 'high'" in detail(r)

    anim = {"scene": fog_scene(fog), "orbit": {}, "quality": "draft"}
    r = client.post("/v1/animations", json=anim | {"frames": 601})
    assert r.status_code == 422 and "frames 601 is over the limit of 600" in detail(r)
    r = client.post("/v1/animations", json={k: v for k, v in anim.items() if k != "orbit"} | {"frames": 3})
    assert r.status_code == 422 and "exactly one of 'keyframes'" in detail(r)


def test_cancelling_a_finished_job_is_409(client, fog):
    r = client.post("/v1/renders", json={"scene": fog_scene(fog, 8), "integrator": "volpath"})
    assert r.status_code == 200, r.text
    job = r.headers["x-job-id"]
    r = client.post(f"/v1/jobs/{job}/cancel")
    assert r.status_code == 409 and "has already ended (finished)" in detail(r)
    assert client.get(f"/v1/jobs/{job}").json()["status"] == "finished"
    assert client.post("/v1/jobs/no-such-job/cancel").status_code == 404


def test_a_running_precompute_stops_at_its_next_report_and_the_api_stays_quick(svc, client, fog):
    smoke = upload(client, SMOKE)
    assert smoke.status_code == 201, smoke.text
    before = cache_files(svc)
    r = client.post("/v1/caches", json=cache_of(smoke_scene(smoke.json()["id"], 0.37), "default"))
    assert r.status_code == 202, r.text
    job = job_of(r)
    wait_stage(client, job)

    latencies = []  # the worker is busy with a precompute of 40 s or so
    for _ in range(10):
        t0 = time.perf_counter()
        assert client.get("/healthz").status_code == 200
        latencies.append(time.perf_counter() - t0)
        time.sleep(0.05)
    assert max(latencies) < 0.5, latencies

    r = client.post(f"/v1/jobs/{job}/cancel")
    assert r.status_code == 200, r.text
    assert r.json()["status"] == "canceled"
    rjob = rq_job(svc, job)
    wait_until(lambda: rjob.get_status() == JobStatus.STOPPED, 60, "the precompute did not stop")
    assert len(rjob.results()) == 1 and "JobCancelled" in rjob.latest_result().exc_string  # not retried
    assert client.get(f"/v1/jobs/{job}").json()["status"] == "canceled"
    assert client.post(f"/v1/jobs/{job}/cancel").status_code == 409
    assert cache_files(svc) == before  # nothing written, nothing half-written
    # the worker is free again: a quick render comes straight back
    r = client.post("/v1/renders", json={"scene": fog_scene(fog, 8), "integrator": "volpath"})
    assert r.status_code == 200, r.text


# -------------------------------------------------------------- a service without a worker


@pytest.fixture(scope="module")
def idle(tmp_path_factory):
    """No worker at first, a 1 MiB upload limit and room for four waiting jobs."""
    s = start_service(tmp_path_factory.mktemp("idle"), workers=0, MAX_UPLOAD_MB=1, MAX_QUEUED=4)
    yield s
    try:
        no_server_errors(s)
    finally:
        s.stop()


def test_without_a_worker_readyz_is_503_and_healthz_200(idle):
    with idle.client() as c:
        assert c.get("/healthz").json() == {"status": "ok"}
        r = c.get("/readyz")
        assert r.status_code == 503 and "no worker is alive" in detail(r)
        r = c.get("/metrics")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
        assert "cloudgraph_workers 0.0" in r.text
        assert 'cloudgraph_http_requests_total{method="GET",route="/readyz",status="503"} 1.0' in r.text


def test_an_upload_over_the_size_limit_is_413(idle):
    with idle.client() as c:
        r = upload(c, SMOKE)  # 2.5 MB
        assert r.status_code == 413, r.text
        assert "upload is over the limit of 1 MiB" in detail(r)
        assert c.get("/v1/volumes").json() == []
        assert not [p for p in (idle.data_dir / "volumes").iterdir() if p.is_file()]


def test_jobs_waiting_on_a_cancelled_precompute_are_cancelled_too(idle):
    with idle.client() as c:
        vid = upload(c, FOG).json()["id"]
        scene = fog_scene(vid, 8, density=9.0)
        render = c.post("/v1/renders", json={"scene": scene, "quality": "draft"})
        anim = c.post("/v1/animations", json={"scene": scene, "orbit": {}, "frames": 4, "quality": "draft"})
        assert (render.status_code, anim.status_code) == (202, 202), (render.text, anim.text)
        assert render.json()["status"] == anim.json()["status"] == "waiting"
        cache = c.post("/v1/caches", json=cache_of(scene))
        assert cache.status_code == 202

        r = c.post(f"{cache.json()['job']}/cancel")
        assert r.status_code == 200 and r.json()["status"] == "canceled"
        for job in (job_of(render), job_of(anim)):
            j = c.get(f"/v1/jobs/{job}").json()
            assert j["status"] == "canceled", j
            assert j["error"].endswith("which was cancelled"), j
        waiting = [ln for ln in c.get("/metrics").text.splitlines() if ln.startswith("cloudgraph_jobs_")]
        assert "cloudgraph_jobs_waiting 0.0" in waiting and "cloudgraph_jobs_queued 0.0" in waiting, waiting


def test_a_cancelled_queued_job_never_runs_and_a_full_queue_answers_429(idle):
    with idle.client() as c:
        vid = upload(c, FOG).json()["id"]
        first = c.post("/v1/caches", json=cache_of(fog_scene(vid, density=1.0)))
        assert first.status_code == 202
        job = job_of(first)
        r = c.post(f"/v1/jobs/{job}/cancel")
        assert r.status_code == 200 and r.json()["status"] == "canceled"
        r = c.post(f"/v1/jobs/{job}/cancel")
        assert r.status_code == 409 and "already ended (canceled)" in detail(r)

        others = [
            c.post("/v1/caches", json=cache_of(fog_scene(vid, density=d))) for d in (2.0, 3.0, 4.0, 5.0)
        ]
        assert [o.status_code for o in others] == [202] * 4
        full = c.post("/v1/caches", json=cache_of(fog_scene(vid, density=6.0)))
        assert full.status_code == 429, full.text
        assert full.headers["retry-after"] == "10"
        assert "the render queue is full (4 jobs waiting)" in detail(full)
        full = c.post("/v1/renders", json={"scene": fog_scene(vid, 8), "integrator": "volpath"})
        assert full.status_code == 429

        # a worker comes: it is ready, runs the four, and never the cancelled one
        idle.start_worker()
        idle.wait_ready()
        assert c.get("/readyz").json()["workers"] == 1
        assert "cloudgraph_workers 1.0" in c.get("/metrics").text
        for o in others:
            assert wait_job(c, job_of(o))["status"] == "finished"
        assert c.get(f"/v1/jobs/{job}").json()["status"] == "canceled"
        rjob = rq_job(idle, job)
        assert rjob.get_status() == JobStatus.CANCELED and rjob.results() == []

        # asked for again, the cancelled cache starts afresh and is built
        again = c.post("/v1/caches", json=cache_of(fog_scene(vid, density=1.0)))
        assert again.status_code == 202, again.text
        assert job_of(again) == job
        assert wait_job(c, job)["status"] == "finished"


# ------------------------------------------------------------------------------------ auth


def test_with_api_keys_v1_needs_the_key_and_health_does_not(tmp_path):
    s = start_service(tmp_path / "auth", workers=0, API_KEYS=f"{KEY},another-key-0123456789")
    try:
        with s.client() as c:
            r = c.get("/v1/volumes")
            assert r.status_code == 401, r.text
            assert r.headers["www-authenticate"] == "Bearer"
            assert "send 'Authorization: Bearer <key>'" in detail(r)
            for auth in ("Bearer wrong-key-wrong-key", f"Basic {KEY}", KEY, "Bearer", f"Bearer {KEY[:-1]}"):
                r = c.get("/v1/volumes", headers={"Authorization": auth})
                assert r.status_code == 401, auth
            r = upload(c, FOG)
            assert r.status_code == 401
            assert c.get("/v1/jobs/x", headers={"Authorization": "Bearer nope"}).status_code == 401

            good = {"Authorization": f"Bearer {KEY}"}
            assert c.get("/v1/volumes", headers=good).json() == []
            with open(FOG, "rb") as f:
                r = c.post("/v1/volumes", files={"file": ("fog.vdb", f)}, headers=good)
            assert r.status_code == 201, r.text
            r = c.get("/v1/volumes", headers={"Authorization": "Bearer another-key-0123456789"})
            assert r.status_code == 200 and len(r.json()) == 1
            assert c.get("/v1/jobs/x", headers=good).status_code == 404

            assert c.get("/healthz").status_code == 200
            assert c.get("/readyz").status_code == 503  # no worker; but not 401
            assert c.get("/metrics").status_code == 200
        no_server_errors(s)
    finally:
        s.stop()


def test_without_api_keys_v1_needs_none(client):
    assert client.get("/v1/volumes").status_code == 200
    assert client.get("/v1/volumes", headers={"Authorization": "Bearer anything"}).status_code == 200


# ---------------------------------------------------------------------------------- faults


def test_a_killed_workers_job_is_retried_by_another_and_leaves_no_partial_cache(tmp_path):
    s = start_service(tmp_path / "kill", workers=2, HEARTBEAT_S=2)
    try:
        with s.client() as c:
            vid = upload(c, SMOKE).json()["id"]
            r = c.post("/v1/caches", json=cache_of(smoke_scene(vid, 0.37)))
            assert r.status_code == 202, r.text
            job = job_of(r)
            assert c.get("/readyz").json()["workers"] == 2
            building = ("group", "reinforce")  # the graph is being built: nothing is written yet
            wait_until(lambda: c.get(f"/v1/jobs/{job}").json()["stage"] in building, 120, "no graph build")
            redis = rq(s)
            name = rq_job(s, job).worker_name
            pid = next(w.pid for w in Worker.all(connection=redis) if w.name == name)
            victim = next(w for w in s.workers if w.pid == pid)
            os.kill(victim.pid, signal.SIGKILL)
            victim.wait(10)

            end = wait_job(c, job, timeout=180)
            assert end["status"] == "finished", end
            assert end["result"]["stats"]["nodes"] > 1000
            rjob = rq_job(s, job)
            assert rjob.worker_name != name
            assert rjob.retries_left == 1  # one of the two retries used
            assert [r.type for r in rjob.results()] == [Result.Type.SUCCESSFUL]

            files = [p for p in (s.data_dir / "cache").rglob("*") if p.is_file()]
            assert sorted(p.parent.name for p in files) == ["graphs", "radiance"], files
            for p in files:  # whole files, complete archives
                assert p.suffix == ".npz" and not p.name.startswith(".")
                with np.load(p) as z:
                    assert len(z.files) > 2
            # the dead worker is no longer counted (its heartbeat is older than HEARTBEAT_S + 15 s)
            r = c.get("/readyz")
            assert r.status_code == 200 and r.json()["workers"] == 1, r.text
            assert "cloudgraph_workers 1.0" in c.get("/metrics").text

            # and when the last worker dies too, /readyz says so within HEARTBEAT_S + 15 s
            os.kill(next(w for w in s.workers if w is not victim).pid, signal.SIGKILL)
            r = wait_until(lambda: (r := c.get("/readyz")).status_code == 503 and r, 30, "still ready")
            assert "no worker is alive" in detail(r)
        no_server_errors(s)
    finally:
        s.stop()


def test_a_queued_render_survives_a_redis_restart(tmp_path):
    s = start_service(tmp_path / "aof", workers=0)
    try:
        with s.client() as c:
            vid = upload(c, FOG).json()["id"]
            scene = fog_scene(vid, 16, density=7.0)
            r = c.post("/v1/renders", json={"scene": scene, "quality": "draft"})
            assert r.status_code == 202, r.text  # its cache is not built: a job that waits on it
            render = job_of(r)
            assert r.json()["status"] == "waiting"

            s.stop_redis()
            r = c.get(f"/v1/jobs/{render}")  # meanwhile: a clear 503, not a 500
            assert r.status_code == 503 and r.headers["retry-after"] == "5", r.text
            assert "the job store (Redis) is not reachable" in detail(r)
            r = c.get("/readyz")
            assert r.status_code == 503 and "redis is not reachable" in detail(r)
            assert c.get("/healthz").status_code == 200
            s.start_redis()
            assert c.get(f"/v1/jobs/{render}").json()["status"] == "waiting"
            s.start_worker()
            end = wait_job(c, render, timeout=120)
            assert end["status"] == "finished", end
            img = c.get(end["result_url"])
            assert img.status_code == 200 and png_size(img.content) == (16, 16)
        no_server_errors(s)
    finally:
        s.stop()


def test_a_render_whose_client_left_is_cancelled(tmp_path):
    import httpx
    from redis import Redis
    from rq import Queue

    s = start_service(tmp_path / "gone", workers=0)  # nothing runs: the render waits in the queue
    try:
        with s.client() as c:
            vid = upload(c, FOG).json()["id"]
        queue = Queue("cloudgraph", connection=Redis(port=s.redis_port))
        with pytest.raises(httpx.ReadTimeout), s.client(timeout=1.0) as c:
            c.post("/v1/renders", json={"scene": fog_scene(vid, 16), "integrator": "volpath"})
        wait_until(lambda: queue.count == 0, 5, "the render stayed queued after its client left")
        assert len(queue.canceled_job_registry) == 1
    finally:
        s.stop()
