"""Equal-error speed-up of a warm 64^2 ``field`` frame over RR-free volpath on one bench view,
against a reference of ``--ref-spp`` (4096) samples: the field frame's time and MAE, then
volpath's time to reach that MAE (spp doubled up to ``--max-spp``, interpolated in log-log,
extrapolated with MAE ~ spp^-1/2 beyond; harness.volpath_equal_error). In-process times of one
run; results under bench/results/.

    .venv/bin/python bench/field_speedup.py [--scene dense] [--camera side] [--albedo 1.0]
"""

from __future__ import annotations

import argparse
import json
import time
from functools import partial
from pathlib import Path

from cloudgraph.mitsuba_scene import set_variant

set_variant()

from bench.harness import (  # noqa: E402
    LIGHT,
    _scene,
    bench_scenes,
    cameras,
    reference,
    timed_frames,
    volpath_equal_error,  # noqa: E402
)
from bench.report import machine  # noqa: E402
from cloudgraph.cache import CacheStore  # noqa: E402
from cloudgraph.metrics import bias_metrics, compare  # noqa: E402
from cloudgraph.precompute import precompute  # noqa: E402
from cloudgraph.render import GraphRenderer  # noqa: E402

ROOT = Path(__file__).resolve().parent


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="dense")
    ap.add_argument("--camera", default="side")
    ap.add_argument("--albedo", type=float, default=1.0)
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel of the field frame")
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--max-spp", type=int, default=64)
    args = ap.parse_args()
    bs = bench_scenes([args.scene])[0]
    scene = _scene(bs, cameras(bs.volume, LIGHT, 64)[args.camera], args.albedo, args.spp, seed=0)
    cache = precompute(scene, bs.volume, "default", CacheStore(ROOT / "cache"))
    ref = reference(bs, scene, args.ref_spp, ROOT / "reference-cache")
    renderer = GraphRenderer(cache, bs.volume, scene)
    frame_s, image = timed_frames(partial(renderer.render, scene.camera, args.spp, estimator="field"))
    err = compare(image, ref)
    row = {
        "scene": bs.name,
        "camera": args.camera,
        "albedo": args.albedo,
        "field_spp": args.spp,
        "field_frame_s": round(frame_s, 5),
        "field_MAE": err["MAE"],
        **{"field_" + k: v for k, v in bias_metrics(image, ref).items()},
        "ref_spp": args.ref_spp,
    }
    for rr in (False, True):
        vp = volpath_equal_error(bs, scene, ref, err["MAE"], rr, args.max_spp)
        row[f"volpath_rr_{'on' if rr else 'off'}_s"] = round(vp["seconds"], 3)
        row[f"volpath_rr_{'on' if rr else 'off'}_extrapolated"] = vp["extrapolated"]
        row[f"volpath_rr_{'on' if rr else 'off'}_trace"] = vp["trace"]
    best = min(row["volpath_rr_off_s"], row["volpath_rr_on_s"])
    row["speedup"] = round(best / frame_s, 1)
    out = ROOT / "results" / f"field-speedup-{bs.name}-{time.strftime('%Y%m%d-%H%M%S')}.json"
    out.write_text(json.dumps({"machine": machine(), "row": row}, indent=2))
    print(json.dumps({k: v for k, v in row.items() if not k.endswith("trace")}, indent=1))


if __name__ == "__main__":
    main()
