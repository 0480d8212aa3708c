"""Faults: dead workers, a Redis restart, failures that must run once and end what waits on
them, no worker at all, and jobs that would run for ever."""

from __future__ import annotations

import os
import signal
import time

import httpx
import numpy as np
import pytest
from rq import Queue, Retry, Worker
from rq.job import JobStatus
from rq.results import Result

from ..harness import (
    BLENDER,
    FOG,
    SMOKE,
    assert_no_leak,
    blender_cache,
    cache_of,
    detail,
    fog_scene,
    job_of,
    no_server_errors,
    png_size,
    rq,
    rq_job,
    smoke_scene,
    start_service,
    upload,
    wait_job,
    wait_stage,
    wait_until,
)


def _enqueue(svc, func: str, timeout: int, depends_on=None, retries: int = 2):
    """A job put in the service's queue directly, as the API would (kind, stage, budget)."""
    queue = Queue("cloudgraph", connection=rq(svc))
    return queue.enqueue(
        func,
        job_timeout=timeout,
        retry=Retry(max=retries),
        depends_on=depends_on,
        meta={"kind": "test", "stage": "queued", "fraction": 0.0},
    )


def test_a_killed_workers_job_is_retried_by_another_and_leaves_no_partial_cache(tmp_path):
    s = start_service(tmp_path / "kill", workers=2, HEARTBEAT_S=2)
    try:
        with s.client() as c:
            vid = upload(c, BLENDER).json()["id"]
            r = c.post("/v1/caches", json=blender_cache(vid))
            assert r.status_code == 202, r.text
            job = job_of(r)
            assert c.get("/readyz").json()["workers"] == 2
            wait_stage(c, job)  # killed mid-precompute
            redis = rq(s)
            name = rq_job(s, job).worker_name
            pid = next(w.pid for w in Worker.all(connection=redis) if w.name == name)
            os.kill(pid, signal.SIGKILL)  # the worker process, under its supervisor

            end = wait_job(c, job, timeout=180)
            assert end["status"] == "finished", end
            assert end["result"]["stats"]["nodes"] > 1000
            assert (s.data_dir / "worker0.log").read_text().count("put back in the queue") + (
                s.data_dir / "worker1.log"
            ).read_text().count("put back in the queue") == 1
            rjob = rq_job(s, job)
            assert rjob.worker_name != name
            assert rjob.retries_left == 1  # one of the two retries used
            assert [r.type for r in rjob.results()] == [Result.Type.SUCCESSFUL]

            cache = s.data_dir / "cache"
            files = [p for p in cache.rglob("*") if p.is_file() and p.relative_to(cache).parts[0] != "runs"]
            assert {p.parent.name for p in files} >= {"graphs", "radiance"}, files
            # Of shared-precompute scratch only the killed coordinator's run folder may be left
            # (the next coordinator removes it once stale); the finished run removed its own
            assert len(list((cache / "runs").glob("*"))) <= 1
            for p in files:  # whole files, complete archives
                assert not p.name.startswith("."), p
                if p.suffix == ".npz":
                    with np.load(p) as z:
                        assert len(z.files) > 2
            # the supervisor started a fresh worker process: two workers again
            r = wait_until(lambda: (r := c.get("/readyz")).json().get("workers") == 2 and r, 60, "no restart")
            assert "cloudgraph_workers 2.0" in c.get("/metrics").text

            # when the supervisors die, their worker processes die with them, and /readyz says
            # so within HEARTBEAT_S + 15 s
            for w in s.workers:
                w.send_signal(signal.SIGKILL)
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


def test_without_a_worker_a_sync_render_is_503_at_once_and_readyz_says_why(tmp_path):
    s = start_service(tmp_path / "none", workers=0)
    try:
        with s.client() as c:
            vid = upload(c, FOG).json()["id"]
            t0 = time.perf_counter()
            r = c.post("/v1/renders", json={"scene": fog_scene(vid, 8), "integrator": "volpath"})
            assert time.perf_counter() - t0 < 1.0
            assert r.status_code == 503, r.text
            assert r.headers["retry-after"] == "10" and "no worker is running" in detail(r)
            assert rq(s).llen("rq:queue:cloudgraph") == 0  # nothing was left queued
            big = c.post("/v1/renders", json={"scene": fog_scene(vid, 600), "integrator": "volpath"})
            assert big.status_code == 202, big.text  # a batch render waits for a worker

            assert c.get("/healthz").json() == {"status": "ok"}
            r = c.get("/readyz")
            assert r.status_code == 503 and "no worker is alive" in detail(r)
            assert r.headers["retry-after"] == "10"
            r = c.get("/metrics")
            assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
            assert "cloudgraph_workers 0.0" in r.text
            assert 'cloudgraph_http_requests_total{method="GET",route="/readyz",status="503"} 1.0' in r.text
        no_server_errors(s)
    finally:
        s.stop()


