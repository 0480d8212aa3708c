"""Several lights and a sky on the bench (docs/measurements.md, "Several lights").

Per scene, light setup (sun + uniform sky, two suns), camera (side- and back-lit to the sun) and
albedo: volpath with Mitsuba's emitters (Russian roulette off) as the reference, ``gather`` at
1024 spp and ``field`` at 16 spp on the cache, both also on the bins that show the cloud (the
reference over 2 % from the bare sky), the relight (a new light list on the graph already made)
against the first precompute, the relight that adds one more sun to the setup's cache, and a
re-mix (new intensities of the same lights: set_lights and a field frame). Rows are printed and
written as they finish (bench/results/lights-<date>.json and .md); each run's caches are its own,
made in a temporary store and removed at the end. ``--timing`` leaves out the
references and the renders: the precompute times only; ``--remix`` the re-mixes only (the median
of REMIXES, alternating two intensity sets on a warm renderer).

    .venv/bin/python -m bench.lights --scenes sphere noise holdout --ref-spp 4096
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from cloudgraph.cache import CacheStore
from cloudgraph.lights import Lights
from cloudgraph.metrics import bias_metrics, binned
from cloudgraph.precompute import precompute
from cloudgraph.render import GraphRenderer
from cloudgraph.scene import parse_scene

from .harness import LIGHT, RELIGHT, _scene, bench_scenes, cameras, reference
from .report import add_accuracy_args, row_md, write_accuracy_rows

SKY = [0.25, 0.35, 0.55]
SETUPS = {
    "sun+sky": [
        {"type": "directional", "direction": LIGHT.tolist(), "irradiance": 1.0},
        {"type": "sky", "radiance": SKY},
    ],
    "two suns": [
        {"type": "directional", "direction": LIGHT.tolist(), "irradiance": 1.0},
        {"type": "directional", "direction": RELIGHT.tolist(), "irradiance": [0.6, 0.5, 0.4]},
    ],
    # ENVMAP: written by run(), a lat-long gradient (bright and white at +y, dim and blue below)
    "sun+envmap": [
        {"type": "directional", "direction": LIGHT.tolist(), "irradiance": 1.0},
        {"type": "envmap", "path": "ENVMAP", "scale": 0.5},
    ],
}


#: Re-mixes timed per row: remix_ms is their median, remix_max_ms the slowest.
REMIXES = 7


#: The sun that add_sun_s adds to a setup's lights.
EXTRA_SUN = {"type": "directional", "direction": [0.3, -0.9, 0.3], "irradiance": 0.5}


def write_envmap(path: Path) -> str:
    """The sun+envmap setup's map: 128 x 64, radiance 2 at the top row to 0.2 at the bottom,
    bluer downwards."""
    from cloudgraph.image import write_exr

    h, w = 64, 128
    ramp = np.linspace(2.0, 0.2, h, dtype=np.float32)[:, None, None]
    tint = np.array([1.0, 0.9, 0.8], np.float32) ** np.linspace(0, 3, h, dtype=np.float32)[:, None, None]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_exr(np.ascontiguousarray(np.broadcast_to(ramp * tint, (h, w, 3)), np.float32), path)
    return str(path)


COLUMNS = [
    "scene",
    "lights",
    "camera",
    "albedo",
    "gather_mean",
    "gather_binned_pct",
    "gather_cloud_pct",
    "field_mean",
    "field_binned_pct",
    "field_cloud_pct",
    "field_vs_gather_pct",
    "ref_spp",
    "pre_s",
    "relight_s",
    "add_sun_s",
    "remix_ms",
    "remix_max_ms",
    "field_MB",
]


def with_lights(scene, lights, envmap: str = ""):
    d = scene.model_dump(mode="json")
    d.pop("light", None)
    lights = [{**li, "path": envmap} if li.get("path") == "ENVMAP" else li for li in lights]
    return parse_scene({**d, "lights": lights})


def cloud_bins(ref: np.ndarray, sky: np.ndarray) -> np.ndarray:
    """4x4 bins where the reference is more than 2 % from the bare sky (the cloud shows)."""
    b = binned(ref, 4).mean(axis=-1)
    s = float(np.mean(sky))
    return np.abs(b - s) > 0.02 * max(s, 1e-6) if s > 0 else b > 0


def cloud_pct(image, ref, mask) -> float:
    a, b = binned(image, 4).mean(axis=-1)[mask], binned(ref, 4).mean(axis=-1)[mask]
    return float(100 * np.abs(a - b).mean() / max(b.mean(), 1e-12))


def run(
    scenes,
    albedos,
    setups,
    ref_spp: int,
    gather_spp: int,
    size: int,
    quality: str,
    out_dir: Path,
    timing=False,
    remix_only=False,
):
    # a store of this run's own: the times are those of precomputes that find no cache (a store
    # kept between runs found every one of them, and timed the reads)
    scratch = Path(tempfile.mkdtemp(prefix="cloudgraph-lights-"))
    try:
        return _run(
            scenes, albedos, setups, ref_spp, gather_spp, size, quality, out_dir, timing, remix_only, scratch
        )
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _run(scenes, albedos, setups, ref_spp, gather_spp, size, quality, out_dir, timing, remix_only, scratch):
    store = CacheStore(scratch)
    ref_dir = out_dir.parent / "reference-cache"
    stem = out_dir / f"lights-{time.strftime('%Y%m%d-%H%M%S')}"
    envmap = write_envmap(out_dir.parent / "cache-lights" / "gradient.exr")
    rows = []
    for bs in bench_scenes(scenes):
        for albedo in albedos:
            base = _scene(bs, cameras(bs.volume, LIGHT, size)["side"], albedo, 16, seed=0)
            t0 = time.perf_counter()
            precompute(base, bs.volume, quality, store)  # the sun alone: the graph, first made
            pre = time.perf_counter() - t0
            for setup in setups:
                lit = with_lights(base, SETUPS[setup], envmap)
                t0 = time.perf_counter()
                cache = precompute(lit, bs.volume, quality, store)  # a relight: the graph reused
                relight = time.perf_counter() - t0
                t0 = time.perf_counter()  # one more sun: that component alone is computed
                precompute(with_lights(base, SETUPS[setup] + [EXTRA_SUN], envmap), bs.volume, quality, store)
                times = {
                    "pre_s": round(pre, 2),
                    "relight_s": round(relight, 2),
                    "add_sun_s": round(time.perf_counter() - t0, 2),
                }
                if timing:
                    rows.append({"scene": bs.name, "lights": setup, "albedo": albedo, **times})
                    print(row_md(rows[-1], COLUMNS), flush=True)
                    _write(stem, rows, ref_spp, gather_spp, size, quality)
                    continue
                for cam_name, camera in cameras(bs.volume, LIGHT, size).items():
                    scene = with_lights(_scene(bs, camera, albedo, gather_spp, seed=0), SETUPS[setup], envmap)
                    lights = Lights.of(scene)
                    r = GraphRenderer(cache, bs.volume, scene)
                    row = {"scene": bs.name, "lights": setup, "camera": cam_name, "albedo": albedo}
                    if not remix_only:
                        ref = reference(bs, scene, ref_spp, ref_dir)
                        mask = cloud_bins(ref, lights.sky_radiance)
                        gather = r.render(scene.camera, gather_spp, 1, "gather")
                        field = r.render(scene.camera, 16, 1, "field")
                        for name, image in (("gather", gather), ("field", field)):
                            m = bias_metrics(image, ref)
                            row[f"{name}_mean"] = m["mean_ratio"]
                            row[f"{name}_binned_pct"] = 100 * m["binned_relMAE"]
                            row[f"{name}_cloud_pct"] = cloud_pct(image, ref, mask)
                        row["field_vs_gather_pct"] = 100 * bias_metrics(field, gather)["binned_relMAE"]
                    row.update(remix_times(r, scene.camera, lights))
                    row.update(
                        ref_spp=None if remix_only else ref_spp,
                        **times,
                        field_MB=round(cache.stats["field_bytes"] / 2**20, 2),
                    )
                    rows.append(row)
                    print(row_md(row, COLUMNS), flush=True)
                    _write(stem, rows, ref_spp, gather_spp, size, quality)
    return rows


def remix_times(r: GraphRenderer, camera, lights: Lights) -> dict:
    """A re-mix: other intensities of the same lights and one 16-spp field frame, REMIXES times
    on a warm renderer, alternating the lights' own intensities and half of them (each is a
    change: set_lights re-mixes only what changed)."""
    dimmer = dataclasses.replace(lights, intensity=0.5 * lights.intensity)
    r.render(camera, 16, 1, "field", dimmer)  # (kernels warm)
    times = []
    for k in range(REMIXES):
        t0 = time.perf_counter()
        r.render(camera, 16, 1, "field", lights if k % 2 == 0 else dimmer)
        times.append(1000 * (time.perf_counter() - t0))
    return {"remix_ms": round(float(np.median(times)), 1), "remix_max_ms": round(max(times), 1)}


def _write(stem: Path, rows, ref_spp, gather_spp, size, quality) -> None:
    legend = (
        "*_mean: image mean / reference's; *_binned_pct: 4x4-binned relMAE (%) over the image, *_cloud_pct "
        "over the bins where the cloud shows (reference over 2 % from the bare sky; sun+envmap: every bin); "
        "pre_s: the first precompute (graph and the sun alone); relight_s: the setup's precompute on that "
        "graph; add_sun_s: the setup's lights and one more sun, on the setup's cache; remix_ms: new "
        f"intensities and a 16-spp field frame, median of {REMIXES} on a warm renderer "
        "(remix_max_ms the slowest)."
    )
    reference = "Mitsuba's directional, constant and envmap emitters"
    settings = {"quality": quality, "size": size, "gather_spp": gather_spp, "ref_spp": ref_spp}
    write_accuracy_rows(stem, "Several lights (bench/lights.py)", reference, legend, rows, COLUMNS, settings)


def main(argv=None) -> None:
    from cloudgraph.mitsuba_scene import set_variant

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_accuracy_args(p, ["sphere", "noise", "holdout"])
    p.add_argument("--setups", nargs="*", default=list(SETUPS), choices=list(SETUPS))
    p.add_argument("--timing", action="store_true", help="precompute times only: no references, no renders")
    p.add_argument("--remix", action="store_true", help="re-mix times only: no references, no gather")
    a = p.parse_args(argv)
    set_variant()
    run(
        a.scenes,
        a.albedo,
        a.setups,
        a.ref_spp,
        a.gather_spp,
        a.size,
        a.quality,
        Path(a.out),
        a.timing,
        a.remix,
    )


if __name__ == "__main__":
    main()
