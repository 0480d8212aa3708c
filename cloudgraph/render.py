"""Rendering a scene spec with either integrator, shared by the CLI, the worker and the bench:
Mitsuba's volpath (:func:`render_volpath`, the reference) or the graph radiance cache
(:class:`GraphRenderer`, :func:`render_graph`).
"""

from __future__ import annotations

import mitsuba as mi
import numpy as np

from .edges import REFINE_SIDE, edge_pixels, refine_lanes, refined, strata_positions
from .errors import SceneError
from .graph import gradient_operators, node_gradients
from .lights import Lights
from .mitsuba_scene import load_mitsuba_scene, sensor_dict, volpath_dict
from .options import ESTIMATORS
from .params import GRADIENT, suns_apart
from .precompute import precompute
from .scene import Scene
from .spatial import NodeGrid
from .tracing import DensityField, cpu_threads, linear_texture
from .volume import Volume, load_volume


def scene_volume(scene: Scene) -> Volume:
    """Loads the scene's volume from ``volume.path`` (ids are resolved by the service)."""
    if scene.volume.path is None:
        raise SceneError("volume.path is required here (volume ids are for the HTTP API)")
    return load_volume(scene.volume.path, scene.volume.grid, scene.volume.scale)


def render_volpath(scene: Scene, volume: Volume, rr: bool = False) -> np.ndarray:
    """Mitsuba's volpath on the scene: (H, W, 3) float32 linear radiance. RR off by default."""
    mscene = load_mitsuba_scene(scene, volume, volpath_dict(scene.render.max_depth, rr=rr))
    return np.array(mi.render(mscene, seed=scene.render.seed), dtype=np.float32)


