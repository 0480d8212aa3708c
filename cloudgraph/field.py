"""The radiance field: the cache baked onto a grid, for a noise-free camera stage (docs/method.md,
"The radiance field").

After transport, the in-scattered radiance of Eq. 4.24 is evaluated once on a grid aligned with
the density grid, split as the ``gather`` estimator splits it:

    L_in(x) = E exp(-tau_light(x)) / 4pi  +  L_ms(x)

- single scattering, exact to the grid: ``tau_light`` is the optical depth from each grid point
  to the light, by a deterministic midpoint march of the trilinear density in Dr.Jit (step
  light_march.TAU_STEP voxels), interpolated between grid points as a power of exp(-tau) (neither
  tau, too dark at a shadow's edge between grid points, nor exp(-tau), too bright), on a grid
  twice as fine where that fits (its points in optically thick voxels marched too), else on
  the field's, fitted there to sub-voxel samples of the march (light_march.py, light_depth.py);
- everything after the first scattering, from the graph, as ``gather`` computes it at its
  camera collision (field_ms.py: one more flight from the grid point, integrated over a fixed
  set of directions; walks with the view's dependence kept, for an anisotropic phase). It is
  smooth, so it lives on a grid :data:`MS_COARSEN` times coarser per axis (more for large media),
  each sun's over that sun's light factor exp(-min(P tau_light, range)) (field_ms.MS_LIGHT_POWER:
  below a lit surface it falls within a voxel as the light does), multiplied back where read.

A camera render is then a deterministic ray march with two texture lookups per step (the
``field`` estimator of the graph integrator, and the page's WebGL view), of one file
(field_file.py). Grid values sit at texel centres, (i + 0.5) / n of the unit cube that
``Volume.unit_to_world`` maps onto the medium box, and are interpolated trilinearly (clamped).
Only points within one voxel of some density are baked (the rest hold 0): interpolation at a
point where sigma_t > 0 reads no other.
"""

from __future__ import annotations

import threading
import time
import weakref

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.ndimage import distance_transform_edt, maximum_filter
from scipy.spatial import cKDTree

from .chunks import placed
from .field_file import RadianceField, component_names, pack_array, shape_name
from .field_grid import FieldPoints, MsGrid, make_ms_grid, read_mask, scattered
from .field_ms import (
    G_POWER,
    G_POWER_COARSE,
    MS_LIGHT_RANGE,
    MS_STEP,
    forward_orders,
    g_texture,
    gather_ms,
    light_factor,
    ms_light_power,
    smooth,
    view_light_power,
    walk_ms,
    walk_smoothing,
    walks_per_point,
)
from .graph import gradient_operators, node_gradients
from .image import latlong_directions
from .light_march import light_depths, march_light
from .lights import Lights
from .mitsuba_scene import envmap_emitter
from .params import GRADIENT, suns_apart
from .phase import SHAPE_DEGREES, light_frame, memory_bounces
from .spatial import NodeGrid, node_bins
from .tracing import (
    block_majorant,
    cpu_threads,
    depth_at,
    depth_texture,
    envmap_seen,
    from_jit,
    opaque,
    optical_depth,
    to_jit,
    towards_light,
)

#: The multiple-scattering grid is this many times coarser per axis than the field grid, or
#: coarser still until at most MS_MAX_POINTS of its points lie next to the medium. In a dense
#: cloud L_ms changes within a voxel near lit surfaces: at the field grid's resolution the
#: dense bench cloud's field reads 1.6 % from converged gather, at half of it 2.7 %. Where a
#: sun's L_ms is walked (an anisotropic phase) the grid may hold MS_WALK_POINTS, with half the
#: walks a point over MS_MAX_POINTS (field_ms.walks_per_point): smoke1 at g = 0.5 read a point
#: closer to gather side-lit on a grid 2x coarser than the field's than on one 3x coarser.
MS_COARSEN = 1
MS_MAX_POINTS = 1 << 17
MS_WALK_POINTS = 1 << 18
#: Multiple-scattering grid points per chunk (times field_ms.MS_DIRECTIONS rays; WALK_CHUNK where
#: they are walked, times the walks a point), and field points per chunk of the light march:
#: chunks bound the device memory and may run on other workers. 2^14 points a chunk of the
#: gather in place of 2^12 (each chunk traces its march anew): the held-out cloud's bake 0.125 ->
#: 0.109 s, 14.6 -> 12.8 % of its precompute, the noise cloud's 0.369 -> 0.330 s (medians of 7,
#: alternately in one process).
MS_CHUNK = 1 << 14
WALK_CHUNK = 1 << 12
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


