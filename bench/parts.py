"""``cloudgraph bench --parts``: the field's error split into single scattering (``max_depth`` 1)
and the whole, beside converged ``gather`` on the same cache and volpath (docs/benchmark.md).

Per scene, camera and albedo, for single scattering and for all orders: ``gather`` at
CONVERGED_SPP, ``field`` at 16 spp and at 1, each against an RR-free volpath reference (binned
relMAE and mean ratio, metrics.bias_metrics), and ``field`` against ``gather`` directly (the
field's own error where gather is right, without the reference's noise; ``ref_spp`` 0: that
alone, no reference rendered).
"""

from __future__ import annotations

from pathlib import Path

from cloudgraph.cache import CacheStore
from cloudgraph.metrics import bias_metrics
from cloudgraph.precompute import precompute
from cloudgraph.render import GraphRenderer

from .harness import CONVERGED_SPP, _scene, bench_views, reference
from .report import machine, row_md, table, write_results

#: The scenes of ``--parts`` when none are named: the optically thick ones, held-out included.
PARTS_SCENES = ["dense", "thick", "holdout_thick"]
PARTS = {"single": 1, "all": -1}

PARTS_COLUMNS = [
    "scene",
    "camera",
    "albedo",
    "part",
    "gather_binned_relMAE_pct",
    "gather_mean_ratio",
    "field16_binned_relMAE_pct",
    "field16_mean_ratio",
    "field1_binned_relMAE_pct",
    "field1_mean_ratio",
    "field16_vs_gather_pct",
    "field16_vs_gather_mean",
    "ref_spp",
]


def run_parts(
    scenes: list[str] | None = None,
    out_dir: str | Path = "bench/results",
    quality="default",
    ref_spp=4096,
    parts: list[str] | None = None,
) -> dict:
    """The parts table (module docstring; ``parts``: of PARTS, default all), written as JSON and
    markdown under ``out_dir``."""
    out_dir = Path(out_dir)
    store = CacheStore(out_dir.parent / "cache")
    refs = out_dir.parent / "reference-cache"
    rows = []
    for bs, albedo, cam_name, camera in bench_views(scenes or PARTS_SCENES):
        for part in parts or PARTS:
            depth = PARTS[part]
            scene = _scene(bs, camera, albedo, 16, seed=0)
            scene = scene.model_copy(update={"render": scene.render.model_copy(update={"max_depth": depth})})
            cache = precompute(scene, bs.volume, quality, store)
            ref = reference(bs, scene, ref_spp, refs) if ref_spp > 0 else None
            renderer = GraphRenderer(cache, bs.volume, scene)
            gather = renderer.render(scene.camera, CONVERGED_SPP, 1, "gather")
            field16 = renderer.render(scene.camera, 16, 1, "field")
            field1 = renderer.render(scene.camera, 1, 1, "field")
            row = {"scene": bs.name, "camera": cam_name, "albedo": albedo, "part": part}
            for name, image in (("gather", gather), ("field16", field16), ("field1", field1)):
                if ref is not None:
                    m = bias_metrics(image, ref)
                    row[f"{name}_binned_relMAE_pct"] = 100 * m["binned_relMAE"]
                    row[f"{name}_mean_ratio"] = m["mean_ratio"]
            m = bias_metrics(field16, gather)
            row["field16_vs_gather_pct"] = 100 * m["binned_relMAE"]
            row["field16_vs_gather_mean"] = m["mean_ratio"]
            row["ref_spp"] = ref_spp if ref is not None else None
            rows.append(row)
            print(row_md(row, PARTS_COLUMNS), flush=True)
    result = {"machine": machine(), "quality": quality, "reference_spp": ref_spp, "rows": rows}
    m = result["machine"]
    text = (
        f"# cloudgraph bench --parts\n\nMachine: {m['cpu']}, {m['cores']} cores; variant "
        f"{m['variant']}; quality {quality}; gather {CONVERGED_SPP} spp; reference volpath "
        f"{ref_spp} spp, RR off; 64^2, 4x4-binned.\n\n" + table(rows, PARTS_COLUMNS)
    )
    write_results(out_dir, "parts", result, text)
    return result
