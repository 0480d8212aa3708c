"""Scene spec -> Mitsuba scene: a medium in a null-BSDF box, a directional light, a pinhole camera.

Variant selection lives here too; entry points (CLI, worker start, test fixtures) call
:func:`set_variant` once, never an import.
"""

from __future__ import annotations

import os

import numpy as np

from .errors import SceneError
from .scene import CameraSpec, PhaseSpec, Scene, envmap_problem
from .sunsky import expanded, sunsky_dict
from .volume import Volume

#: Russian roulette depth that turns roulette off in practice (docs/method.md, "What is known about
#: accuracy": default RR is firefly-ridden and biased low in thick albedo-1 clouds).
RR_OFF = 100000


def set_variant(variant: str | None = None) -> str:
    """Chooses the Mitsuba variant: the argument, else ``CLOUDGRAPH_VARIANT``, else
    ``cuda_ad_rgb`` when a CUDA GPU is present, else ``llvm_ad_rgb``. Returns the variant."""
    import drjit as dr
    import mitsuba as mi

    variant = variant or os.environ.get("CLOUDGRAPH_VARIANT")
    if not variant:
        variant = "cuda_ad_rgb" if dr.has_backend(dr.JitBackend.CUDA) else "llvm_ad_rgb"
    if mi.variant() != variant:
        mi.set_variant(variant)
    return variant


def mitsuba_max_depth(max_depth: int) -> int:
    """Scene spec depth (most scattering events, -1 unbounded) -> Mitsuba's path depth,
    where 1 means directly visible emitters only and 2 single scattering."""
    return -1 if max_depth < 0 else max_depth + 1


def medium_dict(volume: Volume, scene: Scene) -> dict:
    """Mitsuba ``heterogeneous`` medium: sigma_t = density * density_scale, constant albedo, the
    scene's phase function."""
    import mitsuba as mi

    grid = np.ascontiguousarray(volume.density.transpose(2, 1, 0)[..., None], np.float32)  # (z, y, x, 1)
    return {
        "type": "heterogeneous",
        "sigma_t": {
            "type": "gridvolume",
            "grid": mi.VolumeGrid(grid),
            "filter_type": "trilinear",
            "to_world": mi.ScalarTransform4f(volume.unit_to_world.tolist()),
        },
        "albedo": {"type": "constvolume", "value": {"type": "rgb", "value": list(scene.medium.albedo_rgb())}},
        "scale": float(scene.medium.density_scale),
        "phase": phase_dict(scene.medium.phase),
    }


def phase_dict(phase: PhaseSpec) -> dict:
    """Mitsuba's phase function of a scene's: ``isotropic``, ``hg`` (the same sign of g), or for
    ``hg2`` a ``blendphase`` of two ``hg``, whose ``weight`` is the *second* one's."""
    if phase.type == "isotropic":
        return {"type": "isotropic"}
    if phase.type == "hg":
        return {"type": "hg", "g": float(phase.g)}
    g1, g2 = phase.g
    return {
        "type": "blendphase",
        "weight": 1.0 - float(phase.weight),
        "phase1": {"type": "hg", "g": float(g1)},
        "phase2": {"type": "hg", "g": float(g2)},
    }


def box_to_world(volume: Volume) -> np.ndarray:
    """(4, 4) map from Mitsuba's cube [-1, 1]^3 onto the medium's extent."""
    cube_to_unit = np.diag([0.5, 0.5, 0.5, 1.0])
    cube_to_unit[:3, 3] = 0.5
    return volume.unit_to_world @ cube_to_unit


def sensor_dict(camera: CameraSpec, volume: Volume, spp: int, seed: int = 0) -> dict:
    """Pinhole camera with fov along the width and a box pixel filter."""
    import mitsuba as mi

    lo, hi = volume.world_bbox()
    far = float(np.linalg.norm(np.asarray(camera.eye) - (lo + hi) / 2) + np.linalg.norm(hi - lo)) * 2.0
    return {
        "type": "perspective",
        "fov": float(camera.fov),
        "fov_axis": "x",
        "near_clip": far * 1e-6,
        "far_clip": far,
        "to_world": mi.ScalarTransform4f().look_at(
            origin=list(camera.eye), target=list(camera.target), up=list(camera.up)
        ),
        "film": {
            "type": "hdrfilm",
            "width": int(camera.width),
            "height": int(camera.height),
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
            "component_format": "float32",
        },
        "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
    }


