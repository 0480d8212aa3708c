"""/v1/jobs: status, events, cancel; a full queue answers 429."""

from __future__ import annotations

import time

from rq.job import JobStatus

from ..harness import (
    FOG,
    SMOKE,
    cache_files,
    cache_of,
    detail,
    fog_scene,
    job_of,
    rq_job,
    smoke_scene,
    upload,
    wait_job,
    wait_stage,
    wait_until,
)


def test_cancelling_a_finished_job_is_409(client, fog):
    r = client.post("/v1/renders", json={"scene": fog_scene(fog, 8), "integrator": "volpath"})
    assert r.status_code == 200, r.text
    job = r.headers["x-job-id"]
    r = client.post(f"/v1/jobs/{job}/cancel")
    assert r.status_code == 409 and "has already ended (finished)" in detail(r)
    assert client.get(f"/v1/jobs/{job}").json()["status"] == "finished"
    assert client.post("/v1/jobs/no-such-job/cancel").status_code == 404


def test_unknown_and_malformed_job_ids_are_404(client):
    for job in ("no-such-job", "a.b", "%C3%A9t%C3%A9", "x" * 3000):
        for path in (f"/v1/jobs/{job}", f"/v1/jobs/{job}/events"):
            r = client.get(path)
            assert r.status_code == 404 and "no job" in detail(r), (path[:40], r.text)
            assert len(r.text) < 300
        assert client.post(f"/v1/jobs/{job}/cancel").status_code == 404


def test_a_running_precompute_stops_at_its_next_report_and_the_api_stays_quick(svc, client, fog):
    smoke = upload(client, SMOKE)
    assert smoke.status_code in (200, 201), smoke.text
    before = cache_files(svc)
    r = client.post("/v1/caches", json=cache_of(smoke_scene(smoke.json()["id"], 0.37), "high"))
    assert r.status_code == 202, r.text
    job = job_of(r)
    wait_stage(client, job)

    latencies = []  # the worker is busy with a precompute of half a minute or more
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
    assert len(rjob.results()) == 1  # not retried
    end = client.get(f"/v1/jobs/{job}").json()
    assert end["status"] == "canceled" and end["error"] == "cancelled by a client", end
    assert client.post(f"/v1/jobs/{job}/cancel").status_code == 409
    assert cache_files(svc) == before  # nothing written, nothing half-written

    # the worker is free again (once the stopped job's work horse is reaped: the service says
    # 503 "try again shortly" until then, enqueuing nothing): a quick render comes straight back
    def render():
        r = client.post("/v1/renders", json={"scene": fog_scene(fog, 8), "integrator": "volpath"})
        return r if r.status_code != 503 else None

    r = wait_until(render, 15, "no worker came free after the cancel", interval=0.2)
    assert r.status_code == 200, r.text


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
        assert r.json()["error"] == "cancelled by a client", r.json()  # (as a running one's says)
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
