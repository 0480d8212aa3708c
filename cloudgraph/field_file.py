"""The radiance field's file: one file, the same bytes for the server's ``field`` estimator and the
page's WebGL view: a small JSON header and float16 arrays, gzip-compressed
(:meth:`RadianceField.encode`):

    bytes 0..7     b"CGFIELD1"
    bytes 8..11    uint32 LE, header length H
    12..12+H       UTF-8 JSON header: format, version, radiance_key, unit_to_world (4x4),
                   world_bbox, light {direction, irradiance}, albedo, step, max_dtau, edge,
                   arrays
    then           arrays at header["arrays"][name]["offset"] (16-byte aligned), little-endian,
                   C order, (nz, ny, nx[, 3]): x varies fastest; value = stored * scale

Arrays: ``sigma_t`` (per world unit), ``tau_light`` (at sigma_t's resolution or twice it:
light_depth.py), ``radiance_ms`` (RGB, per-channel scale)
and ``majorant`` (max sigma_t over blocks of :data:`~cloudgraph.tracing.BLOCK`^3 field voxels,
dilated by one voxel: empty-space skipping). What the arrays hold: field.py. A field of v1.1
``lights`` has the header's ``lights`` in place of ``light``: per light component its type, its
``direction`` and ``tau`` array (directional) and its ``ms`` array, at unit intensity; the
first component's are ``tau_light`` and ``radiance_ms``, the others' ``tau_light_K`` and
``radiance_ms_K`` after ``majorant`` (``tau_light`` is zero without a directional light); an
environment map's component also its ``background``: the array ``background_K``, (h, 2h, 3)
the map's radiance seen along the directions of image.latlong_directions, at scale 1.
A field of an anisotropic phase also holds, per directional light, ``ms_shape`` (header
``ms_shape``, or the component's ``shape``: its array ``ms_shape_K``, its frame and
``light_power``): (mz', my', mx', 20) coefficients c_i of the functions of direction of
phase.shape_basis at unit intensity, at half radiance_ms's resolution, over the light's factor
f = exp(-min(light_power tau_light, ms_light's range)); radiance_ms + E f sum_i c_i B_i(d),
clamped at 0, is L_ms seen along a ray of direction d (field_ms.py, ``walk_ms``; api.md).
"""

from __future__ import annotations

import dataclasses
import gzip
import json
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from .tracing import BLOCK

MAGIC = b"CGFIELD1"


VERSION = 1


