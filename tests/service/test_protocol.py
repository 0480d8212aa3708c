"""The typed boundaries between the API and the workers: job payloads by name, validated at both
ends; a cache's radiance key handed down with a render; settings declared once, read at start-up."""

from __future__ import annotations

import inspect
import os
import subprocess
import sys
from pathlib import Path

import pytest
from rq import Queue

from cloudgraph_service.errors import PayloadError
from cloudgraph_service.protocol import (
    PAYLOAD,
    RENDER_JOB,
    EncodeJob,
    FramesJob,
    PrecomputeJob,
    RenderJob,
    enqueue_payload,
    render_path,
)
from cloudgraph_service.settings import Settings

from ..harness import ROOT, cache_of, fog_scene, free_port, rq, rq_job, wait_job

PAYLOADS = (PrecomputeJob, RenderJob, FramesJob, EncodeJob)


def _function(payload) -> object:
    module, _, name = payload.FUNC.rpartition(".")
    return getattr(__import__(module, fromlist=[name]), name)


# ---------------------------------------------------------------------------------- payloads
@pytest.mark.parametrize("payload", PAYLOADS, ids=lambda p: p.__name__)
def test_every_job_function_takes_its_payload_by_name_and_nothing_else(payload):
    params = inspect.signature(_function(payload)).parameters
    assert list(params) == [PAYLOAD]
    assert params[PAYLOAD].kind is inspect.Parameter.POSITIONAL_OR_KEYWORD
    assert params[PAYLOAD].default is inspect.Parameter.empty


def test_a_render_payload_round_trips_through_json_unchanged():
    sent = RenderJob(
        scene=fog_scene("v" * 64),
        integrator="graph",
        estimator="gather",
        quality="draft",
        format="exr",
        exposure=-1.5,
        out="/data/outputs/renders/render-1.exr",
        radiance_key="abc",
    )
    kwargs = sent.job_kwargs()
    assert list(kwargs) == [PAYLOAD]
    assert RenderJob.received(kwargs[PAYLOAD]) == sent


def test_a_payload_missing_a_field_is_refused_at_the_worker_before_any_work():
    from worker.jobs import render_job

    payload = RenderJob(
        scene=fog_scene("v" * 64),
        integrator="graph",
        estimator="gather",
        quality="draft",
        format="png",
        exposure=0.0,
        out="/nowhere/x.png",
    ).model_dump(mode="json")
    del payload["out"]
    with pytest.raises(PayloadError) as err:
        render_job(payload)  # no worker state, no volume: it stops at the payload
    assert str(err.value) == f"{RENDER_JOB} refused its payload: out: Field required"


def test_a_payload_with_a_wrong_or_unknown_field_is_refused_and_each_is_named():
    from worker.jobs import frames_job

    payload = {
        "scene": {},
        "cameras": [],
        "first": "two",
        "integrator": "graph",
        "estimator": "gather",
        "quality": "draft",
        "exposure": 0.0,
        "out_dir": "/nowhere",
        "fps": 24,  # the encode job's, not this one's
    }
    with pytest.raises(PayloadError) as err:
        frames_job(payload)
    message = str(err.value)
    assert message.startswith("worker.jobs.frames_job refused its payload: ")
    assert "cameras: List should have at least 1 item" in message
    assert "first: Input should be a valid integer" in message
    assert "fps: Extra inputs are not permitted" in message
    with pytest.raises(PayloadError, match="format: Input should be 'png' or 'exr'"):
        RenderJob.received({**payload, "format": "gif"})
    with pytest.raises(PayloadError, match=r"the payload: Input should be a valid dictionary"):
        EncodeJob.received(["/data/outputs/animations/anim-1", 24.0, 2])  # by position: refused


def test_a_refused_payload_fails_its_job_once_and_the_log_says_why(svc, client):
    queue = Queue("cloudgraph", connection=rq(svc))
    job = queue.enqueue(
        RENDER_JOB,
        kwargs={PAYLOAD: {"scene": {}, "integrator": "graph"}},  # a sender that forgot the rest
        job_timeout=60,
        meta={"kind": "render", "stage": "queued", "fraction": 0.0},
    )
    end = wait_job(client, job.id, timeout=60)
    assert end["status"] == "failed", end
    assert end["error"] == (
        f"an internal error ended job {job.id}; the service log has the details under that id"
    )
    assert len(rq_job(svc, job.id).results()) == 1  # not rerun: it would be refused again
    log = (svc.data_dir / "worker0.log").read_text()
    assert f"{RENDER_JOB} refused its payload: estimator: Field required; quality: Field required" in log


# ------------------------------------------------------------------- payloads of the routes
def _finished_cache(client, scene) -> dict:
    r = client.post("/v1/caches", json=cache_of(scene))
    assert r.status_code in (200, 202), r.text
    assert wait_job(client, f"cache-{r.json()['id']}")["status"] == "finished"
    return client.get(f"/v1/caches/{r.json()['id']}").json()


