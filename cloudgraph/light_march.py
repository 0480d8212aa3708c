"""The bake's light march: the optical depth to each sun from every field point and sub-voxel
sample (``field_tau`` chunks: tracing.optical_depth, a deterministic midpoint march of the
trilinear density in Dr.Jit, Eq. 4.22 at a point), and each sun's tau_light grid made from it
(light_depth.py: at twice the field's resolution, or on its own grid fitted to the sub-voxel
samples). It needs the medium and the lights only: a precompute puts it out first, and it runs
beside the graph's build (stages.LATE_STAGES)."""

from __future__ import annotations

import numpy as np

from .chunks import placed
from .field_grid import FieldPoints, scattered
from .light_depth import FINE_POWER, TAU_POWER, fine_depth, fine_shape, fit_depth
from .tracing import towards_light

#: Light march step, in field voxels (midpoint rule).
TAU_STEP = 0.5


def march_light(builder, fp: FieldPoints, directions, chunks) -> list:
    """Puts out the bake's light marches (``field_tau`` chunks: the optical depth to the light from
    every field point and sub-voxel sample, Eq. 4.22 at a point, deterministic), one per
    directional light of ``directions`` ((3,) or (D, 3), the ways they travel), and returns the
    iterators of their results. They need the medium and the lights only, so a precompute puts
    them out before the graph is written (precompute.py)."""
    step = np.array([TAU_STEP * fp.voxel])
    points = np.concatenate([fp.points, fp.sub])
    return [
        chunks(builder, "field_tau", {"points": points, "to_light": towards_light(d), "step": step})
        for d in np.asarray(directions, float).reshape(-1, 3)
    ]


def light_depths(fp: FieldPoints, marched: list) -> tuple[list, float]:
    """Each sun's tau_light grid from its light march (:func:`march_light`'s results), and the
    power of T that its texture interpolates: at twice the field's resolution where that fits
    (:func:`fine_depth`), else on the field's grid fitted to the sub-voxel samples
    (:func:`fit_depth`). Numpy alone: a precompute makes them on a thread of their own
    while it solves the transport."""
    nx, ny, nz = fp.shape
    fine = fine_shape((nz, ny, nx), len(marched)) is not None
    taus = []
    for results in marched:  # (a sun's: the grid points', then the sub-voxel samples')
        tau = placed(results, len(fp.points) + len(fp.sub), 1)[:, 0]
        tau_grid = scattered(fp.near, tau[: len(fp.points)], (nz, ny, nx))
        samples = tau[len(fp.points) :]
        if fine:
            taus.append(fine_depth(tau_grid, fp.near.reshape(nz, ny, nx), fp.sub_coords, samples))
        else:
            taus.append(fit_depth(tau_grid, fp.sigma_t, fp.sub_centres, samples))
    return taus, FINE_POWER if fine else TAU_POWER
