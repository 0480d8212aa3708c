"""Synthetic radiance fields in the route's binary layout, and an independent numpy ray march of
them (fine steps, no skipping), to check the page's decoder and WebGL2 march without a server.

Layout (api.md, GET /v1/caches/{id}/field): b"CGFIELD1", uint32 LE header length, JSON header,
then float16 little-endian C-order arrays at 16-byte aligned offsets.
"""

from __future__ import annotations

import gzip
import itertools
import json
import math

import numpy as np
from scipy.ndimage import map_coordinates

from cloudgraph.field_grid import unit_points
from cloudgraph.light_depth import FINE_POWER, TAU_POWER, depth_floor

from ..helpers import box_interval, latlong_lookup, pixel_rays


def make_field(shape=(24, 20, 28), unit_to_world=None, block=4, seed=1, ms_coarsen=2) -> dict:
    """A blob of medium in part of the unit cube, with empty corners for the majorant to skip.

    shape: (nz, ny, nx) of the density grid; the radiance grid is ms_coarsen times coarser.
    Returns {"header": dict, "arrays": {name: float32 array of the decoded values}} where the
    values are the float16 values the page sees (scale applied).
    """
    rng = np.random.default_rng(seed)
    nz, ny, nx = shape
    if unit_to_world is None:
        unit_to_world = np.diag([2.0, 1.6, 2.4, 1.0])
        unit_to_world[:3, 3] = [-1.0, -0.7, -1.1]
    z, y, x = np.meshgrid(*[(np.arange(n) + 0.5) / n for n in shape], indexing="ij")
    r = np.sqrt((x - 0.55) ** 2 + (y - 0.45) ** 2 + (z - 0.5) ** 2)
    sigma = np.clip(1.0 - r / 0.38, 0, None) * (0.7 + 0.3 * rng.random(shape)) * 9.0
    sigma[r > 0.38] = 0.0
    tau = 3.0 * np.clip(1.2 - y, 0, None) * (sigma > 0) + 0.2 * x
    mz, my, mx = (-(-n // ms_coarsen) for n in (nz, ny, nx))
    mzz, myy, mxx = np.meshgrid(*[(np.arange(n) + 0.5) / n for n in (mz, my, mx)], indexing="ij")
    rad = np.stack([0.05 + 0.04 * mxx, 0.04 + 0.05 * myy, 0.06 * (1 - mzz) + 0.01], axis=-1)

    sigma_scale = float(sigma.max()) / 1000.0
    rad_scale = rad.reshape(-1, 3).max(axis=0) / 1000.0
    q = {
        "sigma_t": (sigma / sigma_scale).astype(np.float16),
        "tau_light": (tau / 2.5).astype(np.float16),
        "radiance_ms": (rad / rad_scale).astype(np.float16),
    }
    # majorant: max over each block, dilated by one voxel
    pad = np.pad(q["sigma_t"].astype(np.float32), 1, mode="edge")
    bz, by, bx = (math.ceil(n / block) for n in shape)
    maj = np.zeros((bz, by, bx), np.float32)
    for k in range(bz):
        for j in range(by):
            for i in range(bx):
                maj[k, j, i] = pad[
                    k * block : (k + 1) * block + 2,
                    j * block : (j + 1) * block + 2,
                    i * block : (i + 1) * block + 2,
                ].max()
    q["majorant"] = maj.astype(np.float16)
    lo = unit_to_world @ np.array([0, 0, 0, 1.0])
    hi = unit_to_world @ np.array([1, 1, 1, 1.0])
    voxel = np.linalg.norm(unit_to_world[:3, :3] / np.array([nx, ny, nz]), axis=0).min()
    header = {
        "format": "cloudgraph-field",
        "version": 1,
        "radiance_key": f"synthetic-{seed}",
        "unit_to_world": unit_to_world.tolist(),
        "world_bbox": [np.minimum(lo, hi)[:3].tolist(), np.maximum(lo, hi)[:3].tolist()],
        "light": {"direction": [0.0, -1.0, 0.0], "irradiance": [1.0, 0.9, 0.8]},
        "albedo": [0.95, 0.9, 0.85],
        "step": float(voxel / 2),
        "max_dtau": 0.5,
        "edge": float(1.5 * voxel),
        "tau_power": TAU_POWER,
        "arrays": {
            "sigma_t": {"dtype": "float16", "shape": list(shape), "scale": sigma_scale},
            "tau_light": {"dtype": "float16", "shape": list(shape), "scale": 2.5},
            "radiance_ms": {"dtype": "float16", "shape": [mz, my, mx, 3], "scale": rad_scale.tolist()},
            "majorant": {"dtype": "float16", "shape": [bz, by, bx], "scale": sigma_scale, "block": block},
        },
    }
    values = {
        "sigma_t": q["sigma_t"].astype(np.float32) * sigma_scale,
        "tau_light": q["tau_light"].astype(np.float32) * 2.5,
        "radiance_ms": q["radiance_ms"].astype(np.float32) * rad_scale.astype(np.float32),
    }
    return {"header": header, "raw": q, "values": values}


def encode(field: dict, compress: bool = False) -> bytes:
    """The route's body for ``field`` (gzip-compressed when ``compress``)."""
    header = json.loads(json.dumps(field["header"]))
    names = list(field["raw"])  # the four arrays, then any others (ms_shape)
    # offsets depend on the header's length, which depends on the offsets: iterate to a fixpoint
    offsets = {n: 0 for n in names}
    for _ in range(4):
        for n in names:
            header["arrays"][n]["offset"] = offsets[n]
        text = json.dumps(header).encode()
        pos = 12 + len(text)
        new = {}
        for n in names:
            pos = (pos + 15) // 16 * 16
            new[n] = pos
            pos += field["raw"][n].nbytes
        if new == offsets:
            break
        offsets = new
    body = bytearray(b"CGFIELD1" + len(text).to_bytes(4, "little") + text)
    for n in names:
        body.extend(b"\0" * (offsets[n] - len(body)))
        body.extend(field["raw"][n].astype("<f2").tobytes())
    return gzip.compress(bytes(body)) if compress else bytes(body)


def add_view_terms(field: dict, seed: int = 3, sun: int = 0, light_power: float = 0.0) -> None:
    """Gives ``field`` an anisotropic phase's view terms (api.md, ``ms_shape``): 20 smooth
    channels on the radiance grid, of the size of radiance_ms, in a frame about the light (of a
    v1.1 field: about its directional light ``sun``); with ``light_power`` kept over the sun's
    light factor of that grey power (the header's ``ms_light`` range)."""
    rng = np.random.default_rng(seed)
    rad = field["values"]["radiance_ms"]
    mz, my, mx = rad.shape[:3]
    zz, yy, xx = np.meshgrid(*[(np.arange(n) + 0.5) / n for n in (mz, my, mx)], indexing="ij")
    lum = rad.mean(axis=-1)
    a, b = rng.uniform(-0.5, 0.5, 14), rng.uniform(0, 1, 14)
    # degree 3's six, whose functions reach 15-30 (view_basis), smaller
    a, b = np.append(a, rng.uniform(-0.5, 0.5, 6) / 30), np.append(b, rng.uniform(0, 1, 6))
    terms = np.stack(
        [lum * ai * (0.6 + 0.8 * (bi * xx + (1 - bi) * zz)) for ai, bi in zip(a, b, strict=True)], -1
    )
    terms[..., 1] = 1.5 * lum  # P_1: the forward peak, toward the light
    suns = _suns(field["header"])
    to_light = -np.asarray(suns[sun]["direction"], float)
    ez = to_light / np.linalg.norm(to_light)
    ex = np.cross([0.0, 0.0, 1.0] if abs(ez[2]) < 0.9 else [1.0, 0.0, 0.0], ez)
    ex /= np.linalg.norm(ex)
    frame = np.stack([ex, np.cross(ez, ex), ez])
    name = "ms_shape" if sun == 0 else f"ms_shape_{sun}"
    put_array(field, name, terms, np.abs(terms).reshape(-1, 20).max(axis=0) / 1000.0)
    entry = {"array": name, "frame": frame.tolist()}
    if light_power:
        entry["light_power"] = light_power
    if "lights" in field["header"]:
        suns[sun]["shape"] = entry
    else:
        field["header"]["ms_shape"] = entry


def _suns(header: dict) -> list[dict]:
    """The field's directional lights as v1.1 components: {direction, tau[, shape]} (a v1
    field's one light: tau_light, its ms_shape)."""
    if "lights" in header:
        return [c for c in header["lights"] if c["type"] == "directional"]
    sun = {"direction": header["light"]["direction"], "tau": "tau_light"}
    if "ms_shape" in header:
        sun["shape"] = header["ms_shape"]
    return [sun]


def light_depth_from_above(field: dict, fine: bool = False) -> None:
    """Replaces ``field``'s tau_light by the optical depth its density really gives for its
    light from above (direction -y): the integral of sigma_t from each texel centre up to the
    box's top face, continuous across the medium's edge (make_field's own tau_light jumps
    there, which moving frames, interpolating exp(-tau), cannot follow). ``fine``: on a grid
    twice as fine (the density read there as the texture reads it), read as T^FINE_POWER, as
    the server's bake makes it where the grid allows (light_depth.py)."""
    h, v = field["header"], field["values"]
    assert h["light"]["direction"] == [0.0, -1.0, 0.0]
    sigma = v["sigma_t"]  # (nz, ny, nx), y up; sigma per world unit
    if fine:
        nz, ny, nx = (2 * n for n in sigma.shape)
        sigma = _sample(sigma, unit_points((nx, ny, nz))).reshape(nz, ny, nx)
        h["tau_power"] = FINE_POWER
    dy = float(np.asarray(h["unit_to_world"])[1, 1]) / sigma.shape[1]
    above = np.cumsum(sigma[:, ::-1, :], axis=1)[:, ::-1, :] * dy - 0.5 * sigma * dy
    put_array(field, "tau_light", above, float(above.max()) / 1000.0)


def put_array(field: dict, name: str, values: np.ndarray, scale) -> None:
    """Stores an array of decoded ``values`` as the page sees it: float16 of values / scale."""
    scale = np.asarray(scale, np.float32)
    field["raw"][name] = (values / scale).astype(np.float16)
    field["values"][name] = field["raw"][name].astype(np.float32) * scale
    field["header"]["arrays"][name] = {
        "dtype": "float16",
        "shape": list(values.shape),
        "scale": scale.tolist() if scale.ndim else float(scale),
    }


def add_lights(field: dict, directions, sky: bool = False, seed: int = 5, envmap: bool = False) -> None:
    """Makes ``field`` a v1.1 field of several lights (api.md, ``lights``): the directional
    lights ``directions`` (the way light travels; the first keeps tau_light and radiance_ms),
    each with a tau array of its own, then a sky if ``sky``, each with its own radiance array,
    all at unit intensity, then an environment map if ``envmap`` (its radiance array and a
    64 x 32 lat-long background, api.md). Each tau grows away from its light, so the suns light
    different sides."""
    rng = np.random.default_rng(seed)
    h, v = field["header"], field["values"]
    nz, ny, nx = v["sigma_t"].shape
    z, y, x = np.meshgrid(*[(np.arange(n) + 0.5) / n for n in (nz, ny, nx)], indexing="ij")
    rad = v["radiance_ms"]
    mz, my, mx = rad.shape[:3]
    mzz, myy, mxx = np.meshgrid(*[(np.arange(n) + 0.5) / n for n in (mz, my, mx)], indexing="ij")
    lights = []
    for k, direction in enumerate(directions):
        entry = {"type": "directional", "direction": list(map(float, direction))}
        entry["tau"], entry["ms"] = (
            ("tau_light", "radiance_ms") if k == 0 else (f"tau_light_{k}", f"radiance_ms_{k}")
        )
        if k > 0:
            # optical depth along the light's way through the (unit) box, in the sigma > 0 body
            dz = np.asarray(direction, float)
            depth = 0.5 + (x - 0.5) * dz[0] + (y - 0.5) * dz[1] + (z - 0.5) * dz[2]
            tau = (2.0 + k) * np.clip(depth, 0, None) * (v["sigma_t"] > 0) + 0.1 * (1 + k) * x
            put_array(field, entry["tau"], tau, float(tau.max()) / 1000.0)
            a, b = rng.uniform(0.02, 0.06, 3), rng.uniform(-0.03, 0.03, 3)
            ms = np.stack([a[c] + b[c] * (mxx, myy, mzz)[c] for c in range(3)], axis=-1)
            put_array(field, entry["ms"], ms, ms.reshape(-1, 3).max(axis=0) / 1000.0)
        lights.append(entry)
    if sky:
        name = "radiance_ms_sky"
        ms = np.stack([0.03 + 0.02 * myy, 0.035 + 0.02 * myy, 0.05 + 0.01 * mxx], axis=-1)
        put_array(field, name, ms, ms.reshape(-1, 3).max(axis=0) / 1000.0)
        lights.append({"type": "sky", "ms": name})
    if envmap:
        ms = np.stack([0.02 + 0.03 * mxx, 0.03 + 0.01 * mzz, 0.02 + 0.02 * myy], axis=-1)
        put_array(field, "radiance_ms_env", ms, ms.reshape(-1, 3).max(axis=0) / 1000.0)
        v, u = np.meshgrid((np.arange(32) + 0.5) / 32, (np.arange(64) + 0.5) / 64, indexing="ij")
        bg = np.stack(
            [0.5 + 0.4 * np.sin(2 * np.pi * u), 0.3 + 0.5 * v, 0.6 - 0.3 * np.cos(2 * np.pi * u) * v], -1
        )
        put_array(field, "background_env", bg, bg.reshape(-1, 3).max(axis=0) / 1000.0)
        lights.append({"type": "envmap", "ms": "radiance_ms_env", "background": "background_env"})
    del h["light"]
    h["lights"] = lights


def view_basis(d: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(N, 20) the view terms' functions of direction at unit directions d (N, 3), written out
    as api.md gives them: in the frame's coordinates (x, y, z), y, z, x, 6xy, 3yz, P_2(z), 3xz,
    3(x^2 - y^2), then P_3(z) .. P_8(z), then 15(3x^2 y - y^3), 30xyz, 1.5(5z^2 - 1) y,
    1.5(5z^2 - 1) x, 15z(x^2 - y^2), 15(x^3 - 3xy^2)."""
    x, y, z = (d @ np.asarray(frame, float).T).T
    P = [np.polynomial.legendre.Legendre.basis(n)(z) for n in range(9)]
    q = 1.5 * (5 * z * z - 1)
    degree3 = [
        15 * (3 * x * x * y - y**3),
        30 * x * y * z,
        q * y,
        q * x,
        15 * z * (x * x - y * y),
        15 * (x**3 - 3 * x * y * y),
    ]
    return np.stack(
        [y, z, x, 6 * x * y, 3 * y * z, P[2], 3 * x * z, 3 * (x * x - y * y), *P[3:], *degree3], axis=1
    )


def _sample(grid: np.ndarray, unit: np.ndarray) -> np.ndarray:
    """Trilinear lookup at unit coordinates (N, 3) (x, y, z) of a (nz, ny, nx[, c]) grid, values
    at texel centres, clamped at the edges (what LINEAR + CLAMP_TO_EDGE does)."""
    nz, ny, nx = grid.shape[:3]
    coords = np.stack([unit[:, 2] * nz - 0.5, unit[:, 1] * ny - 0.5, unit[:, 0] * nx - 0.5])
    if grid.ndim == 3:
        return map_coordinates(grid, coords, order=1, mode="nearest")
    return np.stack(
        [map_coordinates(grid[..., c], coords, order=1, mode="nearest") for c in range(grid.shape[3])], -1
    )


def _tau_light(header: dict, values: dict, p: np.ndarray, sun: dict) -> np.ndarray:
    """tau_light of directional light ``sun`` (_suns) at unit points p (N, 3) as the field's
    header says: its grid's (interpolated as exp(-tau_power tau)), or within ``edge`` of where
    the light enters the box the integral of sigma_t to it (3 midpoints)."""
    m = np.asarray(header["unit_to_world"], float)
    to_light = -np.asarray(sun["direction"], float)
    lu = np.linalg.inv(m)[:3, :3] @ (to_light / np.linalg.norm(to_light))  # unit cube per world unit
    pc = np.clip(p, 0.0, 1.0)  # a point on the box's surface counts as inside
    with np.errstate(divide="ignore", invalid="ignore"):
        te = np.where(np.abs(lu) < 1e-9, 1e30, np.maximum(-pc / lu, (1 - pc) / lu))
    t_exit = np.maximum(te.min(axis=1), 0.0)
    edge = t_exit <= header["edge"]
    power = header.get("tau_power", 0.0)  # the grid interpolates exp(-power tau) (0: tau)
    if power:
        q = _sample(np.exp(-power * values[sun["tau"]]), p)
        tau = -np.log(np.maximum(q, depth_floor(power))) / power
    else:
        tau = _sample(values[sun["tau"]], p)
    if edge.any():
        q, t = pc[edge], t_exit[edge]
        sums = sum(_sample(values["sigma_t"], q + ((k + 0.5) / 3) * t[:, None] * lu) for k in range(3))
        tau[edge] = sums * t / 3
    return tau


def hg4pi(g, mu):
    """4pi times the Henyey-Greenstein phase at cosine ``mu``."""
    return (1 - g * g) / (1 + g * g - 2 * g * mu) ** 1.5


def reference_render(
    field: dict,
    camera: dict,
    exposure: float = 0.0,
    substeps: int = 4,
    lobes=((1.0, 0.0),),
    mix: dict | None = None,
) -> np.ndarray:
    """The field's image (H, W, 3) as 8-bit sRGB, by the spec's march with segments of
    step / ``substeps`` at their midpoints (converges to the same integral as any jitter).
    ``lobes``: (weight, g) of the phase; single scattering is weighted by 4pi p(mu) per ray,
    mu = d . (towards the light) (1 for the isotropic default). A v1.1 field (add_lights) is
    drawn in ``mix`` ({"suns": [RGB irradiance per directional light], "sky": RGB, "envmaps":
    [RGB scale per map]}): each component's radiance array times its intensity, each sun's
    single scattering, and the sky and the maps' backgrounds seen behind the medium."""
    h = field["header"]
    v = field["values"]
    suns = _suns(h)
    if "lights" in h:
        E = [np.asarray(e, float) for e in mix["suns"]]
        sky = np.asarray(mix.get("sky", [0, 0, 0]), float)
        suns_e, maps_e = iter(E), iter(np.asarray(e, float) for e in mix.get("envmaps", []))
        kinds = {"sky": lambda: sky, "directional": lambda: next(suns_e), "envmap": lambda: next(maps_e)}
        weights = [kinds[c["type"]]() for c in h["lights"]]
        maps = [
            (w, v[c["background"]])
            for w, c in zip(weights, h["lights"], strict=True)
            if c["type"] == "envmap"
        ]
        apart = ["ms_light" in h and c["type"] == "directional" for c in h["lights"]]
        rad_grid = sum(w * v[c["ms"]] for w, c, a in zip(weights, h["lights"], apart, strict=True) if not a)
        sun_grids = [w * v[c["ms"]] for w, c, a in zip(weights, h["lights"], apart, strict=True) if a]
        if not any(c["type"] == "sky" for c in h["lights"]):
            sky = np.zeros(3)
    else:
        E, sky, rad_grid, maps = (
            [np.asarray(h["light"]["irradiance"], float)],
            np.zeros(3),
            0.0 if "ms_light" in h else v["radiance_ms"],
            [],
        )
        sun_grids = [v["radiance_ms"]] if "ms_light" in h else []
    m = np.asarray(h["unit_to_world"], float)
    inv = np.linalg.inv(m)
    d = pixel_rays(
        camera["eye"], camera["target"], camera["up"], camera["fov"], camera["width"], camera["height"]
    )
    d = d.reshape(-1, 3)
    factors = []
    for sun in suns:
        to_light = -np.asarray(sun["direction"], float)
        factors.append(sum(w * hg4pi(g, d @ (to_light / np.linalg.norm(to_light))) for w, g in lobes))
    o_u = inv[:3, :3] @ np.asarray(camera["eye"], float) + inv[:3, 3]
    d_u = d @ inv[:3, :3].T
    t0, t1 = box_interval(o_u, d_u, [0, 0, 0], [1, 1, 1])
    hit = t1 > t0
    step = h["step"] / substeps
    n = np.where(hit, np.ceil((t1 - t0) / step), 0).astype(int)
    dt = np.where(hit, (t1 - t0) / np.maximum(n, 1), 0)
    L = np.zeros((len(d), 3))
    Tr = np.ones(len(d))
    direct = [e / (4 * math.pi) for e in E]
    bases = [view_basis(d, sun["shape"]["frame"]) if "shape" in sun else None for sun in suns]
    albedo = np.asarray(h["albedo"])
    for k in range(int(n.max(initial=0))):
        live = k < n
        idx = np.nonzero(live)[0]
        t = t0[idx] + (k + 0.5) * dt[idx]
        p = o_u + t[:, None] * d_u[idx]
        s = _sample(v["sigma_t"], p)
        rad = _sample(rad_grid, p) if np.ndim(rad_grid) else np.zeros((len(p), 3))
        taus = [_tau_light(h, v, p, sun) for sun in suns]  # each sun's, read once a step
        for tau, grid in zip(taus[: len(sun_grids)], sun_grids, strict=True):  # (ms_light) times it
            power, limit = np.asarray(h["ms_light"]["power"]), h["ms_light"]["range"]
            rad = rad + _sample(grid, p) * np.exp(-np.minimum(tau[:, None] * power, limit))
        if any(b is not None for b in bases):  # per sun E sum_i c_i B_i(d), L_ms clamped at 0
            for sun, tau, basis, e in zip(suns, taus, bases, direct, strict=True):
                if basis is not None:
                    view = (_sample(v[sun["shape"]["array"]], p) * basis[idx]).sum(axis=1)
                    if sun["shape"].get("light_power"):  # over the sun's grey light factor
                        power, limit = sun["shape"]["light_power"], h["ms_light"]["range"]
                        view = view * np.exp(-np.minimum(power * tau, limit))
                    rad = rad + 4 * math.pi * e * view[:, None]
                    if h.get("ms_forward"):  # the sun's light still in its beam, in closed form
                        to_light = -np.asarray(sun["direction"], float)
                        mu = d[idx] @ (to_light / np.linalg.norm(to_light))
                        rad = rad + 4 * math.pi * e * forward_light(lobes, h["ms_forward"], albedo, tau, mu)
            rad = np.maximum(rad, 0.0)
        a = np.exp(-s * dt[idx])
        L_in = rad.copy()  # sum over suns E p exp(-tau) + L_ms
        for tau, e, factor in zip(taus, direct, factors, strict=True):
            L_in += e * (factor[idx] * np.exp(-tau))[:, None]
        L[idx] += (Tr[idx] * (1 - a))[:, None] * albedo * L_in
        Tr[idx] *= a
    behind = sky + sum((w * latlong_lookup(bg, d) for w, bg in maps), np.zeros((len(d), 3)))
    L += Tr[:, None] * behind  # the sky and the maps behind the medium
    x = np.clip(L * 2.0**exposure, 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return np.round(srgb * 255).reshape(camera["height"], camera["width"], 3)


def forward_light(lobes, orders: int, albedo, tau, mu) -> np.ndarray:
    """(M, 3) sum_n exp(-tau) (albedo tau)^n / n! p^(n+1)(mu), n = 1..orders, per steradian
    (api.md, ms_forward): p^m, the phase convolved with itself m times, is the blend of HG lobes of
    every product of m of its lobes' g, weighted by the product of their weights."""
    out = np.zeros((len(tau), 3))
    for n in range(1, orders + 1):
        power = sum(
            np.prod([w for w, _ in pick]) * hg4pi(np.prod([g for _, g in pick]), mu)
            for pick in itertools.product(lobes, repeat=n + 1)
        ) / (4 * math.pi)
        out += (np.exp(-tau) * tau**n / math.factorial(n) * power)[:, None] * np.asarray(albedo) ** n
    return out


def rel_mae(test: np.ndarray, ref: np.ndarray) -> float:
    """relMAE of two 8-bit sRGB images on linear values (as the page's compareImages)."""

    def lin(a):
        c = np.asarray(a, float) / 255
        return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)

    a, b = lin(test), lin(ref)
    return float(np.abs(a - b).mean() / b.mean())
