"""The radiance field: the cache baked onto a grid, for a noise-free camera stage (docs/method.md,
"The radiance field").

After transport, the in-scattered radiance of Eq. 4.24 is evaluated once on a grid aligned with
the density grid, split as the ``gather`` estimator splits it:

    L_in(x) = E exp(-tau_light(x)) / 4pi  +  L_ms(x)

- single scattering, exact to the grid: ``tau_light`` is the optical depth from each grid point
  to the light, by a deterministic midpoint march of the trilinear density in Dr.Jit (step
  :data:`TAU_STEP` voxels), interpolated between grid points as a power of exp(-tau) (neither
  tau, too dark at a shadow's edge between grid points, nor exp(-tau), too bright), on a grid
  twice as fine where that fits (its points in optically thick voxels marched too), else on
  the field's, fitted there to sub-voxel samples of the march (light_depth.py);
- everything after the first scattering, from the graph, as ``gather`` computes it at its
  camera collision: one more flight from the grid point to p'', where albedo L'_search (the
  ``radiance_gather`` of Eq. 4.25) stands in for the rest; the flight is integrated over
  :data:`MS_DIRECTIONS` directions in closed form, not sampled. It is smooth, so it lives on a
  grid :data:`MS_COARSEN` times coarser per axis (more for large media).

An anisotropic phase (docs/method.md, "Anisotropic scattering") bakes each sun's L_ms by the
walks of ``gather`` (its first scattering events exact) from the grid points, and keeps how it
depends on the view as coefficients of 14 functions of direction (``ms_shape``,
:func:`_walk_ms`).

A camera render is then a deterministic ray march with two texture lookups per step (the
``field`` estimator of the graph integrator, and the page's WebGL view), of one file
(field_file.py). Grid values sit at texel centres, (i + 0.5) / n of the unit cube that
``Volume.unit_to_world`` maps onto the medium box, and are interpolated trilinearly (clamped).
Only points within one voxel of some density are baked (the rest hold 0): interpolation at a
point where sigma_t > 0 reads no other.
"""

from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.ndimage import gaussian_filter, maximum_filter
from scipy.spatial import cKDTree

from .chunks import placed
from .field_file import RadianceField, component_names, pack_array, shape_name
from .field_grid import FieldPoints, to_world, unit_points
from .light_depth import FINE_POWER, TAU_MAX, TAU_POWER, fine_depth, fine_shape, fit_depth
from .lights import Lights
from .mitsuba_scene import envmap_emitter
from .phase import (
    SHAPE_DEGREES,
    SHAPE_NORMS,
    hg_phase,
    light_frame,
    phase_bounces,
    phase_legendre,
    phase_walk,
    sample_phase,
    shape_basis,
)
from .spatial import NodeGrid, node_bins
from .tracing import (
    ISOTROPIC_PDF,
    block_majorant,
    cpu_threads,
    depth_at,
    depth_texture,
    envmap_nee,
    envmap_pdf,
    envmap_seen,
    exponential_segment,
    from_jit,
    jit_rng,
    linear_texture,
    power_heuristic,
    step_length,
    to_jit,
    towards_light,
    uniform_sphere,
)

