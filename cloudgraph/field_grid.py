"""The radiance field's grid: its shape, its points in the unit cube and in the world, and the
points a bake evaluates (field.py bakes onto it)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter

from .light_depth import sub_centres, sub_coords
from .tracing import DensityField

#: Field grid points at most (the density grid's resolution up to this; coarser beyond, by one
#: integer factor on every axis). 2^24 points: 64 MiB of float32 per scalar array in memory.
MAX_POINTS = 1 << 24


def field_shape(volume_shape) -> tuple[int, int, int]:
    """(nx, ny, nz) of the field grid: the density grid's, or coarser by one integer factor
    until at most :data:`MAX_POINTS` points."""
    n = np.asarray(volume_shape, np.int64)
    f = 1
    while np.prod(-(-n // f)) > MAX_POINTS:
        f += 1
    return tuple(int(v) for v in -(-n // f))


def unit_points(shape) -> np.ndarray:
    """(nz*ny*nx, 3) unit-cube texel centres of a grid of (nx, ny, nz), in C order (x fastest)."""
    nx, ny, nz = shape
    z, y, x = np.meshgrid(
        (np.arange(nz) + 0.5) / nz, (np.arange(ny) + 0.5) / ny, (np.arange(nx) + 0.5) / nx, indexing="ij"
    )
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


@dataclass
class MsGrid:
    """A field grid's multiple-scattering grid (field.py bakes L_ms on it): ``coarsen`` times
    coarser per axis, its ``shape`` (mx, my, mz), the points gathered (``near``, flat: those that
    the camera's interpolation reads, :func:`read_mask`) and where they are (``points``, (M, 3) world,
    float32), and every point's unit-cube coordinates (``units``, float32, C order)."""

    coarsen: int
    shape: tuple
    near: np.ndarray
    points: np.ndarray
    units: np.ndarray


@dataclass
class FieldPoints:
    """The field grid of a medium: its ``shape`` (nx, ny, nz), sigma_t at its points (nz, ny,
    nx), which points are baked (``near``, flat: within one voxel of some density; the rest stay
    zero) and where those are (``points``, (M, 3) world), ``voxel`` its smallest world step, and
    the light march's sub-voxel samples in optically thick voxels (``sub``, (S, 3) world;
    ``sub_coords``, the same in grid coordinates; ``sub_centres``, the grid points they sit
    around: light_depth.py), and ``unit_to_world`` (the volume's). Made once, by the process that
    bakes the field (:meth:`of`, precompute.py), from the medium alone; the bake's chunks get the
    points they need as inputs."""

    shape: tuple
    sigma_t: np.ndarray
    near: np.ndarray
    points: np.ndarray
    voxel: float
    sub: np.ndarray
    sub_coords: np.ndarray
    sub_centres: np.ndarray
    unit_to_world: np.ndarray

    @classmethod
    def of(cls, volume, medium: DensityField) -> FieldPoints:
        u2w = np.asarray(volume.unit_to_world, float)
        shape = field_shape(volume.shape)
        nx, ny, nz = shape
        units = unit_points(shape)
        if shape == tuple(volume.shape):  # texel centres: the voxels, read as they are
            density = np.ascontiguousarray(volume.density.transpose(2, 1, 0), np.float32)
            sigma_t = density * np.float32(medium.scale)
        else:
            sigma_t = medium.sigma_t_at(to_world(u2w, units)).astype(np.float32).reshape(nz, ny, nx)
        # Trilinear interpolation at any point of the medium reads 8 grid points, all within one
        # voxel of a non-zero one
        near = maximum_filter(sigma_t > 0, size=3, mode="constant").ravel()
        points = to_world(u2w, units[near]).astype(np.float32)
        voxel = float((np.linalg.norm(u2w[:3, :3], axis=0) / np.asarray(shape)).min())
        centres = sub_centres(sigma_t, voxel)
        coords = sub_coords(centres)
        sub = to_world(u2w, (coords + 0.5) / np.asarray(shape)).astype(np.float32)
        return cls(shape, sigma_t, near, points, voxel, sub, coords, centres, u2w)


def to_world(u2w: np.ndarray, u: np.ndarray) -> np.ndarray:
    return u @ u2w[:3, :3].T + u2w[:3, 3]


def read_mask(dense: np.ndarray, shape) -> np.ndarray:
    """Flat mask of the points of a grid of ``shape`` (mx, my, mz) over the same unit cube that
    trilinear interpolation (clamped at the faces, as a texture is) reads anywhere the fine grid's
    interpolation of ``dense`` ((nz, ny, nx) bool) is not zero: within one fine step, on each
    axis, of a point of ``dense``. Per axis the fine points d reach the coarse points from
    floor(c(d - 1)) to floor(c(d + 1)) + 1, c the coarse coordinate of a fine one (open at the
    ends: a corner of weight 0 is not read); a point of the grid is read where all three axes'
    reach it from one point of ``dense``. (The march also reads a segment's end up to a step
    past the medium: field.py gives the points next to these their nearest one's value.)"""
    out = dense.astype(np.float32)
    for axis, m in enumerate(shape[::-1]):  # (z, y, x)
        n = dense.shape[axis]
        d = np.arange(n)
        c_lo = (d - 0.5 + 1e-4) * m / n - 0.5  # (coarse coordinate of fine x = d - 1, just inside)
        c_hi = (d + 1.5 - 1e-4) * m / n - 0.5  # (of x = d + 1)
        lo = np.clip(np.floor(c_lo), 0, m - 1)
        hi = np.clip(np.floor(c_hi) + 1, 0, m - 1)
        j = np.arange(m)[:, None]
        reach = ((j >= lo[None, :]) & (j <= hi[None, :])).astype(np.float32)  # (m, n)
        out = np.moveaxis(np.tensordot(reach, out, axes=([1], [axis])), 0, axis)
    return (out > 0).ravel()


def make_ms_grid(fp: FieldPoints, coarsen: int, max_points: int) -> MsGrid:
    """The multiple-scattering grid of ``fp``: ``coarsen`` times coarser per axis, or coarser
    still until at most ``max_points`` of its points are gathered: those that the camera's
    interpolation reads (:func:`read_mask`)."""
    k = coarsen
    while True:
        shape = tuple(-(-n // k) for n in fp.shape)
        ms_near = read_mask(fp.sigma_t > 0, shape)
        if ms_near.sum() <= max_points:
            break
        k += 1
    units = unit_points(shape)
    points = to_world(fp.unit_to_world, units[ms_near]).astype(np.float32)
    return MsGrid(k, shape, ms_near, points, units.astype(np.float32))


def scattered(mask: np.ndarray, values: np.ndarray, shape) -> np.ndarray:
    """A zero array of ``shape`` with ``values`` at the points where the flat ``mask`` is set."""
    out = np.zeros((mask.size, *values.shape[1:]), np.float32)
    out[mask.ravel()] = values
    return out.reshape(shape)
