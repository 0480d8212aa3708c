"""Scale benchmark of one precompute over a Dask cluster (docs/cluster.md, "Measurements"): the
same cache built through the service (one RQ worker, a Dask client) on a fresh
``distributed.LocalCluster`` of 1 and of N worker processes, each run in a fresh service and
cluster (kernels loaded in every run alike), and whether the cache files are the same bytes.
Every process runs one Dr.Jit thread (``CLOUDGRAPH_WORKER_THREADS=1``) and every Dask worker one
task at a time, so that N workers ask for N cores. The Dask workers have the variant set and the
engine imported before the clock starts. Runs alternate (1, N, 1, N, ...) and the speed-up is
the ratio of the medians: a shared machine's pace drifts over minutes, which a single pair of
runs reads as a change of speed-up. Before each pair the machine's own capacity is measured: how
much faster N copies of a CPU-bound probe finish together than one after another (2.0 on two
idle cores), the ceiling of any speed-up measured beside it. Beside both, the bound that the
one-worker runs set themselves: their run time with the worker's busy time (from Dask's task
stream) shared by N and the rest as it was, the most N workers could gain on N idle cores.

``--threads`` measures instead how many threads one Dask worker should run beside Dr.Jit's pool:
one worker with 1 or 2 threads (``--nthreads``) and Dr.Jit's pool of one thread per core or of
one thread, the configurations alternated, medians reported.

    .venv/bin/python bench/scale_workers.py [--volume ../shared/data/smoke1.vdb] [--workers 2]
        [--repeats 3] [--threads]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.harness import machine  # noqa: E402
from tests.harness import job_of, start_service, wait_job  # noqa: E402


def precompute_through(
    workers: int, volume: Path, quality: str, data: Path, nthreads: int = 1, drjit_threads: int = 1
) -> tuple[float, dict, dict]:
    """(seconds from POST to finished, {file: bytes}, stage times) of one precompute on a fresh
    service whose one RQ worker sends its chunks to a fresh cluster of ``workers`` Dask workers
    (``nthreads`` each; ``drjit_threads`` Dr.Jit threads in every process, 0: one per core). The
    stage times gain ``dask_busy_s``: the seconds the Dask workers spent running chunks, in all
    (from the scheduler's task stream)."""
    from distributed import LocalCluster, get_task_stream

    from cloudgraph_service.dask_chunks import client

    shutil.rmtree(data, ignore_errors=True)
    env = {"CLOUDGRAPH_WORKER_THREADS": str(drjit_threads)}
    with LocalCluster(
        n_workers=workers, threads_per_worker=nthreads, processes=True, dashboard_address=None, env=env
    ) as cluster:
        c = client(cluster.scheduler_address)  # sets the variant on every worker
        c.run(__import__, "cloudgraph.precompute")
        svc = start_service(
            data, workers=1, WORKER_THREADS=drjit_threads, DASK_SCHEDULER=cluster.scheduler_address
        )
        try:
            with svc.client() as http:
                with open(volume, "rb") as f:
                    info = http.post("/v1/volumes", files={"file": (volume.name, f)}).json()
                body = {
                    "volume": {"id": info["id"]},
                    "medium": {"density_scale": 1.0 / (info["value_range"][1] * max(info["voxel_size"]))},
                    "light": {"direction": [0.55, -0.25, -0.8]},
                    "quality": quality,
                }
                t0 = time.perf_counter()
                with get_task_stream(c) as tasks:
                    r = http.post("/v1/caches", json=body)
                    assert wait_job(http, job_of(r), timeout=3600)["status"] == "finished"
                seconds = time.perf_counter() - t0
                busy = sum(
                    s["stop"] - s["start"]
                    for t in tasks.data
                    for s in t["startstops"]
                    if s["action"] == "compute"
                )
                stats = http.get(f"/v1/caches/{r.json()['id']}").json()["stats"]
        finally:
            svc.stop()
        c.close()
    files = {
        str(p.relative_to(data / "cache")): p.read_bytes() for p in (data / "cache").rglob("*") if p.is_file()
    }
    return (
        seconds,
        files,
        {k: v for k, v in stats.items() if k.endswith("_s")} | {"dask_busy_s": round(busy, 2)},
    )


#: A CPU-bound stand-in for a worker's work (numpy sorts and Python), about a second alone
PROBE = """import time, numpy as np
t, r = time.perf_counter(), np.random.default_rng(0)
for _ in range(6):
    np.sort(r.random(1 << 21)); sum(i * i for i in range(300000))
print(time.perf_counter() - t)"""


def machine_capacity(n: int) -> float:
    """How many times faster n copies of the probe finish together than one after another: the
    most that n workers could gain on this machine at this moment (n on idle cores of their own;
    less where its cores share the host's with others)."""

    def start():
        return subprocess.Popen([sys.executable, "-c", PROBE], stdout=subprocess.PIPE, text=True)

    alone = float(start().communicate()[0])
    together = max(float(p.communicate()[0]) for p in [start() for _ in range(n)])
    return n * alone / together


def scale(args, volume: Path) -> dict:
    one_runs, n_runs, capacity, same, bounds = [], [], [], True, []
    for _ in range(args.repeats):
        capacity.append(round(machine_capacity(args.workers), 2))
        one_s, one, one_times = precompute_through(1, volume, args.quality, Path("/tmp/cloudgraph-scale-1"))
        # Amdahl: the one worker's busy time shared by N, the rest (the client's merges, the
        # transport, waiting on either) as it was
        busy = one_times["dask_busy_s"]
        bounds.append(round(one_s / (one_s - busy + busy / args.workers), 2))
        n_s, many, n_times = precompute_through(
            args.workers, volume, args.quality, Path("/tmp/cloudgraph-scale-n")
        )
        one_runs, n_runs, same = one_runs + [round(one_s, 2)], n_runs + [round(n_s, 2)], same and one == many
    one_s, n_s = float(np.median(one_runs)), float(np.median(n_runs))
    return {
        "machine": machine(),
        "volume": volume.name,
        "quality": args.quality,
        "scheduler": "dask distributed (LocalCluster of processes), one RQ worker as its client",
        "drjit_threads": 1,
        "dask_threads_per_worker": 1,
        "one_worker_s": round(one_s, 2),
        f"{args.workers}_workers_s": round(n_s, 2),
        "speedup": round(one_s / n_s, 2),
        "one_worker_runs_s": one_runs,
        f"{args.workers}_workers_runs_s": n_runs,
        "pair_speedups": [round(a / b, 2) for a, b in zip(one_runs, n_runs, strict=True)],
        "speedup_bound": float(np.median(bounds)),
        "speedup_bound_runs": bounds,
        "machine_capacity": float(np.median(capacity)),
        "machine_capacity_runs": capacity,
        "same_bytes": same,
        "one_worker_stages": one_times,
        f"{args.workers}_workers_stages": n_times,
        "files": sorted(one),
    }


def threads(args, volume: Path) -> dict:
    """One Dask worker: (its threads, Dr.Jit's threads) alternated; medians of the runs."""
    configs = [(1, 0), (2, 0), (1, 1), (2, 1)]  # Dr.Jit threads 0: one per core
    runs: dict[str, list[float]] = {f"nthreads={n} drjit_threads={d or 'per core'}": [] for n, d in configs}
    files, same = None, True
    for _ in range(args.repeats):
        for (n, d), name in zip(configs, runs, strict=True):
            s, got, _ = precompute_through(1, volume, args.quality, Path("/tmp/cloudgraph-threads"), n, d)
            runs[name].append(round(s, 2))
            same, files = same and (files is None or got == files), got
    return {
        "machine": machine(),
        "volume": volume.name,
        "quality": args.quality,
        "dask_workers": 1,
        "median_s": {name: float(np.median(r)) for name, r in runs.items()},
        "runs_s": runs,
        "same_bytes": same,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--volume", default=str(ROOT.parent / "shared" / "data" / "smoke1.vdb"))
    ap.add_argument("--quality", default="default")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", action="store_true", help="one Dask worker: its threads and Dr.Jit's")
    args = ap.parse_args()
    from cloudgraph.mitsuba_scene import set_variant

    set_variant()  # the variant the Dask workers are given (cloudgraph_service/dask_chunks.py)
    result = (threads if args.threads else scale)(args, Path(args.volume))
    print(json.dumps(result, indent=2))
    kind = "scale-threads" if args.threads else "scale-workers"
    out = ROOT / "bench" / "results" / f"{kind}-{time.strftime('%Y%m%d-%H%M%S')}.json"
    out.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