def test_the_routes_enqueue_payloads_by_name_and_a_ready_cache_hands_its_key_down(svc, client, fog):
    scene = fog_scene(fog, 16, density=3.5)  # a cache of this test's own
    first = client.post("/v1/renders", json={"scene": scene, "quality": "draft"})
    assert first.status_code == 202, first.text  # before its cache: a job that waits on it
    cache = _finished_cache(client, scene)
    precompute = rq_job(svc, f"cache-{cache['id']}")
    assert precompute.args == ()
    sent = PrecomputeJob.received(precompute.kwargs[PAYLOAD])
    assert sent.quality == "draft" and sent.scene["volume"]["id"] == fog

    render = rq_job(svc, first.json()["id"])
    assert render.args == ()
    assert RenderJob.received(render.kwargs[PAYLOAD]).radiance_key is None  # not known yet

    ready = client.post("/v1/renders", json={"scene": scene, "quality": "draft"})
    assert ready.status_code == 200, ready.text
    sent = RenderJob.received(rq_job(svc, ready.headers["x-job-id"]).kwargs[PAYLOAD])
    assert sent.radiance_key == cache["keys"]["radiance_key"]
    assert sent.out == str(render_path(svc.data_dir / "outputs", ready.headers["x-job-id"], "png"))
    assert wait_job(client, first.json()["id"])["status"] == "finished"


def test_an_animation_sends_one_scene_and_its_cameras_to_each_frames_job(svc, client, fog):
    scene = fog_scene(fog, 8)
    cameras = [scene["camera"], {**scene["camera"], "eye": [1, 2, 6]}]
    body = {"scene": scene, "keyframes": cameras, "frames": 5, "integrator": "volpath", "fps": 10}
    r = client.post("/v1/animations", json=body)
    assert r.status_code == 202, r.text
    anim = rq_job(svc, r.json()["id"])
    assert anim.args == ()
    encode = EncodeJob.received(anim.kwargs[PAYLOAD])
    assert (encode.fps, encode.frames) == (10.0, 5)
    sent = [FramesJob.received(rq_job(svc, c).kwargs[PAYLOAD]) for c in anim.meta["children"]]
    assert [(p.first, len(p.cameras)) for p in sent] == [(0, 4), (4, 1)]
    assert all(p.scene == sent[0].scene and p.out_dir == encode.out_dir for p in sent)
    assert sent[0].cameras[0]["eye"] == [0.0, 2.0, 6.0] and sent[1].cameras[0]["eye"] == [1.0, 2.0, 6.0]
    assert wait_job(client, anim.id)["status"] == "finished"
    assert sorted(p.name for p in Path(encode.out_dir).glob("frame_*.png")) == [
        f"frame_{i:05d}.png" for i in range(5)
    ]


def test_a_handed_radiance_key_that_is_not_the_scenes_is_checked_and_not_used(svc, client, fog):
    scene = fog_scene(fog, 16, density=4.5)
    cache = _finished_cache(client, scene)
    queue = Queue("cloudgraph", connection=rq(svc))
    means = []
    for key in (cache["keys"]["radiance_key"], "not-this-scenes-key"):
        out = svc.data_dir / "outputs" / "renders" / f"protocol-{key}.png"
        payload = RenderJob(
            scene=scene,
            integrator="graph",
            estimator="gather",
            quality="draft",
            format="png",
            exposure=0.0,
            out=str(out),
            radiance_key=key,
        )
        job = enqueue_payload(queue, payload, job_timeout=120, meta={"kind": "render", "stage": "queued"})
        end = wait_job(client, job.id)
        assert end["status"] == "finished", end
        assert out.is_file()
        means.append(end["result"]["mean"])
    assert means[0] > 0 and means[1] == pytest.approx(means[0], rel=1e-4)  # the same cache
    log = (svc.data_dir / "worker0.log").read_text()
    assert "was handed radiance key not-this-scenes-key, but its scene's is " in log


# ---------------------------------------------------------------------------------- settings
#: The settings and their defaults as the service had them before they were declared once (a
#: dataclass plus from_env parsing; api.md, "Settings", names them): none renamed, none changed.
DEFAULTS = {
    "CACHE_DIR": None,
    "REDIS_URL": "redis://127.0.0.1:6379/0",
    "API_KEYS": (),
    "QUEUE": "cloudgraph",
    "MAX_UPLOAD_MB": 512,
    "MAX_BODY_KB": 256,
    "MAX_VOXELS": 268435456,
    "MAX_IMAGE_SIDE": 2048,
    "MAX_SPP": 4096,
    "MAX_FRAMES": 600,
    "MAX_DEPTH": 1000,
    "MAX_VOXEL_TAU": 100.0,
    "MAX_QUEUED": 200,
    "SYNC_MAX_PIXELS": 262144,
    "SYNC_WAIT_S": 60.0,
    "JOB_TIMEOUT_S": 3600,
    "JOB_RETRIES": 2,
    "HEARTBEAT_S": 30,
    "UPLOAD_CHECK_S": 120.0,
    "CACHE_MAX_GB": 20.0,
    "WORKER_RENDERERS": 4,
    "WORKER_THREADS": 0,
    "DASK_SCHEDULER": None,
}
GOOD_KEY = "k3y-for-tests-0123456789abcdef"


