"""A variant of ``gather``'s node lookup measured and not adopted (docs/measurements.md, "The dense
cloud's back-lit bias is node size"): each node's radiance extrapolated to the lookup point by
its gradient, L(p) = sum_a w_a (L_a + G_a (p - c_a)) / sum_a w_a, in place of Eq. 4.25's
sum_a w_a L_a / sum_a w_a (c_a: the node's position, the mean of its collisions).

G_a is transport's gradient (cloudgraph.graph.gradient_operators: a weighted least-squares
plane through the node's nearest nodes, a linear operator on the radiance; the figures of
bench/results/node-gradient-20261203.md were taken with 16 nodes at two search ranges, before
transport read each edge where its flights landed).

    .venv/bin/python bench/node_gradient.py [SCENE ...]

per scene (default dense thick holdout_thick), view and albedo: ``gather`` at 1024 spp with
today's lookup and with the gradients, against the 1024-spp RR-free volpath references that
``cloudgraph bench --parts`` keeps in bench/reference-cache.
"""

import dataclasses
import sys

import numpy as np

from cloudgraph.mitsuba_scene import set_variant

set_variant()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from bench.harness import CONVERGED_SPP, dense_cases  # noqa: E402
from cloudgraph.graph import gradient_operators  # noqa: E402
from cloudgraph.metrics import bias_metrics  # noqa: E402
from cloudgraph.render import GraphRenderer  # noqa: E402
from cloudgraph.spatial import NodeGrid  # noqa: E402
from cloudgraph.tracing import to_jit  # noqa: E402


class GradientGrid(NodeGrid):
    """A node grid whose lookup extrapolates each node by its gradient (module docstring), as
    weighted means of Eq. 4.25's own weights: sum_a w_a (L_a + G_a (p - c_a)) / sum_a w_a is
    mean(L) + p . mean(G) - mean(G . c), each mean today's lookup of another per-node array."""

    @classmethod
    def of(cls, grid: NodeGrid, positions, search_radius, radiance) -> "GradientGrid":
        out = cls(**{f: getattr(grid, f) for f in grid.__dataclass_fields__})
        D = gradient_operators(positions.astype(np.float64), search_radius.astype(np.float64), 16, 2.0, 0.05)
        grad = (D @ radiance.astype(np.float64)).reshape(len(positions), 3, -1)
        g = [grad[:, axis] for axis in range(3)]  # (N, 3) each: dL/dx, dL/dy, dL/dz
        g_dot_c = sum(g[axis] * positions[:, axis : axis + 1] for axis in range(3))
        out.terms = [to_jit(mi.Color3f, a.astype(np.float32)) for a in (*g, g_dot_c)]
        return out

    def lookup(self, p: mi.Point3f, eps2: float, active: mi.Bool) -> mi.Color3f:
        def mean(values):
            return NodeGrid.lookup(dataclasses.replace(self, radiance=values), p, eps2, active)

        gx, gy, gz, g_dot_c = (mean(t) for t in self.terms)
        L = NodeGrid.lookup(self, p, eps2, active) + p.x * gx + p.y * gy + p.z * gz - g_dot_c
        return dr.maximum(L, 0.0)


if __name__ == "__main__":
    print("| scene, view, albedo | gather (Eq. 4.25) | gather, nodes extrapolated by gradient |")
    print("|---|---|---|")
    for bs, view, albedo, scene, cache, ref in dense_cases(sys.argv[1:]):
        renderer = GraphRenderer(cache, bs.volume, scene)
        cells = []
        for variant in ("today", "gradient"):
            if variant == "gradient":
                integrator = renderer.integrator("gather")
                positions, search_radius = cache.nodes
                integrator.grid = GradientGrid.of(
                    integrator.grid, positions, search_radius, cache.radiance_gather
                )
                renderer._scenes.clear()  # (a new kernel)
            m = bias_metrics(renderer.render(scene.camera, CONVERGED_SPP, 1, "gather"), ref)
            cells.append(f"{100 * m['binned_relMAE']:.2f} % / {m['mean_ratio']:.3f}")
        print(f"| {bs.name}, {view}, {albedo:g} | {cells[0]} | {cells[1]} |", flush=True)
