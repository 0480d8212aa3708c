"""A scene's lights as the cache keeps them: components whose radiance is kept apart and mixed.

Transport is linear, so a cache holds one radiance per light *component*: each directional light
in the list's order, then one for the sky (all ``sky`` lights share it: a uniform environment of
any colour is the same component times its radiance). What a component holds:

- a v1 scene (one ``light``): the light's radiance at its irradiance, as before v1.1 (its keys
  and files unchanged);
- a v1.1 scene (``lights``): each component at unit intensity (white, 1), and the scene's
  intensities mix them at render time. The radiance key then holds the lights' directions and
  kinds only: new intensities or colours of the same lights are the same cache, re-mixed, with
  no solve (docs/method.md, "Several lights").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scene import LightSpec, Scene


@dataclass(frozen=True)
class Lights:
    """The light components of a scene.

    Attributes:
        directions: (D, 3) unit directions the directional components travel.
        sky: whether the last component is the sky's.
        intensity: (K, 3) each component's irradiance (directional) or radiance (sky), RGB;
            K = D + sky.
        basis: whether caches hold the components at unit intensity (v1.1 ``lights``) or at
            their intensity (a v1 ``light``).
    """

    directions: np.ndarray
    sky: bool
    intensity: np.ndarray
    basis: bool

    @classmethod
    def of(cls, scene: Scene) -> Lights:
        lights = scene.light_list()
        directional = [li for li in lights if isinstance(li, LightSpec)]
        skies = [li for li in lights if not isinstance(li, LightSpec)]
        intensity = [li.intensity_rgb() for li in directional]
        if skies:
            intensity.append(tuple(np.sum([s.intensity_rgb() for s in skies], axis=0)))
        return cls(
            directions=np.array([li.unit_direction() for li in directional], float).reshape(-1, 3),
            sky=bool(skies),
            intensity=np.array(intensity, float).reshape(-1, 3),
            basis=scene.lights is not None,
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
        return self.intensity[-1] if self.sky else np.zeros(3)

    def key(self) -> list:
        """What the radiance key holds of v1.1 lights: kinds and directions, no intensities."""
        doc = [{"directional": d.round(9).tolist()} for d in self.directions]
        return doc + ([{"sky": True}] if self.sky else [])

    def mixed(self, components: np.ndarray) -> np.ndarray:
        """(..., 3) sum over k of mix[k] * components[k], for (K, ..., 3) cached components."""
        c = np.asarray(components)
        m = self.mix.reshape((self.count,) + (1,) * (c.ndim - 2) + (3,))
        return (c * m.astype(c.dtype)).sum(axis=0)
