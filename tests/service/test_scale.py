"""One precompute over a Dask cluster (cloudgraph_service/dask_chunks.py): the cache is the same
bytes as one process builds, on 1, 2 and 4 Dask workers, when a worker is SIGKILLed in the middle
and when the scheduler is lost; through the service, a precompute job runs on the cluster,
reports its progress and, cancelled, leaves no task behind. Real worker processes
(``distributed.LocalCluster(processes=True)``, ``dask scheduler`` / ``dask worker``), real Redis."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from cloudgraph.cache import CacheStore
from cloudgraph.procedural import noise_volume
from cloudgraph.stages import STAGES

from ..harness import (
    BLENDER,
    blender_cache,
    free_port,
    job_of,
    sse,
    start_service,
    upload,
    wait_job,
    wait_until,
)
from ..helpers import medium_scene

distributed = pytest.importorskip("distributed")

N_PATHS = 1 << 16  # 4 light-path chunks, so that every stage but one has work for 2 workers


def _files(store: CacheStore, cache) -> dict[str, bytes]:
    keys = cache.keys
    return {
        "graph": store.graph_path(keys["graph_key"]).read_bytes(),
        "radiance": store.radiance_path(keys["radiance_key"]).read_bytes(),
        "field": store.field_path(keys["radiance_key"]).read_bytes(),
    }


@pytest.fixture(scope="module")
def cloud(variant, tmp_path_factory) -> dict:
    """A small noise cloud and its cache's bytes, built in this process alone."""
    from cloudgraph.precompute import precompute

    volume = noise_volume(32, seed=7)
    scene = medium_scene(volume, density_scale=1.0 / float(volume.density.max() * volume.voxel_size.max()))
    store = CacheStore(tmp_path_factory.mktemp("alone"))
    return {
        "volume": volume,
        "scene": scene,
        "bytes": _files(store, precompute(scene, volume, "draft", store, n_paths=N_PATHS)),
    }


def _on_dask(cloud, address: str, store: Path, progress=None, **kwargs):
    """(the cache's bytes, its DaskChunks) of the cloud precomputed on the cluster at ``address``."""
    import cloudgraph.precompute as precompute_module
    from cloudgraph.precompute import precompute
    from cloudgraph_service.dask_chunks import precompute_chunks

    store = CacheStore(store)
    precompute_module._KEPT.clear()  # (as a process of its own: every stage on the cluster)
    with precompute_chunks(address, **kwargs) as chunks:
        cache = precompute(cloud["scene"], cloud["volume"], "draft", store, progress, chunks, n_paths=N_PATHS)
    return _files(store, cache), chunks


def _local_cluster(n: int):
    return distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None)


def test_the_cache_is_the_same_bytes_in_process_and_on_1_2_and_4_dask_workers(cloud, tmp_path):
    from cloudgraph_service.dask_chunks import DaskChunks, client

    with _local_cluster(1) as cluster:
        c = client(cluster.scheduler_address)
        for n in (1, 2, 4):
            cluster.scale(n)
            c.wait_for_workers(n, timeout=120)
            with distributed.get_task_stream(c) as tasks:
                files, chunks = _on_dask(cloud, cluster.scheduler_address, tmp_path / str(n))
            assert isinstance(chunks, DaskChunks) and not chunks.lost
            assert files == cloud["bytes"], n
            ran_on = Counter(t["worker"] for t in tasks.data)
            assert {t["key"].split("-")[0] for t in tasks.data} == {*STAGES, "volume", "inputs"}  # all there
            assert len(ran_on) == 1 if n == 1 else len(ran_on) >= 2, ran_on  # shared when it can be
        # Every worker, those that joined after the client, has the client's variant
        import mitsuba as mi

        assert set(c.run(lambda: __import__("mitsuba").variant()).values()) == {mi.variant()}


def test_a_dask_worker_sigkilled_mid_precompute_is_made_good_and_the_bytes_are_the_same(cloud, tmp_path):
    """The worker killed holds a result not yet merged (the graph file's bytes, a late stage put
    out before the transport and wanted at the end; the light march's results are taken as they
    come) and may be running a chunk of the bake: Dask computes them again elsewhere, from the
    inputs and volume scattered to every worker."""
    from cloudgraph_service.dask_chunks import client

    with _local_cluster(2) as cluster:
        c = client(cluster.scheduler_address)
        c.wait_for_workers(2, timeout=120)
        killed = {}

        def progress(stage, fraction):  # in the bake
            if stage != "field" or killed:
                return
            pids = c.run(os.getpid)
            for worker, keys in c.has_what().items():
                if any(str(k).startswith("graph_file") for k in keys):
                    os.kill(pids[worker], signal.SIGKILL)
                    killed[worker] = pids[worker]
                    break

        with distributed.get_task_stream(c) as tasks:
            files, chunks = _on_dask(cloud, cluster.scheduler_address, tmp_path / "killed", progress)
        assert killed, "no worker held the graph file's bytes in the bake"
        assert files == cloud["bytes"]
        assert not chunks.lost
        again = [k for k, n in Counter(t["key"] for t in tasks.data).items() if n > 1]
        assert any(k.startswith("graph_file") for k in again), again  # computed twice: lost, then redone
        c.wait_for_workers(2, timeout=60)  # the nanny started a fresh worker process
        assert set(killed.values()).isdisjoint(c.run(os.getpid).values())


