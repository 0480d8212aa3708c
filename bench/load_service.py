"""Load benchmark of the service (issue 4 targets): warm-cache 256^2 graph renders over HTTP,
and /healthz latency while the worker is saturated. Starts its own real service.

``--remix``: re-mixes over HTTP instead, a sun and a sky whose intensities change from request
to request (the same cache: no precompute), one camera, ``field`` renders of ``--size``: each
request's round trip and the worker's render time (X-Render-Seconds).

    .venv/bin/python bench/load_service.py [--volume ../shared/data/smoke1.vdb] [--quality default]
    .venv/bin/python bench/load_service.py --remix --size 64
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
    ap.add_argument("--remix", action="store_true", help="re-mixes of a sun and a sky, field renders")
    ap.add_argument("--size", type=int, default=256)
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
                light = {"light": {"direction": [0.55, -0.25, -0.8]}}
                extra = {}
                if args.remix:  # one camera; the sun's and the sky's intensities change
                    eye = [centre[0] + 2 * size, centre[1], centre[2]]
                    light = {
                        "lights": [
                            {
                                "type": "directional",
                                "direction": [0.55, -0.25, -0.8],
                                "irradiance": 1 + 0.1 * i,
                            },
                            {"type": "sky", "radiance": [0.25, 0.35, 0.55 / (1 + 0.1 * i)]},
                        ]
                    }
                    extra = {"integrator": "graph", "estimator": "field"}
                return {
                    "scene": {
                        "volume": {"id": info["id"]},
                        "medium": {"density_scale": ds},
                        **light,
                        "camera": {
                            "eye": eye,
                            "target": centre,
                            "fov": 40,
                            "width": args.size,
                            "height": args.size,
                        },
                        "render": {"spp": args.spp, "seed": 0 if args.remix else i},
                    },
                    "quality": args.quality,
                    **extra,
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
            lat, render_s, health, stop = [], [], [], threading.Event()

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
                render_s.append(float(r.headers["X-Render-Seconds"]))
            stop.set()
            th.join()
        from cloudgraph.mitsuba_scene import set_variant

        set_variant()  # the variant the workers choose on this machine, for the record
        result = {
            "machine": machine(),
            "volume": Path(args.volume).name,
            "quality": args.quality,
            "spp": args.spp,
            "size": args.size,
            "remix": args.remix,
            "first_request_s": round(first, 2),
            "renders": len(lat),
            "median_s": round(statistics.median(lat), 3),
            "p90_s": round(sorted(lat)[int(0.9 * len(lat))], 3),
            "render_median_s": round(statistics.median(render_s), 4),
            "render_max_s": round(max(render_s), 4),
            "healthz_median_ms": round(1000 * statistics.median(health), 1),
            "healthz_max_ms": round(1000 * max(health), 1),
            "healthz_requests": len(health),
        }
        print(json.dumps(result, indent=2))
        kind = "remix" if args.remix else "load"
        out = ROOT / "bench" / "results" / f"{kind}-{time.strftime('%Y%m%d-%H%M%S')}.json"
        out.write_text(json.dumps(result, indent=2))
    finally:
        svc.stop()


if __name__ == "__main__":
    main()
