"""Forward scattering on the bench (issue 25; docs/measurements.md, "Forward scattering").

Per scene, camera (side- and back-lit), Henyey-Greenstein g and albedo: volpath with ``hg``
(Russian roulette off) as the reference, its own binned noise from an independent run, and the
approaches to an anisotropic phase that the engine can be asked for (docs/method.md,
"Anisotropic scattering"):

| approach | cache | ``gather``'s exact scattering events |
|---|---|---|
| ``sim1`` | similarity-scaled graph (precompute.py) | 1 (the issue's approach (a)) |
| ``simK`` | the same cache | ``phase_bounces(g)`` (the engine's default) |
| ``isoK`` | the isotropic medium's graph, unchanged | ``phase_bounces(g)`` |
| ``iso1`` | the same | 1: today's cache with exact single scattering only |

and the ``field`` estimator on the engine's cache (16 spp). Rows are printed and written as
they finish (bench/results/phase-<date>.json and .md), so a cut run keeps what it measured.
``--ref-spp 0`` renders no reference: the field against ``simK`` and the precompute's times only.

    .venv/bin/python -m bench.phase --scenes sphere noise --ref-spp 4096
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from cloudgraph.cache import CacheStore
from cloudgraph.metrics import bias_metrics
from cloudgraph.precompute import precompute
from cloudgraph.render import GraphRenderer, render_volpath
from cloudgraph.scene import PhaseSpec

from .harness import LIGHT, _scene, bench_scenes, cameras, reference
from .report import add_accuracy_args, row_md, write_accuracy_rows

COLUMNS = [
    "scene",
    "camera",
    "g",
    "albedo",
    "K",
    "sim1_mean",
    "sim1_binned_pct",
    "simK_mean",
    "simK_binned_pct",
    "isoK_mean",
    "isoK_binned_pct",
    "iso1_mean",
    "iso1_binned_pct",
    "field_mean",
    "field_binned_pct",
    "field_vs_gather_pct",
    "field_vs_gather_mean",
    "gather_noise_pct",
    "ref_spp",
    "ref_noise_pct",
    "nodes_sim",
    "nodes_iso",
    "pre_sim_s",
    "pre_iso_s",
    "graph_MB_sim",
    "graph_MB_iso",
    "field_MB_sim",
    "field_MB_iso",
    "field_bake_s",
    "gather_s",
]

#: The independent volpath run that measures each reference's own binned noise.
PROBE_SPP = 256


def with_phase(scene, phase: PhaseSpec):
    return scene.model_copy(update={"medium": scene.medium.model_copy(update={"phase": phase})})


def own_noise(bs, scene, ref: np.ndarray, spp: int) -> float:
    """The reference's own binned relMAE: an independent run of PROBE_SPP against it measures
    c sqrt(1/PROBE_SPP + 1/spp); the reference's share is c / sqrt(spp)."""
    probe = scene.model_copy(
        update={"render": scene.render.model_copy(update={"spp": PROBE_SPP, "seed": 99})}
    )
    return bias_metrics(render_volpath(probe, bs.volume), ref)["binned_relMAE"] / np.sqrt(
        1.0 + spp / PROBE_SPP
    )


