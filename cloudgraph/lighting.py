"""Direct radiance per node (thesis §4.4, Eq. 4.22).

L_d(a) = E * T_r(a, light) / 4pi for the isotropic phase function, where T_r is averaged over
points on a disk of the node's radius through the node, perpendicular to the light, each
estimated by ratio tracking towards the light. Per colour channel: sigma_t is grey, so the
channels differ by the light's irradiance only.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .tracing import DensityField, ratio_tracking


def direct_radiance(
    field: DensityField,
    positions: np.ndarray,
    radius: float,
    light_dir,
    irradiance,
    disk_samples: int = 16,
    seed: int = 0,
) -> np.ndarray:
    """In-scattered direct radiance at each node (Eq. 4.22).

    Args:
        positions: (N, 3) node positions, world units.
        radius: disk radius, world units (the node radius r).
        light_dir: (3,) direction the light travels.
        irradiance: scalar or (3,) irradiance of the directional light.
        disk_samples: points on the disk per node.

    Returns:
        (N, 3) float64 radiance per node, phase function (1/4pi) included.
    """
    n = len(positions)
    if n == 0:
        return np.zeros((0, 3))
    m = n * disk_samples
    rng = mi.PCG32(m, initstate=seed, initseq=dr.arange(mi.UInt64, m))
    node = dr.arange(mi.UInt32, m) // disk_samples
    centre = dr.gather(mi.Point3f, mi.Point3f(*(positions[:, i].astype(np.float32) for i in range(3))), node)
    to_light = -np.asarray(light_dir, float) / np.linalg.norm(light_dir)
    frame = mi.Frame3f(mi.Vector3f(*(float(c) for c in to_light)))
    disk = mi.warp.square_to_uniform_disk_concentric(mi.Point2f(rng.next_float32(), rng.next_float32()))
    o = mi.Point3f(centre + radius * (disk.x * mi.Vector3f(frame.s) + disk.y * mi.Vector3f(frame.t)))
    Tr = ratio_tracking(field, o, mi.Vector3f(frame.n), rng, mi.Bool(True))
    # Mean over each node's disk points (in numpy: a fixed summation order on every backend)
    transmittance = np.array(Tr, np.float64).reshape(n, disk_samples).mean(axis=1)
    e = np.broadcast_to(np.asarray(irradiance, float), (3,))
    return transmittance[:, None] * e[None, :] / (4.0 * np.pi)  # Eq. 4.22
