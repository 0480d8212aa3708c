"""Content keys and the on-disk cache store (DESIGN.md, "Cache levels and keys").

Keys are sha256 of canonical JSON with the engine format version included:
- volume id: the density values and the transform;
- graph key: volume id + density_scale + build parameters;
- radiance key: graph key + albedo + light + max_depth (+ lighting parameters).

Files are ``.npz`` archives carrying their format version, written to a temporary name in the
same folder and renamed into place, so a reader never sees a half-written cache. Their bytes
depend on their content only (no timestamps, no stage times): the same key gives the same file
however many workers built it.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
import zipfile
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import ENGINE_FORMAT_VERSION
from .errors import CacheError

if TYPE_CHECKING:  # the API process imports this module; it must not load the renderer
    from .graph import Graph
    from .volume import Volume


def _digest(obj) -> str:
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def volume_id(volume: Volume, version: int = ENGINE_FORMAT_VERSION) -> str:
    """Content hash of the density values, their index placement and the world transform (with
    the engine format ``version``: a new engine gets new keys)."""
    h = hashlib.sha256()
    h.update(f"cloudgraph-volume-v{version}".encode())
    h.update(np.asarray(volume.shape, np.int64).tobytes())
    h.update(np.asarray(volume.index_min, np.int64).tobytes())
    h.update(np.round(volume.index_to_world, 9).astype(np.float64).tobytes())
    h.update(np.ascontiguousarray(volume.density, np.float32).tobytes())
    return h.hexdigest()


def graph_key(vol_id: str, density_scale: float, build_params: dict) -> str:
    return _digest(
        {
            "v": ENGINE_FORMAT_VERSION,
            "volume": vol_id,
            "density_scale": float(density_scale),
            "build": build_params,
        }
    )


def radiance_key(g_key: str, albedo, light_dir, irradiance, max_depth: int, lighting: dict) -> str:
    unit = np.asarray(light_dir, float) / np.linalg.norm(light_dir)
    return _digest(
        {
            "v": ENGINE_FORMAT_VERSION,
            "graph": g_key,
            "albedo": np.broadcast_to(np.asarray(albedo, float), (3,)).round(9).tolist(),
            "light_dir": unit.round(9).tolist(),
            "irradiance": np.broadcast_to(np.asarray(irradiance, float), (3,)).round(9).tolist(),
            "max_depth": int(max_depth),
            "lighting": lighting,
        }
    )


def default_cache_dir() -> Path:
    return Path(os.environ.get("CLOUDGRAPH_CACHE_DIR", Path.home() / ".cache" / "cloudgraph"))


class CacheStore:
    """Graph and radiance files under one folder, keyed by content."""

    def __init__(self, root: str | Path | None = None):
        self.root = Path(root) if root is not None else default_cache_dir()

    def graph_path(self, key: str) -> Path:
        return self.root / "graphs" / f"{key}.npz"

    def radiance_path(self, key: str) -> Path:
        return self.root / "radiance" / f"{key}.npz"

    def field_path(self, key: str) -> Path:
        """The radiance field of a radiance key: gzip-compressed bytes (``cloudgraph/field.py``)."""
        return self.root / "fields" / f"{key}.cgf.gz"

    # ------------------------------------------------------------------ graphs
    def save_graph(self, key: str, graph: Graph) -> Path:
        """Compact and compressed: counts and sample totals in the smallest unsigned type that
        holds them, column indices as uint32 (the edges are most of the file)."""
        c = graph.counts.tocsr()
        return _atomic_save(
            self.graph_path(key),
            kind="graph",
            compress=True,
            positions=graph.positions.astype(np.float32),
            search_radius=graph.search_radius.astype(np.float32),
            out_samples=_compact(graph.out_samples),
            indptr=c.indptr.astype(np.int64),
            indices=c.indices.astype(np.uint32),
            data=_compact(c.data),
            stats=json.dumps(_content(graph.stats)),
        )

    def load_graph(self, key: str) -> Graph | None:
        import scipy.sparse as sp

        from .graph import Graph

        z = _load(self.graph_path(key), "graph")
        if z is None:
            return None
        n = len(z["positions"])
        counts = sp.csr_matrix(
            (z["data"].astype(np.int64), z["indices"].astype(np.int32), z["indptr"]), shape=(n, n)
        )
        stats = json.loads(str(z["stats"]))
        return Graph(z["positions"], z["search_radius"], z["out_samples"].astype(np.int64), counts, stats)

    def load_nodes(self, key: str) -> tuple[np.ndarray, np.ndarray] | None:
        """(positions, search ranges) of a graph: all that a render reads of it (not the counts)."""
        z = _load(self.graph_path(key), "graph", ("positions", "search_radius"))
        return None if z is None else (z["positions"], z["search_radius"])

    # ---------------------------------------------------------------- radiance
    def save_radiance(self, key: str, radiance: np.ndarray, radiance_gather: np.ndarray, stats: dict) -> Path:
        """Node radiance L' and L' with one scattering event fewer, (N, 3) each."""
        return _atomic_save(
            self.radiance_path(key),
            kind="radiance",
            radiance=radiance.astype(np.float32),
            radiance_gather=radiance_gather.astype(np.float32),
            stats=json.dumps(_content(stats)),
        )

    def load_radiance(self, key: str) -> tuple[tuple[np.ndarray, np.ndarray], dict] | None:
        z = _load(self.radiance_path(key), "radiance")
        return None if z is None else ((z["radiance"], z["radiance_gather"]), json.loads(str(z["stats"])))

    # ------------------------------------------------------------------ fields
    def save_field(self, key: str, data: bytes) -> Path:
        path = self.field_path(key)
        with atomic_writer(path) as f:
            f.write(data)
        return path

    def load_field(self, key: str) -> bytes | None:
        path = self.field_path(key)
        try:
            os.utime(path)  # last use, for least-recently-used eviction
            return path.read_bytes()
        except FileNotFoundError:
            return None


@contextmanager
def atomic_writer(path: Path):
    """A binary file that appears at ``path`` whole or not at all: written under a temporary name
    in the same folder, synced, then renamed into place (removed if the writer fails)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _atomic_save(path: Path, kind: str, compress: bool = False, **arrays) -> Path:
    """An .npz as ``np.savez`` writes it, but with fixed timestamps: the same arrays give the same
    bytes, whichever worker wrote them and when. Compressed at zlib level 1: on smoke1's graph
    2 % larger than level 6 in a quarter of the time (0.4 s against 1.6 s)."""
    arrays = {"format_version": ENGINE_FORMAT_VERSION, "kind": kind, **arrays}
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with atomic_writer(path) as f, zipfile.ZipFile(f, "w", method, allowZip64=True) as z:
        for name, a in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(a), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            z.writestr(info, buf.getbuffer(), compress_type=method, compresslevel=1)
    return path