def run(
    scenes,
    gs,
    albedos,
    ref_spp: int,
    gather_spp: int,
    size: int,
    quality: str,
    out_dir: Path,
    approaches=None,
):
    from cloudgraph.phase import phase_bounces

    store = CacheStore(out_dir.parent / "cache")
    ref_dir = out_dir.parent / "reference-cache"
    stem = out_dir / f"phase-{time.strftime('%Y%m%d-%H%M%S')}"
    rows = []
    for bs in bench_scenes(scenes):
        for albedo in albedos:
            iso_scene = _scene(bs, cameras(bs.volume, LIGHT, size)["side"], albedo, 16, seed=0)
            t0 = time.perf_counter()
            iso_cache = precompute(iso_scene, bs.volume, quality, store)
            pre_iso = time.perf_counter() - t0
            iso_field_bytes = iso_cache.stats["field_bytes"]
            for g in gs:
                phase = PhaseSpec(type="hg", g=g)
                K = phase_bounces(phase)
                t0 = time.perf_counter()
                sim_cache = precompute(with_phase(iso_scene, phase), bs.volume, quality, store)
                pre_sim = time.perf_counter() - t0
                for cam_name, camera in cameras(bs.volume, LIGHT, size).items():
                    scene = with_phase(_scene(bs, camera, albedo, gather_spp, seed=0), phase)
                    ref = reference(bs, scene, ref_spp, ref_dir) if ref_spp > 0 else None
                    row = {"scene": bs.name, "camera": cam_name, "g": g, "albedo": albedo, "K": K}
                    sim = GraphRenderer(sim_cache, bs.volume, scene)
                    iso = GraphRenderer(iso_cache, bs.volume, scene)  # the hg scene on today's cache
                    images = {}
                    for name, renderer, bounces in (
                        ("sim1", sim, 1),
                        ("simK", sim, K),
                        ("isoK", iso, K),
                        ("iso1", iso, 1),
                    ):
                        if approaches and name not in approaches:
                            continue
                        renderer.integrator("gather").bounces = bounces
                        t0 = time.perf_counter()
                        images[name] = renderer.render(scene.camera, gather_spp, 1, "gather")
                        if name == "simK":
                            row["gather_s"] = round(time.perf_counter() - t0, 2)
                            # gather's own binned noise: another seed, against this one
                            again = renderer.render(scene.camera, gather_spp, 2, "gather")
                            row["gather_noise_pct"] = (
                                100 * bias_metrics(again, images[name])["binned_relMAE"] / np.sqrt(2)
                            )
                        if ref is not None:
                            m = bias_metrics(images[name], ref)
                            row[f"{name}_mean"], row[f"{name}_binned_pct"] = (
                                m["mean_ratio"],
                                100 * m["binned_relMAE"],
                            )
                    field = sim.render(scene.camera, 16, 1, "field")
                    if ref is not None:
                        m = bias_metrics(field, ref)
                        row["field_mean"], row["field_binned_pct"] = m["mean_ratio"], 100 * m["binned_relMAE"]
                        row["ref_noise_pct"] = 100 * own_noise(bs, scene, ref, ref_spp)
                    m = bias_metrics(field, images["simK"])
                    row["field_vs_gather_pct"] = 100 * m["binned_relMAE"]
                    row["field_vs_gather_mean"] = m["mean_ratio"]
                    row.update(
                        ref_spp=ref_spp,
                        nodes_sim=sim_cache.stats["nodes"],
                        nodes_iso=iso_cache.stats["nodes"],
                        pre_sim_s=round(pre_sim, 2),
                        pre_iso_s=round(pre_iso, 2),
                        graph_MB_sim=round(sim_cache.stats["graph_bytes"] / 2**20, 2),
                        graph_MB_iso=round(iso_cache.stats["graph_bytes"] / 2**20, 2),
                        field_MB_sim=round(sim_cache.stats["field_bytes"] / 2**20, 2),
                        field_MB_iso=round(iso_field_bytes / 2**20, 2),
                        field_bake_s=sim_cache.stats.get("field_s"),
                    )
                    rows.append(row)
                    print(row_md(row, COLUMNS), flush=True)
                    _write(stem, rows, ref_spp, gather_spp, size, quality)
    return rows


def _write(stem: Path, rows, ref_spp, gather_spp, size, quality) -> None:
    legend = (
        "*_mean: image mean / reference's; *_binned_pct: 4x4-binned relMAE (%); K: gather's exact "
        "scattering events for simK and isoK; field_vs_gather_pct: field against simK; gather_noise_pct, "
        "ref_noise_pct: simK's and the reference's own binned noise; pre_*_s: precompute seconds (reused "
        "graphs count 0)."
    )
    settings = {"quality": quality, "size": size, "gather_spp": gather_spp, "ref_spp": ref_spp}
    write_accuracy_rows(stem, "Forward scattering (bench/phase.py)", "hg", legend, rows, COLUMNS, settings)


def main(argv=None) -> None:
    from cloudgraph.mitsuba_scene import set_variant

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_accuracy_args(p)
    p.add_argument("--g", nargs="*", type=float, default=[0.5, 0.85])
    p.add_argument(
        "--approaches",
        nargs="*",
        choices=["sim1", "simK", "isoK", "iso1"],
        help="gather's approaches to run (all)",
    )
    a = p.parse_args(argv)
    set_variant()
    run(a.scenes, a.g, a.albedo, a.ref_spp, a.gather_spp, a.size, a.quality, Path(a.out), a.approaches)


if __name__ == "__main__":
    main()
