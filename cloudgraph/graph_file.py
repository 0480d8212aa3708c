"""The graph and radiance files: what a cache keeps on disk, packed and read back.

Files are ``.npz`` archives carrying their format version; their bytes depend on their content
only (no timestamps, no stage times): the same key gives the same file however many workers
built it. What the files keep is what the precompute goes on with: it packs, then unpacks and
uses that (as it does the field), so a cache renders the same fresh or loaded.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from . import ENGINE_FORMAT_VERSION
from .errors import CacheError
from .graph import Graph, compact_uint


def npz_bytes(kind: str, compress: bool = False, **arrays) -> bytes:
    """An .npz as ``np.savez`` writes it, but with fixed timestamps: the same arrays give the same
    bytes, whichever worker made them and when. Compressed at zlib level 1: on smoke1's graph
    2 % larger than level 6 in a quarter of the time (0.4 s against 1.6 s)."""
    arrays = {"format_version": ENGINE_FORMAT_VERSION, "kind": kind, **arrays}
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", method, allowZip64=True) as z:
        for name, a in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(a), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            z.writestr(info, buf.getbuffer(), compress_type=method, compresslevel=1)
    return out.getvalue()


def content_stats(stats: dict) -> dict:
    """Stats without the stage times (``*_s``): what a file keeps, so that its bytes depend on its
    content only."""
    return {k: v for k, v in stats.items() if not k.endswith("_s")}


def _planes(a: np.ndarray) -> np.ndarray:
    """(itemsize, n) uint8: the little-endian byte planes of a 1-D array. Stored apart, the high
    planes of small numbers are runs of zeros that zlib all but removes."""
    a = np.ascontiguousarray(a, a.dtype.newbyteorder("<"))
    return np.ascontiguousarray(a.view(np.uint8).reshape(len(a), a.dtype.itemsize).T)


def _unplanes(planes: np.ndarray, kind: str) -> np.ndarray:
    """The array of :func:`_planes` again; ``kind`` 'u' (unsigned) or 'f' (float)."""
    return np.ascontiguousarray(planes.T).view(f"<{kind}{len(planes)}").ravel()


def _zigzag(a: np.ndarray) -> np.ndarray:
    return np.where(a < 0, -2 * a - 1, 2 * a).astype(np.uint64)


def _unzigzag(a: np.ndarray) -> np.ndarray:
    a = a.astype(np.int64)
    return np.where(a & 1, -(a >> 1) - 1, a >> 1)


#: The arrays of a graph file that a render reads (:func:`read_nodes`).
NODE_ARRAYS = ("box_lo", "box_step", "positions", "search_unit", "search_radius")


def pack_graph(graph: Graph) -> dict:
    """The arrays of a graph file:

    - node positions: 16 bits an axis across the nodes' box (a step of 1/65535 of it: 0.003
      voxels on smoke1); search ranges: float16 multiples of the smallest;
    - edge ends as gaps: in each row from the row's own node, then from the previous end (nodes
      are in order of their cell keys, so a node's ends are near it): about 12 bits an edge
      after compression, against 32 for the indices;
    - counts, samples and row lengths in the smallest unsigned type that holds them;
    - where each edge's flights landed (``Graph.landing``): int8 steps of 1/LANDING_STEPS
      search ranges of the edge's end, an axis a plane;
    - multi-byte arrays as byte planes (:func:`_planes`).
    """
    c = graph.counts.tocsr()
    c.sort_indices()
    lo, step, positions = _box_quantized(graph.positions)
    unit, search = _search_quantized(graph.search_radius)
    landing = {}
    if graph.landing is not None:
        landing["landing"] = _landing_quantized(graph.landing, _search_radii(unit, search)[c.indices])
    lengths = np.diff(c.indptr)
    ends = c.indices.astype(np.int64)
    before = np.concatenate([[0], ends[:-1]])
    before[c.indptr[:-1][lengths > 0]] = np.flatnonzero(lengths)  # a row's first end: from its node
    return {
        "box_lo": lo,
        "box_step": step,
        "positions": _planes(positions.T.ravel()),
        "search_unit": unit,
        "search_radius": _planes(search),
        "out_samples": _planes(compact_uint(graph.out_samples)),
        "row_lengths": _planes(compact_uint(lengths)),
        "edge_gaps": _planes(compact_uint(_zigzag(ends - before))),
        "counts": _planes(compact_uint(c.data)),
        **landing,
        "stats": json.dumps(content_stats(graph.stats)),
    }


#: Landing offsets are kept in steps of 1/LANDING_STEPS of the edge's end node's search range,
#: within 127 steps (a flight lands within its end's cell, and a search range reaches past the
#: cell's neighbours: on the bench's dense cloud the offsets' median is 0.17 ranges, their largest
#: 0.9). An edge's mean landing point is of a few samples: finer steps keep more of their noise,
#: in more bytes (there 2.6 bytes an edge at 1/127, 2.0 at 1/31, against 1.9 for the rest).
LANDING_STEPS = 31


def _landing_quantized(landing: np.ndarray, search: np.ndarray) -> np.ndarray:
    """(3, E) int8 of (E, 3) landing offsets, in steps of 1/LANDING_STEPS ``search`` ranges (E,)."""
    steps = np.round(landing / search[:, None] * LANDING_STEPS)
    return np.ascontiguousarray(np.clip(steps, -127, 127).astype(np.int8).T)


def _landing_offsets(quantized: np.ndarray, search: np.ndarray) -> np.ndarray:
    """(E, 3) float32 landing offsets of :func:`_landing_quantized`."""
    return quantized.T.astype(np.float32) * (search[:, None] / np.float32(LANDING_STEPS))


def _box_quantized(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(box corner, step, (N, 3) uint16 positions) of (N, 3) node positions (pack_graph)."""
    n = len(positions)
    lo = positions.min(axis=0).astype(np.float64) if n else np.zeros(3)
    hi = positions.max(axis=0).astype(np.float64) if n else np.zeros(3)
    step = np.where(hi > lo, (hi - lo) / 65535.0, 1.0)
    return lo, step, np.round((positions - lo) / step).astype(np.uint16)


