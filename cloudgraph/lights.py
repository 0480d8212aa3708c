"""A scene's lights as the cache keeps them: components whose radiance is kept apart and mixed.

Transport is linear, so a cache holds one radiance per light *component*: each directional light
in the list's order, then one for the sky (all ``sky`` lights share it: a uniform environment of
any colour is the same component times its radiance), then each environment map in the list's
order. A ``sunsky`` light is two components: its sun among the directional ones and its sky
among the maps, each in the light's place (sunsky.py). What a component holds:

- a v1 scene (one ``light``): the light's radiance at its irradiance, as before v1.1 (its keys
  and files unchanged);
- a v1.1 scene (``lights``): each component at unit intensity (white, 1), and the scene's
  intensities mix them at render time. The radiance key then holds the lights' directions and
  kinds only: new intensities or colours of the same lights are the same cache, re-mixed, with
  no solve (docs/method.md, "Several lights"). A sunsky's sun keys its colour at sun_scale 1
  too (``base``): the field's header carries it, and the page mixes that sun by sun_scale.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from .errors import SceneError
from .scene import EnvmapSpec, LightSpec, Scene, SkySpec
from .sunsky import sky_light, sun_irradiance, sun_light

#: The light types that make a directional component, and an environment map's.
SUNS, MAPS = ("directional", "sunsky"), ("envmap", "sunsky")


@dataclass(frozen=True)
class Lights:
    """The light components of a scene.

    Attributes:
        directions: (D, 3) unit directions the directional components travel.
        sky: whether the component after the directional ones is the sky's.
        intensity: (K, 3) each component's irradiance (directional), radiance (sky) or scale
            (envmap), RGB; K = D + sky + E.
        basis: whether caches hold the components at unit intensity (v1.1 ``lights``) or at
            their intensity (a v1 ``light``).
        envmaps: the E environment maps' files (.exr), the last components.
        sun_base: (D, 3) each directional component's colour at its light's scale 1: 1, or
            a ``sunsky`` sun's irradiance (its intensity is that times sun_scale).
    """

    directions: np.ndarray
    sky: bool
    intensity: np.ndarray
    basis: bool
    envmaps: tuple[str, ...]
    sun_base: np.ndarray

    @classmethod
    def of(cls, scene: Scene) -> Lights:
        """The scene's components; a ``sunsky`` light is its sun, a directional component, and
        its sky, an environment map (sunsky.py), each in the light's place among its kind."""
        lights = scene.light_list()
        suns = [sun_light(li) if li.type == "sunsky" else li for li in lights if li.type in SUNS]
        skies = [li for li in lights if li.type == "sky"]
        envmaps = [sky_light(li) if li.type == "sunsky" else li for li in lights if li.type in MAPS]
        if any(e.path is None for e in envmaps):
            raise SceneError("an envmap light needs its 'path' here (ids are for the HTTP API)")
        intensity = [li.intensity_rgb() for li in suns]
        if skies:
            intensity.append(tuple(np.sum([s.intensity_rgb() for s in skies], axis=0)))
        intensity += [e.intensity_rgb() for e in envmaps]
        # a sunsky's sun: its colour at sun_scale 1, which the page's mixer scales (api.md)
        base = [sun_irradiance(li) if li.type == "sunsky" else (1.0,) * 3 for li in lights if li.type in SUNS]
        return cls(
            directions=np.array([li.unit_direction() for li in suns], float).reshape(-1, 3),
            sky=bool(skies),
            intensity=np.array(intensity, float).reshape(-1, 3),
            basis=scene.lights is not None,
            envmaps=tuple(e.path for e in envmaps),
            sun_base=np.array(base, float).reshape(-1, 3),
        )

    @property
    def count(self) -> int:
        """K, the number of components."""
        return len(self.intensity)

    @property
    def cached(self) -> np.ndarray:
        """(K, 3) the intensity each component has in the cache: 1, or the light's (v1)."""
        return np.ones_like(self.intensity) if self.basis else self.intensity

    @property
    def mix(self) -> np.ndarray:
        """(K, 3) the factors that turn the cached components into the scene's light."""
        return self.intensity if self.basis else np.ones_like(self.intensity)

    @property
    def sky_radiance(self) -> np.ndarray:
        """(3,) the sky's radiance (0 without a sky)."""
        return self.intensity[len(self.directions)] if self.sky else np.zeros(3)

    @property
    def envmap_scale(self) -> np.ndarray:
        """(E, 3) each environment map's scale."""
        return self.intensity[len(self.intensity) - len(self.envmaps) :]

    def kind(self, k: int) -> str:
        """Component k's kind: ``directional``, ``sky`` or ``envmap``."""
        d = len(self.directions)
        return "directional" if k < d else "sky" if self.sky and k == d else "envmap"

    def key(self) -> list:
        """What the radiance key holds of v1.1 lights: kinds and directions (an environment
        map: its file's sha256), no intensities."""
        doc = [{"directional": d.round(9).tolist()} for d in self.directions]
        for entry, base in zip(doc, self.sun_base, strict=True):
            if not np.all(base == 1.0):  # a sunsky's sun: the page mixes it by sun_scale alone
                entry["base"] = base.round(6).tolist()
        doc += [{"sky": True}] if self.sky else []
        return doc + [{"envmap": file_digest(path)} for path in self.envmaps]

    def mixed(self, components: np.ndarray) -> np.ndarray:
        """(..., 3) sum over k of mix[k] * components[k], for (K, ..., 3) cached components."""
        c = np.asarray(components)
        m = self.mix.reshape((self.count,) + (1,) * (c.ndim - 2) + (3,))
        return (c * m.astype(c.dtype)).sum(axis=0)


def component_scenes(scene: Scene) -> list[Scene]:
    """Per light component of a v1.1 scene (Lights.of's order: the directional lights, the sky,
    the environment maps), the scene lit by that component alone at unit intensity: its own
    cache is that component's (transport and the bake are linear in the light)."""
    lights = Lights.of(scene)
    specs = [LightSpec(direction=tuple(d)) for d in lights.directions]
    specs += [SkySpec()] if lights.sky else []
    specs += [EnvmapSpec(path=path) for path in lights.envmaps]
    return [scene.model_copy(update={"lights": (spec,)}) for spec in specs]


@lru_cache(maxsize=64)
def _digest(path: str, mtime_ns: int, size: int) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def file_digest(path: str) -> str:
    """sha256 of a file's bytes (kept per path, size and modification time).

    Raises:
        SceneError: the file cannot be read.
    """
    try:
        st = Path(path).stat()
        return _digest(str(path), st.st_mtime_ns, st.st_size)
    except OSError as err:
        raise SceneError(f"cannot read the environment map {path}: {err.strerror}") from None