def _content(stats: dict) -> dict:
    """Stats without the stage times (``*_s``): what a file keeps, so that its bytes depend on its
    content only."""
    return {k: v for k, v in stats.items() if not k.endswith("_s")}


def _compact(a: np.ndarray) -> np.ndarray:
    """Non-negative integers in the smallest unsigned type that holds them."""
    return a.astype(np.min_scalar_type(int(a.max())) if a.size else np.uint8)


def _load(path: Path, kind: str, names: tuple[str, ...] | None = None) -> dict | None:
    """The arrays of a cache file (only ``names`` where given; an .npz is read array by array)."""
    if not path.is_file():
        return None
    try:
        os.utime(path)  # last use, for least-recently-used eviction (store.evict_lru)
    except OSError:
        return None  # evicted between the check and now: treat as missing
    try:
        with np.load(path, allow_pickle=False) as z:
            wanted = {"format_version", "kind", *(names or z.files)}
            data = {k: z[k] for k in z.files if k in wanted}
    except (OSError, ValueError, EOFError) as err:
        raise CacheError(f"cache file {path} is corrupt ({err}); delete it to rebuild") from None
    if int(data.get("format_version", -1)) != ENGINE_FORMAT_VERSION or str(data.get("kind")) != kind:
        raise CacheError(f"cache file {path} is of another format version or kind; delete it to rebuild")
    return data