# ------------------------------------------------------------------ baking


def ms_grid(fp: FieldPoints, walked: bool) -> MsGrid:
    """The grid the bake gathers L_ms on (``walked``: each sun's L_ms by walks, an anisotropic
    phase, on a grid of up to MS_WALK_POINTS points; else MS_MAX_POINTS), made once for ``fp``
    (:func:`_once`): a precompute makes it while the graph is built, and a relight in this process
    reuses it with the grid points."""
    return lookup_grid(fp) if walked else _once(fp, make_ms_grid, MS_COARSEN, MS_MAX_POINTS)


def lookup_grid(fp: FieldPoints) -> MsGrid:
    """The grid the bake looks the nodes' G up on (albedo L'_search, what the gather's march and
    the walks' tails read), of up to :data:`MS_WALK_POINTS` points: the field's own but for a
    large medium (where L_ms is walked, the grid it is walked on). Made once for ``fp`` as
    :func:`ms_grid` is. On smoke1 (1.26 M field points, 183,404 on a grid 2x coarser) the bake
    0.70 -> 0.44 s, 18 -> 12 % of the precompute; field at 16 spp against gather at 1024 on one
    cache (binned relMAE / mean, side-lit albedo 1 / 0.8, back-lit 1 / 0.8) 1.17 / 0.93 / 1.16 /
    1.15 % -> 1.33 / 0.95 / 1.17 / 1.17 %, its mean 0.997-1.000 -> 0.993-0.998 (on the L_ms
    grid, 3x coarser: 1.56 % / 0.989 side-lit)."""
    return _once(fp, make_ms_grid, MS_COARSEN, MS_WALK_POINTS)


def packed_depth(tau: np.ndarray):
    """The field file's packed array of a sun's tau_light, made once for the array
    (:func:`_once`): a precompute packs it on the thread that made it, while the transport runs."""
    return _once(tau, _packed, "tau_light")


def medium_arrays(fp: FieldPoints) -> tuple[np.ndarray, dict]:
    """What the field file holds of the medium alone: sigma_t's block majorant, and sigma_t's and
    the majorant's packed arrays. Made once for a grid's points (:func:`_once`): a precompute
    makes them while the graph is built, and a relight in this process reuses them."""
    majorant = _once(fp.sigma_t, block_majorant)
    return majorant, {
        "sigma_t": _once(fp.sigma_t, _packed, "sigma_t"),
        "majorant": _once(majorant, _packed, "majorant"),
    }


