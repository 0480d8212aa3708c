"""A bench scene's bias against the node radius or other build parameters
(bench/results/dense-backlit-radius-*):

    .venv/bin/python bench/node_radius.py SCENE VIEW ALBEDO REF_SPP '{}' '{"radius_vox": 0.4}' ...

one precompute per JSON object of build overrides (``radius_vox``: the node radius in voxels),
``gather`` at 256 spp and ``field`` against a volpath reference (RR off) kept in bench/reference-cache.
"""

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cloudgraph.mitsuba_scene import set_variant

set_variant()

from bench.harness import LIGHT, _scene, bench_scenes, cameras, reference  # noqa: E402
from cloudgraph.cache import CacheStore  # noqa: E402
from cloudgraph.metrics import bias_metrics  # noqa: E402
from cloudgraph.precompute import precompute  # noqa: E402
from cloudgraph.render import GraphRenderer  # noqa: E402

bs = bench_scenes([sys.argv[1]])[0]
view, albedo, spp_ref = sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
scene = _scene(bs, cameras(bs.volume, LIGHT, 64)[view], albedo, 64, 0)
ref = reference(bs, scene, spp_ref, Path(__file__).resolve().parent / "reference-cache")
voxel = float(np.mean(bs.volume.voxel_size))
for spec in sys.argv[5:]:
    overrides = json.loads(spec)
    if "radius_vox" in overrides:
        overrides["radius"] = overrides.pop("radius_vox") * voxel
    t = time.perf_counter()
    cache = precompute(scene, bs.volume, "default", CacheStore(tempfile.mkdtemp()), **overrides)
    pre = time.perf_counter() - t
    r = GraphRenderer(cache, bs.volume, scene)
    g = bias_metrics(r.render(scene.camera, 256, 1, "gather"), ref)
    f = bias_metrics(r.render(scene.camera, 1, 1, "field"), ref)
    print(
        bs.name,
        view,
        albedo,
        spec,
        "nodes",
        cache.stats["nodes"],
        f"precompute {pre:.1f} s",
        f"gather {g['mean_ratio']:.3f} / {100 * g['binned_relMAE']:.1f} %",
        f"field {f['mean_ratio']:.3f} / {100 * f['binned_relMAE']:.1f} %",
        flush=True,
    )
