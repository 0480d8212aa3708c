"""Volumes: OpenVDB (.vdb) and Mitsuba (.vol) files, placed in world space.

Placement (docs/method.md, "Scene spec v1"): world = volume.scale * (grid's index-to-world map).
Voxel (i, j, k) holds its value at index point (i, j, k); values are interpolated trilinearly
between voxel centres; the medium fills the active-voxel bounding box grown by half a voxel on
every side. A :class:`Volume` keeps that box densely, as a float32 array indexed [i, j, k].
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import VolumeError
from .vdb import VDB_MAGIC, default_grid, pick_grid, value_type, vdb_grid_table

#: Refuse to densify a bounding box with more voxels than this (float32: 4 bytes each).
DEFAULT_MAX_VOXELS = 256 * 1024 * 1024


def max_voxels() -> int:
    """The densify cap, from ``CLOUDGRAPH_MAX_VOXELS`` (a count of voxels)."""
    raw = os.environ.get("CLOUDGRAPH_MAX_VOXELS")
    return int(raw) if raw else DEFAULT_MAX_VOXELS


@dataclass(frozen=True, eq=False)
class Volume:
    """A dense density grid with its placement.

    Attributes:
        density: (nx, ny, nz) float32, >= 0; density[i, j, k] is the value at index point
            index_min + (i, j, k).
        index_min: index coordinates of density[0, 0, 0].
        index_to_world: (4, 4) float64 affine map from index space to world units, including
            the scene's ``volume.scale``.
        grid: the grid's name.
    """

    density: np.ndarray
    index_min: tuple[int, int, int]
    index_to_world: np.ndarray
    grid: str = "density"

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.density.shape)

    @property
    def voxel_size(self) -> np.ndarray:
        """(3,) world length of one voxel step along i, j and k."""
        return np.linalg.norm(self.index_to_world[:3, :3], axis=0)

    @property
    def unit_to_world(self) -> np.ndarray:
        """(4, 4) map from the unit cube [0, 1]^3 onto the medium's extent in world space.

        Mitsuba's grid volumes put voxel centres at (i + 0.5) / n of the unit cube, so the unit
        cube spans index_min - 0.5 .. index_min + n - 0.5 (the half-voxel rule).
        """
        unit_to_index = np.diag([*self.shape, 1.0])
        unit_to_index[:3, 3] = np.asarray(self.index_min, float) - 0.5
        return self.index_to_world @ unit_to_index

    def world_corners(self) -> np.ndarray:
        """(8, 3) world positions of the medium box's corners."""
        u = np.array([[x, y, z, 1.0] for x in (0, 1) for y in (0, 1) for z in (0, 1)])
        return (u @ self.unit_to_world.T)[:, :3]

    def world_bbox(self) -> tuple[np.ndarray, np.ndarray]:
        c = self.world_corners()
        return c.min(axis=0), c.max(axis=0)

    def scaled(self, scale: float) -> Volume:
        """The same volume with world space scaled by ``scale`` about the origin."""
        if scale == 1.0:
            return self
        s = np.diag([scale, scale, scale, 1.0])
        return Volume(self.density, self.index_min, s @ self.index_to_world, self.grid)


# ------------------------------------------------------------------------ loading


#: The voxel sizes a loaded volume may have, world units: outside them, float32 (Mitsuba's and
#: Dr.Jit's) has no room for a medium's extent, its free paths and their products.
VOXEL_SIZES = (1e-15, 1e15)


def load_volume(path: str | Path, grid: str | None = None, scale: float = 1.0) -> Volume:
    """Reads a ``.vdb`` or ``.vol`` file into a :class:`Volume` placed in world space.

    Raises:
        VolumeError: missing, unreadable, truncated or corrupt file; no such grid; a grid that
            does not hold float density; an empty grid; a bounding box over the densify cap.
    """
    path = Path(path)
    if path.is_dir():
        raise VolumeError(f"{path} is a folder, not a volume file")
    if not path.is_file():
        raise VolumeError(f"volume file not found: {path}")
    with open(path, "rb") as f:
        head = f.read(8)
    if len(head) == 8 and struct.unpack("<q", head)[0] == VDB_MAGIC:
        vol = _load_vdb(path, grid)
    elif head[:3] == b"VOL":
        vol = _load_vol(path)
    else:
        raise VolumeError(f"{path} is neither an OpenVDB (.vdb) nor a Mitsuba (.vol) volume file")
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):  # (refused below, quietly)
        vol = vol.scaled(scale)
        size = np.asarray(vol.voxel_size, float)
    if not np.all((size >= VOXEL_SIZES[0]) & (size <= VOXEL_SIZES[1])):  # (NaN too)
        raise VolumeError(
            f"{path} at scale {scale:g} has voxels of {size.tolist()} world units: a voxel must be "
            f"{VOXEL_SIZES[0]:g} to {VOXEL_SIZES[1]:g} on every axis (Mitsuba computes in float32)"
        )
    return vol


