"""Procedural test volumes: a fog sphere, a homogeneous block and a fixed-seed noise cloud."""

from __future__ import annotations

import numpy as np

from .volume import Volume


def sphere_volume(n: int = 32, density: float = 1.0, voxel_size: float = 1.0, soft: float = 0.0) -> Volume:
    """A fog sphere filling an n^3 grid centred on the origin, radius n/2 - 1 voxels.

    ``soft`` > 0 fades the edge over that many voxels; 0 gives a hard, homogeneous ball.
    """
    c = (n - 1) / 2.0
    i = np.arange(n) - c
    r = np.sqrt(i[:, None, None] ** 2 + i[None, :, None] ** 2 + i[None, None, :] ** 2)
    radius = n / 2.0 - 1.0
    if soft > 0:
        d = np.clip((radius - r) / soft, 0.0, 1.0)
    else:
        d = (r <= radius).astype(np.float32)
    m = np.diag([voxel_size] * 3 + [1.0])
    m[:3, 3] = -c * voxel_size
    return Volume((density * d).astype(np.float32), (0, 0, 0), m, "density")


def box_volume(
    dims: tuple[int, int, int],
    density: float = 1.0,
    index_min=(0, 0, 0),
    index_to_world: np.ndarray | None = None,
) -> Volume:
    """A homogeneous block of voxels (a slab or a cube) with any affine placement."""
    m = np.eye(4) if index_to_world is None else np.asarray(index_to_world, float)
    return Volume(np.full(dims, density, np.float32), tuple(int(i) for i in index_min), m, "density")


def noise_volume(n: int = 64, seed: int = 7, density: float = 1.0, voxel_size: float = 1.0) -> Volume:
    """A fixed-seed cloud: fractal value noise (4 octaves) shaped by a soft ellipsoid, in [0, density]."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, n, dtype=np.float32)
    field = np.zeros((n, n, n), np.float32)
    amp, total = 1.0, 0.0
    for octave in range(4):  # a loop over octaves, not voxels
        cells = 4 * 2**octave
        lattice = rng.random((cells + 1,) * 3, dtype=np.float32)
        field += amp * _trilinear_upsample(lattice, x * cells)
        total += amp
        amp *= 0.5
    field /= total
    c = x[:, None, None] - 0.5, x[None, :, None] - 0.5, x[None, None, :] - 0.5
    r = np.sqrt((c[0] / 0.42) ** 2 + (c[1] / 0.32) ** 2 + (c[2] / 0.42) ** 2)
    shape = np.clip(1.0 - r, 0.0, 1.0)
    d = np.clip((field * 1.6 - 0.55) + shape * 0.9 - 0.35, 0.0, None) * (r < 1.0)
    d /= d.max()
    m = np.diag([voxel_size] * 3 + [1.0])
    m[:3, 3] = -(n - 1) / 2.0 * voxel_size
    return Volume((density * d).astype(np.float32), (0, 0, 0), m, "density")


def _trilinear_upsample(lattice: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Samples a lattice at t (lattice units, along each axis) with smoothstep interpolation."""
    i0 = np.minimum(np.floor(t).astype(int), lattice.shape[0] - 2)
    f = t - i0
    f = f * f * (3 - 2 * f)
    out = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (
                    (f if dx else 1 - f)[:, None, None]
                    * (f if dy else 1 - f)[None, :, None]
                    * (f if dz else 1 - f)[None, None, :]
                )
                out = out + w * lattice[np.ix_(i0 + dx, i0 + dy, i0 + dz)]
    return out.astype(np.float32)
