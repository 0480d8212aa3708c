"""A forward-scattering cloud beside volpath's image of it (docs/measurements.md, "Forward
scattering"): one bench scene, its back-lit camera, Henyey-Greenstein g; panels left to right
volpath (RR off), ``gather`` and ``field`` on the engine's cache, and the same cloud with the
isotropic phase (field), all at one exposure. Prints each panel's mean ratio and binned relMAE
against volpath.

    .venv/bin/python -m bench.phase_image --scene smoke1 --g 0.85 \\
        --out docs/images/forward-scattering-smoke1.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cloudgraph.cache import CacheStore
from cloudgraph.image import write_png
from cloudgraph.metrics import bias_metrics
from cloudgraph.precompute import precompute
from cloudgraph.render import GraphRenderer
from cloudgraph.scene import PhaseSpec

from .harness import LIGHT, _scene, bench_scenes, cameras, reference


def main(argv=None) -> None:
    from cloudgraph.mitsuba_scene import set_variant

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="smoke1")
    p.add_argument("--g", type=float, default=0.85)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--ref-spp", type=int, default=1024)
    p.add_argument("--quality", default="default")
    p.add_argument("--out", default="docs/images/forward-scattering-smoke1.png")
    a = p.parse_args(argv)
    set_variant()
    (bs,) = bench_scenes([a.scene])
    iso = _scene(bs, cameras(bs.volume, LIGHT, a.size)["back"], 1.0, 16, seed=0)
    scene = iso.model_copy(
        update={"medium": iso.medium.model_copy(update={"phase": PhaseSpec(type="hg", g=a.g)})}
    )
    store = CacheStore(Path("bench/cache"))
    ref = reference(bs, scene, a.ref_spp, Path("bench/reference-cache")).astype(np.float64)
    r = GraphRenderer(precompute(scene, bs.volume, a.quality, store), bs.volume, scene)
    panels = {
        "volpath": ref,
        "gather": r.render(scene.camera, 1024, 1, "gather"),
        "field": r.render(scene.camera, 16, 1, "field"),
        "isotropic field": GraphRenderer(precompute(iso, bs.volume, a.quality, store), bs.volume, iso).render(
            iso.camera, 16, 1, "field"
        ),
    }
    for name, image in panels.items():
        m = bias_metrics(np.asarray(image, np.float64), ref)
        print(f"{name}: mean ratio {m['mean_ratio']:.3f}, binned relMAE {100 * m['binned_relMAE']:.1f} %")
    exposure = -float(np.log2(np.percentile(ref, 99.5)))  # the reference's brightest at 1
    write_png(np.concatenate(list(panels.values()), axis=1), a.out, exposure)
    print("wrote", a.out)


if __name__ == "__main__":
    main()