def _load_vdb(path: Path, grid: str | None) -> Volume:
    import pyopenvdb as vdb

    table = vdb_grid_table(path)
    if not table:
        raise VolumeError(f"cannot read {path}: the OpenVDB file is truncated or corrupt")
    name, tree_type = pick_grid(path, table, grid)
    kind = value_type(tree_type)
    if kind not in ("float", "half", "double"):
        raise VolumeError(f"grid {name!r} in {path} holds {kind} values; density needs a scalar float grid")
    try:
        g = vdb.read(str(path), name)
    except TypeError as err:  # a grid type these bindings were built without
        bad = [
            f"{n!r} ({value_type(t)})" for n, t in table if value_type(t) not in ("float", "vec3s", "bool")
        ]
        raise VolumeError(
            f"cannot read {path}: its grid(s) {', '.join(bad) or str(err)} have a type this OpenVDB "
            "build cannot read (Debian's bindings read float and half grids, not double); "
            "resave the grids as float"
        ) from None
    except (LookupError, RuntimeError, OSError, ValueError) as err:
        raise VolumeError(f"cannot read {path}: the OpenVDB file is truncated or corrupt ({err})") from None
    if g.valueTypeName != "float":
        raise VolumeError(
            f"grid {name!r} in {path} holds {g.valueTypeName} values; density needs a float grid"
        )
    if g.activeVoxelCount() == 0:
        raise VolumeError(f"grid {name!r} in {path} is empty (no active voxels)")
    if not g.transform.isLinear:
        raise VolumeError(
            f"grid {name!r} in {path} has a non-linear (frustum) transform, which is not supported"
        )
    lo, hi = g.evalActiveVoxelBoundingBox()
    dims = tuple(int(b - a + 1) for a, b in zip(lo, hi, strict=True))
    _check_size(path, dims)
    density = np.zeros(dims, dtype=np.float32)
    g.copyToArray(density, ijk=lo)
    return Volume(_clean(path, density), tuple(int(v) for v in lo), _affine(g.transform), name)


def _affine(transform) -> np.ndarray:
    """(4, 4) matrix of a linear OpenVDB transform, from the images of the origin and unit axes."""
    o = np.array(transform.indexToWorld((0.0, 0.0, 0.0)))
    m = np.eye(4)
    m[:3, 3] = o
    for axis in range(3):
        e = [0.0, 0.0, 0.0]
        e[axis] = 1.0
        m[:3, axis] = np.array(transform.indexToWorld(tuple(e))) - o
    return m


def _check_size(path: Path, dims: tuple[int, int, int]) -> None:
    n = int(dims[0]) * int(dims[1]) * int(dims[2])  # Python integers: never overflows
    cap = max_voxels()
    if n > cap:
        raise VolumeError(
            f"{path}: its active bounding box {dims[0]}x{dims[1]}x{dims[2]} ({n} voxels, "
            f"{4 * n / 2**30:.1f} GiB dense) is over the limit of {cap} voxels "
            "(CLOUDGRAPH_MAX_VOXELS); crop or resample the grid"
        )


def _clean(path: Path, density: np.ndarray) -> np.ndarray:
    """The density grid, negative values read as 0; refused where it is not finite or holds no
    positive value (a medium of nothing: every flight would leave it, and a graph has no nodes)."""
    if not np.isfinite(density).all():
        raise VolumeError(f"{path}: the density grid holds NaN or infinite values")
    if density.max(initial=0.0) <= 0.0:
        raise VolumeError(f"{path}: the density grid holds no positive value (negative ones read as 0)")
    return np.maximum(density, 0.0, out=density)