class GraphRenderer:
    """A radiance cache loaded for rendering: any camera, any estimator, kernels reused.

    One integrator is made per estimator when first asked for (the ``field`` estimator needs no
    node grid, the others no field), and one Mitsuba scene per (image size, estimator); a new
    camera only updates the sensor's parameters, which Mitsuba passes to the kernels as opaque
    values. A cache of v1.1 ``lights`` holds each light apart (lights.py): a render with new
    intensities or colours of the same lights re-mixes them, with no solve and no recompile.
    """

    def __init__(self, cache, volume, scene, estimator: str = "gather", step: float | None = None):
        self.cache, self.volume, self.estimator, self.step = cache, volume, estimator, step
        self.medium = DensityField.from_volume(volume, scene.medium.density_scale)
        self.albedo, self.lights = scene.medium.albedo_rgb(), Lights.of(scene)
        self.phase, self.max_depth = scene.medium.phase, scene.render.max_depth
        self._integrators: dict = {}
        self._scenes: dict[tuple, tuple] = {}
        self._gradient_op = None

    def integrator(self, estimator: str):
        """The integrator of one estimator, made (and its node grid or field uploaded) once."""
        if estimator not in ESTIMATORS:
            raise ValueError(f"unknown estimator {estimator!r}; choose one of {', '.join(ESTIMATORS)}")
        if estimator not in self._integrators:
            # The plugin subclasses a variant's class, so it is imported once a variant is set
            # (entry points set it after importing this module)
            from .field_textures import FieldTextures
            from .integrators.graph import GraphIntegrator

            grid = field = None
            if estimator == "field":
                field = FieldTextures.from_field(self.cache.field, self.lights)
            else:
                positions, search_radius = self.cache.nodes  # the counts stay on disk
                radiance = self._node_radiance(estimator)
                grid = NodeGrid.build(
                    positions, search_radius, radiance, gradient=self._gradient(estimator, radiance)
                )
            integrator = GraphIntegrator(mi.Properties())
            integrator.set_cache(
                self.medium, self.albedo, self.lights, estimator, grid, field, self.cache.stats["radius"],
                self.step, self.phase, self.max_depth,
            )  # fmt: skip
            self._integrators[estimator] = integrator
        return self._integrators[estimator]

    def _node_radiance(self, estimator: str) -> np.ndarray:
        """(N, 3) the nodes' radiance in the renderer's light (the components mixed)."""
        radiance = self.cache.radiance_gather if estimator == "gather" else self.cache.radiance
        if not self.lights.basis:
            return radiance
        return self.lights.mixed(radiance.reshape(self.lights.count, -1, 3))

    def _gradient(self, estimator: str, radiance: np.ndarray) -> np.ndarray | None:
        """(N, 3, 3) the nodes' radiance gradient, by the operator transport reads each edge
        with (graph.gradient_operators, params.GRADIENT; made once), where the estimator's node
        radiance is without the suns' direct light (params.suns_apart; else None)."""
        if estimator != "gather" or not suns_apart(self.phase.isotropic, self.max_depth):
            return None
        if self._gradient_op is None:
            self._gradient_op = gradient_operators(*self.cache.nodes, **GRADIENT, workers=cpu_threads())
        return node_gradients(self._gradient_op, radiance)

    def set_lights(self, lights: Lights) -> None:
        """New intensities or colours for the cache's lights (:meth:`Lights.of` a scene whose
        lights are those of the cache): the loaded estimators' node radiance and field are
        re-mixed in place, nothing is solved or compiled again."""
        if lights.basis != self.lights.basis or lights.key() != self.lights.key():
            raise SceneError("these lights are not the cache's: a new light list needs its own precompute")
        if not lights.basis or np.array_equal(lights.intensity, self.lights.intensity):
            return
        self.lights = lights
        for estimator, integrator in self._integrators.items():
            integrator.set_intensities(lights)
            if estimator == "field":
                rest = integrator.field.mixed_ms(self.cache.field, lights)  # (the suns' are opaque)
                integrator.field.ms = None if rest is None else linear_texture(rest)
            else:
                radiance = self._node_radiance(estimator)
                integrator.grid.set_radiance(radiance, self._gradient(estimator, radiance))

    def render(
        self,
        camera,
        spp: int,
        seed: int = 0,
        estimator: str | None = None,
        lights: Lights | None = None,
        refine: bool = True,
    ) -> np.ndarray:
        """(H, W, 3) float32 linear radiance for a :class:`~cloudgraph.scene.CameraSpec`, in the
        renderer's light or ``lights`` (the cache's lights, new intensities: :meth:`set_lights`).
        A ``field`` frame of fewer than REFINE_SIDE² samples a pixel has its edges refined
        (edges.py) unless ``refine`` is False."""
        if lights is not None:
            self.set_lights(lights)
        estimator = estimator or self.estimator
        sensor = sensor_dict(camera, self.volume, spp, seed)
        # Stratified positions in the pixel: the box filter's integral with far less noise at a
        # few samples (a back-lit dense cloud's thin bright rim: 10 % binned relMAE at 16 spp
        # with independent positions, 6 % stratified). The field's march has no noise of its
        # own to hide: its positions are the strata's centres, a regular grid in the pixel (the
        # bench's thick cloud back-lit, single scattering at 16 spp: 2.61 % binned relMAE
        # jittered, 1.48 % regular; at 1 spp, the pixel's centre, 23.3 % and 12.9 %)
        sensor["sampler"] = {
            "type": "stratified",
            "sample_count": int(spp),
            "seed": int(seed),
            "jitter": estimator != "field",
        }
        key = (camera.width, camera.height, estimator)
        if key not in self._scenes:
            integrator = self.integrator(estimator)
            mscene = mi.load_dict({"type": "scene", "integrator": integrator, "sensor": sensor})
            self._scenes[key] = (mscene, mi.traverse(mscene))
        mscene, params = self._scenes[key]
        params["sensor.to_world"] = sensor["to_world"]
        params["sensor.x_fov"] = sensor["fov"]
        # near_clip and far_clip are plain floats that Mitsuba compiles into the kernel: they stay
        # as the first camera set them (this integrator clips rays to the medium box itself).
        params.update()
        if estimator == "field":  # (a field with view terms sums them toward this camera)
            self.integrator(estimator).field.look_from(camera.eye)
        image = np.array(mi.render(mscene, spp=spp, seed=seed), dtype=np.float32)
        if estimator == "field" and refine and spp < REFINE_SIDE**2:
            # The pixels that one ray (or a few) at fixed places cannot stand for: a rim thinner
            # than a pixel, marched again at REFINE_SIDE² strata's centres (edges.py)
            # (at one sample a pixel its ray is the middle stratum's: 8 more rays, not 9)
            mask, centre = edge_pixels(image), spp == 1 and REFINE_SIDE % 2 == 1
            if mask.any():
                lanes = refine_lanes(camera.width, camera.height, centre=centre)
                positions = strata_positions(mask, centre=centre)
                field = self.integrator(estimator)
                samples = field.field_at_film(mscene.sensors()[0], positions, seed, lanes)
                image = refined(image, mask, samples, centre)
        return image


def render_graph(
    scene, volume, quality: str = "default", store=None, estimator: str = "gather", progress=None
) -> np.ndarray:
    """Renders a scene spec from its radiance cache, building the cache first if it is missing."""
    cache = precompute(scene, volume, quality, store, progress)
    renderer = GraphRenderer(cache, volume, scene, estimator)
    return renderer.render(scene.camera, scene.render.spp, scene.render.seed)
