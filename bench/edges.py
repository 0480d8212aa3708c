"""The field's edge refinement at one sample a pixel (cloudgraph/edges.py) on every bench view.

Per scene, camera and albedo: the 1-spp ``field`` frame without and with refinement against the
field's own 64-spp frame (4x4-binned relMAE: the aliasing alone, no reference needed), the
fraction of pixels refined, and warm frame times at 64² and 256² (median of 5); with
``--volpath``, one RR-free volpath sample a pixel at 256² too (warm, median of 3) and the
refined 256² frame's speed-up over it. No reference: the references' rows are
``cloudgraph bench --parts``.

    .venv/bin/python -m bench.edges [--scenes sphere dense ...] [--volpath]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .harness import _scene, bench_views, timed_frames
from .report import machine, row_md, table, write_results

SCENES = ["sphere", "noise", "smoke1", "blender", "holdout", "dense", "thick", "holdout_thick"]
COLUMNS = [
    "scene",
    "camera",
    "albedo",
    "plain_vs_aa_pct",
    "refined_vs_aa_pct",
    "refined_fraction",
    "rays_per_pixel",
    "ms64_plain",
    "ms64_refined",
    "ms256_plain",
    "ms256_refined",
]
VOLPATH_COLUMNS = ["volpath_1spp_256_ms", "vs_volpath_1spp"]


def _ms(render, repeats: int = 5) -> float:
    """Warm milliseconds of ``render()``, the median of ``repeats`` (harness.timed_frames)."""
    return round(1000 * timed_frames(lambda seed: render(), repeats)[0], 1)


def run(scenes, out_dir: Path, quality: str = "default", volpath: bool = False) -> list[dict]:
    from cloudgraph.cache import CacheStore
    from cloudgraph.edges import REFINE_SIDE, edge_pixels
    from cloudgraph.metrics import bias_metrics
    from cloudgraph.precompute import precompute
    from cloudgraph.render import GraphRenderer, render_volpath

    columns = COLUMNS + (VOLPATH_COLUMNS if volpath else [])
    store = CacheStore(out_dir.parent / "cache")
    rows = []
    for bs, albedo, view, cam in bench_views(scenes):
        scene = _scene(bs, cam, albedo, 16, seed=0)
        r = GraphRenderer(precompute(scene, bs.volume, quality, store), bs.volume, scene)
        antialiased = r.render(scene.camera, 64, 1, "field")
        plain = r.render(scene.camera, 1, 1, "field", refine=False)
        sharp = r.render(scene.camera, 1, 1, "field")
        fraction = float(edge_pixels(plain).mean())
        row = {
            "scene": bs.name,
            "camera": view,
            "albedo": albedo,
            "plain_vs_aa_pct": 100 * bias_metrics(plain, antialiased)["binned_relMAE"],
            "refined_vs_aa_pct": 100 * bias_metrics(sharp, antialiased)["binned_relMAE"],
            "refined_fraction": round(fraction, 3),
            # (at one sample a pixel the middle stratum is the frame's own ray)
            "rays_per_pixel": round(1 + (REFINE_SIDE**2 - 1) * fraction, 2),
        }
        for size in (64, 256):
            c = scene.camera.model_copy(update={"width": size, "height": size})
            for refine in (False, True):

                def frame(r=r, c=c, refine=refine):
                    return r.render(c, 1, 1, "field", refine=refine)

                row[f"ms{size}_{'refined' if refine else 'plain'}"] = _ms(frame)
        if volpath:  # (the 256² camera, one sample a pixel, Russian roulette off)
            big = scene.model_copy(
                update={"camera": c, "render": scene.render.model_copy(update={"spp": 1, "seed": 1})}
            )
            row["volpath_1spp_256_ms"] = _ms(lambda big=big, v=bs.volume: render_volpath(big, v), 3)
            row["vs_volpath_1spp"] = round(row["volpath_1spp_256_ms"] / row["ms256_refined"], 1)
        rows.append(row)
        print(row_md(row, columns), flush=True)
    m = machine()
    text = (
        f"# Edge refinement of 1-spp field frames (bench/edges.py)\n\nMachine: {m['cpu']}, {m['cores']} "
        f"cores; variant {m['variant']}; quality {quality}; 64² views; *_vs_aa_pct: 4x4-binned relMAE "
        "against the field's 64-spp frame; rays_per_pixel at 64²; ms*: warm frames, median of 5"
        + ("; volpath: RR off, 1 spp at 256², median of 3" if volpath else "")
        + ".\n\n"
        + table(rows, columns)
    )
    write_results(out_dir, "edges", {"machine": m, "quality": quality, "rows": rows}, text)
    return rows


def main(argv=None) -> None:
    from cloudgraph.mitsuba_scene import set_variant

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="*", default=SCENES)
    p.add_argument("--quality", default="default")
    p.add_argument("--volpath", action="store_true", help="time volpath at 256², 1 spp, beside")
    p.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    a = p.parse_args(argv)
    set_variant()
    run(a.scenes, Path(a.out), a.quality, a.volpath)


if __name__ == "__main__":
    main()