def bake_field(
    builder,
    fp: FieldPoints,
    graph,
    radiance_gather: np.ndarray,
    albedo,
    lights: Lights,
    radiance_key: str,
    chunks,
    depths=None,
    bins=None,
    progress=None,
    phase=None,
    max_depth: int = -1,
    gradient_op=None,
) -> tuple[RadianceField, dict]:
    """Bakes the field of a radiance cache (a variant must be set).

    Args:
        builder: the :class:`~cloudgraph.build.GraphBuilder` of the graph (volume, medium, node
            radius r, the Eq. 4.25 weight's floor).
        fp: the field's grid points (:meth:`FieldPoints.of` the builder's volume and medium).
        graph: the :class:`~cloudgraph.graph.Graph` (positions, search ranges, counts).
        radiance_gather: (K, N, 3) node radiance with one scattering event fewer (as ``gather``),
            per light component (lights.py); with the isotropic phase without the suns' direct
            light (precompute.without_sun), which the bake's march adds where it reads G, from
            tau_light.
        albedo: (3,); lights: the scene's :class:`~cloudgraph.lights.Lights`.
        chunks: runs the marches' chunks (:func:`field_chunk`; stages.py), as in ``build_graph``.
        depths: each sun's tau_light and the power its texture reads (:func:`light_depths`), if
            made (a precompute makes them while the transport runs); else marched and made here.
        bins: the graph's nodes binned (:func:`~cloudgraph.spatial.node_bins`), if made.
        progress: ``progress("field", fraction)`` is called between the bake's parts (a caller's
            cancel raises from it).
        phase: the medium's :class:`~cloudgraph.scene.PhaseSpec` (None: isotropic). An
            anisotropic one bakes each sun's L_ms by walks that take its first events exactly,
            and keeps how it depends on the view (``ms_shape``, below).
        max_depth: the scene's (-1: unbounded); bounded, the walks take every event exactly, as
            ``gather`` does, and read no graph.
        gradient_op: the nodes' gradient operator (graph.gradient_operators, params.GRADIENT) if
            transport made it (None: made here where the lookups read each node by its plane).

    Returns:
        (field, stats): stats hold the bake's seconds per part.
    """
    volume = builder.volume
    progress = progress or (lambda stage, fraction: None)
    t_start = time.perf_counter()
    u2w = np.asarray(volume.unit_to_world, float)
    shape, near, voxel = fp.shape, fp.near, fp.voxel
    # single scattering: the optical depth to each sun (made while the transport ran, or now)
    t0 = time.perf_counter()
    if depths is None:
        depths = light_depths(fp, march_light(builder, fp, lights.directions, chunks))
    taus, tau_power = depths
    t_tau = time.perf_counter() - t0

    # Multiple scattering, as ``gather`` computes it but on the grid: one more flight from the
    # grid point, to p'', where the graph's albedo L' stands in for the rest (Eq. 4.25):
    #   L_ms(x) = 1/4pi int_S2 int_0^inf T_r(x, x + t w) sigma_t(x + t w) G(x + t w) dt dw,
    #   G = albedo L'_search (radiance_gather) + albedo E exp(-tau_light) / 4pi per sun,
    # with albedo L'_search baked first on a grid (one node lookup per point: the field's, or
    # coarser for a large medium, lookup_grid; G is smooth, the search ranges' mean), the suns'
    # part read from tau_light where the march is (the camera march's own), then K fixed directions
    # per point (a spherical Fibonacci set, turned at random per point) marched in closed form.
    # The sky's component also takes what escapes: its single scattering, smooth, baked here.
    # One lookup and one gather per light component.
    t0 = time.perf_counter()
    start, entries, grid = bins if bins is not None else node_bins(graph.positions, graph.search_radius)
    binned = {"start": start, "entries": entries, "grid": grid}
    lobes = None if phase is None or phase.isotropic else np.array(phase.lobes(), float)
    forward = forward_orders(phase, max_depth)  # (the sun's light in its beam, in closed form)
    # With the isotropic phase the nodes' radiance is without the suns' direct light
    # (precompute.without_sun): the march adds it where it reads G, from tau_light, and each node
    # is read by its plane where a lookup falls, as gather's lookups are (render.py)
    sun_exact = suns_apart(lobes is None, max_depth)
    node_G = [component * np.asarray(albedo, np.float32)[None, :] for component in radiance_gather]
    planes = {}
    if sun_exact:
        D = gradient_op
        if D is None:  # (a radiance found in the store: transport did not run)
            D = gradient_operators(graph.positions, graph.search_radius, **GRADIENT, workers=cpu_threads())
        planes = {c: {"gradient": node_gradients(D, G)} for c, G in enumerate(node_G)}
    walks = lobes is not None and len(lights.directions) > 0  # (each sun's L_ms walked, below)
    grid_ms = ms_grid(fp, walks)
    ms_shape, ms_near, q = grid_ms.shape, grid_ms.near, grid_ms.points
    grid_G = lookup_grid(fp)
    looked = [
        chunks(
            builder,
            "field_lookup",
            {
                "points": grid_G.points,
                "positions": graph.positions,
                "search_radius": graph.search_radius,
                "G": G,
                **planes.get(c, {}),
                **binned,
            },
        )
        for c, G in enumerate(node_G)
    ]
    step = np.array([MS_STEP * voxel])
    g_power = np.array([G_POWER_COARSE if grid_G.coarsen > 1 else G_POWER])  # (field_ms.G_POWER_COARSE)
    gathered, walked = [], []
    for c, lk in enumerate(looked):
        G = scattered(grid_G.near, placed(lk, len(grid_G.points), 3), (*grid_G.shape[::-1], 3))
        inputs = {"points": q, "G": G, "g_power": g_power, "step": step}
        inputs["sky"] = np.array([int(lights.kind(c) == "sky")])
        if sun_exact and lights.kind(c) == "directional":  # (component c is directional light c)
            # the sun's part of G read where the march is, from tau_light as the camera's march
            # reads it: baked into G at the grid points, its steep fall below a lit surface
            # read bright between them (the dense cloud back-lit: field 1.2 % over gather, 0.5 %)
            inputs["sun"] = np.asarray(albedo, np.float32) * lights.cached[c] / np.float32(4.0 * np.pi)
            inputs["tau"], inputs["tau_power"] = taus[c], np.array([tau_power])
        if lights.kind(c) == "envmap":  # what escapes sees the map: the file, read where it runs
            inputs["envmap"] = np.array([lights.envmaps[c - lights.count + len(lights.envmaps)]])
        if lobes is not None and lights.kind(c) == "directional":  # a sun's, by walks
            inputs = {
                "points": q,
                "G": G,
                "g_power": g_power,
                "albedo": np.asarray(albedo, np.float32),
                "to_light": towards_light(lights.directions[c]),
                "irradiance": lights.cached[c],
                "lobes": lobes,
                # (x's own event is the camera's: the walks take one fewer)
                "bounces": np.array([memory_bounces(phase) - 1 if max_depth < 0 else max_depth - 1]),
                "tail": np.array([int(max_depth < 0)]),
                "tau": taus[c],  # (a sun's component c is directional light c)
                "tau_power": np.array([tau_power]),
                "forward": np.array([forward]),
                "walks": np.array([walks_per_point(len(q), MS_MAX_POINTS)]),
                "step": step,
            }
            walked.append(c)
        gathered.append(chunks(builder, "field_ms", inputs))
    progress("field", 0.2)
    t_ms = time.perf_counter() - t0

    # While the gather's chunks run: the arrays that do not depend on the gather packed (most of
    # the file's bytes; precompute.py encodes it at the end)
    progress("field", 0.6)
    majorant, medium = medium_arrays(fp)
    tau_light = taus[0] if taus else np.zeros_like(fp.sigma_t)
    packed = {
        "sigma_t": medium["sigma_t"],
        "tau_light": packed_depth(tau_light),
        "majorant": medium["majorant"],
    }
    t0 = time.perf_counter()
    width = [3 + len(SHAPE_DEGREES) if c in walked else 3 for c in range(len(gathered))]
    ms = [
        scattered(ms_near, placed(g, len(q), n), (*ms_shape[::-1], n))
        for g, n in zip(gathered, width, strict=True)
    ]
    mask = ms_near.reshape(ms_shape[::-1])
    for c in walked:
        ms[c] = smooth(ms[c], mask, walk_smoothing(phase))
    views = {c: ms[c][..., 3:] for c in walked}
    ms = [np.ascontiguousarray(m[..., :3]) for m in ms]
    # each sun's L_ms over its light factor, as the readers read its tau (field_ms.MS_LIGHT_POWER):
    # they multiply it back where they read L_ms; its view terms too, over the factor's grey
    # power (field_ms.view_light_power), before they are halved
    ms_light, view_power = None, None
    if taus:
        power = ms_light_power(albedo, walks)
        ms_light = {"power": power.tolist(), "range": MS_LIGHT_RANGE}
        view_power = view_light_power(albedo, walks)
        pu = to_jit(mi.Point3f, grid_ms.units)
        for c in range(len(ms)):
            if lights.kind(c) == "directional":  # (a sun's component c is directional light c)
                tau = depth_at(depth_texture(taus[c], tau_power), pu, mi.Bool(True), tau_power)
                tau = np.array(tau, np.float64).reshape(ms_shape[::-1])
                ms[c] = (ms[c] / light_factor(tau, power, MS_LIGHT_RANGE)).astype(np.float32)
                if c in views:
                    views[c] = views[c] / light_factor(tau, [view_power], MS_LIGHT_RANGE)
    shapes = {c: _halve(v, mask, fp.sigma_t > 0) for c, v in views.items()}  # (smooth: half the resolution)
    # The march reads L_ms at a segment's end up to a step past the medium (sigma_t the mean of
    # the ends'): the grid's points next to those gathered take the nearest gathered one's
    shell = maximum_filter(mask, size=3, mode="constant") & ~mask
    ms = [_nearest_filled(m, mask, shell) for m in ms]
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
    if ms_light is not None:
        meta["ms_light"] = ms_light
    if walked and forward:
        meta["ms_forward"] = forward
    extra = {}
    if not lights.basis:  # a v1 light
        direction = -towards_light(lights.directions[0])
        meta["light"] = {"direction": direction.tolist(), "irradiance": lights.intensity[0].tolist()}
        if shapes:
            meta["ms_shape"] = _shape_entry("ms_shape", lights, 0, view_power)
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
                entry["shape"] = _shape_entry(shape_name(c), lights, c, view_power)
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
        "field_ms_coarsen": grid_ms.coarsen,
        "field_points": int(near.sum()),
        "field_ms_points": int(ms_near.sum()),
        "field_lookup_coarsen": grid_G.coarsen,
        "field_lookup_points": len(grid_G.points),
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
    size, medium = _chunk(stage, inputs), builder.field
    a = index * size
    q = np.asarray(inputs["points"][a : a + size], np.float32)
    if stage == "field_lookup":
        return np.array([a]), _lookup(inputs, q, builder.params.radius)
    if stage == "field_tau":
        step = float(inputs["step"][0])
        to_light = opaque(mi.Vector3f, inputs["to_light"])  # (a new light compiles nothing)
        tau = optical_depth(medium, to_jit(mi.Point3f, q), to_light, step)
        values = np.array(tau, np.float32)[:, None]
    else:
        G_tex = _once(inputs["G"], g_texture, float(inputs["g_power"][0]))
        power = float(inputs["tau_power"][0]) if "tau" in inputs else 0.0
        tau_tex = _once(inputs["tau"], depth_texture, power) if "tau" in inputs else None
        if "lobes" in inputs:
            values = walk_ms(medium, G_tex, tau_tex, q, inputs, seed=a)
        else:
            sky = float(inputs["sky"][0]) if "sky" in inputs else 0.0
            env = envmap_emitter(str(inputs["envmap"][0])) if "envmap" in inputs else None
            step = float(inputs["step"][0])
            sun = None
            if "sun" in inputs:
                sun = (opaque(mi.Color3f, inputs["sun"]), tau_tex, power)
            values = gather_ms(medium, G_tex, q, step, seed=a, sky=sky, env=env, sun=sun)
    return np.array([a]), values