def scene_dict(scene: Scene, volume: Volume, integrator: dict | None = None) -> dict:
    """The whole Mitsuba scene as a dict for ``mi.load_dict``.

    ``integrator`` defaults to ``volpath`` with the scene's depth and Russian roulette off.
    """
    import mitsuba as mi

    if integrator is None:
        integrator = volpath_dict(scene.render.max_depth)
    lights = scene.light_list()
    sensor = sensor_dict(scene.camera, volume, scene.render.spp, scene.render.seed)
    lo, hi = volume.world_bbox()
    if np.all((np.asarray(scene.camera.eye) > lo) & (np.asarray(scene.camera.eye) < hi)):
        # a camera inside the medium's box starts in the medium (Mitsuba's rays start in the
        # sensor's medium: none, unless given, and then cross the box's faces as if from outside)
        sensor["medium"] = {"type": "ref", "id": "cloud"}
    return {
        "type": "scene",
        "integrator": integrator,
        "cloud": medium_dict(volume, scene),
        "sensor": sensor,
        # (a v1 scene's one light keeps its name: "light")
        **{"light" if i == 0 else f"light_{i}": emitter for i, emitter in enumerate(emitter_dicts(lights))},
        "medium_box": {
            "type": "cube",
            "to_world": mi.ScalarTransform4f(box_to_world(volume).tolist()),
            "bsdf": {"type": "null"},
            "interior": {"type": "ref", "id": "cloud"},
        },
    }


#: The light types that are Mitsuba environment emitters (one a scene).
ENVIRONMENTS = ("sky", "envmap", "sunsky")


def emitter_dicts(lights) -> list[dict]:
    """The scene's lights as Mitsuba's emitters (emitter_dict), in order; Mitsuba takes one
    environment emitter a scene, so several (skies, maps, a sunsky's sky) are one, their sum
    (:func:`environment_sum`), in the first one's place, and a sunsky's sun then a
    ``directional`` light (sunsky.expanded)."""
    env = [li for li in lights if li.type in ENVIRONMENTS]
    if len(env) > 1 and any(li.type == "sunsky" for li in env):  # its sky as a map, summed
        return emitter_dicts(expanded(lights))
    if len(env) <= 1:
        return [emitter_dict(li) for li in lights]
    out = []
    for li in lights:
        if li.type not in ENVIRONMENTS:
            out.append(emitter_dict(li))
        elif li is env[0]:
            out.append(environment_sum(env))
    return out


def environment_sum(env) -> dict:
    """One environment emitter whose radiance is the sum of several skies' and maps' (each map
    times its scale): a ``constant`` for skies alone, else an ``envmap`` of the summed image at
    the largest map's resolution (others resampled to it, nearest texel)."""
    import mitsuba as mi

    sky = np.sum([li.intensity_rgb() for li in env if li.type == "sky"] or [(0.0, 0.0, 0.0)], axis=0)
    maps = [li for li in env if li.type == "envmap"]
    if not maps:
        return {"type": "constant", "radiance": {"type": "rgb", "value": sky.tolist()}}
    images = [(_rgb_image(li.path), float(li.scale)) for li in maps]
    h, w = max(im.shape[0] for im, _ in images), max(im.shape[1] for im, _ in images)
    total = np.zeros((h, w, 3), np.float32) + sky.astype(np.float32)
    for im, scale in images:
        rows = (np.arange(h) * im.shape[0]) // h
        cols = (np.arange(w) * im.shape[1]) // w
        total += scale * im[rows[:, None], cols[None, :]]
    return {"type": "envmap", "bitmap": mi.Bitmap(total)}


def _rgb_image(path) -> np.ndarray:
    """(h, w, 3) float32 linear RGB of an image file, read by Mitsuba."""
    import mitsuba as mi

    try:
        bitmap = mi.Bitmap(str(path))
    except RuntimeError as err:  # Mitsuba's, with the file's problem
        raise SceneError(f"cannot read the environment map {path}: {_last_line(err)}") from err
    bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
    return np.array(bitmap, np.float32)


