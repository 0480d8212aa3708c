"""Fingerprints of the engine's output: sha256 of every cache file and of rendered images.

A change that must move no byte (a refactor) keeps every line of this script's JSON; run it
before and after and diff the two:

    .venv/bin/python bench/fingerprint.py > before.json
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path

#: Bench scenes and the quality each is built at
SCENES = {
    "sphere": "default",
    "noise": "default",
    "dense": "compact",
    "smoke1": "draft",
    "blender": "default",
}
ESTIMATORS = ("gather", "free_flight", "march", "field")


def main() -> None:
    from cloudgraph.mitsuba_scene import set_variant

    set_variant()
    try:  # the engine's names, as they stand before and after the layering
        from cloudgraph.render import GraphRenderer, precompute
    except ImportError:
        from cloudgraph.precompute import precompute
        from cloudgraph.render import GraphRenderer
    try:
        from bench.harness import LIGHT, _scene, bench_scenes, cameras
    except ImportError:
        from cloudgraph.bench import LIGHT, _scene, bench_scenes, cameras
    from cloudgraph.cache import CacheStore

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        store = CacheStore(tmp)
        for bs in bench_scenes(list(SCENES)):
            camera = cameras(bs.volume, LIGHT, 32)["side"]
            scene = _scene(bs, camera, 0.8, 4, seed=0)
            cache = precompute(scene, bs.volume, SCENES[bs.name], store)
            renderer = GraphRenderer(cache, bs.volume, scene)
            for est in ESTIMATORS:
                image = renderer.render(scene.camera, 4, 1, est)
                out[f"{bs.name}/image/{est}"] = hashlib.sha256(image.tobytes()).hexdigest()[:16]
        for f in sorted(Path(tmp).rglob("*")):
            if f.is_file():
                out[f"file/{f.relative_to(tmp)}"] = hashlib.sha256(f.read_bytes()).hexdigest()[:16]
    json.dump(out, sys.stdout, indent=1, sort_keys=True)
    print()


if __name__ == "__main__":
    main()
