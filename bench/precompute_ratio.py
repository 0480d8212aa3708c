"""Precompute time as a ratio to a volpath frame (256², 1 spp) measured in the same run (issue 11):
one process, a fresh store each time, medians of ``--repeats`` precomputes and 3x as many frames.
With ``--g``, each scene is also precomputed with a Henyey-Greenstein phase of that g, alternating
with the isotropic one, and the row gives the ratio of the two medians (issue 25: at most 1.5x).
Run it with an older checkout first on ``PYTHONPATH`` to compare code on one machine state:

    PYTHONPATH=/path/to/old/checkout .venv/bin/python bench/precompute_ratio.py --scene blender
    .venv/bin/python bench/precompute_ratio.py --scene blender
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from cloudgraph.mitsuba_scene import set_variant

set_variant()

import cloudgraph  # noqa: E402
from bench.harness import LIGHT, _scene, bench_scenes, cameras  # noqa: E402
from bench.phase import with_phase  # noqa: E402
from cloudgraph.cache import CacheStore  # noqa: E402
from cloudgraph.precompute import precompute  # noqa: E402
from cloudgraph.render import render_volpath  # noqa: E402
from cloudgraph.scene import CameraSpec, PhaseSpec  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="blender,sphere", help="bench scenes, comma-separated")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--g", type=float, help="also precompute with Henyey-Greenstein g (ratio to isotropic)")
    args = ap.parse_args()
    rows = []
    for bs in bench_scenes(args.scene.split(",")):
        scene = _scene(bs, cameras(bs.volume, LIGHT, 64)["side"], 1.0, 64, seed=0)
        frame = scene.model_copy(
            update={
                "camera": CameraSpec(**cameras(bs.volume, LIGHT, 256)["side"]),
                "render": scene.render.model_copy(update={"spp": 1}),
            }
        )
        render_volpath(frame, bs.volume)  # kernels compiled
        hg = None if args.g is None else with_phase(scene, PhaseSpec(type="hg", g=args.g))
        pre, pre_g, frames = [], [], []
        for _ in range(args.repeats):
            pre.append(_timed_precompute(scene, bs))
            if hg is not None:
                pre_g.append(_timed_precompute(hg, bs))
            for _ in range(3):
                t = time.perf_counter()
                render_volpath(frame, bs.volume)
                frames.append(time.perf_counter() - t)
        row = {
            "scene": bs.name,
            "precompute_s": [round(x, 2) for x in pre],
            "volpath_frame_s": [round(x, 3) for x in frames],
            "frames": round(float(np.median(pre) / np.median(frames)), 1),
        }
        if hg is not None:
            row["g"] = args.g
            row["precompute_g_s"] = [round(x, 2) for x in pre_g]
            row["g_over_isotropic"] = round(float(np.median(pre_g) / np.median(pre)), 2)
        print(json.dumps(row), flush=True)
        rows.append(row)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = Path(__file__).resolve().parent / "results" / f"precompute-ratio-{stamp}.json"
    out.write_text(json.dumps({"code": str(Path(cloudgraph.__file__).parent), "rows": rows}, indent=2))


def _timed_precompute(scene, bs) -> float:
    """Seconds of one precompute into a fresh store (removed after)."""
    store = tempfile.mkdtemp()
    try:
        t = time.perf_counter()
        precompute(scene, bs.volume, "default", CacheStore(store))
        return time.perf_counter() - t
    finally:
        shutil.rmtree(store, ignore_errors=True)


if __name__ == "__main__":
    main()