def _box_positions(lo: np.ndarray, step: np.ndarray, quantized: np.ndarray) -> np.ndarray:
    return (lo + quantized * step).astype(np.float32)


def stored_positions(positions: np.ndarray) -> np.ndarray:
    """(N, 3) node positions as a graph file keeps them (:func:`pack_graph`), without packing."""
    return _box_positions(*_box_quantized(positions))


def node_arrays(z: dict) -> tuple[np.ndarray, np.ndarray]:
    positions = _box_positions(z["box_lo"], z["box_step"], _unplanes(z["positions"], "u").reshape(3, -1).T)
    return positions, _search_radii(np.float32(z["search_unit"]), _unplanes(z["search_radius"], "f"))


def _search_quantized(search_radius: np.ndarray) -> tuple[np.float32, np.ndarray]:
    """(unit, float16 multiples of it) of (N,) search ranges (pack_graph)."""
    unit = np.float32(search_radius.min() if len(search_radius) else 1.0)
    return unit, (search_radius / unit).astype(np.float16)


def _search_radii(unit: np.float32, search: np.ndarray) -> np.ndarray:
    """(N,) float32 search ranges from :func:`_search_quantized`'s (unit, multiples)."""
    return search.astype(np.float32) * unit


def stored_graph(graph: Graph) -> Graph:
    """``graph`` as its file (:func:`pack_graph`) keeps it, without packing it: positions and
    search ranges as stored; its edges, counts and samples, which the file keeps exactly, as they
    are; its landing offsets as stored."""
    search_radius = _search_radii(*_search_quantized(graph.search_radius))
    landing = graph.landing
    if landing is not None:
        c = graph.counts.tocsr()
        c.sort_indices()
        search = search_radius[c.indices]
        landing = _landing_offsets(_landing_quantized(landing, search), search)
    return Graph(
        stored_positions(graph.positions),
        search_radius,
        graph.out_samples,
        graph.counts,
        graph.stats,
        landing,
    )