def test_a_deterministic_failure_runs_once_and_ends_what_waits_on_it(tmp_path):
    s = start_service(tmp_path / "fail", workers=0)
    try:
        with s.client() as c:
            vid = upload(c, FOG).json()["id"]
            scene = fog_scene(vid, 8)
            r = c.post("/v1/renders", json={"scene": scene, "quality": "draft"})
            assert r.status_code == 202 and r.json()["status"] == "waiting", r.text
            render = job_of(r)
            cache = f"cache-{c.post('/v1/caches', json=cache_of(scene)).json()['id']}"
            assert c.delete(f"/v1/volumes/{vid}").status_code == 204  # the precompute will fail
            internal = _enqueue(s, "tests.harness.fails_with_a_path", 60)
            s.start_worker()

            end = wait_job(c, render)
            assert end["status"] == "failed", end
            assert end["error"].startswith(f"it waited on job {cache}, which failed: volume "), end
            assert "is not stored (upload it with POST /v1/volumes)" in end["error"]
            failed = c.get(f"/v1/jobs/{cache}").json()
            assert failed["status"] == "failed" and "is not stored" in failed["error"], failed
            assert len(rq_job(s, cache).results()) == 1  # run once: it would fail again
            assert rq(s).zcard("rq:deferred:cloudgraph") == 0  # the render takes no room

            end = wait_job(c, internal.id)
            assert end["status"] == "failed" and len(internal.results()) == 1
            assert end["error"] == (
                f"an internal error ended job {internal.id}; the service log has the details under that id"
            )
            for text in (failed["error"], end["error"]):
                assert_no_leak(text, s)
            log = (s.data_dir / "worker0.log").read_text()
            assert f"job {internal.id} failed" in log and "secret/volume.vdb" in log  # the log keeps it

            # a job queued after what it waits on has failed ends too: at once when asked about,
            late = _enqueue(s, "tests.harness.stuck_forever", 60, depends_on=cache)
            j = c.get(f"/v1/jobs/{late.id}").json()
            assert j["status"] == "failed" and j["error"].startswith(
                f"it waited on job {cache}, which failed"
            )
            # and by the supervisor's sweep when nobody asks
            later = _enqueue(s, "tests.harness.stuck_forever", 60, depends_on=cache)
            wait_until(lambda: later.get_status() == JobStatus.CANCELED, 15, "the late job still waits")
            assert later.get_meta(refresh=True)["failed"] is True
        no_server_errors(s)
    finally:
        s.stop()


def test_a_job_past_its_budget_is_stopped_and_failed_for_good_and_the_worker_goes_on(tmp_path):
    s = start_service(tmp_path / "budget", workers=1, JOB_TIMEOUT_S=8)
    try:
        with s.client() as c:
            vid = upload(c, FOG).json()["id"]
            stuck = _enqueue(s, "tests.harness.stuck_forever", 8)
            wait_until(lambda: stuck.get_status() == JobStatus.STARTED, 30, "the stuck job never started")
            t0 = time.monotonic()

            # meanwhile a render waits behind it; its client leaves, and it is cancelled
            queue = Queue("cloudgraph", connection=rq(s))
            with pytest.raises(httpx.ReadTimeout), s.client(timeout=1.0) as gone:
                gone.post("/v1/renders", json={"scene": fog_scene(vid, 16), "integrator": "volpath"})
            wait_until(lambda: queue.count == 0, 5, "the render stayed queued after its client left")
            assert len(queue.canceled_job_registry) == 1

            # past its budget, /readyz reports the worker stuck until the supervisor acts
            r = wait_until(lambda: (r := c.get("/readyz")).status_code == 503 and r, 20, "never stuck")
            assert "stuck past its job's budget" in detail(r)
            end = wait_job(c, stuck.id, timeout=30)
            took = time.monotonic() - t0
            assert end["status"] == "failed" and end["error"] == "stopped: it ran past its time budget of 8 s"
            assert 8 <= took < 8 + 5 + 5, took
            stuck.refresh()
            assert stuck.get_status() == JobStatus.FAILED and stuck.retries_left == 0  # for good
            assert stuck.id not in queue.started_job_registry.get_job_ids()
            assert queue.count == 0  # nothing brings it back

            # a fresh worker process takes the next job
            s.wait_ready(60)
            r = c.post("/v1/renders", json={"scene": fog_scene(vid, 8), "integrator": "volpath"})
            assert r.status_code == 200, r.text

            # a job busy in Python past its budget is stopped from inside, also once ("high": a
            # default-quality smoke1 precompute now ends within the 8 s on a quiet machine)
            smoke = upload(c, SMOKE).json()["id"]
            r = c.post("/v1/caches", json=cache_of(smoke_scene(smoke, 0.37), "high"))
            job = job_of(r)
            end = wait_job(c, job, timeout=60)
            assert end["status"] == "failed" and end["error"] == "stopped: it ran past its time budget of 8 s"
            assert len(rq_job(s, job).results()) == 1
            # ready again (at once when Python stopped it; after a restart when a native call
            # outlasted the grace and the supervisor had to kill the process)
            wait_until(lambda: c.get("/readyz").status_code == 200, 30, "the service did not become ready")

            # a cancelled job that never reaches a progress report is stopped by force too
            stuck = _enqueue(s, "tests.harness.stuck_forever", 600)
            wait_until(lambda: stuck.get_status() == JobStatus.STARTED, 60, "the stuck job never started")
            r = c.post(f"/v1/jobs/{stuck.id}/cancel")
            assert r.status_code == 200 and r.json()["status"] == "canceled", r.text
            t0 = time.monotonic()
            wait_until(lambda: stuck.get_status() == JobStatus.STOPPED, 30, "the cancelled job still runs")
            assert time.monotonic() - t0 < 10 + 5
            end = c.get(f"/v1/jobs/{stuck.id}").json()
            assert end["status"] == "canceled" and end["error"] == "cancelled by a client", end
            s.wait_ready(60)
            r = c.post("/v1/renders", json={"scene": fog_scene(vid, 8), "integrator": "volpath"})
            assert r.status_code == 200, r.text
        no_server_errors(s)
    finally:
        s.stop()
