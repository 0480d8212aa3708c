"""``python -m server.volume_check FILE NAME [API_PID [KIND]]``: reads an upload in a child process
of the API, and dies with it (an upload whose API died is not stored). KIND is ``volume`` (the
default) or ``environment`` (a lat-long .exr map, read by Mitsuba: cloudgraph.store).

A volume file is small and sparse, but densified it can be huge, and a corrupt one can crash
the OpenVDB reader: both happen here, never in the API process. The process runs under a memory
limit derived from ``MAX_VOXELS``; before anything is densified, every float grid's active
bounding box is checked against ``MAX_VOXELS`` in Python integers (no overflow). Then the file
is stored (``VolumeStore.put``) and its description gains, per float grid, the densest value
and the voxel size that the API's density_scale check needs.

Prints one JSON line: ``{"info": ..., "created": ...}`` or ``{"error": ..., "status": 413|422|507}``
(507: the uploads volume is full or not writable).
"""

from __future__ import annotations

import ctypes
import json
import os
import resource
import signal
import sys
from pathlib import Path

from cloudgraph.files import write_atomic
from cloudgraph_service.errors import storage_message
from cloudgraph_service.settings import Settings

_FLOAT = ("float", "half")


def memory_limit(max_voxels: int) -> int:
    """Bytes of address space for the check: the dense float32 grid, two more arrays of its size
    on the way (the finite check, the copy), and 1 GiB for the interpreter and libraries."""
    return 6 * max_voxels + 2**30


def grid_stats(path: Path, name: str, max_voxels: int) -> dict[str, dict]:
    """Per float grid of a .vdb: active bounding box size, densest value, voxel size.

    Raises:
        VolumeError: a grid whose bounding box holds more than ``max_voxels`` voxels.
    """
    import pyopenvdb as vdb

    from cloudgraph.errors import VolumeError
    from cloudgraph.vdb import value_type, vdb_grid_table

    out = {}
    for grid, tree in vdb_grid_table(path):
        if value_type(tree) not in _FLOAT:
            continue
        try:
            g = vdb.read(str(path), grid)
        except (TypeError, LookupError, RuntimeError, OSError, ValueError):
            continue  # put() below says what is wrong if this grid is the one it reads
        if g.activeVoxelCount() == 0:
            continue
        lo, hi = g.evalActiveVoxelBoundingBox()
        dims = [int(b) - int(a) + 1 for a, b in zip(lo, hi, strict=True)]
        n = dims[0] * dims[1] * dims[2]  # Python integers: no overflow
        if n > max_voxels:
            raise VolumeError(
                f"{name}: grid {grid!r} has active voxels spread over a {dims[0]}x{dims[1]}x{dims[2]} box "
                f"({n} voxels dense), over the limit of {max_voxels} (MAX_VOXELS); crop or resample it"
            )
        vmin, vmax = g.evalMinMax()
        out[grid] = {
            "dims": dims,
            "value_max": float(vmax),
            "voxel_size": [float(v) for v in g.transform.voxelSize()],
        }
    return out


def check(path: Path, name: str, settings: Settings, tag: str = "", kind: str = "volume") -> dict:
    """Checks and stores one upload; the JSON answer for the API. ``tag``: the API process's
    writer tag, which the store's temporary copy carries (cloudgraph.store.sweep_temporaries)."""
    from cloudgraph.errors import VolumeError
    from cloudgraph.store import EnvironmentStore, VolumeStore

    volume = kind == "volume"
    store = VolumeStore(settings.volumes_dir) if volume else EnvironmentStore(settings.environments_dir)
    try:
        with open(path, "rb") as f:
            is_vdb = f.read(3) != b"VOL"
        stats = grid_stats(path, name, settings.MAX_VOXELS) if volume and is_vdb else {}
        with open(path, "rb") as f:
            info, created = store.put(f, settings.MAX_UPLOAD_MB * 2**20, name, tag)
        if created and volume:
            for g in info["grids"]:
                g.update(stats.get(g["name"], {}))
            if not stats:  # a .vol: its one grid is the density
                g = info["grids"][0]
                g.update(value_max=info["value_range"][1], voxel_size=info["voxel_size"])
            write_atomic(store.root / f"{info['id']}.json", json.dumps(info).encode())
    except VolumeError as err:
        return {"error": str(err), "status": 422}
    except MemoryError:
        return {"error": f"{name} needs more memory to read than the service allows", "status": 422}
    except OSError as err:
        message = storage_message(err, {"uploads": store.root})
        if message is None:
            raise
        return {"error": message, "status": 507}
    return {"info": info, "created": created}


def die_with(parent: int) -> None:
    """Linux: this process gets SIGKILL when the API process ``parent`` dies, and ends at once if
    it already has (the kernel was asked too late)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:
        os._exit(1)


def main() -> None:
    parent = int(sys.argv[3]) if len(sys.argv) > 3 else 0
    if parent:
        die_with(parent)
    settings = Settings.from_env()
    limit = memory_limit(settings.MAX_VOXELS)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    from cloudgraph.store import writer_tag

    tag = writer_tag(parent) if parent else ""
    kind = sys.argv[4] if len(sys.argv) > 4 else "volume"
    print(json.dumps(check(Path(sys.argv[1]), sys.argv[2], settings, tag, kind)))


if __name__ == "__main__":
    main()