#: What is made from an input once while it lives (:func:`_once`): the textures that
#: ``field_ms`` chunks read (the chunks of one gather share their inputs' arrays, in this process
#: and on a Dask worker alike, and making a field-sized texture took longer than marching a
#: chunk: smoke1, 16 chunks, 1.6 s of the bake's 4.3 s), sigma_t's and tau_light's packed arrays,
#: the nodes' k-d tree and the L_ms grid of a field's points.
_ONCE: dict = {}
_ONCE_LOCK = threading.Lock()


def _once(values, make, *args):
    """``make(values, *args)``, made once per object (an array, the field's points) while it
    lives."""
    key = (id(values), make, args)
    with _ONCE_LOCK:  # (a chunk on another thread waits for the texture, not makes it again)
        if key not in _ONCE:
            _ONCE[key] = make(values, *args)
            weakref.finalize(values, _ONCE.pop, key, None)
        return _ONCE[key]


def _packed(values: np.ndarray, name: str):
    return pack_array(name, values)


def field_chunks(stage: str, inputs: dict) -> int:
    return -(-len(inputs["points"]) // _chunk(stage, inputs))


def _chunk(stage: str, inputs: dict) -> int:
    """Points per chunk of a bake's stage (a sun's walks: WALK_CHUNK)."""
    return WALK_CHUNK if stage == "field_ms" and "lobes" in inputs else _CHUNK[stage]


def _lookup(inputs: dict, q: np.ndarray, node_radius: float) -> np.ndarray:
    """(M, 3) L'_search of the nodes' ``G`` at (M, 3) points q (a ``field_lookup`` chunk), and
    where no node reaches, the nearest node's (:func:`fill_unreached`)."""
    positions, search_radius, node_G = (np.asarray(inputs[k]) for k in ("positions", "search_radius", "G"))
    bins = tuple(np.asarray(inputs[k]) for k in ("start", "entries", "grid"))
    gradient = np.asarray(inputs["gradient"]) if "gradient" in inputs else None
    grid = NodeGrid.build(positions, search_radius, node_G, bins, gradient)
    G = grid.lookup(to_jit(mi.Point3f, q), (0.05 * node_radius) ** 2, mi.Bool(True))
    dr.eval(G)  # one kernel for the three channels
    tree = _once(positions, cKDTree) if len(positions) else None  # (shared by the chunks)
    return fill_unreached(from_jit(G), q, tree, node_G)


def background_map(path: str, width: int = BACKGROUND_WIDTH) -> np.ndarray:
    """(width // 2, width, 3) the radiance an environment map (scale 1) sends toward a camera
    ray of each of :func:`latlong_directions`: Mitsuba's own lookup, so the page draws the
    map behind the medium as the server's estimators see it."""
    d = latlong_directions(width).reshape(-1, 3)
    seen = envmap_seen(envmap_emitter(path), to_jit(mi.Vector3f, d))
    dr.eval(seen)
    return np.stack([np.array(seen[i], np.float32) for i in range(3)], axis=-1).reshape(width // 2, width, 3)


def _shape_entry(name: str, lights: Lights, c: int, light_power: float) -> dict:
    """The header's entry of sun c's view terms: their array's name, frame and the grey power of
    the light factor they are kept over (api.md)."""
    frame = light_frame(towards_light(lights.directions[c])).tolist()
    return {"array": name, "frame": frame, "light_power": light_power}


def _halve(values: np.ndarray, mask: np.ndarray, dense: np.ndarray) -> np.ndarray:
    """(mz, my, mx, C) grid values at half the resolution per axis (rounded up): the mean of each
    2^3 block's points of ``mask``; a point that the camera's interpolation reads (where the
    field grid's ``dense`` is, :func:`~cloudgraph.field_grid.read_mask`) whose block holds none
    takes the nearest block's that does (a half-resolution point reaches two field voxels past
    the points gathered), as do the points next to those (the march reads a segment's end up to
    a step past the medium). Measured on the bench sphere at g = 0.85: the view's terms at half
    resolution render as at full (binned relMAE 7.75 / 4.29 % side / back-lit against 7.71 /
    4.13 %), in a fifth of the bytes."""
    pads = [(0, n % 2) for n in mask.shape]
    m = np.pad(mask.astype(np.float64), pads)
    v = np.pad(values * mask[..., None], pads + [(0, 0)])
    mz, my, mx = (n // 2 for n in m.shape)
    total = v.reshape(mz, 2, my, 2, mx, 2, -1).sum(axis=(1, 3, 5))
    count = m.reshape(mz, 2, my, 2, mx, 2).sum(axis=(1, 3, 5))
    half = np.where(count[..., None] > 0, total / np.maximum(count, 1)[..., None], 0.0)
    read = maximum_filter(read_mask(dense, (mx, my, mz)).reshape(mz, my, mx), size=3, mode="constant")
    return _nearest_filled(half.astype(np.float32), count > 0, read & (count == 0))


def _nearest_filled(values: np.ndarray, have: np.ndarray, where: np.ndarray) -> np.ndarray:
    """(..., C) grid ``values`` with the points of ``where`` ((...) bool) set to the nearest
    point of ``have``'s value (as they are where nothing has a value)."""
    values = np.ascontiguousarray(values, np.float32)
    if where.any() and have.any():
        nearest = distance_transform_edt(~have, return_distances=False, return_indices=True)
        values[where] = values[tuple(i[where] for i in nearest)]
    return values


def fill_unreached(G: np.ndarray, points: np.ndarray, tree: cKDTree | None, node_G: np.ndarray) -> np.ndarray:
    """(M, 3) G at (M, 3) points, where points that no node's search range reaches (zero: at the
    medium's edge) take their nearest node's value (``node_G`` of the nodes in the k-d ``tree``;
    None: no nodes), so that interpolation there never blends in a false zero. A k-d tree of the
    nodes: a few hundredths of a second where a distance transform of the whole grid took most
    of a second."""
    unreached = ~(G > 0).any(axis=1)
    if not unreached.any() or tree is None:
        return G
    G = G.copy()
    G[unreached] = node_G[tree.query(points[unreached], workers=cpu_threads())[1]]
    return G