def _load_vol(path: Path) -> Volume:
    """Mitsuba's binary grid format: 'VOL', version 3, encoding 1 (float32), resolution, channels, bbox."""
    raw = path.read_bytes()
    if len(raw) < 48:
        raise VolumeError(f"cannot read {path}: the .vol header is truncated")
    version = raw[3]
    encoding, nx, ny, nz, channels = struct.unpack_from("<5i", raw, 4)
    if version != 3 or encoding != 1:
        raise VolumeError(
            f"{path}: only .vol version 3 with float32 data is supported "
            f"(got version {version}, encoding {encoding})"
        )
    if channels != 1:
        raise VolumeError(f"{path}: a density .vol has 1 channel, this one has {channels}")
    if min(nx, ny, nz) < 1:
        raise VolumeError(f"{path}: invalid resolution {nx}x{ny}x{nz}")
    _check_size(path, (nx, ny, nz))
    expected = 48 + 4 * nx * ny * nz
    if len(raw) < expected:
        raise VolumeError(f"cannot read {path}: the .vol file is truncated ({len(raw)} of {expected} bytes)")
    bmin = np.array(struct.unpack_from("<3f", raw, 24), float)
    bmax = np.array(struct.unpack_from("<3f", raw, 36), float)
    data = np.frombuffer(raw, np.float32, nx * ny * nz, 48).reshape(nz, ny, nx).transpose(2, 1, 0)
    density = np.ascontiguousarray(data, dtype=np.float32)
    # Voxel centres at bmin + (i + 0.5) * step, so the medium fills exactly [bmin, bmax].
    step = (bmax - bmin) / np.array([nx, ny, nz])
    m = np.diag([*step, 1.0])
    m[:3, 3] = bmin + 0.5 * step
    return Volume(_clean(path, density), (0, 0, 0), m, "density")


def voxel_points(volume: Volume, ijk: np.ndarray) -> np.ndarray:
    """(M, 3) world points of (M, 3) voxel coordinates (density[i, j, k] sits at (i, j, k))."""
    index = ijk + np.asarray(volume.index_min)
    return index @ volume.index_to_world[:3, :3].T + volume.index_to_world[:3, 3]


def write_vol(volume: Volume, path: str | Path) -> None:
    """Writes an axis-aligned volume as a Mitsuba .vol file (its bbox is the medium's extent)."""
    lo, hi = volume.world_bbox()
    nx, ny, nz = volume.shape
    header = b"VOL" + struct.pack("<Bi4i6f", 3, 1, nx, ny, nz, 1, *lo, *hi)
    body = np.ascontiguousarray(volume.density.transpose(2, 1, 0), np.float32).tobytes()
    Path(path).write_bytes(header + body)


def write_vdb(volume: Volume, path: str | Path, half: bool = False) -> None:
    """Writes a volume as a float grid in an OpenVDB file (``half``: stored as half floats)."""
    import pyopenvdb as vdb

    g = vdb.FloatGrid()
    g.name = volume.grid
    g.copyFromArray(
        np.ascontiguousarray(volume.density, np.float32),
        ijk=tuple(int(i) for i in volume.index_min),
        tolerance=0.0,
    )
    g.transform = vdb.createLinearTransform(volume.index_to_world.T.tolist())  # OpenVDB: row vectors
    g.gridClass = vdb.GridClass.FOG_VOLUME
    g.saveFloatAsHalf = half
    vdb.write(str(path), grids=[g])


def volume_info(path: str | Path) -> dict:
    """What a volume file holds: its grids with types, the grid a scene that names none reads
    (``grid``; None where the file has several float grids and none named 'density': a scene
    must name one), and for that grid (else the first float grid) the active bounding box in
    index and world space, the voxel size and the value range."""
    path = Path(path)
    table = []
    if path.is_file() and path.read_bytes()[:3] != b"VOL":
        table = vdb_grid_table(path)
    scalars = [n for n, t in table if value_type(t) in ("float", "half", "double")]
    floats = [n for n, t in table if value_type(t) in ("float", "half")]  # (doubles: not readable)
    ambiguous = bool(table) and default_grid(table) is None and len(scalars) > 1 and bool(floats)
    vol = load_volume(path, floats[0] if ambiguous else None)
    lo, hi = vol.world_bbox()
    index_max = [a + n - 1 for a, n in zip(vol.index_min, vol.shape, strict=True)]
    grids = [{"name": n, "type": value_type(t)} for n, t in table]
    return {
        "path": str(path),
        "grids": grids or [{"name": vol.grid, "type": "float"}],
        "grid": None if ambiguous else vol.grid,
        "index_bbox": [list(vol.index_min), index_max],
        "world_bbox": [lo.tolist(), hi.tolist()],
        "voxel_size": vol.voxel_size.tolist(),
        "value_range": [float(vol.density.min()), float(vol.density.max())],
        "active_fraction": float((vol.density > 0).mean()),
    }