@pytest.fixture
def env(monkeypatch, tmp_path):
    """No CLOUDGRAPH_ setting from outside; the working directory is a fresh folder."""
    for name in list(os.environ):
        if name.startswith("CLOUDGRAPH_"):
            monkeypatch.delenv(name)
    monkeypatch.chdir(tmp_path)
    return monkeypatch


def test_the_settings_and_their_defaults_are_those_documented(env, tmp_path):
    s = Settings.from_env()
    assert {k: getattr(s, k) for k in DEFAULTS} == DEFAULTS
    assert s.DATA_DIR == tmp_path / "data"  # made absolute, from the working directory
    assert (s.volumes_dir, s.cache_dir, s.outputs_dir) == (
        tmp_path / "data" / "volumes",
        tmp_path / "data" / "cache",
        tmp_path / "data" / "outputs",
    )
    assert set(type(s).model_fields) == set(DEFAULTS) | {"DATA_DIR"}


def test_each_setting_is_read_from_its_variable_and_an_empty_one_is_unset(env, tmp_path):
    env.setenv("CLOUDGRAPH_DATA_DIR", "d")
    env.setenv("CLOUDGRAPH_CACHE_DIR", str(tmp_path / "c"))
    env.setenv("CLOUDGRAPH_MAX_SPP", "64")
    env.setenv("CLOUDGRAPH_SYNC_WAIT_S", "2.5")
    env.setenv("CLOUDGRAPH_QUEUE", "")
    env.setenv("CLOUDGRAPH_MAX_FRAMES", "")
    env.setenv("CLOUDGRAPH_NOT_A_SETTING", "x")  # other CLOUDGRAPH_ variables are not settings
    s = Settings.from_env()
    assert (s.DATA_DIR, s.cache_dir) == (tmp_path / "d", tmp_path / "c")
    assert (s.MAX_SPP, s.SYNC_WAIT_S) == (64, 2.5)
    assert (s.QUEUE, s.MAX_FRAMES) == ("cloudgraph", 600)
    with pytest.raises(ValueError):
        s.MAX_SPP = 1  # frozen: read once, at start-up


def test_api_keys_are_comma_separated_and_placeholder_or_short_ones_are_refused(env):
    env.setenv("CLOUDGRAPH_API_KEYS", f" {GOOD_KEY} ,, {GOOD_KEY[::-1]},")
    assert Settings.from_env().API_KEYS == (GOOD_KEY, GOOD_KEY[::-1])
    assert GOOD_KEY not in repr(Settings.from_env())  # not in a log that prints the settings
    for bad in ("changeme", "secret", f"{GOOD_KEY},short-key"):
        env.setenv("CLOUDGRAPH_API_KEYS", bad)
        with pytest.raises(ValueError) as err:
            Settings.from_env()
        assert str(err.value) == (
            "CLOUDGRAPH_API_KEYS holds a placeholder or short key; use 16+ random characters"
        )


def test_a_value_that_does_not_parse_is_one_line_naming_its_variable(env):
    env.setenv("CLOUDGRAPH_MAX_SPP", "many")
    with pytest.raises(ValueError) as err:
        Settings.from_env()
    assert str(err.value) == "CLOUDGRAPH_MAX_SPP='many' is not a valid int"
    env.setenv("CLOUDGRAPH_MAX_SPP", "1.5")
    env.setenv("CLOUDGRAPH_CACHE_MAX_GB", "lots")
    with pytest.raises(ValueError) as err:
        Settings.from_env()
    assert str(err.value) == (
        "CLOUDGRAPH_MAX_SPP='1.5' is not a valid int; CLOUDGRAPH_CACHE_MAX_GB='lots' is not a valid float"
    )


def _run(args: list[str], **env) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("CLOUDGRAPH_")}
    return subprocess.run(
        [sys.executable, *args], cwd=ROOT, env={**clean, **env}, capture_output=True, text=True, timeout=60
    )


def test_no_settings_are_read_at_import_and_a_bad_one_stops_the_worker_in_one_line(tmp_path):
    bad = {"CLOUDGRAPH_MAX_SPP": "many", "CLOUDGRAPH_DATA_DIR": str(tmp_path)}
    modules = "server.main, server.deps, server.volume_check, worker.jobs, worker.state, worker.__main__"
    imported = _run(["-c", f"import {modules}"], **bad)
    assert imported.returncode == 0, imported.stderr
    worker = _run(["-m", "worker"], **bad)
    assert worker.returncode == 1
    assert worker.stderr.strip() == "cloudgraph worker: CLOUDGRAPH_MAX_SPP='many' is not a valid int"


def test_the_api_refuses_to_start_with_a_placeholder_key_and_says_why(tmp_path):
    port = free_port()
    api = _run(
        ["-m", "uvicorn", "--factory", "server.main:create_app", "--port", str(port)],
        CLOUDGRAPH_API_KEYS="changethis",
        CLOUDGRAPH_DATA_DIR=str(tmp_path),
    )
    assert api.returncode != 0
    assert api.stderr.strip().splitlines()[-1] == (
        "ValueError: CLOUDGRAPH_API_KEYS holds a placeholder or short key; use 16+ random characters"
    )
