"""A variant of ``gather``'s node lookup measured and not adopted (docs/measurements.md, "The dense
cloud's back-lit bias is node size"): each node's radiance extrapolated to the lookup point by
its gradient, L(p) = sum_a w_a (L_a + G_a (p - c_a)) / sum_a w_a, in place of Eq. 4.25's
sum_a w_a L_a / sum_a w_a (c_a: the node's position, the mean of its collisions).

G_a is a weighted least-squares fit over the node's ``k`` nearest nodes b,
minimising sum_b w_b (L_b - L_a - G (c_b - c_a))^2 with w_b Gaussian in the distance
(``width`` search ranges), a linear operator on the radiance: three sparse (N, N) matrices.

    .venv/bin/python bench/node_gradient.py [SCENE ...]

per scene (default dense thick holdout_thick), view and albedo: ``gather`` at 1024 spp with
today's lookup and with the gradients, against the 1024-spp RR-free volpath references that
``cloudgraph bench --parts`` keeps in bench/reference-cache.
"""

import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from cloudgraph.mitsuba_scene import set_variant

set_variant()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from bench.harness import CONVERGED_SPP, LIGHT, _scene, bench_scenes, cameras, reference  # noqa: E402
from cloudgraph.cache import CacheStore  # noqa: E402
from cloudgraph.metrics import bias_metrics  # noqa: E402
from cloudgraph.precompute import precompute  # noqa: E402
from cloudgraph.render import GraphRenderer  # noqa: E402
from cloudgraph.spatial import NodeGrid  # noqa: E402
from cloudgraph.tracing import to_jit  # noqa: E402


def gradient_operators(positions: np.ndarray, radius: np.ndarray, k: int = 16, width: float = 2.0) -> list:
    """Three sparse (N, N) matrices D_x, D_y, D_z: G = (D_x L, D_y L, D_z L) (module docstring)."""
    n = len(positions)
    _, j = cKDTree(positions).query(positions, k + 1)
    j = j[:, 1:]
    d = positions[j] - positions[:, None, :]  # (N, k, 3)
    h = radius[:, None]
    w = np.exp(-np.sum(d**2, -1) / (2 * (width * h) ** 2))
    m = np.einsum("nk,nki,nkj->nij", w, d, d) + 0.05 * h[:, :, None] ** 2 * np.eye(3)  # (regularised)
    coef = np.einsum("nij,nk,nkj->nki", np.linalg.inv(m), w, d)  # G = sum_b coef_b (L_b - L_a)
    rows = np.repeat(np.arange(n), k)
    ops = []
    for axis in range(3):
        a = sp.csr_matrix((coef[:, :, axis].ravel(), (rows, j.ravel())), shape=(n, n))
        ops.append((a - sp.diags(np.asarray(a.sum(axis=1)).ravel())).tocsr())
    return ops


class GradientGrid(NodeGrid):
    """A node grid whose lookup extrapolates each node by its gradient (module docstring)."""

    @classmethod
    def of(cls, grid: NodeGrid, positions, search_radius, radiance) -> "GradientGrid":
        out = cls(**{f: getattr(grid, f) for f in grid.__dataclass_fields__})
        ops = gradient_operators(positions.astype(np.float64), search_radius.astype(np.float64))
        out.gradient = tuple(to_jit(mi.Color3f, (op @ radiance.astype(np.float64)).astype(np.float32)) for op in ops)
        return out

    @dr.syntax
    def lookup(self, p: mi.Point3f, eps2: float, active: mi.Bool) -> mi.Color3f:
        gx, gy, gz = self.gradient  # (read outside the loop: Dr.Jit's loop state holds the fields)
        g = (p - mi.Point3f(*self.origin)) / self.cell
        inside = active & dr.all((g >= 0) & (g < mi.Point3f(*self.dims)))
        gi = mi.Vector3u(dr.clip(mi.Vector3i(g), 0, mi.Vector3i(*self.dims) - 1))
        c = gi.x + self.dims[0] * (gi.y + self.dims[1] * gi.z)
        i = dr.gather(mi.UInt32, self.cell_start, c, inside)
        end = dr.gather(mi.UInt32, self.cell_start, c + 1, inside)
        L = mi.Color3f(0.0)
        W = mi.Float(0.0)
        loop = inside & (i < end)
        while dr.hint(loop, label="node_gather_gradient"):
            a = dr.gather(mi.UInt32, self.entries, i, loop)
            dp = p - dr.gather(mi.Point3f, self.positions, a, loop)
            d2 = dr.squared_norm(dp)
            near = loop & (d2 < dr.gather(mi.Float, self.radius2, a, loop))
            w = dr.rcp(dr.maximum(d2, eps2))
            La = dr.gather(mi.Color3f, self.radiance, a, near)
            dL = (
                dr.gather(mi.Color3f, gx, a, near) * dp.x
                + dr.gather(mi.Color3f, gy, a, near) * dp.y
                + dr.gather(mi.Color3f, gz, a, near) * dp.z
            )
            W[near] += w
            L[near] += w * (La + dr.clip(dL, -La, La))  # (never below 0, at most twice L_a)
            i += 1
            loop &= i < end
        return dr.select(W > 0, L / W, 0.0)


if __name__ == "__main__":
    refs = Path(__file__).resolve().parent / "reference-cache"
    store = CacheStore(Path(__file__).resolve().parent / "cache")
    print("| scene, view, albedo | gather (Eq. 4.25) | gather, nodes extrapolated by gradient |")
    print("|---|---|---|")
    for bs in bench_scenes(sys.argv[1:] or ["dense", "thick", "holdout_thick"]):
        for view, camera in cameras(bs.volume, LIGHT, 64).items():
            for albedo in (1.0, 0.8):
                scene = _scene(bs, camera, albedo, 16, seed=0)
                cache = precompute(scene, bs.volume, "default", store)
                ref = reference(bs, scene, 1024, refs)
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
