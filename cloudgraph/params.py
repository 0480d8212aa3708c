"""Parameters in one place: the graph build's (quality presets, :class:`BuildParams`) and the
lighting and transport's (:data:`LIGHTING`), with the volume statistics they are scaled by."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .volume import Volume

#: Quality presets. The node radius is a fraction of the typical mean free path, since the
#: method's bias grows with node size measured in free paths (§5.4). Measured on the bench
#: sphere (optical radius 10, albedo 1), ratio of graph to volpath image means, side-lit /
#: back-lit: radius 0.6 free paths 1.13 / 1.39, 0.4: 1.05 / 1.13, 0.25: 1.03 / 1.07. The radius
#: is clamped to a range of voxels: far below a voxel nodes resolve nothing more, and the node
#: count grows as 1 / r^3. Where the medium is thinner than typical, nodes grow by up to
#: 2^max_level to the same size in local free paths (:class:`NodeCells`): on smoke1 that is 36 %
#: of the nodes at the same converged accuracy (docs/measurements.md, "Scale").
PRESETS: dict[str, dict] = {
    "draft": {
        "radius_mfp": 0.6,
        "radius_voxels": (1.0, 4.0),
        "n_paths": 1 << 15,
        "max_collisions": 32,
        "min_out_samples": 16,
        "max_level": 3,
    },
    # default's sampling with larger nodes (0.45 free paths, at least a voxel): a fifth to a half
    # of default's nodes, under a quarter of those of the code issue 11 was filed against and
    # more accurate than that code, less accurate than default (docs/measurements.md, "Scale")
    "compact": {
        "radius_mfp": 0.45,
        "radius_voxels": (1.0, 3.0),
        "n_paths": 1 << 17,
        "max_collisions": 48,
        "min_out_samples": 32,
        "max_level": 3,
    },
    "default": {
        "radius_mfp": 0.35,
        "radius_voxels": (0.6, 3.0),
        "n_paths": 1 << 17,
        "max_collisions": 48,
        "min_out_samples": 32,
        "max_level": 3,
    },
    "high": {
        "radius_mfp": 0.25,
        "radius_voxels": (0.5, 2.0),
        "n_paths": 1 << 18,
        "max_collisions": 64,
        "min_out_samples": 64,
        "max_level": 3,
    },
}


@dataclass(frozen=True)
class BuildParams:
    """Graph build parameters (names after the thesis's App. B where it names them).

    Attributes:
        radius: node radius r, world units (§4.3.1), where the medium is densest.
        radius_mfp, max_level: where the medium is thinner, nodes grow to radius_mfp free paths,
            at most 2^max_level r (:class:`NodeCells`).
        n_paths: light paths traced from the directional light.
        max_collisions: collisions kept per light path; the walk is Markov, so cutting a path
            short drops samples but biases no transition estimate.
        min_out_samples: reinforcement tops every node up to this many outgoing samples (§4.3).
        min_out_edges: nodes with fewer distinct out-edges get min_out_samples more.
        reinforce_rounds: reinforcement passes (new nodes found in one are filled in the next).
        coverage_seeds: points drawn in proportion to density that seed nodes where cut light
            paths do not reach (0: from the volume, about two per node cell).
        search_k: the k of Eq. 4.21 (search range from the k-th nearest node).
        seed: random seed; the same seed gives the same graph.
    """

    radius: float
    radius_mfp: float = 0.35
    max_level: int = 0
    n_paths: int = 1 << 17
    max_collisions: int = 48
    min_out_samples: int = 32
    min_out_edges: int = 6
    reinforce_rounds: int = 3
    coverage_seeds: int = 0
    search_k: int = 8
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def typical_free_path(volume: Volume, density_scale: float) -> float:
    """1 / sigma_t averaged where collisions happen (density-weighted), world units."""
    rho = volume.density[volume.density > 0].astype(np.float64)
    if rho.size == 0 or density_scale <= 0:
        return np.inf
    return 1.0 / (density_scale * float((rho * rho).sum() / rho.sum()))


def build_params(volume: Volume, density_scale: float, quality: str = "default", **overrides) -> BuildParams:
    """Preset parameters for a volume and density scale (see :data:`PRESETS`)."""
    if quality not in PRESETS:
        raise ValueError(f"unknown quality {quality!r}; choose one of {', '.join(PRESETS)}")
    p = dict(PRESETS[quality])
    voxel = float(np.mean(volume.voxel_size))
    lo, hi = p.pop("radius_voxels")
    mfp = typical_free_path(volume, density_scale)
    radius = float(np.clip(p["radius_mfp"] * mfp, lo * voxel, hi * voxel))
    p.update(overrides)
    radius = p.pop("radius", radius)
    if not p.get("coverage_seeds"):
        cell = (2.0 * radius / np.sqrt(3.0)) ** 3
        p["coverage_seeds"] = (
            int(2 * np.count_nonzero(volume.density) * float(np.prod(volume.voxel_size)) / cell) + 1
        )
    return BuildParams(radius=radius, **p)


#: Lighting parameters that enter the radiance key, with the version of the field's bake (its
#: file is kept under the radiance key: a new bake must not find an old one's) and of what
#: ``gather``'s node radiance holds (2: without the suns' direct light, precompute.without_sun).
#: Transport reads each edge where its flights landed, by its end node's radiance gradient
#: (graph.Graph.transitions): a weighted least-squares plane through the node's ``nodes`` nearest
#: nodes, weighted by a Gaussian of ``width`` search ranges, regularised by ``ridge`` search ranges
#: squared. On the bench's thick, dense and held-out clouds 8 nodes at one range and 16 at two
#: read the same image means within 0.3 % (docs/measurements.md, "Where a flight lands"); 8 take
#: half the time.
GRADIENT = {"nodes": 8, "width": 1.0, "ridge": 0.05}
#: ``landing``: the gradient's parameters (the radiance changes with them); ``curvature``: with
#: the landing points' second-order term where the medium absorbs (graph.Graph.transitions).
LIGHTING = {
    "samples": 16,
    "tol": 1e-5,
    "transport": "krylov",
    "field": 9,
    "gather": 2,
    "landing": GRADIENT,
    "curvature": True,
}


def suns_apart(isotropic: bool, max_depth: int) -> bool:
    """Whether ``gather``'s node radiance is without the suns' direct light, which ``gather`` and
    the field's bake then take exactly where they look the graph up (precompute.without_sun): the
    isotropic phase, with a second scattering event. Only such radiance is read by each node's
    plane (spatial.NodeGrid): what is left is smooth, where the direct light's exp(-tau) is
    convex and a plane through a node reads it low (a nearly isotropic HG cache, whose tail reads
    it: 0.978 of the isotropic image's mean; by node means 0.997)."""
    return isotropic and not 0 <= max_depth < 2
