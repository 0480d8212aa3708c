"""Load benchmark of the service (issue 4 targets): warm-cache 256^2 graph renders over HTTP,
and /healthz latency while the worker is saturated. Starts its own real service.

    .venv/bin/python bench/load_service.py [--volume ../shared/data/smoke1.vdb] [--quality default]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.harness import machine  # noqa: E402
from tests.harness import start_service  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--volume", default=str(ROOT.parent / "shared" / "data" / "smoke1.vdb"))
    ap.add_argument("--quality", default="default")
    ap.add_argument("--renders", type=int, default=20)
    ap.add_argument("--spp", type=int, default=16)
    args = ap.parse_args()
    svc = start_service(Path("/tmp/cloudgraph-load"), workers=1)
    try:
        with svc.client() as c:
            with open(args.volume, "rb") as f:
                info = c.post("/v1/volumes", files={"file": (Path(args.volume).name, f)}).json()
            lo, hi = info["world_bbox"]
            centre = [(a + b) / 2 for a, b in zip(lo, hi, strict=True)]
            size = max(b - a for a, b in zip(lo, hi, strict=True))
            ds = 1.0 / (info["value_range"][1] * max(info["voxel_size"]))

            def body(i: int) -> dict:
                eye = [centre[0] + 2 * size * (1 - i / 100), centre[1], centre[2] + 2 * size * (i / 100)]
                return {
                    "scene": {
                        "volume": {"id": info["id"]},
                        "medium": {"density_scale": ds},
                        "light": {"direction": [0.55, -0.25, -0.8]},
                        "camera": {"eye": eye, "target": centre, "fov": 40, "width": 256, "height": 256},
                        "render": {"spp": args.spp, "seed": i},
                    },
                    "quality": args.quality,
                }

            t0 = time.perf_counter()
            r = c.post("/v1/renders", json=body(0), timeout=900)  # builds the cache, warms the worker
            while r.status_code == 202:
                time.sleep(1)
                j = c.get(f"/v1/jobs/{r.json()['id']}").json()
                if j["status"] in ("finished", "failed"):
                    break
            first = time.perf_counter() - t0
            c.post("/v1/renders", json=body(1))  # compile once at this size
            lat, health, stop = [], [], threading.Event()

            def poll_health():
                with svc.client() as h:
                    while not stop.is_set():
                        health.append(h.get("/healthz").elapsed.total_seconds())
                        time.sleep(0.05)

            th = threading.Thread(target=poll_health)
            th.start()
            for i in range(2, 2 + args.renders):
                t = time.perf_counter()
                r = c.post("/v1/renders", json=body(i))
                assert r.status_code == 200, r.text
                lat.append(time.perf_counter() - t)
            stop.set()
            th.join()
        from cloudgraph.mitsuba_scene import set_variant

        set_variant()  # the variant the workers choose on this machine, for the record
        result = {
            "machine": machine(),
            "volume": Path(args.volume).name,
            "quality": args.quality,
            "spp": args.spp,
            "first_request_s": round(first, 2),
            "renders": len(lat),
            "median_s": round(statistics.median(lat), 3),
            "p90_s": round(sorted(lat)[int(0.9 * len(lat))], 3),
            "healthz_median_ms": round(1000 * statistics.median(health), 1),
            "healthz_max_ms": round(1000 * max(health), 1),
            "healthz_requests": len(health),
        }
        print(json.dumps(result, indent=2))
        out = ROOT / "bench" / "results" / f"load-{time.strftime('%Y%m%d-%H%M%S')}.json"
        out.write_text(json.dumps(result, indent=2))
    finally:
        svc.stop()


if __name__ == "__main__":
    main()
