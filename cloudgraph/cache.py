"""Content keys and the on-disk cache store (docs/method.md, "Cache levels and keys").

Keys are sha256 of canonical JSON with the engine format version included:
- volume id: the density values and the transform;
- graph key: volume id + density_scale + build parameters; for an anisotropic phase the
  density_scale of the similarity-scaled medium whose graph it is (``MediumSpec.graph_medium``);
- radiance key: graph key + albedo + light + max_depth (+ lighting parameters), and the phase
  when it is not isotropic (an isotropic scene keeps its v1 keys).

Files (graph_file.py, field_file.py) are written to a temporary name in the same folder and
renamed into place, so a reader never sees a half-written cache.
"""

from __future__ import annotations

import hashlib
import json
import os
import weakref
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import ENGINE_FORMAT_VERSION
from .files import default_cache_dir, write_atomic
from .lights import Lights
from .params import LIGHTING, BuildParams

if TYPE_CHECKING:  # the API process imports this module; it must not load the renderer
    from .scene import Scene
    from .volume import Volume


def _digest(obj) -> str:
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def volume_id(volume: Volume, version: int = ENGINE_FORMAT_VERSION) -> str:
    """Content hash of the density values, their index placement and the world transform (with
    the engine format ``version``: a new engine gets new keys)."""
    h = hashlib.sha256()
    h.update(f"cloudgraph-volume-v{version}".encode())
    h.update(np.asarray(volume.shape, np.int64).tobytes())
    h.update(np.asarray(volume.index_min, np.int64).tobytes())
    h.update(np.round(volume.index_to_world, 9).astype(np.float64).tobytes())
    h.update(np.ascontiguousarray(volume.density, np.float32).tobytes())
    return h.hexdigest()


def graph_key(vol_id: str, density_scale: float, build_params: dict) -> str:
    return _digest(
        {
            "v": ENGINE_FORMAT_VERSION,
            "volume": vol_id,
            "density_scale": float(density_scale),
            "build": build_params,
        }
    )


#: The bake of an anisotropic phase's field (field.py): 2 since its L_ms depends on the view
#: (``ms_shape``), 3 since the sun's light in its beam is the march's in closed form
#: (``ms_forward``), 4 since the view terms are kept over the sun's light factor (``light_power``),
#: 5 since they hold the degree-3 harmonics at half weight (20 terms, phase.SHAPE_TERMS), 6 since
#: the walks also estimate the sun's light by flights drawn about it (phase.SUN_LOBE_NEE), 7
#: since they take the beam's orders as a control variate (phase.BEAM_CV_ORDERS), 8 since a
#: large cloud's grid is finer, with fewer walks a point (field.MS_WALK_POINTS), and the light
#: factor's P_0 is the walks' own (field_ms.WALK_LIGHT_POWER_0), 9 since the degree-3 harmonics
#: are at three quarters of their weight (phase.SHAPE_HALF), 10 since the walks take only the
#: points that the camera's interpolation reads (field_grid.read_mask), 11 since they keep fewer
#: walks outside the medium and deep inside it (field_ms.OUTSIDE_SHARE, DEEP_SHARE), 12 since the
#: points next to those take the nearest one's value (the march reads them a step past the
#: medium), 13 since a large medium's G is looked up on a grid coarser than the field's
#: (field.lookup_grid; isotropic fields baked before stay, as before).
#: Its caches' radiance keys hold it, so that fields baked before are baked again; isotropic keys
#: are as they were.
PHASE_FIELD_VERSION = 13


def radiance_key(
    g_key: str,
    albedo,
    light_dir,
    irradiance,
    max_depth: int,
    lighting: dict,
    phase_lobes=None,
    lights=None,
) -> str:
    """``phase_lobes``: ((weight, g), ...) of an anisotropic phase (``PhaseSpec.lobes``), None for
    the isotropic one, whose keys stay as they were before phases. ``lights``: the v1.1 light
    list's :meth:`~cloudgraph.lights.Lights.key` (kinds and directions: such a cache holds unit
    components), in place of the one light's direction and irradiance."""
    doc = {
        "v": ENGINE_FORMAT_VERSION,
        "graph": g_key,
        "albedo": np.broadcast_to(np.asarray(albedo, float), (3,)).round(9).tolist(),
        "max_depth": int(max_depth),
        "lighting": lighting,
    }
    if lights is None:
        unit = np.asarray(light_dir, float) / np.linalg.norm(light_dir)
        doc["light_dir"] = unit.round(9).tolist()
        doc["irradiance"] = np.broadcast_to(np.asarray(irradiance, float), (3,)).round(9).tolist()
    else:
        doc["lights"] = lights
    if phase_lobes is not None:
        doc["phase"] = np.asarray(phase_lobes, float).round(9).tolist()
        doc["phase_field"] = PHASE_FIELD_VERSION
    return _digest(doc)


_VOLUME_IDS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def cache_keys(scene: Scene, volume: Volume, params: BuildParams) -> dict:
    """volume_id, graph_key and radiance_key of a scene (the volume's hash is kept per object)."""
    vid = _VOLUME_IDS.get(volume)
    if vid is None:
        vid = _VOLUME_IDS[volume] = volume_id(volume)
    phase, lights = scene.medium.phase, Lights.of(scene)
    # An anisotropic phase's graph is that of its similarity-scaled medium (docs/method.md,
    # "Anisotropic scattering"): keyed by that medium's density_scale, so that a new g (or, for
    # such a phase, a new albedo) builds its own graph
    gkey = graph_key(vid, scene.medium.graph_medium()[0], params.to_dict())
    rkey = radiance_key(
        gkey,
        scene.medium.albedo_rgb(),
        scene.light.unit_direction(),
        scene.light.irradiance_rgb(),
        scene.render.max_depth,
        LIGHTING,
        None if phase.isotropic else phase.lobes(),
        lights.key() if lights.basis else None,
    )
    return {"volume_id": vid, "graph_key": gkey, "radiance_key": rkey}


class CacheStore:
    """Graph, radiance and field files under one folder, keyed by content: where each lives, and
    their bytes. The API process reads it too (it serves fields), so it decodes nothing."""

    def __init__(self, root: str | Path | None = None):
        self.root = Path(root) if root is not None else default_cache_dir()

    def graph_path(self, key: str) -> Path:
        return self.root / "graphs" / f"{key}.npz"

    def radiance_path(self, key: str) -> Path:
        return self.root / "radiance" / f"{key}.npz"

    def field_path(self, key: str) -> Path:
        """The radiance field of a radiance key: gzip-compressed bytes (``cloudgraph/field.py``)."""
        return self.root / "fields" / f"{key}.cgf.gz"

    # Files are written whole (files.py); their contents are graph_file.py's and field_file.py's.
    def save_graph(self, key: str, data: bytes) -> Path:
        """A graph file: :func:`~cloudgraph.graph_file.graph_file`'s bytes."""
        return write_atomic(self.graph_path(key), data)

    def save_radiance(self, key: str, data: bytes) -> Path:
        """A radiance file: :func:`~cloudgraph.graph_file.radiance_file`'s bytes."""
        return write_atomic(self.radiance_path(key), data)

    def save_field(self, key: str, data: bytes) -> Path:
        return write_atomic(self.field_path(key), data)

    def load_field(self, key: str) -> bytes | None:
        path = self.field_path(key)
        try:
            os.utime(path)  # last use, for least-recently-used eviction
            return path.read_bytes()
        except FileNotFoundError:
            return None
