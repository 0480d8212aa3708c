"""Scale benchmark of one precompute over several workers (docs/measurements.md, "Scale"): the same cache
built through the service by 1 and by N workers of one Dr.Jit thread each, each in a fresh
service (kernels compiled in every run alike), and whether the cache files are the same bytes.
Runs alternate (1, N, 1, N, ...) and the speed-up is the ratio of the medians: a shared
machine's pace drifts over minutes, which a single pair of runs reads as a change of speed-up.
Before each pair the machine's own capacity is measured: how much faster N copies of a CPU-bound
probe finish together than one after another (2.0 on two idle cores; this 2-core VM gave
1.5–2.0 over an hour), the ceiling of any speed-up measured beside it.

    .venv/bin/python bench/scale_workers.py [--volume ../shared/data/smoke1.vdb] [--workers 2]
        [--repeats 3]
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


def precompute_through(workers: int, volume: Path, quality: str, data: Path) -> tuple[float, dict, dict]:
    """(seconds from POST to finished, {file: bytes}, stage times) of one precompute on a fresh
    service."""
    shutil.rmtree(data, ignore_errors=True)
    svc = start_service(data, workers=workers, WORKER_THREADS=1)
    try:
        with svc.client() as c:
            with open(volume, "rb") as f:
                info = c.post("/v1/volumes", files={"file": (volume.name, f)}).json()
            body = {
                "volume": {"id": info["id"]},
                "medium": {"density_scale": 1.0 / (info["value_range"][1] * max(info["voxel_size"]))},
                "light": {"direction": [0.55, -0.25, -0.8]},
                "quality": quality,
            }
            t0 = time.perf_counter()
            r = c.post("/v1/caches", json=body)
            assert wait_job(c, job_of(r), timeout=3600)["status"] == "finished"
            seconds = time.perf_counter() - t0
            stats = c.get(f"/v1/caches/{r.json()['id']}").json()["stats"]
        files = {
            str(p.relative_to(data / "cache")): p.read_bytes()
            for p in (data / "cache").rglob("*")
            if p.is_file() and p.parts[-3:-2] != ("runs",)
        }
        return seconds, files, {k: v for k, v in stats.items() if k.endswith("_s")}
    finally:
        svc.stop()


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


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--volume", default=str(ROOT.parent / "shared" / "data" / "smoke1.vdb"))
    ap.add_argument("--quality", default="default")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    volume = Path(args.volume)
    one_runs, n_runs, capacity, same = [], [], [], True
    for _ in range(args.repeats):
        capacity.append(round(machine_capacity(args.workers), 2))
        one_s, one, one_times = precompute_through(1, volume, args.quality, Path("/tmp/cloudgraph-scale-1"))
        n_s, many, n_times = precompute_through(
            args.workers, volume, args.quality, Path("/tmp/cloudgraph-scale-n")
        )
        one_runs, n_runs, same = one_runs + [round(one_s, 2)], n_runs + [round(n_s, 2)], same and one == many
    one_s, n_s = float(np.median(one_runs)), float(np.median(n_runs))
    result = {
        "machine": machine(),
        "volume": volume.name,
        "quality": args.quality,
        "worker_threads": 1,
        "one_worker_s": round(one_s, 2),
        f"{args.workers}_workers_s": round(n_s, 2),
        "speedup": round(one_s / n_s, 2),
        "one_worker_runs_s": one_runs,
        f"{args.workers}_workers_runs_s": n_runs,
        "pair_speedups": [round(a / b, 2) for a, b in zip(one_runs, n_runs, strict=True)],
        "machine_capacity": float(np.median(capacity)),
        "machine_capacity_runs": capacity,
        "same_bytes": same,
        "one_worker_stages": one_times,
        f"{args.workers}_workers_stages": n_times,
        "files": sorted(one),
    }
    print(json.dumps(result, indent=2))
    out = ROOT / "bench" / "results" / f"scale-workers-{time.strftime('%Y%m%d-%H%M%S')}.json"
    out.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