#: The multiple-scattering grid is this many times coarser per axis than the field grid, or
#: coarser still until at most MS_MAX_POINTS of its points lie next to the medium. In a dense
#: cloud L_ms changes within a voxel near lit surfaces: at the field grid's resolution the
#: dense bench cloud's field reads 1.6 % from converged gather, at half of it 2.7 %.
MS_COARSEN = 1
MS_MAX_POINTS = 1 << 17
#: Directions per point of the multiple-scattering gather (8 and 16 measure the same on the
#: dense bench cloud: the camera march averages neighbouring points' turned sets), and its march
#: step in field voxels.
MS_DIRECTIONS = 8
MS_STEP = 1.0
#: The gather's steps span at most this optical depth (at the block majorant), and at most
#: MS_STRIDE times MS_STEP in thin media.
MS_MAX_DTAU = 0.5
MS_STRIDE = 4.0
#: The gather stops where this much light is left, and adds the rest at the last G seen.
MS_TR_MIN = 1e-2
#: Multiple-scattering grid points per chunk (times MS_DIRECTIONS rays), and field points per
#: chunk of the light march: chunks bound the device memory and may run on other workers.
MS_CHUNK = 1 << 12
#: The bake's G = albedo L' (what a flight from a grid point reaches) is interpolated between
#: grid points as G^G_POWER per channel, as tau_light is as T^TAU_POWER: it rises steeply toward
#: a lit surface, and interpolating G itself read the field's multiple scattering bright back-
#: lit. thick (blender at optical depth 2 a voxel), all orders, albedo 1, field at 16 spp against
#: 1024-spp volpath, binned relMAE / mean: back-lit 5.59 % / 1.053 with G, 5.21 % / 1.049 with
#: G^0.5, 5.09 % / 1.047 with G^0.3 (gather 4.32 % / 1.037); side-lit 2.63, 2.58, 2.56 %.
G_POWER = 0.3
#: An anisotropic phase: walks per multiple-scattering point (phase.phase_walk, its first
#: events exact, from directions half uniform and half from the phase about the light).
WALKS = 64
#: ... and the width (standard deviation, in multiple-scattering grid points) of the Gaussian
#: that smooths the walks' estimates over the grid: 0 up to |g_eff| = 0.5, WALK_SMOOTH from
#: 0.85 on, linear between. A peaked phase makes the walks heavy-tailed (next-event estimation
#: weighted by the peak): on the bench sphere at g = 0.85 (64^2, field against volpath at 16,384
#: spp, binned relMAE / mean) 128 walks unsmoothed read 8.2 % / 1.040 side-lit and 512 walks
#: 7.5 % / 1.039, 64 walks smoothed over 2 points 7.9 % / 0.985 (back-lit 4.2 % / 0.984). At
#: g = 0.5 (draft, against 4096 spp) smoothing costs more than it saves: unsmoothed 3.9 %, over
#: 1 point 5.9 %, 2 points 8.4 % (gather 3.0 %); smoothing the ratio to the one-flight L_ms
#: instead read 4.8 % there and 7.9 / 5.5 % at g = 0.85.
WALK_SMOOTH = 2.0
TAU_CHUNK = 1 << 18
LOOKUP_CHUNK = 1 << 19
_CHUNK = {"field_tau": TAU_CHUNK, "field_lookup": LOOKUP_CHUNK, "field_ms": MS_CHUNK}
#: The camera march's segments span at most this optical depth at their block's majorant, and
#: within EDGE_VOXELS field voxels of where the light enters the medium box its single scattering
#: integrates sigma_t to the box instead of reading tau_light (whose texture clamps in the last
#: half voxel). Both go into the file's header, for the server's march and the page's alike.
MARCH_MAX_DTAU = 0.5
EDGE_VOXELS = 1.5

#: An environment map's component keeps what a camera ray sees of it behind the medium, for the
#: page: a lat-long image this many texels around and half as many from pole to pole
#: (:func:`background_map`).
BACKGROUND_WIDTH = 512
#: Light march step, in field voxels (midpoint rule).
TAU_STEP = 0.5


# ------------------------------------------------------------------ baking


def march_light(builder, fp: FieldPoints, directions, chunks) -> list:
    """Puts out the bake's light marches (``field_tau`` chunks: the optical depth to the light from
    every field point and sub-voxel sample, Eq. 4.22 at a point, deterministic), one per
    directional light of ``directions`` ((3,) or (D, 3), the ways they travel), and returns the
    iterators of their results. They need the medium and the lights only, so a precompute puts
    them out before the graph is written (precompute.py)."""
    step = np.array([TAU_STEP * fp.voxel])
    points = np.concatenate([fp.points, fp.sub])
    return [
        chunks(builder, "field_tau", {"points": points, "to_light": towards_light(d), "step": step})
        for d in np.asarray(directions, float).reshape(-1, 3)
    ]


