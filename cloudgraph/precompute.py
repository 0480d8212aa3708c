"""The precompute: graph (§4.3) -> direct radiance (§4.4) -> transport (§4.5) -> radiance field,
through the cache.

A changed albedo, light or depth reuses the graph and recomputes only the radiance and the field
(a relight). A cache of several lights (v1.1 ``lights``) is made of each light component's own
cache, found or made (:func:`_composed`): a new light list on a graph computes its new lights
only. An anisotropic phase (docs/method.md, "Anisotropic scattering") builds, lights and
transports the graph of the similarity-scaled isotropic medium (``MediumSpec.graph_medium``),
and bakes the field in the real one: its single scattering and its flights to the graph's
radiance are those of the real medium.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .build import GraphBuilder, build_graph
from .cache import CacheStore, cache_keys
from .chunks import placed
from .errors import CacheError
from .field import bake_field, lookup_grid, medium_arrays, ms_grid, packed_depth
from .field_file import RadianceField, combined
from .field_grid import FieldPoints
from .graph import Graph
from .graph_file import (
    pack_radiance,
    radiance_file,
    read_graph,
    read_nodes,
    read_radiance,
    stored_graph,
    stored_positions,
    unpack_radiance,
)
from .light_march import light_depths, march_light
from .lights import Lights, component_scenes
from .params import GRADIENT, LIGHTING, BuildParams, build_params, suns_apart
from .scene import Scene
from .stages import local_chunks
from .tracing import cpu_threads, new_scope
from .transport import transport
from .volume import Volume

log = logging.getLogger(__name__)

#: What a precompute keeps of its graph for the next one in this process (a relight: a new light
#: on the same graph, which a worker runs in the same process): the graph as stored, its
#: transition operator (the albedo enters last: Transitions.with_albedo) and the field's grid
#: points and the nodes' bins, by the graph's key (content-addressed: one key, one graph) and the
#: field medium's density scale. One graph at a time (smoke1: about 150 MB; a relight 3.6 -> 2.5 s).
_KEPT: dict = {}


#: The thread that makes the suns' tau_light (light_march.light_depths: numpy, 0.4 s on smoke1)
#: from the light march, then the file's arrays of the medium (field.medium_arrays) and the grids
#: that L_ms is gathered on and G looked up on (field.ms_grid, field.lookup_grid), while the
#: graph is read or built and the transport solved.
_DEPTHS = ThreadPoolExecutor(1, thread_name_prefix="field-depths")


def _light_depths(fp: FieldPoints, marched: list) -> tuple[list, float]:
    """light_march.light_depths on the thread of :data:`_DEPTHS`, which lives on: in a Dr.Jit
    scope of its own (a chunk that it runs itself, where a Dask cluster was lost, reads the
    builder's arrays)."""
    new_scope()
    taus, power = light_depths(fp, marched)
    if taus:  # (and the field file's array of the first, packed while the transport runs)
        packed_depth(taus[0])
    return taus, power


def _known(gkey: str, what: tuple):
    """What :func:`_kept` holds of graph ``gkey`` (None: nothing yet)."""
    return _KEPT.get(what) if _KEPT.get("graph_key") == gkey else None


def _kept(gkey: str, what: tuple, make):
    """``make()``, kept for the next precompute of graph ``gkey`` (:data:`_KEPT`)."""
    if _KEPT.get("graph_key") != gkey:
        _KEPT.clear()
        _KEPT["graph_key"] = gkey
    if what not in _KEPT:
        value = make()
        if value is None:  # (nothing to keep: a graph not stored yet)
            return None
        _KEPT[what] = value
    return _KEPT[what]


@dataclass
class RadianceCache:
    """A graph with the transported radiance of one (albedo, light, max_depth), and its field.

    Attributes:
        radiance: (N, 3) float32 node radiance L' (Algorithm 1), phase function included.
        radiance_gather: (N, 3) the same with one scattering event fewer (max_depth - 1), less
            the directional lights' direct radiance (:func:`without_sun`), for estimators that
            scatter once more before looking up and take the sun's light there exactly.
        field: the baked :class:`~cloudgraph.field_file.RadianceField` (the ``field`` estimator's),
            decoded from ``field_data`` (the field file's bytes) when first used: a precompute job
            never uses it.
        keys: volume_id, graph_key, radiance_key.
        stats: graph, radiance and field stats, stage times, bytes.
        graph: the graph, read from the store only when first used: a ``field`` render of a
            cached scene never reads it (it is by far the largest file).
        nodes: (positions, search ranges) of the graph, all that a Monte Carlo render needs of it:
            read without the counts (most of the graph file) when the graph is not loaded.
    """

    radiance: np.ndarray
    radiance_gather: np.ndarray
    field_data: bytes
    keys: dict
    stats: dict
    store: CacheStore
    _graph: Graph | None = None
    _nodes: tuple[np.ndarray, np.ndarray] | None = None
    _field: RadianceField | None = None

    @property
    def field(self) -> RadianceField:
        if self._field is None:
            self._field = RadianceField.decode(self.field_data)
        return self._field

    @property
    def graph(self) -> Graph:
        if self._graph is None:
            self._graph = read_graph(self.store.graph_path(self.keys["graph_key"]))
            if self._graph is None:
                raise CacheError("the graph of this cache was evicted; run the precompute again")
        return self._graph

    @property
    def nodes(self) -> tuple[np.ndarray, np.ndarray]:
        if self._graph is not None:
            return self._graph.positions, self._graph.search_radius
        if self._nodes is None:
            self._nodes = read_nodes(self.store.graph_path(self.keys["graph_key"]))
            if self._nodes is None:
                raise CacheError("the graph of this cache was evicted; run the precompute again")
        return self._nodes


def lighting_inputs(positions: np.ndarray, lights: Lights, params: BuildParams) -> dict:
    """What the direct-lighting chunks of a graph's nodes ((N, 3) positions) need (GraphBuilder's
    ``lighting``): one directional light as before v1.1, or each component (lights.py)."""
    inputs = {
        "positions": positions,
        "light_dir": lights.directions,
        "irradiance": lights.cached[: len(lights.directions)],
        "samples": np.array([LIGHTING["samples"]]),
        "seed": np.array([params.seed]),
    }
    if not lights.basis:  # a v1 light: its inputs as they were
        inputs["light_dir"], inputs["irradiance"] = lights.directions[0], lights.cached[0]
    else:
        inputs["sky"] = np.array([int(lights.sky)])
        if lights.envmaps:
            inputs["envmaps"] = np.array(lights.envmaps)
    return inputs


def precompute(
    scene: Scene,
    volume: Volume,
    quality: str = "default",
    store: CacheStore | None = None,
    progress=None,
    chunks=local_chunks,
    **build_overrides,
) -> RadianceCache:
    """Finds or builds the radiance cache for the scene's (volume, medium, light, depth).

    ``progress(stage, fraction)`` is called as it goes; ``chunks`` runs the chunks of the graph
    build, the direct lighting and the field bake (stages.py): here, or over workers, with the
    same result. A variant must be set.
    """
    store = store or CacheStore()
    progress = progress or (lambda stage, fraction: None)
    # The build parameters are the scene's medium's (node radius from its free path: the same
    # as the service works out for its keys), whatever medium the graph is of
    params = build_params(volume, scene.medium.density_scale, quality, **build_overrides)
    keys = cache_keys(scene, volume, params)
    gkey, rkey = keys["graph_key"], keys["radiance_key"]
    lights = Lights.of(scene)
    made = store.radiance_path(rkey).is_file() and store.field_path(rkey).is_file()
    if lights.basis and lights.count > 1 and not made:
        return _composed(scene, volume, quality, store, progress, chunks, keys, build_overrides)
    # The graph's medium: the scene's, or for an anisotropic phase its similarity-scaled
    # isotropic medium (sigma_t' = sigma_t (1 - a g), albedo' = a (1 - g) / (1 - a g)). The
    # field is baked in the real medium, by a builder of its own; its chunks then run here, as
    # a Dask run's chunks are all made with the run's first builder (cloudgraph_service).
    isotropic = scene.medium.phase.isotropic
    graph_density, graph_albedo = scene.medium.graph_medium()
    field_builder, field_chunks = None, chunks if isotropic else local_chunks
    # An environment map is a file of this machine's: the chunks that read it (the lighting and
    # the bake) run here too (a cluster's workers have no data volume: compose.yaml)
    light_chunks = local_chunks if lights.envmaps else chunks
    if lights.envmaps:
        field_chunks = local_chunks

    found = read_radiance(store.radiance_path(rkey))
    found_field = store.load_field(rkey)
    graph, graph_reused, builder, lit, t_light, depths = None, True, None, None, 0.0, None
    points = None  # the field's grid points, made once when the field needs them

    def field_points() -> FieldPoints:
        nonlocal points
        if points is None:
            scale = float(field_builder.field.scale)
            points = _kept(gkey, ("points", scale), lambda: FieldPoints.of(volume, field_builder.field))
        return points

    def light(positions):
        # The direct light's chunks, at the node positions as stored, go out as soon as the
        # nodes are known: workers that share this precompute light them while the graph is
        # finished and written
        nonlocal lit, t_light
        t_light = time.perf_counter()
        lit = light_chunks(builder, "lighting", lighting_inputs(positions, lights, params))

    if found is None or found_field is None:  # the graph is needed: read it, or build it
        builder = GraphBuilder(volume, graph_density, params)
        field_builder = builder if isotropic else GraphBuilder(volume, scene.medium.density_scale, params)

        def march():
            # The field's light march needs the medium and the light only: it goes out early,
            # for workers that share this precompute to run whenever the other stages leave them
            # idle (stages.LATE_STAGES): before the graph is read, or right after a new
            # graph's light paths (helpers start on those while this worker finds the field's
            # points)
            nonlocal depths
            if depths is None and found_field is None:
                marched = march_light(field_builder, field_points(), lights.directions, field_chunks)
                # ... and each sun's tau_light made from it on a thread of its own, as it comes in
                depths = _DEPTHS.submit(_light_depths, field_points(), marched)
                # (then the file's arrays of sigma_t, and the grids that L_ms is gathered on and
                # G looked up on)
                _DEPTHS.submit(medium_arrays, field_points())
                _DEPTHS.submit(ms_grid, field_points(), not isotropic and len(lights.directions) > 0)
                _DEPTHS.submit(lookup_grid, field_points())

        if store.graph_path(gkey).is_file():
            march()
        graph = None
        if store.graph_path(gkey).is_file():  # (kept only while its file is there: renders read it)
            graph = _kept(gkey, ("graph",), lambda: read_graph(store.graph_path(gkey)))
        graph_reused = graph is not None
        if graph is None:
            built = build_graph(
                volume,
                graph_density,
                params,
                chunks,
                lambda s, f: progress(s, 0.7 * f),
                builder,
                nodes_found=(lambda p: light(stored_positions(p))) if found is None else None,
                started=march,
            )
            graph = stored_graph(built)  # go on with what is stored: fresh and loaded alike
            _kept(gkey, ("graph",), lambda: graph)
    if found is None and lit is None:
        light(graph.positions)
    # The field's node bins need the graph only: put out now, for a worker that shares this
    # precompute to make while this one solves the transport (a late stage)
    bins = None  # (kept from a precompute of this graph before, or put out now)
    if found_field is None and _known(gkey, ("bins",)) is None:
        bins = chunks(builder, "bins", {"positions": graph.positions, "search_radius": graph.search_radius})
    if not graph_reused:
        # The file's bytes (packed and compressed: 0.6-0.9 s on blender) are a late stage too,
        # wanted only at the end: put out after the bins, so that an idle worker takes those first
        filed = chunks(builder, "graph_file", built.to_arrays())
    gradient_op = None  # the nodes' gradient operator, once transport has made it
    if found is not None:
        (radiance, radiance_gather), rstats = found
    else:
        progress("lighting", 0.7)
        # (N, 3 K): the K light components side by side, transported at once
        L_d = placed(lit, graph.n_nodes, 3 * lights.count, np.float64)
        t_light = time.perf_counter() - t_light
        progress("transport", 0.85)
        t0 = time.perf_counter()
        albedo = np.tile(graph_albedo, lights.count)

        def transitions():  # (the nodes' sigma_t: the curvature's term where the medium absorbs)
            sigma_t = builder.field.sigma_t_at(graph.positions) if LIGHTING["curvature"] else None
            return graph.transitions(GRADIENT, cpu_threads(), sigma_t)

        made_with = ("transitions", LIGHTING["curvature"], repr(sorted(GRADIENT.items())))
        C = _kept(gkey, made_with, transitions).with_albedo(albedo)
        gradient_op = C.D
        depth = scene.render.max_depth

        def still_wanted():  # progress() raises when the job was cancelled
            progress("transport", 0.85)

        L, iterations = transport(C, L_d, albedo, depth, LIGHTING["tol"], cancelled=still_wanted)
        if depth < 0:
            L_gather = L
        else:
            L_gather = transport(C, L_d, albedo, depth - 1, LIGHTING["tol"], cancelled=still_wanted)[0]
        if suns_apart(isotropic, depth):  # (an anisotropic phase's walks read the graph's all)
            L_gather = without_sun(L_gather, L_d, lights)
        t_transport = time.perf_counter() - t0
        packed = pack_radiance(stack_components(L, lights.count), stack_components(L_gather, lights.count))
        radiance, radiance_gather = unpack_radiance(packed)
        rstats = {
            **graph.stats,  # kept with the radiance, so that a reused cache needs no graph read
            "lighting_s": round(t_light, 3),
            "transport_s": round(t_transport, 3),
            "transport_iterations": iterations,
        }
        if lights.basis:
            rstats["light_components"] = lights.count
    if found is None:
        store.save_radiance(rkey, radiance_file(packed, rstats))
    if found_field is not None:
        field_data, fstats = found_field, {}
    else:
        progress("field", 0.95)
        # (the real albedo: L_ms is albedo L' gathered through the real medium, as gather's)
        field, fstats = bake_field(
            field_builder,
            field_points(),
            graph,
            radiance_gather.reshape(lights.count, graph.n_nodes, 3),
            scene.medium.albedo_rgb(),
            lights,
            rkey,
            field_chunks,
            depths.result() if depths is not None else None,
            _kept(gkey, ("bins",), lambda: next(iter(bins))),
            lambda stage, f: progress(stage, 0.95 + 0.05 * f),
            phase=scene.medium.phase,
            max_depth=scene.render.max_depth,
            gradient_op=gradient_op,
        )
        if not isotropic:  # the page's march applies it to single scattering (api.md)
            field.meta["phase"] = scene.medium.phase.model_dump()
        field_data = field.encode()  # render what is stored, fresh or loaded alike
    # The graph is written last: a worker that shares this precompute makes its bytes whenever
    # the other stages leave it idle
    if not graph_reused:
        store.save_graph(gkey, next(iter(filed))[0].tobytes())
    if found_field is None:
        store.save_field(rkey, field_data)
    progress("done", 1.0)
    stats = {
        **rstats,
        **fstats,
        "graph_reused": graph_reused,
        "radiance_reused": found is not None,
        "field_reused": found_field is not None,
        **{
            f"{kind}_bytes": _size(path)
            for kind, path in (
                ("graph", store.graph_path(gkey)),
                ("radiance", store.radiance_path(rkey)),
                ("field", store.field_path(rkey)),
            )
        },
        "radius": params.radius,
        "quality": quality,
    }
    if not isotropic:
        stats["similarity"] = {"density_scale": graph_density, "albedo": list(graph_albedo)}
    return RadianceCache(radiance, radiance_gather, field_data, keys, stats, store, graph)


def _composed(scene, volume, quality, store, progress, chunks, keys, build_overrides) -> RadianceCache:
    """The cache of a scene of several light components, made of each component's own cache
    (component_scenes: found in the store, or precomputed now on the one graph): transport and
    the bake are linear in the light and each component's depend on that light alone, so its
    radiance and field arrays are the components' side by side."""
    parts = []
    scenes = component_scenes(scene)
    for c, single in enumerate(scenes):

        def part_progress(stage, fraction, c=c):  # the components in turn
            progress(stage, (c + fraction) / len(scenes))

        parts.append(precompute(single, volume, quality, store, part_progress, chunks, **build_overrides))
    rkey = keys["radiance_key"]
    radiance = np.concatenate([p.radiance for p in parts])  # (K N, 3): component after component
    radiance_gather = np.concatenate([p.radiance_gather for p in parts])
    # the time of what was computed now (a found part's stats hold the times it took once)
    times = {"radiance": ("lighting_s", "transport_s"), "field": ("field_s", "field_tau_s", "field_ms_s")}
    spent = {
        k: round(sum(p.stats.get(k, 0.0) for p in parts if not p.stats[f"{what}_reused"]), 3)
        for what, keys in times.items()
        for k in keys
    }
    rstats = {
        **{k: v for k, v in parts[0].stats.items() if not k.endswith("_bytes")},
        **spent,
        "light_components": len(parts),
        # components whose cache was there already: their lighting, transport and bake reused
        "components_reused": sum(p.stats["radiance_reused"] and p.stats["field_reused"] for p in parts),
        "graph_reused": all(p.stats["graph_reused"] for p in parts),
        "radiance_reused": False,
        "field_reused": False,
    }
    # The file keeps what its content is (the first component's file's stats: the graph's), not
    # what this run found or made: the same key, the same bytes
    first = read_radiance(store.radiance_path(parts[0].keys["radiance_key"]))[1]
    kept = {**first, "light_components": len(parts)}
    store.save_radiance(rkey, radiance_file(pack_radiance(radiance, radiance_gather), kept))
    field = combined([p.field for p in parts], rkey, Lights.of(scene).sun_base)
    field_data = field.encode()
    store.save_field(rkey, field_data)
    progress("done", 1.0)
    paths = {
        "graph": store.graph_path(keys["graph_key"]),
        "radiance": store.radiance_path(rkey),
        "field": store.field_path(rkey),
    }
    stats = {**rstats, **{f"{kind}_bytes": _size(path) for kind, path in paths.items()}}
    return RadianceCache(radiance, radiance_gather, field_data, keys, stats, store, parts[0]._graph)


def without_sun(L_gather: np.ndarray, L_d: np.ndarray, lights: Lights) -> np.ndarray:
    """(N, 3 K) ``gather``'s node radiance of the isotropic phase: L' with one event fewer, less
    the directional lights' direct radiance L_d, which ``gather`` and the field's bake take
    exactly where they look the graph up (the second scattering event: params.suns_apart). A
    node's L_d is the light at its position, but the points looked up near it lie around it,
    where the light falls by exp(-tau) across the node (docs/method.md)."""
    suns = np.repeat([lights.kind(c) == "directional" for c in range(lights.count)], 3)
    return np.where(suns, np.maximum(L_gather - L_d, 0.0), L_gather)


def stack_components(L: np.ndarray, k: int) -> np.ndarray:
    """(K N, 3) node radiance, component after component, of (N, 3 K) with the K side by side
    (the radiance file's rows: for one component, the (N, 3) array itself)."""
    n = len(L)
    return L if k == 1 else L.reshape(n, k, 3).transpose(1, 0, 2).reshape(k * n, 3)


def _size(path) -> int:
    """Bytes of a cache file; 0 once evicted."""
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0
