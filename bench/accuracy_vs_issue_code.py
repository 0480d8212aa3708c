"""Converged accuracy of the code issue 11 was filed against (8a89f9e) beside this code's
``default`` and ``compact`` presets, on the same volpath references
(bench/results/compact-*.md). Three steps, the second run by the old code:

    git worktree add /tmp/issue-code 8a89f9e
    .venv/bin/python bench/accuracy_vs_issue_code.py prepare OUT blender:side:1:4096 ...
    PYTHONPATH=/tmp/issue-code .venv/bin/python bench/accuracy_vs_issue_code.py old OUT blender-side-1 ...
    .venv/bin/python bench/accuracy_vs_issue_code.py compare OUT blender-side-1 ...

``prepare`` writes each view's scene, its volume's arrays and the reference (RR-free volpath at
the spp given, kept in bench/reference-cache); ``old`` builds a default-quality cache with the
old code and renders ``gather`` at 1024 spp; ``compare`` does the same with this code's presets
and prints mean ratio / 4x4-binned relMAE of each against the reference.
"""

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cloudgraph.mitsuba_scene import set_variant

set_variant()

from cloudgraph.cache import CacheStore  # noqa: E402

try:  # this code's module, or the old code's
    from cloudgraph.render import GraphRenderer  # noqa: E402
except ImportError:
    from cloudgraph.integrators.graph import GraphRenderer  # noqa: E402
from cloudgraph.precompute import precompute  # noqa: E402
from cloudgraph.scene import parse_scene  # noqa: E402

SPP = 1024
REFS = Path(__file__).resolve().parent / "reference-cache"


def load(out: Path, tag: str):
    name = tag.split("-")[0]
    data = json.loads((out / f"{tag}.json").read_text())
    data["volume"] = {"path": name}
    return name, parse_scene(data)


def metrics(image: np.ndarray, ref: np.ndarray) -> str:
    from cloudgraph.metrics import bias_metrics

    m = bias_metrics(image, ref)
    return f"{m['mean_ratio']:.3f} / {100 * m['binned_relMAE']:.2f} %"


def main(mode: str, out: Path, items: list[str]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    stores = {}
    for item in items:
        if mode == "prepare":
            from bench.harness import LIGHT, _scene, bench_scenes, cameras, reference

            name, view, albedo, spp = item.split(":")
            bs = bench_scenes([name])[0]
            scene = _scene(bs, cameras(bs.volume, LIGHT, 64)[view], float(albedo), 64, 0)
            tag = f"{name}-{view}-{albedo}"
            np.save(out / f"{tag}-ref.npy", reference(bs, scene, int(spp), REFS))
            v = bs.volume
            arrays = {"density": v.density, "index_min": v.index_min, "to_world": v.index_to_world}
            np.savez(out / f"{name}-vol.npz", **arrays)
            (out / f"{tag}.json").write_text(json.dumps(scene.model_dump(mode="json")))
            continue
        name, scene = load(out, item)
        z = np.load(out / f"{name}-vol.npz")
        from cloudgraph.volume import Volume

        volume = Volume(z["density"], tuple(int(i) for i in z["index_min"]), z["to_world"])
        qualities = ["default"] if mode == "old" else ["default", "compact"]
        row = [item]
        if mode == "compare":
            ref = np.load(out / f"{item}-ref.npy")
            row.append("issue's code " + metrics(np.load(out / f"{item}-old.npy"), ref))
        for q in qualities:
            store = stores.setdefault((name, q), CacheStore(tempfile.mkdtemp()))
            t = time.perf_counter()
            cache = precompute(scene, volume, q, store)
            pre = time.perf_counter() - t
            image = GraphRenderer(cache, volume, scene).render(scene.camera, SPP, 1)
            if mode == "old":
                np.save(out / f"{item}-old.npy", image)
                row.append(f"nodes {cache.stats['nodes']} precompute {pre:.1f} s")
            else:
                row.append(f"{q} {cache.stats['nodes']} nodes {metrics(image, ref)}")
        print(" | ".join(row), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], Path(sys.argv[2]), sys.argv[3:])
