"""A ``sunsky`` light (scene spec v1.1) as the engine takes it: a directional sun and an
environment map of the sky, both made from Mitsuba's own ``sunsky`` emitter (the Hosek-Wilkie
sky and its sun), so that every estimator, the field and the page take them as they take any
sun and map, and volpath renders the model itself (mitsuba_scene.py).

- The sun: a directional light travelling along -``sun_direction``, of the irradiance of the
  model's sun disk (0.27 degrees across: its radiance times its solid angle, RGB), times
  ``sun_scale``. A disk that small lights a cloud as a point does.
- The sky: the model's sky radiance (the sun left out) at the texel centres of a lat-long map of
  SKY_WIDTH x SKY_WIDTH / 2 (image.latlong_directions: Mitsuba's ``envmap`` orientation), written
  once as an .exr under the sky folder (:func:`sky_dir`), named by the sky's parameters; times
  ``sky_scale``. The folder's files are made again wherever they are missing.

Mitsuba's ``sunsky`` has +z up; the emitter is turned to the spec's ``up`` (:func:`sky_to_world`;
its ``sun_direction`` stays in world space). The model's sky is a function of the angles to the
zenith and to the sun only, so the turn about ``up`` is free.
"""

from __future__ import annotations

import hashlib
import json
import os
from functools import lru_cache
from pathlib import Path

import numpy as np

from .files import atomic_writer, default_cache_dir
from .image import latlong_directions
from .scene import EnvmapSpec, LightSpec, SunskySpec

#: Width of the sky's lat-long map (height half of it): a texel is 1.4 degrees. The sky brightens
#: toward the sun over tens of degrees and is smooth elsewhere.
SKY_WIDTH = 256
#: The sky map's format, in its file's name: a change makes new files (and caches).
SKY_VERSION = 1


def sky_dir() -> Path:
    """Where sky maps are kept: $CLOUDGRAPH_SKY_DIR, or ``skies`` in the cache folder."""
    return Path(os.environ.get("CLOUDGRAPH_SKY_DIR") or default_cache_dir() / "skies")


def sky_to_world(up) -> list:
    """(4, 4) a rotation that takes Mitsuba's sunsky zenith (+z) to ``up`` (unit)."""
    z = np.asarray(up, float)
    x = np.cross((0.0, 0.0, 1.0) if abs(z[2]) < 0.9 else (1.0, 0.0, 0.0), z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)  # columns: the local axes in the world
    return m.tolist()


def sunsky_dict(spec: SunskySpec, sun: bool = True, sky: bool = True) -> dict:
    """Mitsuba's ``sunsky`` emitter of the spec (its sun and its sky, or either alone), turned
    to the scene's zenith."""
    import mitsuba as mi

    return {
        "type": "sunsky",
        "sun_direction": list(spec.unit_sun_direction()),
        "turbidity": float(spec.turbidity),
        "albedo": float(spec.ground_albedo),
        "sun_scale": float(spec.sun_scale) if sun else 0.0,
        "sky_scale": float(spec.sky_scale) if sky else 0.0,
        "to_world": mi.ScalarTransform4f(sky_to_world(spec.unit_up())),
    }


def _unit(spec: SunskySpec) -> SunskySpec:
    return spec.model_copy(update={"sun_scale": 1.0, "sky_scale": 1.0})


def sun_irradiance(spec: SunskySpec) -> np.ndarray:
    """(3,) RGB irradiance of the model's sun at sun_scale 1 (facing it): the mean weight
    (radiance over density) of directions Mitsuba samples on the disk."""
    import mitsuba as mi

    key = (spec.unit_sun_direction(), spec.unit_up(), spec.turbidity, spec.ground_albedo, mi.variant())
    return np.array(_sun_irradiance(*key))


@lru_cache(maxsize=64)
def _sun_irradiance(direction, up, turbidity, ground_albedo, variant) -> tuple:
    import drjit as dr
    import mitsuba as mi

    spec = SunskySpec(sun_direction=direction, up=up, turbidity=turbidity, ground_albedo=ground_albedo)
    emitter = mi.load_dict(sunsky_dict(spec, sky=False))
    n = 4096
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, n)
    _, weight = emitter.sample_direction(dr.zeros(mi.Interaction3f, n), sampler.next_2d(), mi.Bool(True))
    # (at the horizon the model's sun may read a hair below 0 in a channel)
    return tuple(max(0.0, float(c)) for c in np.array(weight, np.float64).reshape(3, n).mean(axis=1))


def sky_map(spec: SunskySpec, width: int = SKY_WIDTH) -> np.ndarray:
    """(width // 2, width, 3) float32 the model's sky radiance (no sun, sky_scale 1) seen along
    each texel centre's direction of a lat-long map (image.latlong_directions)."""
    import drjit as dr
    import mitsuba as mi

    emitter = mi.load_dict(sunsky_dict(_unit(spec), sun=False))
    d = latlong_directions(width).reshape(-1, 3).astype(np.float32)
    si = dr.zeros(mi.SurfaceInteraction3f, len(d))
    si.wi = -mi.Vector3f(*(mi.Float(np.ascontiguousarray(d[:, i])) for i in range(3)))
    radiance = np.array(emitter.eval(si), np.float32).reshape(3, -1)
    return np.ascontiguousarray(radiance.T.reshape(width // 2, width, 3))


def sky_file(spec: SunskySpec) -> str:
    """The path of the sky's map (an .exr in :func:`sky_dir`), made if it is not there."""
    key = {
        "version": SKY_VERSION,
        "width": SKY_WIDTH,
        "sun_direction": [round(c, 9) for c in spec.unit_sun_direction()],
        "up": [round(c, 9) for c in spec.unit_up()],
        "turbidity": spec.turbidity,
        "ground_albedo": spec.ground_albedo,
    }
    name = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:24]
    path = sky_dir() / f"sky-{name}.exr"
    if not path.is_file():
        import mitsuba as mi

        bitmap = mi.Bitmap(sky_map(spec), mi.Bitmap.PixelFormat.RGB)
        with atomic_writer(path) as f:  # (written whole: another worker may read it)
            f.write(_exr_bytes(bitmap))
    return str(path)


def _exr_bytes(bitmap) -> bytes:
    import mitsuba as mi

    stream = mi.MemoryStream()
    bitmap.write(stream, mi.Bitmap.FileFormat.OpenEXR)
    return bytes(stream.raw_buffer())


def sun_light(spec: SunskySpec) -> LightSpec:
    """The sunsky's sun as a directional light: along -sun_direction, at the model's irradiance
    times sun_scale."""
    E = tuple(float(c) for c in sun_irradiance(spec) * spec.sun_scale)
    return LightSpec(direction=tuple(-c for c in spec.unit_sun_direction()), irradiance=E)


def sky_light(spec: SunskySpec) -> EnvmapSpec:
    """The sunsky's sky as an environment map (:func:`sky_file`) at sky_scale."""
    return EnvmapSpec(path=sky_file(spec), scale=spec.sky_scale)


def expanded(lights) -> tuple:
    """A light list with each ``sunsky`` light as its sun and its sky (:func:`sun_light`,
    :func:`sky_light`), in its place; other lights as they are. A variant must be set where
    there is a sunsky light."""
    out = []
    for light in lights:
        out += [sun_light(light), sky_light(light)] if light.type == "sunsky" else [light]
    return tuple(out)