def bake_field(
    builder,
    fp: FieldPoints,
    graph,
    radiance_gather: np.ndarray,
    albedo,
    lights: Lights,
    radiance_key: str,
    chunks,
    marched=None,
    bins=None,
    progress=None,
    phase=None,
    max_depth: int = -1,
) -> tuple[RadianceField, dict]:
    """Bakes the field of a radiance cache (a variant must be set).

    Args:
        builder: the :class:`~cloudgraph.build.GraphBuilder` of the graph (volume, medium, node
            radius r, the Eq. 4.25 weight's floor).
        fp: the field's grid points (:meth:`FieldPoints.of` the builder's volume and medium).
        graph: the :class:`~cloudgraph.graph.Graph` (positions, search ranges, counts).
        radiance_gather: (K, N, 3) node radiance with one scattering event fewer (as ``gather``),
            per light component (lights.py).
        albedo: (3,); lights: the scene's :class:`~cloudgraph.lights.Lights`.
        chunks: runs the marches' chunks (:func:`field_chunk`; stages.py), as in ``build_graph``.
        marched: the light marches' results (:func:`march_light`), if already put out.
        bins: the graph's nodes binned (:func:`~cloudgraph.spatial.node_bins`), if made.
        progress: ``progress("field", fraction)`` is called between the bake's parts (a caller's
            cancel raises from it).
        phase: the medium's :class:`~cloudgraph.scene.PhaseSpec` (None: isotropic). An
            anisotropic one bakes each sun's L_ms by walks that take its first events exactly,
            and keeps how it depends on the view (``ms_shape``, below).
        max_depth: the scene's (-1: unbounded); bounded, the walks take every event exactly, as
            ``gather`` does, and read no graph.

    Returns:
        (field, stats): stats hold the bake's seconds per part.
    """
    volume = builder.volume
    progress = progress or (lambda stage, fraction: None)
    t_start = time.perf_counter()
    u2w = np.asarray(volume.unit_to_world, float)
    shape, near, points, voxel = fp.shape, fp.near, fp.points, fp.voxel
    nx, ny, nz = shape
    marched = marched if marched is not None else march_light(builder, fp, lights.directions, chunks)

    # Multiple scattering, as ``gather`` computes it but on the grid: one more flight from the
    # grid point, to p'', where the graph's albedo L' stands in for the rest (Eq. 4.25):
    #   L_ms(x) = 1/4pi int_S2 int_0^inf T_r(x, x + t w) sigma_t(x + t w) G(x + t w) dt dw,
    #   G = albedo L'_search (radiance_gather),
    # with G baked on the field grid first (one node lookup per point), then K fixed directions
    # per point (a spherical Fibonacci set, turned at random per point) marched in closed form.
    # The sky's component also takes what escapes: its single scattering, smooth, baked here.
    # One lookup and one gather per light component.
    t0 = time.perf_counter()
    start, entries, grid = bins if bins is not None else node_bins(graph.positions, graph.search_radius)
    binned = {"start": start, "entries": entries, "grid": grid}
    looked = [
        chunks(
            builder,
            "field_lookup",
            {
                "points": points,
                "positions": graph.positions,
                "search_radius": graph.search_radius,
                "G": component * np.asarray(albedo, np.float32)[None, :],
                **binned,
            },
        )
        for component in radiance_gather
    ]
    lobes = None if phase is None or phase.isotropic else np.array(phase.lobes(), float)
    k = MS_COARSEN  # coarser still where the points to gather would be over MS_MAX_POINTS
    while True:
        ms_shape = tuple(-(-n // k) for n in shape)
        ms_near = _coarse_mask(near.reshape(nz, ny, nx), ms_shape, k)
        if ms_near.sum() <= MS_MAX_POINTS:
            break
        k += 1
    q = to_world(u2w, unit_points(ms_shape)[ms_near]).astype(np.float32)
    step = np.array([MS_STEP * voxel])
    taus = []

    # optical depth to each sun: at twice the grid's resolution where that fits, else fitted to
    # the sub-voxel samples on the grid (light_depth.py), read as T^tau_power between points
    fine = fine_shape((nz, ny, nx), len(marched)) is not None
    tau_power = FINE_POWER if fine else TAU_POWER

    def light_depths() -> list:  # placed once
        if not taus:
            for m in marched:
                tau = placed(m, len(points) + len(fp.sub), 1)[:, 0]
                tau_grid = _scatter(near, tau[: len(points)], (nz, ny, nx))
                samples = (fp.sub_coords, tau[len(points) :])
                if fine:
                    taus.append(fine_depth(tau_grid, near.reshape(nz, ny, nx), *samples))
                else:
                    taus.append(fit_depth(tau_grid, fp.sigma_t, *samples))
        return taus

    gathered, walked = [], []
    for c, lk in enumerate(looked):
        G = _scatter(near, placed(lk, len(points), 3), (nz, ny, nx, 3))
        inputs = {"points": q, "G": G, "step": step, "sky": np.array([int(lights.kind(c) == "sky")])}
        if lights.kind(c) == "envmap":  # what escapes sees the map: the file, read where it runs
            inputs["envmap"] = np.array([lights.envmaps[c - lights.count + len(lights.envmaps)]])
        if lobes is not None and lights.kind(c) == "directional":  # a sun's, by walks
            inputs = {
                "points": q,
                "G": G,
                "albedo": np.asarray(albedo, np.float32),
                "to_light": towards_light(lights.directions[c]),
                "irradiance": lights.cached[c],
                "lobes": lobes,
                # (x's own event is the camera's: the walks take one fewer)
                "bounces": np.array([phase_bounces(phase) - 1 if max_depth < 0 else max_depth - 1]),
                "tail": np.array([int(max_depth < 0)]),
                "tau": light_depths()[c],  # (a sun's component c is directional light c)
                "tau_power": np.array([tau_power]),
            }
            walked.append(c)
        gathered.append(chunks(builder, "field_ms", inputs))
    progress("field", 0.2)
    t_ms = time.perf_counter() - t0

    # While the gather's chunks run: single scattering placed, and the arrays that do not depend
    # on the gather packed (most of the file's bytes; precompute.py encodes it at the end)
    t0 = time.perf_counter()
    light_depths()
    progress("field", 0.6)
    t_tau = time.perf_counter() - t0
    majorant = block_majorant(fp.sigma_t)
    tau_light = taus[0] if taus else np.zeros_like(fp.sigma_t)
    packed = {
        name: pack_array(name, a)
        for name, a in (("sigma_t", fp.sigma_t), ("tau_light", tau_light), ("majorant", majorant))
    }
    t0 = time.perf_counter()
    width = [3 + len(SHAPE_DEGREES) if c in walked else 3 for c in range(len(gathered))]
    ms = [
        _scatter(ms_near, placed(g, len(q), n), (*ms_shape[::-1], n))
        for g, n in zip(gathered, width, strict=True)
    ]
    mask = ms_near.reshape(ms_shape[::-1])
    for c in walked:
        ms[c] = smooth(ms[c], mask, walk_smoothing(phase))
    shapes = {c: _halve(ms[c][..., 3:], mask) for c in walked}  # (smooth: half the resolution)
    ms = [np.ascontiguousarray(m[..., :3]) for m in ms]
    progress("field", 1.0)
    t_ms += time.perf_counter() - t0

    meta = {
        "radiance_key": radiance_key,
        "unit_to_world": u2w.tolist(),
        "world_bbox": [v.tolist() for v in volume.world_bbox()],
        "light": None,  # (its place in the header: a v1 field's bytes stay as they were)
        "albedo": np.broadcast_to(np.asarray(albedo, float), (3,)).tolist(),
        "step": 0.5 * voxel,
        "max_dtau": MARCH_MAX_DTAU,
        "edge": EDGE_VOXELS * voxel,
        "tau_power": tau_power,
    }
    extra = {}
    if not lights.basis:  # a v1 light
        direction = -towards_light(lights.directions[0])
        meta["light"] = {"direction": direction.tolist(), "irradiance": lights.intensity[0].tolist()}
        if shapes:
            meta["ms_shape"] = _shape_entry("ms_shape", lights, 0)
            extra["ms_shape"] = shapes[0]
    else:  # v1.1: each component's arrays, at unit intensity (the scene's mix them)
        del meta["light"]
        meta["lights"] = []
        for c in range(lights.count):
            entry = {"type": lights.kind(c)}
            if entry["type"] == "directional":
                entry["direction"] = lights.directions[c].tolist()
            entry.update(component_names(c, entry["type"]))
            if c > 0 and "tau" in entry:
                extra[entry["tau"]] = taus[c]
            if entry["type"] == "envmap":
                extra[entry["background"]] = background_map(
                    lights.envmaps[c - lights.count + len(lights.envmaps)]
                )
            if c in shapes:
                entry["shape"] = _shape_entry(shape_name(c), lights, c)
                extra[entry["shape"]["array"]] = shapes[c]
            if c > 0:
                extra[entry["ms"]] = ms[c]
            meta["lights"].append(entry)
    field = RadianceField(fp.sigma_t, tau_light, ms[0], majorant, meta, packed, extra)
    stats = {
        "field_s": round(time.perf_counter() - t_start, 3),
        "field_tau_s": round(t_tau, 3),
        "field_ms_s": round(t_ms, 3),
        "field_shape": list(shape),
        "field_ms_shape": list(ms_shape),
        "field_ms_coarsen": k,
        "field_points": int(near.sum()),
        "field_ms_points": int(ms_near.sum()),
    }
    return field, stats


def field_chunk(builder, stage: str, index: int, inputs: dict) -> tuple[np.ndarray, np.ndarray]:
    """One chunk of the bake, at its ``points`` (world units): ``field_tau``, optical depth to the
    light (``to_light``); ``field_lookup``, albedo L'_search (Eq. 4.25) from the nodes'
    ``positions``, ``search_radius`` and ``G``, binned (``start``, ``entries``, ``grid``:
    :func:`~cloudgraph.spatial.node_bins`); ``field_ms``, the multiple-scattering
    gather through the grid ``G``. Returns (first point, values): chunks may come back in any
    order, from any worker (worker/chunks.py), and each gives the same values wherever it runs.
    The points come as inputs: the field's grid (:class:`FieldPoints`, 0.4 s on smoke1) is
    made once, by the coordinator."""
    size, medium = _CHUNK[stage], builder.field
    a = index * size
    q = np.asarray(inputs["points"][a : a + size], np.float32)
    if stage == "field_lookup":
        return np.array([a]), _lookup(inputs, q, builder.params.radius)
    if stage == "field_tau":
        step = float(inputs["step"][0])
        to_light = mi.Vector3f(*(float(c) for c in inputs["to_light"]))
        tau = _optical_depth(medium, to_jit(mi.Point3f, q), to_light, step)
        values = np.array(tau, np.float32)[:, None]
    elif "lobes" in inputs:
        values = _walk_ms(medium, g_texture(inputs["G"]), q, inputs, seed=a)
    else:
        sky = float(inputs["sky"][0]) if "sky" in inputs else 0.0
        env = envmap_emitter(str(inputs["envmap"][0])) if "envmap" in inputs else None
        step = float(inputs["step"][0])
        values = _gather_ms(medium, g_texture(inputs["G"]), q, step, seed=a, sky=sky, env=env)
    return np.array([a]), values


def field_chunks(stage: str, inputs: dict) -> int:
    return -(-len(inputs["points"]) // _CHUNK[stage])


def _lookup(inputs: dict, q: np.ndarray, node_radius: float) -> np.ndarray:
    """(M, 3) L'_search of the nodes' ``G`` at (M, 3) points q (a ``field_lookup`` chunk), and
    where no node reaches, the nearest node's (:func:`fill_unreached`)."""
    positions, search_radius, node_G = (np.asarray(inputs[k]) for k in ("positions", "search_radius", "G"))
    bins = tuple(np.asarray(inputs[k]) for k in ("start", "entries", "grid"))
    grid = NodeGrid.build(positions, search_radius, node_G, bins)
    G = grid.lookup(to_jit(mi.Point3f, q), (0.05 * node_radius) ** 2, mi.Bool(True))
    dr.eval(G)  # one kernel for the three channels
    return fill_unreached(from_jit(G), q, positions, node_G)


def latlong_directions(width: int) -> np.ndarray:
    """(width // 2, width, 3) unit directions at the texel centres of a lat-long image: row j
    at theta = pi (j + 0.5) / h from +y, column i at phi = 2 pi (i + 0.5) / w, and
    d = (sin theta sin phi, cos theta, -sin theta cos phi) (api.md, the field's ``background``)."""
    h = width // 2
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2 * np.pi * (np.arange(width) + 0.5) / width
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    return np.stack(np.broadcast_arrays(st * np.sin(phi), ct, -st * np.cos(phi)), axis=-1)


def background_map(path: str, width: int = BACKGROUND_WIDTH) -> np.ndarray:
    """(width // 2, width, 3) the radiance an environment map (scale 1) sends toward a camera
    ray of each of :func:`latlong_directions`: Mitsuba's own lookup, so the page draws the
    map behind the medium as the server's estimators see it."""
    d = latlong_directions(width).reshape(-1, 3)
    seen = envmap_seen(envmap_emitter(path), to_jit(mi.Vector3f, d))
    dr.eval(seen)
    return np.stack([np.array(seen[i], np.float32) for i in range(3)], axis=-1).reshape(width // 2, width, 3)


def _shape_entry(name: str, lights: Lights, c: int) -> dict:
    """The header's entry of sun c's view terms: their array's name and frame (api.md)."""
    return {"array": name, "frame": light_frame(towards_light(lights.directions[c])).tolist()}


def walk_smoothing(phase) -> float:
    """The Gaussian's width (grid points) that smooths the walks' estimates (WALK_SMOOTH)."""
    return WALK_SMOOTH * float(np.clip((abs(phase.mean_cosine()) - 0.5) / 0.35, 0.0, 1.0))


def smooth(values: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """(..., C) grid values averaged with a Gaussian of ``sigma`` grid points over the points of
    ``mask`` only (normalised by the mask's own average: the medium's edge blends in no zeros),
    0 off the mask."""
    if sigma <= 0:
        return np.where(mask[..., None], values, 0.0).astype(values.dtype)
    m = mask.astype(np.float64)
    weight = gaussian_filter(m, sigma, mode="constant")
    out = np.zeros_like(values)
    for i in range(values.shape[-1]):
        blurred = gaussian_filter(values[..., i] * m, sigma, mode="constant")
        out[..., i] = np.where(mask, blurred / np.maximum(weight, 1e-12), 0.0)
    return out


def _halve(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(mz, my, mx, C) grid values at half the resolution per axis (rounded up): the mean of each
    2^3 block's points of ``mask``. Measured on the bench sphere at g = 0.85: the view's terms at
    half resolution render as at full (binned relMAE 7.75 / 4.29 % side / back-lit against 7.71 /
    4.13 %), in a fifth of the bytes."""
    pads = [(0, n % 2) for n in mask.shape]
    m = np.pad(mask.astype(np.float64), pads)
    v = np.pad(values * mask[..., None], pads + [(0, 0)])
    mz, my, mx = (n // 2 for n in m.shape)
    total = v.reshape(mz, 2, my, 2, mx, 2, -1).sum(axis=(1, 3, 5))
    count = m.reshape(mz, 2, my, 2, mx, 2).sum(axis=(1, 3, 5))[..., None]
    return np.ascontiguousarray(np.where(count > 0, total / np.maximum(count, 1), 0.0), np.float32)


def _scatter(mask: np.ndarray, values: np.ndarray, shape) -> np.ndarray:
    """A zero array of ``shape`` with ``values`` at the points where the flat ``mask`` is set."""
    out = np.zeros((mask.size, *values.shape[1:]), np.float32)
    out[mask.ravel()] = values
    return out.reshape(shape)


def _coarse_mask(near: np.ndarray, shape, k: int) -> np.ndarray:
    """Flat mask of the coarse (shape = (mx, my, mz)) grid points whose interpolation reaches a
    fine point of ``near`` ((nz, ny, nx)): its block's, dilated by one coarse point."""
    mx, my, mz = shape
    padded = np.pad(near, [(0, m * k - n) for m, n in zip((mz, my, mx), near.shape, strict=True)])
    coarse = padded.reshape(mz, k, my, k, mx, k).any(axis=(1, 3, 5))
    return maximum_filter(coarse, size=3, mode="constant").ravel()


def fill_unreached(
    G: np.ndarray, points: np.ndarray, positions: np.ndarray, node_G: np.ndarray
) -> np.ndarray:
    """(M, 3) G at (M, 3) points, where points that no node's search range reaches (zero: at the
    medium's edge) take their nearest node's value (``node_G`` of ``positions``), so that
    interpolation there never blends in a false zero. A k-d tree of the nodes: a few hundredths of
    a second where a distance transform of the whole grid took most of a second."""
    unreached = ~(G > 0).any(axis=1)
    if not unreached.any() or not len(positions):
        return G
    G = G.copy()
    G[unreached] = node_G[cKDTree(positions).query(points[unreached], workers=cpu_threads())[1]]
    return G


@dr.syntax
def _optical_depth(medium, p: mi.Point3f, w: mi.Vector3f, step: float) -> mi.Float:
    """int_0^boundary sigma_t(p + s w) ds per point, midpoint rule, stopped at TAU_MAX; blocks
    without density are crossed in one step."""
    t, t_end = medium.box_interval(p, w)
    tau = mi.Float(0.0)  # Optical depth accumulator
    active = t < t_end
    while dr.hint(active, label="light_march"):
        sigma_maj, t_leave = medium.block(p, w, t, active)
        empty = sigma_maj <= 0.0
        dt = step_length(empty, t, t_leave, t_end, step, 1e-3 * step)
        tau += dr.select(empty, 0.0, medium.sigma_t(p + (t + 0.5 * dt) * w) * dt)
        t += dt
        active &= (t < t_end) & (tau < TAU_MAX)
    return dr.minimum(tau, TAU_MAX)


def g_texture(G) -> mi.Texture3f:
    """The texture of a grid of G = albedo L' (nz, ny, nx, 3): G^G_POWER, trilinear."""
    return linear_texture(np.maximum(np.asarray(G, np.float32), 0.0) ** np.float32(G_POWER))


def g_at(G_tex, pu, mask=True) -> mi.Color3f:
    """G read from :func:`g_texture` at unit-cube points pu."""
    g = G_tex.eval(pu, mask)
    return mi.Color3f(*(dr.power(c, 1.0 / G_POWER) for c in g))


def _gather_ms(
    medium, G_tex, points: np.ndarray, step: float, seed: int, sky: float = 0.0, env=None
) -> np.ndarray:
    """(M, 3) L_ms at (M, 3) world points: MS_DIRECTIONS flights each, averaged (see bake_field);
    ``sky``: the radiance of a uniform sky that flights leaving the box see (0: none); ``env``:
    an environment map's emitter that they see instead (None: none), and that as many
    directions drawn from the map see too (tracing.envmap_nee: the two weighted by the power
    heuristic, so that a small bright spot in the map is found)."""
    m, k = len(points), MS_DIRECTIONS
    # Spherical Fibonacci directions, the same set for every point, in a random frame per point
    i = np.arange(k) + 0.5
    z = 1.0 - 2.0 * i / k
    phi = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(1.0 - z * z)
    fib = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1).astype(np.float32)
    rng = jit_rng(m, seed, dr.arange(mi.UInt64, m))
    frame = mi.Frame3f(mi.warp.square_to_uniform_sphere(mi.Point2f(rng.next_float32(), rng.next_float32())))
    ray = dr.arange(mi.UInt32, m * k)
    point, j = ray // k, ray % k
    fr = dr.gather(mi.Frame3f, frame, point)
    w = dr.gather(mi.Vector3f, to_jit(mi.Vector3f, fib), j)
    d = fr.to_world(w)
    o = dr.gather(mi.Point3f, to_jit(mi.Point3f, points), point)
    L = _march_ms(medium, G_tex, o, d, step, sky, env)
    if env is not None:  # and as many directions drawn from the map (multiple importance sampling)
        L += envmap_nee(medium, env, o, jit_rng(m * k, seed + 1, dr.arange(mi.UInt64, m * k)), mi.Bool(True))
    dr.eval(L)  # one kernel: read channel by channel, each would run the march again
    out = from_jit(L, np.float64)
    return out.reshape(m, k, 3).mean(axis=1).astype(np.float32)


@dr.syntax
def _march_ms(medium, G_tex, o: mi.Point3f, d: mi.Vector3f, step: float, sky: float, env) -> mi.Color3f:
    """int T_r sigma_t G dt along each ray to the box boundary (trapezoid in optical depth, as the
    field estimator marches), plus T_r to the boundary times ``sky`` or the environment map
    ``env`` seen along the ray; blocks without density are crossed in one step."""
    t, t_end = medium.box_interval(o, d)

    def at(t):
        x = o + t * d
        return medium.sigma_t(x), g_at(G_tex, medium.world_to_unit @ mi.Point3f(x))

    L = mi.Color3f(0.0)  # Gathered radiance
    Tr = mi.Float(1.0)  # Transmittance from the point
    s0, G0 = at(t)
    active = t < t_end
    while dr.hint(active, label="ms_gather"):
        # Steps of at most MS_MAX_DTAU optical depth at the block's majorant, between one and
        # MS_STRIDE voxels; empty blocks in one step
        sigma_maj, t_leave = medium.block(o, d, t, active)
        empty = sigma_maj <= 0.0
        dt = dr.clip(MS_MAX_DTAU / dr.maximum(sigma_maj, 1e-12), step, MS_STRIDE * step)
        dt = step_length(empty, t, t_leave, t_end, dt, 1e-3 * step)
        s1, G1 = at(t + dt)
        seg_Tr, seg_G = exponential_segment(dr.select(empty, 0.0, 0.5 * (s0 + s1) * dt), G0, G1)
        L += Tr * seg_G
        Tr *= seg_Tr
        t += dt
        s0, G0 = s1, G1
        active &= (t < t_end) & (Tr > MS_TR_MIN)
    # What is left past the cut-off, at the last value seen (0 where the ray left the medium)
    L += dr.select(t < t_end, Tr, 0.0) * G0
    if dr.hint(sky > 0.0, mode="scalar"):  # the sky's component only
        L += dr.select(t < t_end, 0.0, Tr) * sky
    if dr.hint(env is not None, mode="scalar"):  # an environment map's, against its own samples
        seen = t >= t_end
        weight = power_heuristic(ISOTROPIC_PDF, envmap_pdf(env, o, d, seen))
        L += dr.select(seen, Tr, 0.0) * envmap_seen(env, d) * weight
    return L


def _walk_ms(medium, G_tex, points: np.ndarray, inputs: dict, seed: int) -> np.ndarray:
    """(M, 3 + len(SHAPE_DEGREES)) a sun's L_ms at (M, 3) world points in an anisotropic
    medium: what reaches each point after its first scattering, as a function of the camera
    ray's direction d, projected on orthogonal functions B_i of direction (phase.shape_basis, in
    the light's frame) and convolved with the phase (Funk-Hecke: degree l scales by g_l,
    phase.phase_legendre):

        L_ms(x, d) = int p(w . d) L(x, w) dw  ~  c_0(x) + sum_i c_i(x) B_i(d),
        c_i = g_l(i) int B_i(w) L(x, w) dw / int B_i^2,

    with L(x, w) the radiance that a walk from x along w brings back (phase.phase_walk: the
    medium's next events exact, the graph's ``G`` after them; x's own event is the camera's).
    WALKS walks a point, their first directions half uniform and half from the phase about the
    light (one-sample mixture pdf). Returns c_0 (RGB) and the c_i at unit intensity (the
    channels' mean over the irradiance's), so that the scene's mix scales them."""
    m, k = len(points), WALKS
    lobes = tuple((float(w), float(g)) for w, g in np.asarray(inputs["lobes"], float))
    to_light = tuple(float(c) for c in inputs["to_light"])
    E = np.asarray(inputs["irradiance"], float)
    albedo = mi.Color3f(*(float(c) for c in inputs["albedo"]))
    n = m * k
    rng = jit_rng(n, seed, dr.arange(mi.UInt64, n))
    o = dr.gather(mi.Point3f, to_jit(mi.Point3f, points), dr.arange(mi.UInt32, n) // k)
    s = mi.Vector3f(*to_light)
    uniform = rng.next_float32() < 0.5
    w = dr.select(uniform, uniform_sphere(rng), sample_phase(lobes, s, rng))
    pdf = 0.5 / (4.0 * dr.pi) + 0.5 * hg_phase(lobes, dr.dot(w, s))

    def tail(q, mask):
        return g_at(G_tex, medium.world_to_unit @ mi.Point3f(q), mask)

    def nothing(mask, w):  # a sun's component: nothing behind the medium
        return mi.Color3f(0.0)

    power = float(inputs["tau_power"][0])
    tau = depth_texture(inputs["tau"], power)

    def sun_tr(i, p, mask):  # the bake's own light march, interpolated as the camera's march does
        return dr.exp(-depth_at(tau, medium.world_to_unit @ mi.Point3f(p), mask, power))

    suns = [(to_light, mi.Color3f(*(float(c) for c in E)))]
    bounces = int(inputs["bounces"][0])
    tail = tail if inputs["tail"][0] else None
    L = phase_walk(medium, lobes, suns, albedo, nothing, tail, o, w, rng, mi.Bool(True), bounces, sun_tr)
    weight = L / pdf
    dr.eval(weight, w)  # the walks once: each sum below reads them
    # Projected per point: the sums over a point's k consecutive walks
    frame = light_frame(to_light)
    local = [dr.dot(w, mi.Vector3f(*(float(c) for c in e))) for e in frame]
    inv = np.where(E > 0, 1.0 / np.where(E > 0, E, 1.0), 0.0) / 3.0
    unit = weight.x * float(inv[0]) + weight.y * float(inv[1]) + weight.z * float(inv[2])
    sums = [dr.block_sum(v, k) for v in (weight.x, weight.y, weight.z)]
    sums += [dr.block_sum(unit * b, k) for b in shape_basis(*local)]
    dr.eval(sums)
    S = np.stack([np.array(v, np.float64) for v in sums], axis=1) / k  # (M, 3 + len(B))
    degrees = np.array((0, 0, 0, *SHAPE_DEGREES))
    scale = phase_legendre(lobes, max(degrees))[degrees] / np.array((4 * np.pi,) * 3 + SHAPE_NORMS)
    return (S * scale[None, :]).astype(np.float32)
