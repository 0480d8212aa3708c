"""Transport with and without each edge read where its flights landed (docs/measurements.md,
"Where a flight lands"): ``gather`` at 1024 spp on one cache, its node radiance transported by
``Graph.transitions`` (the engine's) and by the collision probabilities alone (each edge read at
its end node's position), against the 1024-spp RR-free volpath references that
``cloudgraph bench --parts`` keeps in bench/reference-cache.

    .venv/bin/python bench/landing.py [SCENE ...]

per scene (default dense thick holdout_thick), view and albedo: binned relMAE / mean ratio.
"""

import dataclasses
import sys

import numpy as np

from cloudgraph.mitsuba_scene import set_variant

set_variant()

import mitsuba as mi  # noqa: E402

from bench.harness import CONVERGED_SPP, dense_cases  # noqa: E402
from cloudgraph.build import GraphBuilder  # noqa: E402
from cloudgraph.chunks import placed  # noqa: E402
from cloudgraph.lights import Lights  # noqa: E402
from cloudgraph.metrics import bias_metrics  # noqa: E402
from cloudgraph.params import LIGHTING, build_params  # noqa: E402
from cloudgraph.precompute import lighting_inputs, without_sun  # noqa: E402
from cloudgraph.render import GraphRenderer  # noqa: E402
from cloudgraph.stages import local_chunks  # noqa: E402
from cloudgraph.tracing import to_jit  # noqa: E402
from cloudgraph.transport import transport  # noqa: E402

if __name__ == "__main__":
    print("| scene, view, albedo | each edge read where its flights landed | read at its end |")
    print("|---|---|---|")
    for bs, view, albedo, scene, cache, ref in dense_cases(sys.argv[1:]):
        params = build_params(bs.volume, bs.density_scale, "default")
        builder = GraphBuilder(bs.volume, bs.density_scale, params)
        lights = Lights.of(scene)
        graph = cache.graph
        lit = local_chunks(builder, "lighting", lighting_inputs(graph.positions, lights, params))
        L_d = placed(lit, graph.n_nodes, 3, np.float64)
        L = transport(
            graph.collision_matrix(), L_d, np.asarray(scene.medium.albedo_rgb()), -1, LIGHTING["tol"]
        )[0]
        at_end = without_sun(L, L_d, lights).astype(np.float32)
        cells = []
        for radiance in (cache.radiance_gather, at_end):
            renderer = GraphRenderer(cache, bs.volume, scene)
            integrator = renderer.integrator("gather")
            integrator.grid = dataclasses.replace(integrator.grid, radiance=to_jit(mi.Color3f, radiance))
            renderer._scenes.clear()  # (a new kernel)
            m = bias_metrics(renderer.render(scene.camera, CONVERGED_SPP, 1, "gather"), ref)
            cells.append(f"{100 * m['binned_relMAE']:.2f} % / {m['mean_ratio']:.3f}")
        print(f"| {bs.name}, {view}, {albedo:g} | {cells[0]} | {cells[1]} |", flush=True)
