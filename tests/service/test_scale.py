"""One precompute over several workers (worker/chunks.py): the cache is the same bytes as one
process builds, and a chunk whose worker died is redone. Real redis-server and worker processes."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from rq import Queue
from rq.job import Job

from cloudgraph.cache import CacheStore
from cloudgraph.procedural import noise_volume
from cloudgraph.scene import parse_scene
from cloudgraph.volume import load_volume
from worker.chunks import SharedChunks, _Run

from ..engine.test_graph import graph_arrays
from ..harness import (
    BLENDER,
    Service,
    blender_cache,
    free_port,
    job_of,
    rq,
    start_service,
    upload,
    wait_job,
    wait_until,
)


def _helpers(svc) -> list[Job]:
    queue = Queue("cloudgraph", connection=rq(svc))
    ids = queue.finished_job_registry.get_job_ids() + queue.started_job_registry.get_job_ids()
    return [j for j in Job.fetch_many(ids, connection=rq(svc)) if j and j.meta.get("kind") == "helper"]


def test_two_workers_share_one_precompute_and_write_the_bytes_one_process_writes(tmp_path, variant):
    from cloudgraph.precompute import precompute

    svc = start_service(tmp_path / "svc", workers=2, WORKER_THREADS=1)
    runs = svc.data_dir / "cache" / "runs"
    try:
        with svc.client() as c:
            vid = upload(c, BLENDER).json()["id"]
            # A shared precompute cancelled while both workers run its chunks ends on both
            r = c.post("/v1/caches", json={**blender_cache(vid, density=5.0), "quality": "default"})
            job = job_of(r)
            wait_until(
                lambda: c.get(f"/v1/jobs/{job}").json()["stage"] == "reinforce" and _helpers(svc),
                120,
                "the precompute never reached its reinforcement with a helper",
                interval=0.05,
            )
            assert c.post(f"/v1/jobs/{job}/cancel").status_code == 200
            assert wait_job(c, job)["status"] == "canceled"
            wait_until(
                lambda: all(j.get_status() == "finished" for j in _helpers(svc)), 30, "the helper went on"
            )
            # The API reports the cancel at once; the coordinator then waits (a lease at most) for
            # chunks still held before it removes the run's keys and folder
            wait_until(
                lambda: not list(rq(svc).scan_iter("cloudgraph:run:*")) and not any(runs.iterdir()),
                30,
                "the cancelled run left keys or files",
            )

            body = {**blender_cache(vid), "quality": "default"}  # 8 light-path chunks, then flights
            r = c.post("/v1/caches", json=body)
            assert r.status_code == 202, r.text
            assert wait_job(c, job_of(r), timeout=300)["status"] == "finished"
            keys = c.get(f"/v1/caches/{r.json()['id']}").json()["keys"]
        # The other worker helped: its helper job ran chunks of this build, and ends with the run
        wait_until(
            lambda: all(j.get_status() == "finished" for j in _helpers(svc)), 30, "a helper outlived the run"
        )
        helped = [j.return_value()["chunks"] for j in _helpers(svc)]
        assert len(helped) == 2 and helped[-1] >= 2, helped
        assert not list(rq(svc).scan_iter("cloudgraph:run:*"))  # the run's keys are gone
        assert not any(runs.iterdir())  # and its folder
    finally:
        svc.stop()

    # The same cache, built by this process alone
    camera = {"eye": [30, 0, 5], "target": [0, 0, 5], "up": [0, 0, 1]}  # any: the cache does not depend on it
    scene = parse_scene(
        {"medium": body["medium"], "light": body["light"], "volume": {"path": str(BLENDER)}, "camera": camera}
    )
    local = CacheStore(tmp_path / "local")
    cache = precompute(scene, load_volume(BLENDER), "default", local)
    assert cache.keys == keys
    served = CacheStore(svc.data_dir / "cache")
    for path in ("graph_path", "radiance_path", "field_path"):
        mine, theirs = getattr(local, path), getattr(served, path)
        key = keys["graph_key"] if path == "graph_path" else keys["radiance_key"]
        assert mine(key).read_bytes() == theirs(key).read_bytes(), path


@pytest.fixture
def redis_only(tmp_path):
    svc = Service(tmp_path, {}, free_port(), 0)
    svc.start_redis()
    yield rq(svc)
    svc.stop()


def test_a_chunk_whose_worker_died_is_redone_and_the_graph_is_the_same(tmp_path, variant, redis_only):
    """A worker killed while it holds a chunk looks to the others like this: a claimed task whose
    lease is never renewed and whose result never comes."""
    from cloudgraph.build import build_graph
    from cloudgraph.params import build_params
    from cloudgraph.stages import local_chunks

    volume = noise_volume(24, seed=5)
    ds = 1.0 / float(volume.density.max() * volume.voxel_size.max())
    params = build_params(volume, ds, "draft", n_paths=1 << 16)  # 4 light-path chunks
    alone = build_graph(volume, ds, params, local_chunks)

    dead: list[str] = []

    def claim_and_die():  # takes the first chunk it can, then is never heard of again
        run = _Run(redis_only, "died", lease_s=1.0)
        while not dead and not stop.is_set():
            task = run.claim("killed-worker:1")
            if task is not None:
                dead.append(task)

    stop = threading.Event()
    thief = threading.Thread(target=claim_and_die)
    thief.start()
    try:
        with SharedChunks(redis_only, "died", {}, tmp_path / "runs" / "died", lease_s=1.0) as shared:
            shared_graph = build_graph(volume, ds, params, chunks=shared)
    finally:
        stop.set()
        thief.join()
    assert dead and shared.redone >= 1, (dead, shared.redone)
    for a, b in zip(graph_arrays(alone), graph_arrays(shared_graph), strict=True):
        np.testing.assert_array_equal(a, b)
    assert (
        not list(redis_only.scan_iter("cloudgraph:run:*")) and not Path(tmp_path / "runs" / "died").exists()
    )


def test_late_tasks_wait_until_no_other_task_is_left(redis_only):
    """Tasks of a late stage (the field's light march, stages.LATE_STAGES) fill the gaps:
    a helper takes them only when no other task is out, a coordinator only when it asks, and then
    only those of the stage it asks for."""
    from cloudgraph.stages import LAST_STAGES, LATE_STAGES

    assert {"field_tau", "bins", "graph_file"} <= LATE_STAGES
    assert "trace" not in LATE_STAGES
    run = _Run(redis_only, "late", lease_s=1.0)
    assert LAST_STAGES == {"graph_file"}
    run.put(1, 2, late=True)  # the light march, put out first
    run.put(2, 1, late=False)
    run.put(4, 1, late=True, last=True)  # the graph file's bytes, wanted at the very end
    run.put(3, 2, late=True)  # the node bins, wanted before the march's results
    assert run.claim("coordinator", late=False) == "2:0"
    assert run.claim("coordinator", late=False) is None
    assert run.claim_late("coordinator", ["1:1", "1:0"]) == "1:1"  # not the head of the list
    assert redis_only.get(run.key("lease:1:1")) == b"coordinator"
    claims = [run.claim("helper") for _ in range(5)]
    assert claims == ["3:0", "3:1", "1:0", "4:0", None]
    assert run.claim_late("coordinator", ["1:0", "1:1"]) is None  # all taken


def test_a_helper_that_ends_a_chunk_after_its_run_ended_leaves_no_key(redis_only):
    run = _Run(redis_only, "over", lease_s=1.0)
    redis_only.set(run.key("spec"), "{}")
    run.done(3, "3:0")
    assert redis_only.lrange(run.key("done:3"), 0, -1) == [b"3:0"]
    redis_only.delete(run.key("spec"), run.key("done:3"))  # the coordinator ends the run
    run.done(3, "3:1")
    assert not list(redis_only.scan_iter(run.key("*")))