def graph_file(graph: Graph) -> bytes:
    """A graph file's bytes: :func:`pack_graph`'s arrays, compressed."""
    return npz_bytes("graph", compress=True, **pack_graph(graph))


def unpack_graph(z: dict) -> Graph:
    """The graph of :func:`pack_graph`'s arrays (from a file or fresh)."""
    positions, search_radius = node_arrays(z)
    n = len(positions)
    lengths = _unplanes(z["row_lengths"], "u").astype(np.int64)
    indptr = np.concatenate([[0], np.cumsum(lengths)])
    total = np.cumsum(_unzigzag(_unplanes(z["edge_gaps"], "u")))
    # a row's ends: its node plus the running total of its own gaps
    start = np.concatenate([[0], total])[indptr[:-1]]
    ends = total + np.repeat(np.arange(n) - start, lengths)
    if len(lengths) != n or (len(ends) and (ends.min() < 0 or ends.max() >= n)):
        raise CacheError(
            "a graph file's edges lead to nodes it does not have: the file is corrupt; delete it"
        )
    counts = sp.csr_matrix((_unplanes(z["counts"], "u").astype(np.int64), ends, indptr), shape=(n, n))
    out_samples = _unplanes(z["out_samples"], "u").astype(np.int64)
    landing = _landing_offsets(z["landing"], search_radius[ends]) if "landing" in z else None
    return Graph(positions, search_radius, out_samples, counts, json.loads(str(z["stats"])), landing)


def pack_radiance(radiance: np.ndarray, radiance_gather: np.ndarray) -> dict:
    """Node radiance L' and ``gather``'s (one scattering event fewer, and with the isotropic phase
    without the suns' direct light: precompute.without_sun; (N, 3) each; kept once where they are
    the same), rounded to 8 significant bits (bfloat16: a relative
    error under 0.4 % at any magnitude, well below a node's own sampling noise, and a back-lit
    cloud's dark side keeps its precision)."""
    out = {"radiance": _bfloat16(radiance)}
    if radiance_gather is not radiance and not np.array_equal(radiance_gather, radiance):
        out["radiance_gather"] = _bfloat16(radiance_gather)
    return out


def unpack_radiance(z: dict) -> tuple[np.ndarray, np.ndarray]:
    def one(planes):
        return (_unplanes(planes, "u").astype(np.uint32) << np.uint32(16)).view(np.float32).reshape(-1, 3)

    radiance = one(z["radiance"])
    return radiance, (one(z["radiance_gather"]) if "radiance_gather" in z else radiance)


def _bfloat16(a: np.ndarray) -> np.ndarray:
    """Byte planes of float32 values rounded to their top 16 bits (to nearest, ties to even)."""
    bits = np.ascontiguousarray(a, np.float32).view(np.uint32).ravel()
    bits = (bits + np.uint32(0x7FFF) + ((bits >> np.uint32(16)) & np.uint32(1))) >> np.uint32(16)
    return _planes(bits.astype(np.uint16))


def read_npz(path: Path, kind: str, names: tuple[str, ...] | None = None) -> dict | None:
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


def read_graph(path: Path) -> Graph | None:
    """The graph in a graph file; None where there is none."""
    z = read_npz(path, "graph")
    return None if z is None else unpack_graph(z)


def read_nodes(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(positions, search ranges) of a graph file: all that a render reads of it (not the edges)."""
    z = read_npz(path, "graph", NODE_ARRAYS)
    return None if z is None else node_arrays(z)


def radiance_file(packed: dict, stats: dict) -> bytes:
    """A radiance file's bytes: node radiance as :func:`pack_radiance` packs it, with the stats of
    its precompute (without stage times)."""
    return npz_bytes("radiance", compress=True, stats=json.dumps(content_stats(stats)), **packed)


def read_radiance(path: Path) -> tuple[tuple[np.ndarray, np.ndarray], dict] | None:
    """((radiance, radiance_gather), stats) of a radiance file; None where there is none."""
    z = read_npz(path, "radiance")
    return None if z is None else (unpack_radiance(z), json.loads(str(z["stats"])))