def emitter_dict(light) -> dict:
    """A scene light as Mitsuba's emitter: ``directional``, a ``sky`` as ``constant``, an
    ``envmap`` as ``envmap`` (its file read by Mitsuba), a ``sunsky`` as ``sunsky``."""
    if light.type == "sunsky":
        return sunsky_dict(light)
    if light.type == "sky":
        return {"type": "constant", "radiance": {"type": "rgb", "value": list(light.intensity_rgb())}}
    if light.type == "envmap":
        return {"type": "envmap", "filename": str(light.path), "scale": float(light.scale)}
    return {
        "type": "directional",
        "direction": list(light.unit_direction()),
        "irradiance": {"type": "rgb", "value": list(light.irradiance_rgb())},
    }


_ENVMAPS: dict = {}


def envmap_emitter(path: str):
    """Mitsuba's ``envmap`` emitter of an .exr file at scale 1, made once per file and process
    (a variant must be set): the engine looks environment radiance up and samples directions
    from it with Mitsuba's own code, so its orientation and importance sampling are volpath's.

    Raises:
        SceneError: the file is not an image Mitsuba can read as an environment, or its pixels
            are not radiance (scene.envmap_problem).
    """
    import mitsuba as mi

    key = (str(path), mi.variant())
    if key not in _ENVMAPS:
        check_envmap(path)
        try:
            _ENVMAPS[key] = mi.load_dict({"type": "envmap", "filename": str(path)})
        except RuntimeError as err:  # Mitsuba's, with the file's problem
            raise SceneError(f"cannot read the environment map {path}: {_last_line(err)}") from err
    return _ENVMAPS[key]


def check_envmap(path: str) -> None:
    """Reads an environment map's pixels (Mitsuba's reader) and checks them
    (scene.envmap_problem), keeping nothing.

    Raises:
        SceneError: the file cannot be read, or its pixels are not radiance.
    """
    import mitsuba as mi

    try:
        problem = envmap_problem(np.array(mi.Bitmap(str(path)), np.float32))
    except RuntimeError as err:  # Mitsuba's, with the file's problem
        raise SceneError(f"cannot read the environment map {path}: {_last_line(err)}") from err
    if problem:
        raise SceneError(f"the environment map {path} {problem}")


def volpath_dict(max_depth: int, rr: bool = False) -> dict:
    """Mitsuba's ``volpath``; ``rr`` False turns Russian roulette off (the reference setting)."""
    d = {"type": "volpath", "max_depth": mitsuba_max_depth(max_depth)}
    if not rr:
        d["rr_depth"] = RR_OFF
    return d


#: The fewest Dr.Jit worker threads :func:`set_threads` sets: with one, Mitsuba's EXR reader and
#: writer (Mitsuba 3.9.1, Dr.Jit 1.5) wait on the pool for ever, and a render to EXR or an
#: environment map hangs its worker.
MIN_THREADS = 2


def set_threads(n: int) -> int:
    """Dr.Jit's worker threads: ``n`` (0: its default, one per core), at least MIN_THREADS.
    Returns the count set (0 where the default was kept)."""
    import drjit as dr

    if n <= 0:
        return 0
    n = max(int(n), MIN_THREADS)
    dr.set_thread_count(n)
    return n


def load_mitsuba_scene(scene: Scene, volume: Volume, integrator: dict | None = None):
    """Builds the Mitsuba scene (a variant must be set).

    Raises:
        SceneError: a value Mitsuba refuses (a camera whose clip range is not finite, a depth past
            its integer range), in its own words.
    """
    import mitsuba as mi

    for light in scene.lights or ():
        if light.type == "envmap" and light.path is not None:
            if not os.path.isfile(light.path):
                raise SceneError(f"environment map not found: {light.path}")
            check_envmap(str(light.path))
    spec = scene_dict(scene, volume, integrator)
    try:
        return mi.load_dict(spec)
    except RuntimeError as err:  # Mitsuba's: the plugin, then what it refuses
        raise SceneError(f"Mitsuba refuses the scene: {_last_line(err)}") from err


def _last_line(err: Exception) -> str:
    """The last line of a Mitsuba error (its source positions come first)."""
    lines = str(err).strip().splitlines()
    return lines[-1] if lines else type(err).__name__
