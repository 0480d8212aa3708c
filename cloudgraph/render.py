"""One entry point to render a scene spec with either integrator, shared by CLI and worker."""

from __future__ import annotations

import numpy as np

from .errors import SceneError
from .scene import Scene
from .volume import Volume, load_volume


def scene_volume(scene: Scene) -> Volume:
    """Loads the scene's volume from ``volume.path`` (ids are resolved by the service)."""
    if scene.volume.path is None:
        raise SceneError("volume.path is required here (volume ids are for the HTTP API)")
    return load_volume(scene.volume.path, scene.volume.grid, scene.volume.scale)


def render_volpath(scene: Scene, volume: Volume, rr: bool = False) -> np.ndarray:
    """Mitsuba's volpath on the scene: (H, W, 3) float32 linear radiance. RR off by default."""
    import mitsuba as mi

    from .mitsuba_scene import load_mitsuba_scene, volpath_dict

    mscene = load_mitsuba_scene(scene, volume, volpath_dict(scene.render.max_depth, rr=rr))
    return np.array(mi.render(mscene, seed=scene.render.seed), dtype=np.float32)