@dataclass
class RadianceField:
    """A baked field (see the module docstring), float32 in memory, (nz, ny, nx[, 3]) arrays.

    Attributes:
        sigma_t: extinction per world unit at the field grid points.
        tau_light: optical depth from each point to the light.
        radiance_ms: (mz, my, mx, 3) in-scattered radiance after the first scattering.
        majorant: (bz, by, bx) max sigma_t per block of BLOCK^3 field voxels.
        meta: the header (without ``arrays``): unit_to_world, light, albedo, step, ...
        packed: arrays already encoded for :meth:`encode` (:func:`pack_array` of the arrays as they
            are): a bake packs the ones it has while its last chunks run.
    """

    sigma_t: np.ndarray
    tau_light: np.ndarray
    radiance_ms: np.ndarray
    majorant: np.ndarray
    meta: dict

    packed: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)
    extra: dict = dataclasses.field(default_factory=dict)

    def array(self, name: str) -> np.ndarray:
        """An array by its file name: one of :data:`ARRAYS` or of ``extra``."""
        return self.extra[name] if name in self.extra else getattr(self, name)

    def names(self) -> tuple[str, ...]:
        """The arrays' names in file order: :data:`ARRAYS`, then ``extra``'s."""
        return ARRAYS + tuple(self.extra)

    def encode(self) -> bytes:
        """The gzip-compressed binary layout (module docstring): one gzip member whose deflate
        stream is the header's and each array's, each deflated on its own (:func:`_deflate`), so
        that arrays can be packed as soon as they are known."""
        names = self.names()
        packed = {name: self.packed.get(name) or pack_array(name, self.array(name)) for name in names}
        table, offset = {}, 0
        for name in names:
            table[name] = {**packed[name][0], "offset": offset}  # relative to the data section
            offset += len(packed[name][1])
        header = {"format": "cloudgraph-field", "version": VERSION, **self.meta, "arrays": table}
        # Offsets are from the start of the body, and the header's length moves the data: grow
        # the data's start until the header fits in front of it.
        start = 0
        while True:
            text = json.dumps({**header, "arrays": _shifted(table, start)}).encode()
            need = -(-(12 + len(text)) // 16) * 16
            if need <= start:
                break
            start = need
        head = MAGIC + struct.pack("<I", len(text)) + text
        head += b" " * (start - len(head))
        crc, size = zlib.crc32(head), len(head)
        for name in names:
            crc, size = zlib.crc32(packed[name][1], crc), size + len(packed[name][1])
        deflated = [_deflate(head)] + [packed[name][2] for name in names]
        end = zlib.compressobj(1, zlib.DEFLATED, -15).flush()  # the final (empty) block
        return _GZIP_HEADER + b"".join(deflated) + end + struct.pack("<II", crc, size & 0xFFFFFFFF)

    @classmethod
    def decode(cls, data: bytes) -> RadianceField:
        """Reads :meth:`encode`'s bytes (gzip-compressed or not)."""
        if data[:2] == b"\x1f\x8b":
            data = gzip.decompress(data)
        if data[:8] != MAGIC:
            raise ValueError("not a cloudgraph field (bad magic)")
        (n,) = struct.unpack("<I", data[8:12])
        header = json.loads(data[12 : 12 + n])
        out = {}
        for name, a in header.pop("arrays").items():
            count = int(np.prod(a["shape"]))
            raw = np.frombuffer(data, "<f2", count, a["offset"]).reshape(a["shape"])
            out[name] = raw.astype(np.float32) * np.asarray(a["scale"], np.float32)
        for k in ("format", "version"):
            header.pop(k)
        extra = {name: out.pop(name) for name in list(out) if name not in ARRAYS}
        return cls(meta=header, extra=extra, **out)


#: The arrays of a field file, in file order.
ARRAYS = ("sigma_t", "tau_light", "radiance_ms", "majorant")


def component_names(c: int, kind: str) -> dict:
    """The array names of light component c (of ``kind``) in a v1.1 field's header (module
    docstring): ``ms``, and ``tau`` (directional) or ``background`` (envmap)."""
    names = {"tau": "tau_light" if c == 0 else f"tau_light_{c}"} if kind == "directional" else {}
    names["ms"] = "radiance_ms" if c == 0 else f"radiance_ms_{c}"
    if kind == "envmap":
        names["background"] = f"background_{c}"
    return names


def shape_name(c: int) -> str:
    """The array name of directional component c's view terms."""
    return "ms_shape" if c == 0 else f"ms_shape_{c}"


def combined(parts: list[RadianceField], radiance_key: str, sun_base=None) -> RadianceField:
    """The field of several light components from each component's own v1.1 field (one light
    each, of one graph and medium: their sigma_t and majorant are the same), in ``parts``'
    order: each part's arrays renamed as component_names gives them. ``sun_base``: (D, 3) the
    directional components' colours at their light's scale 1 (lights.Lights.sun_base), each
    kept as the entry's ``base`` where it is not 1 (a sunsky's sun)."""
    first = parts[0]
    meta = {**first.meta, "radiance_key": radiance_key, "lights": []}
    arrays = {}
    bases = [] if sun_base is None else [list(map(float, b)) for b in np.asarray(sun_base, float)]
    for c, part in enumerate(parts):
        (entry,) = part.meta["lights"]
        renamed = {**entry, **component_names(c, entry["type"])}
        if c < len(bases) and bases[c] != [1.0, 1.0, 1.0]:
            renamed["base"] = bases[c]
        for role in ("ms", "tau", "background"):
            if role in entry:
                arrays[renamed[role]] = part.array(entry[role])
        if "shape" in entry:
            renamed["shape"] = {**entry["shape"], "array": shape_name(c)}
            arrays[shape_name(c)] = part.array(entry["shape"]["array"])
        meta["lights"].append(renamed)
    tau = arrays.pop("tau_light", np.zeros_like(first.sigma_t))
    ms = arrays.pop("radiance_ms")
    return RadianceField(first.sigma_t, tau, ms, first.majorant, meta, {}, arrays)


#: A gzip member's header: deflate, no name, mtime 0, fastest level, unknown OS.
_GZIP_HEADER = b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x04\xff"


def pack_array(name: str, a: np.ndarray) -> tuple[dict, bytes, bytes]:
    """One array of a field file: (header entry without its offset, float16 bytes padded to 16,
    the same deflated)."""
    a = np.asarray(a, np.float32)
    rgb = name.startswith(("radiance_ms", "ms_shape", "background"))  # a scale per channel
    peak = np.abs(a).reshape(-1, a.shape[-1]).max(axis=0) if rgb else np.abs(a).max(initial=0.0)
    scale = np.where(np.asarray(peak) > 0, peak, 1.0)
    raw = np.ascontiguousarray(a / scale, "<f2").tobytes()
    raw += b"\0" * (-len(raw) % 16)
    entry = {"dtype": "float16", "shape": list(a.shape), "scale": np.asarray(scale, float).tolist()}
    if name == "majorant":
        entry["block"] = BLOCK
    # radiance_ms is noisier than the others: deflate's level 6 finds a fifth more in it
    return entry, raw, _deflate(raw, 6 if rgb else 1)


def _deflate(data: bytes, level: int = 1) -> bytes:
    """Raw deflate blocks of ``data`` at ``level`` (1 by default: on smoke1 a 4.46 MB file in
    0.15 s, where level 6 took 0.32 s for 4.37 MB), ended by a sync flush: such blocks, each from
    a fresh compressor, concatenate into one deflate stream."""
    c = zlib.compressobj(level, zlib.DEFLATED, -15)
    return c.compress(data) + c.flush(zlib.Z_SYNC_FLUSH)


def _shifted(table: dict, start: int) -> dict:
    return {k: {**v, "offset": v["offset"] + start} for k, v in table.items()}