def test_cloudgraph_precompute_runs_on_the_cluster_that_its_variable_names(variant, tmp_path):
    """The CLI with ``CLOUDGRAPH_DASK_SCHEDULER``: its chunks on the cluster, the bytes of the CLI
    without it."""
    from cloudgraph.volume import write_vdb

    volume = noise_volume(24, seed=3)
    write_vdb(volume, tmp_path / "noise.vdb")
    scene = {"volume": {"path": "noise.vdb"}, "medium": {"density_scale": 4.0}}
    scene |= {"light": {"direction": [0, -1, 0]}, "camera": {"eye": [0, 0, 60], "target": [0, 0, 0]}}
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    env = {k: v for k, v in os.environ.items() if not k.startswith("CLOUDGRAPH_")}

    def cli(cache: str, **more) -> dict[str, bytes]:
        cmd = [sys.executable, "-m", "cloudgraph.cli", "precompute", "scene.json", "--quality", "draft"]
        cmd += ["--cache-dir", cache]
        r = subprocess.run(cmd, cwd=tmp_path, env=env | more, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        return {str(p.relative_to(tmp_path / cache)): p.read_bytes() for p in (tmp_path / cache).rglob("*.*")}

    here = cli("here")
    with _local_cluster(2) as cluster, distributed.Client(cluster.scheduler_address) as c:
        with distributed.get_task_stream(c) as tasks:
            there = cli("there", CLOUDGRAPH_DASK_SCHEDULER=cluster.scheduler_address)
    assert there == here and len(here) == 3, sorted(here)
    assert {t["key"].split("-")[0] for t in tasks.data} >= {"trace", "flights", "field_ms", "graph_file"}


def test_a_lost_scheduler_leaves_the_rest_of_the_precompute_to_this_process(cloud, tmp_path, caplog):
    """The choice for a lost scheduler: the job does not fail; what is left runs here, the same
    bytes, with a warning. With no scheduler to reach at all, the whole precompute runs here."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    scheduler = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port)]
        + ["--no-dashboard"],
        **quiet,
    )
    worker = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1", "--no-dashboard"],
        **quiet,
    )
    try:
        from cloudgraph_service.dask_chunks import client

        client(address, connect_s=30).wait_for_workers(1, timeout=120)

        def progress(stage, fraction):
            if stage == "reinforce" and scheduler.poll() is None:
                scheduler.kill()
                scheduler.wait(10)

        with caplog.at_level(logging.WARNING, logger="cloudgraph.dask"):
            files, chunks = _on_dask(cloud, address, tmp_path / "lost", progress)
        assert scheduler.returncode == -signal.SIGKILL
        assert chunks.lost and files == cloud["bytes"]
        assert "lost the Dask cluster" in caplog.text and "the rest runs here" in caplog.text

        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="cloudgraph.dask"):
            files, chunks = _on_dask(cloud, address, tmp_path / "none", connect_s=1.0)
        from cloudgraph.stages import local_chunks

        assert chunks is local_chunks and files == cloud["bytes"]
        assert f"no Dask scheduler at {address}" in caplog.text
    finally:
        for p in (worker, scheduler):
            p.kill()
            p.wait(10)


def _tasks(dask_client) -> list:
    """The keys the scheduler holds (read in its own event loop)."""
    return dask_client.run_on_scheduler(lambda dask_scheduler: [str(k) for k in dask_scheduler.tasks])


def test_a_precompute_job_runs_on_the_dask_cluster_reports_progress_and_cancels_its_tasks(variant, tmp_path):
    from cloudgraph.precompute import precompute
    from cloudgraph.scene import parse_scene
    from cloudgraph.volume import load_volume

    with _local_cluster(2) as cluster:
        svc = start_service(tmp_path / "svc", workers=1, DASK_SCHEDULER=cluster.scheduler_address)
        try:
            with svc.client() as c, distributed.Client(cluster.scheduler_address, set_as_default=False) as dc:
                vid = upload(c, BLENDER).json()["id"]
                # Cancelled while its flights run on the cluster: no task of it is left there
                r = c.post("/v1/caches", json={**blender_cache(vid, density=5.0), "quality": "default"})
                job = job_of(r)
                wait_until(
                    lambda: c.get(f"/v1/jobs/{job}").json()["stage"] == "reinforce", 180, "no reinforcement"
                )
                assert c.post(f"/v1/jobs/{job}/cancel").status_code == 200
                assert wait_job(c, job)["status"] == "canceled"
                wait_until(lambda: not _tasks(dc), 30, "the cancelled precompute left tasks on the cluster")

                body = blender_cache(vid)
                with distributed.get_task_stream(dc) as tasks:
                    r = c.post("/v1/caches", json=body)
                    assert r.status_code == 202, r.text
                    events = sse(c, job_of(r))
                keys = c.get(f"/v1/caches/{r.json()['id']}").json()["keys"]
            assert events[-1][0] == "end" and events[-1][1]["status"] == "finished", events[-1]
            running = [d for e, d in events if e == "progress" and d["status"] == "running"]
            fractions = [d["fraction"] for d in running]
            assert len(running) >= 3 and fractions == sorted(fractions), running  # sampled every 0.25 s
            assert "reinforce" in {d["stage"] for d in running}, running
            assert len({t["worker"] for t in tasks.data}) == 2  # both Dask workers ran its chunks
        finally:
            svc.stop()

    camera = {"eye": [30, 0, 5], "target": [0, 0, 5], "up": [0, 0, 1]}  # the cache does not depend on it
    scene = parse_scene(
        {**{k: body[k] for k in ("medium", "light")}, "volume": {"path": str(BLENDER)}, "camera": camera}
    )
    local = CacheStore(tmp_path / "local")
    cache = precompute(scene, load_volume(BLENDER), "draft", local)
    assert cache.keys == keys
    assert _files(local, cache) == _files(CacheStore(svc.data_dir / "cache"), cache)
