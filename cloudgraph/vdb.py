"""The OpenVDB file header: which grids a ``.vdb`` file holds, read without the bindings.

Debian's ``pyopenvdb`` refuses a whole file when one grid has a type it was not built with
(double grids); the header alone names every grid and its tree type.
"""

from __future__ import annotations

import struct
from pathlib import Path

from .errors import VolumeError

VDB_MAGIC = 0x56444220


def vdb_grid_table(path: str | Path) -> list[tuple[str, str]]:
    """(name, tree type) of every grid in a .vdb file, read from its header alone.

    This works where the Python bindings refuse a whole file because one grid has a type
    they were not built with (Debian's bindings have no double grids).
    """
    with open(path, "rb") as f:
        data = f.read(1 << 20)
    pos = 8

    def u32() -> int:
        nonlocal pos
        (v,) = struct.unpack_from("<I", data, pos)
        pos += 4
        return v

    def string() -> str:
        nonlocal pos
        n = u32()
        s = data[pos : pos + n].decode("utf-8", "replace")
        pos += n
        return s

    try:
        version = u32()
        if version >= 211:
            pos += 8  # library major, minor
        has_offsets = True
        if version >= 212:
            has_offsets = bool(data[pos])
            pos += 1
        if version < 222:
            pos += 4  # file-level compression flags
        pos += 36  # UUID
        for _ in range(u32()):  # file metadata: name, type, sized value
            string()
            string()
            size = u32()
            pos += size
        if not has_offsets:
            return []
        grids = []
        for _ in range(u32()):
            name, tree_type = string(), string()
            if version >= 216:
                string()  # instance parent (grid instancing, file version 216)
            _, _, end = struct.unpack_from("<qqq", data, pos)
            grids.append((name, tree_type.removesuffix("_HalfFloat")))
            with open(path, "rb") as f:  # descriptors sit between grids: jump to the next one
                f.seek(end)
                data = f.read(1 << 16)
            pos = 0
        return grids
    except (struct.error, IndexError, ValueError, OSError):
        return []


def value_type(tree_type: str) -> str:
    parts = tree_type.split("_")
    return parts[1] if len(parts) > 2 and parts[0] == "Tree" else tree_type


def default_grid(grids: list[tuple[str, str]]) -> str | None:
    """The grid a scene that names none reads: 'density', else the only scalar float grid
    (None: there are several and none is named 'density', or there is none)."""
    names = [n for n, _ in grids]
    if "density" in names:
        return "density"
    floats = [n for n, t in grids if value_type(t) in ("float", "half", "double")]
    return floats[0] if len(floats) == 1 else None


def pick_grid(path: Path, grids: list[tuple[str, str]], grid: str | None) -> tuple[str, str]:
    """Chooses the named grid, else :func:`default_grid`."""
    listing = ", ".join(f"{n!r} ({value_type(t)})" for n, t in grids) or "none"
    by_name = dict(grids)
    if grid is not None:
        if grid not in by_name:
            raise VolumeError(f"{path} has no grid named {grid!r}; its grids: {listing}")
        return grid, by_name[grid]
    default = default_grid(grids)
    if default is not None:
        return default, by_name[default]
    floats = [n for n, t in grids if value_type(t) in ("float", "half", "double")]
    raise VolumeError(
        f"{path} has no grid named 'density' and {len(floats)} scalar grids; "
        f"name one with volume.grid (its grids: {listing})"
    )
