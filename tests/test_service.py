"""The render service against real processes: redis-server, `python -m worker`, uvicorn."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import struct
import time

import pytest

from .conftest import DATA
from .service import start_service, wait_until

FOG = DATA / "fog_sphere.vdb"
SMOKE = DATA / "smoke1.vdb"
KEY = "k3y-for-tests-0123456789abcdef"


def scene(vid: str, size: int = 32, spp: int = 4, **camera) -> dict:
    """The fog sphere (centre (0, 2, 0), radius 1.1) at optical depth 1 per densest voxel."""
    cam = {"eye": [0, 2, 6], "target": [0, 2, 0], "fov": 30, "width": size, "height": size, **camera}
    return {
        "volume": {"id": vid},
        "medium": {"density_scale": 5.0},
        "light": {"direction": [1, -1, 0]},
        "camera": cam,
        "render": {"spp": spp},
    }


def cache_body(vid: str, **over) -> dict:
    s = scene(vid)
    return {"volume": s["volume"], "medium": s["medium"], "light": s["light"], "quality": "draft", **over}


def upload(client, path):
    with open(path, "rb") as f:
        return client.post("/v1/volumes", files={"file": (path.name, f)})


def wait_job(client, job_id: str, timeout: float = 180) -> dict:
    def done():
        j = client.get(f"/v1/jobs/{job_id}").json()
        return j if j["status"] in ("finished", "failed", "canceled") else None

    return wait_until(done, timeout, f"job {job_id} did not end", interval=0.2)


def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


@pytest.fixture(scope="module")
def svc(tmp_path_factory):
    s = start_service(tmp_path_factory.mktemp("svc"), workers=1)
    yield s
    s.stop()


@pytest.fixture(scope="module")
def client(svc):
    with svc.client() as c:
        yield c


@pytest.fixture(scope="module")
def fog(client) -> str:
    r = upload(client, FOG)
    assert r.status_code in (200, 201), r.text
    return r.json()["id"]


# ------------------------------------------------------------------ the whole flow


def test_upload_is_content_addressed_and_described(client, fog):
    assert fog == hashlib.sha256(FOG.read_bytes()).hexdigest()
    again = upload(client, FOG)
    assert again.status_code == 200 and again.json()["id"] == fog
    info = client.get(f"/v1/volumes/{fog}").json()
    assert info["grids"] == [{"name": "density", "type": "float"}]
    assert info["index_bbox"] == [[-5, -4, -5], [5, 4, 5]]
    assert info["voxel_size"] == pytest.approx([0.2] * 3, rel=1e-5)
    assert fog in [v["id"] for v in client.get("/v1/volumes").json()]


def test_cache_progress_streams_then_renders_come_back_directly(client, fog):
    r = client.post("/v1/caches", json=cache_body(fog))
    assert r.status_code in (200, 202), r.text
    cid = r.json()["id"]
    events = []
    if r.status_code == 202:
        job = r.headers["location"].rsplit("/", 1)[1]
        with client.stream("GET", f"/v1/jobs/{job}/events") as s:
            for line in s.iter_lines():
                if line.startswith("data: "):
                    events.append(json.loads(line[6:]))
        assert events[-1]["status"] == "finished"
        fractions = [e["fraction"] for e in events]
        assert fractions == sorted(fractions) and fractions[-1] == 1.0
    stats = client.get(f"/v1/caches/{cid}").json()["stats"]
    assert stats["nodes"] > 10 and stats["edges"] > stats["nodes"]

    r = client.post("/v1/renders", json={"scene": scene(fog, 48), "quality": "draft"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png" and png_size(r.content) == (48, 48)
    exr = client.post("/v1/renders", json={"scene": scene(fog, 16), "quality": "draft", "format": "exr"})
    assert exr.status_code == 200 and exr.content[:4] == b"\x76\x2f\x31\x01"  # OpenEXR magic
    vp = client.post("/v1/renders", json={"scene": scene(fog, 16), "integrator": "volpath"})
    assert vp.status_code == 200 and png_size(vp.content) == (16, 16)


def test_render_before_its_cache_waits_on_the_precompute(client, fog):
    s = scene(fog, 24)
    s["medium"]["density_scale"] = 4.0  # a cache nobody has built
    r = client.post("/v1/renders", json={"scene": s, "quality": "draft"})
    assert r.status_code == 202, r.text
    assert r.json()["status"] in ("waiting", "queued", "running")
    job = wait_job(client, r.json()["id"])
    assert job["status"] == "finished", job
    img = client.get(job["result_url"])
    assert img.status_code == 200 and png_size(img.content) == (24, 24)


def test_animation_renders_frames_across_workers_into_an_mp4(client, fog):
    r = client.post(
        "/v1/animations",
        json={
            "scene": scene(fog, 32),
            "orbit": {"elevation": 10},
            "frames": 5,
            "fps": 10,
            "quality": "draft",
        },
    )
    assert r.status_code == 202, r.text
    job = wait_job(client, r.json()["id"])
    assert job["status"] == "finished", job
    video = client.get(job["result_url"])
    assert video.status_code == 200 and video.headers["content-type"] == "video/mp4"
    assert video.content[4:8] == b"ftyp"
    frame = client.get(f"/v1/animations/{r.json()['id']}/frames/4")
    assert frame.status_code == 200 and png_size(frame.content) == (32, 32)
    assert client.get(f"/v1/animations/{r.json()['id']}/frames/5").status_code == 404


def test_the_same_cache_twice_is_one_job(client, fog):
    body = cache_body(fog, medium={"density_scale": 6.0})
    a, b = client.post("/v1/caches", json=body), client.post("/v1/caches", json=body)
    assert a.json()["id"] == b.json()["id"] and a.json()["job"] == b.json()["job"]
    wait_job(client, a.json()["job"].rsplit("/", 1)[1])
    c = client.post("/v1/caches", json=body)
    assert c.status_code == 200 and c.json()["status"] == "finished"


# -------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "mutate, status, words",
    [
        (lambda b: b["scene"]["camera"].update(fov=0), 422, "scene.camera.fov"),
        (lambda b: b["scene"]["camera"].update(width=0), 422, "scene.camera.width"),
        (lambda b: b["scene"]["camera"].update(width=5000), 422, "camera.width"),
        (lambda b: b["scene"]["render"].update(spp=70000), 422, "render.spp"),
        (lambda b: b["scene"]["volume"].update(id="0" * 64), 404, "upload it with POST /v1/volumes"),
        (lambda b: b.update(integrator="photon"), 422, "integrator"),
    ],
)
def test_bad_render_bodies_get_a_4xx_with_words(client, fog, mutate, status, words):
    body = {"scene": scene(fog), "quality": "draft"}
    mutate(body)
    r = client.post("/v1/renders", json=body)
    assert r.status_code == status, r.text
    assert words in r.json()["detail"]


def test_other_bad_requests_get_clear_answers(client, fog, tmp_path):
    r = client.post("/v1/renders", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 422 and "JSON" in r.json()["detail"]
    assert client.get("/v1/jobs/nope").status_code == 404
    assert client.get("/v1/volumes/" + "a" * 64).status_code == 404
    assert client.get("/v1/caches/abc").status_code == 404
    bad = tmp_path / "bad.vdb"
    bad.write_text("not a volume")
    r = upload(client, bad)
    assert r.status_code == 422 and "bad.vdb is neither an OpenVDB" in r.json()["detail"]
    r = client.post("/v1/volumes", data={"x": "1"})
    assert r.status_code == 422 and "'file'" in r.json()["detail"]
    r = client.post("/v1/animations", json={"scene": scene(fog), "orbit": {}, "frames": 10_000})
    assert r.status_code == 422 and "frames" in r.json()["detail"]
    r = client.post("/v1/animations", json={"scene": scene(fog), "frames": 3})
    assert r.status_code == 422 and "keyframes" in r.json()["detail"]


# -------------------------------------------------------- limits, queue, cancel, health


@pytest.fixture(scope="module")
def idle(tmp_path_factory):
    """A service with no worker, a 1 MiB upload cap and room for three queued jobs."""
    s = start_service(tmp_path_factory.mktemp("idle"), workers=0, MAX_UPLOAD_MB=1, MAX_QUEUED=3)
    yield s
    s.stop()


def test_without_workers_readyz_is_503_and_health_200(idle):
    with idle.client() as c:
        assert c.get("/healthz").status_code == 200
        r = c.get("/readyz")
        assert r.status_code == 503 and "no worker" in r.json()["detail"]
        metrics = c.get("/metrics").text
        assert "cloudgraph_workers 0.0" in metrics and "cloudgraph_http_requests_total" in metrics


def test_oversized_upload_is_413(idle):
    with idle.client() as c:
        r = upload(c, SMOKE)  # 2.5 MB
        assert r.status_code == 413 and "1 MiB" in r.json()["detail"]


def test_queued_job_cancels_and_a_full_queue_answers_429(idle):
    with idle.client() as c:
        vid = upload(c, FOG).json()["id"]
        first = c.post("/v1/caches", json=cache_body(vid, medium={"density_scale": 1.0}))
        assert first.status_code == 202
        job = first.json()["job"].rsplit("/", 1)[1]
        r = c.post(f"/v1/jobs/{job}/cancel")
        assert r.status_code == 200 and r.json()["status"] == "canceled"
        assert c.post(f"/v1/jobs/{job}/cancel").status_code == 409
        codes = [
            c.post("/v1/caches", json=cache_body(vid, medium={"density_scale": ds})).status_code
            for ds in (2.0, 3.0, 4.0)
        ]
        assert codes == [202, 202, 202]
        last = c.post("/v1/caches", json=cache_body(vid, medium={"density_scale": 5.0}))
        assert last.status_code == 429 and last.headers["retry-after"] == "10"
        assert "queue is full" in last.json()["detail"]


def test_running_precompute_stops_when_cancelled(client):
    vid = upload(client, SMOKE).json()["id"]
    body = cache_body(vid, medium={"density_scale": 0.37}, quality="default")
    job = client.post("/v1/caches", json=body).json()["job"].rsplit("/", 1)[1]
    wait_until(lambda: client.get(f"/v1/jobs/{job}").json()["status"] == "running", 60, "never started")
    t0 = time.monotonic()
    assert client.post(f"/v1/jobs/{job}/cancel").status_code == 200
    end = wait_job(client, job, timeout=120)
    assert end["status"] == "canceled"
    # health answers while the worker is busy
    latency = [client.get("/healthz").elapsed.total_seconds() for _ in range(5)]
    assert max(latency) < 0.5
    assert time.monotonic() - t0 < 120


# ------------------------------------------------------------------------ auth


def test_api_keys_guard_v1_but_not_health(tmp_path):
    s = start_service(tmp_path / "auth", workers=0, API_KEYS=KEY)
    try:
        with s.client() as c:
            assert c.get("/v1/volumes").status_code == 401
            wrong = c.get("/v1/volumes", headers={"Authorization": "Bearer wrong-key-wrong-key"})
            assert wrong.status_code == 401 and "Bearer" in wrong.json()["detail"]
            assert c.get("/v1/volumes", headers={"Authorization": f"Bearer {KEY}"}).status_code == 200
            assert c.get("/healthz").status_code == 200
            assert c.get("/metrics").status_code == 200
    finally:
        s.stop()


# ---------------------------------------------------------------------- faults


def test_killed_worker_leaves_its_job_to_another(tmp_path):
    s = start_service(tmp_path / "kill", workers=2, HEARTBEAT_S=3)
    try:
        with s.client() as c:
            vid = upload(c, SMOKE).json()["id"]
            job = c.post("/v1/caches", json=cache_body(vid, medium={"density_scale": 0.37})).json()["job"]
            job = job.rsplit("/", 1)[1]
            wait_until(lambda: c.get(f"/v1/jobs/{job}").json()["status"] == "running", 60, "never started")
            from redis import Redis
            from rq.job import Job

            redis = Redis(port=s.redis_port)
            name = Job.fetch(job, connection=redis).worker_name
            victim = next(w for w in s.workers if name and name.endswith(str(w.pid)) or _runs(redis, w, name))
            os.kill(victim.pid, signal.SIGKILL)
            assert victim.wait(10) == -signal.SIGKILL
            end = wait_job(c, job, timeout=240)
            assert end["status"] == "finished", end
            assert Job.fetch(job, connection=redis).worker_name != name  # the other worker did it
            assert end["result"]["stats"]["nodes"] > 1000
            cache = s.data_dir / "cache"
            leftovers = [p for p in cache.rglob("*") if p.is_file() and not p.name.endswith(".npz")]
            assert not leftovers  # no half-written file is visible
    finally:
        s.stop()


def _runs(redis, proc, name) -> bool:
    from rq import Worker

    return any(w.name == name and w.pid == proc.pid for w in Worker.all(connection=redis))


def test_queued_job_survives_a_redis_restart(tmp_path):
    s = start_service(tmp_path / "aof", workers=0)
    try:
        with s.client() as c:
            vid = upload(c, FOG).json()["id"]
            r = c.post("/v1/renders", json={"scene": scene(vid, 16), "integrator": "volpath"})
            assert r.status_code == 202  # no worker: not ready, a job
            job = r.json()["id"]
            s.stop_redis()
            s.start_redis()
            s.start_worker()
            end = wait_job(c, job, timeout=120)
            assert end["status"] == "finished"
            assert png_size(c.get(end["result_url"]).content) == (16, 16)
    finally:
        s.stop()
