"""Validation at the door: every number finite and in a documented range (api.md, "Limits"),
so that no request can ask a worker for unbounded work.

pydantic checks types and the scene spec's own rules first; these checks add what the service
needs: finite numbers, bounded coordinates and scales, image, sample and depth limits from the
settings, a grid that the volume has, and an optical depth per voxel that stays sane.
"""

from __future__ import annotations

import math

from fastapi import HTTPException

from cloudgraph.scene import (
    CameraSpec,
    EnvmapSpec,
    LightSpec,
    MediumSpec,
    Scene,
    SkySpec,
    SunskySpec,
    VolumeSpec,
    voxel_depth_problem,
)
from cloudgraph.store import EnvironmentStore, VolumeStore
from cloudgraph_service.errors import shown
from cloudgraph_service.settings import Settings

from .errors import InputError

#: Largest magnitude of any coordinate or vector component, in world units.
MAX_COORD = 1e6
#: Shortest vector that is still a direction (light direction, camera up).
MIN_LENGTH = 1e-6
#: volume.scale range.
SCALE_RANGE = (1e-6, 1e6)
#: Largest irradiance per channel.
MAX_IRRADIANCE = 1e6
#: Largest density_scale, whatever the volume.
MAX_DENSITY_SCALE = 1e6
#: Smallest orbit radius, in world units.
MIN_RADIUS = 1e-3


def first_non_finite(data, where: str = "") -> tuple[str, float] | None:
    """(field, value) of the first number in a raw body that is not finite (JSON parsers accept
    NaN, Infinity and 1e999), or None. Fields are named as in answers: ``scene.camera.eye[0]``."""
    if isinstance(data, dict):
        items = ((f"{where}.{k}" if where else str(k), v) for k, v in data.items())
    elif isinstance(data, list | tuple):
        items = ((f"{where}[{i}]", v) for i, v in enumerate(data))
    elif isinstance(data, float) and not math.isfinite(data):
        return where or "body", data
    else:
        return None
    for field, v in items:
        found = first_non_finite(v, field)
        if found is not None:
            return found
    return None


def _vec(v, where: str, *, direction: bool = False) -> None:
    if max(abs(c) for c in v) > MAX_COORD:
        raise InputError(where, f"components must be within ±{MAX_COORD:g}, got {list(v)}")
    if direction and math.hypot(*v) < MIN_LENGTH:
        raise InputError(where, f"must be a vector of length at least {MIN_LENGTH:g}, got {list(v)}")


def check_camera(camera: CameraSpec, settings: Settings, where: str) -> None:
    """Bounded positions and the image size limit."""
    _vec(camera.eye, f"{where}.eye")
    _vec(camera.target, f"{where}.target")
    _vec(camera.up, f"{where}.up", direction=True)
    side = settings.MAX_IMAGE_SIDE
    if max(camera.width, camera.height) > side:
        raise InputError(
            where, f"image {camera.width}x{camera.height} is over the limit of {side} pixels a side"
        )


def check_light(light: LightSpec | SkySpec | EnvmapSpec | SunskySpec, where: str, settings: Settings) -> None:
    if light.type == "envmap":
        if light.id is None:
            raise InputError(
                f"{where}.path",
                "the HTTP API takes an uploaded environment map's 'id' (POST /v1/environments)",
            )
        if EnvironmentStore(settings.environments_dir).info(light.id) is None:
            raise HTTPException(
                404,
                f"{where}.id: no environment map with id {shown(light.id)}; "
                "upload it with POST /v1/environments",
            )
        return
    if light.type == "sky":
        if max(light.intensity_rgb()) > MAX_IRRADIANCE:
            raise InputError(f"{where}.radiance", f"must be at most {MAX_IRRADIANCE:g}")
        return
    if light.type == "sunsky":
        _vec(light.sun_direction, f"{where}.sun_direction", direction=True)
        _vec(light.up, f"{where}.up", direction=True)
        return
    _vec(light.direction, f"{where}.direction", direction=True)
    if max(light.irradiance_rgb()) > MAX_IRRADIANCE:
        raise InputError(f"{where}.irradiance", f"must be at most {MAX_IRRADIANCE:g}")


def check_lights(light: LightSpec, lights, where: str, settings: Settings) -> None:
    """The one ``light`` (``where`` + light) or each of v1.1's ``lights`` (``where`` + lights.i)."""
    if lights is None:
        check_light(light, f"{where}light", settings)
    for i, one in enumerate(lights or ()):
        check_light(one, f"{where}lights.{i}", settings)


def grid_of(spec: VolumeSpec, volumes: VolumeStore, where: str) -> dict:
    """The stored volume's entry for the scene's grid, with its densest value and voxel size
    when known.

    Raises:
        InputError: no ``volume.id``, or a grid the volume does not have or cannot use.
        HTTPException: 404 when no volume has that id.
    """
    if spec.id is None:
        raise InputError(f"{where}.id", "is required: upload the volume with POST /v1/volumes first")
    info = volumes.info(spec.id)
    if info is None:
        raise HTTPException(404, f"no volume with id {shown(spec.id)}; upload it with POST /v1/volumes")
    lo, hi = SCALE_RANGE
    if not lo <= spec.scale <= hi:
        raise InputError(f"{where}.scale", f"must be within [{lo:g}, {hi:g}], got {spec.scale:g}")
    name = spec.grid or info["grid"]
    grids = {g["name"]: g for g in info.get("grids", [])}
    if name is None:
        floats = ", ".join(repr(n) for n, g in grids.items() if g.get("type") in ("float", "half"))
        problem = f"is required: the volume has several float grids and none named 'density' ({floats})"
        raise InputError(f"{where}.grid", problem)
    if name not in grids:
        listing = ", ".join(repr(g) for g in grids) or "none"
        raise InputError(f"{where}.grid", f"the volume has no grid named {shown(name)}; its grids: {listing}")
    grid = dict(grids[name])
    if grid.get("type") not in ("float", "half"):
        raise InputError(f"{where}.grid", f"grid {name!r} holds {grid.get('type')} values, not densities")
    if "value_max" not in grid and name == info["grid"]:  # an upload described before grid stats
        grid.update(value_max=info["value_range"][1], voxel_size=info["voxel_size"])
    if "value_max" in grid and not grid["value_max"] > 0:
        raise InputError(f"{where}.grid", f"grid {name!r} holds no positive value: no medium to render")
    return grid


def check_medium(medium: MediumSpec, grid: dict, scale: float, settings: Settings, where: str) -> None:
    """density_scale bounded so that the optical depth across one voxel at the densest point
    stays at most MAX_VOXEL_TAU: delta tracking then takes a bounded number of steps."""
    d = medium.density_scale
    if d > MAX_DENSITY_SCALE:
        raise InputError(f"{where}.density_scale", f"must be at most {MAX_DENSITY_SCALE:g}, got {d:g}")
    if "value_max" not in grid:
        return
    voxel = max(grid["voxel_size"]) * scale
    problem = voxel_depth_problem(d, grid["value_max"], voxel, settings.MAX_VOXEL_TAU)
    if problem:
        raise InputError(f"{where}.density_scale", problem)


def check_depth(max_depth: int, settings: Settings, where: str) -> None:
    if max_depth > settings.MAX_DEPTH:
        raise InputError(
            where, f"{max_depth} is over the limit of {settings.MAX_DEPTH} (or -1: unbounded, converged)"
        )


def check_cache_parts(
    volume: VolumeSpec,
    medium: MediumSpec,
    light: LightSpec,
    lights,
    max_depth: int,
    settings: Settings,
    volumes: VolumeStore,
    prefix: str = "",
) -> None:
    """What a radiance cache depends on, with field names under ``prefix``."""
    grid = grid_of(volume, volumes, f"{prefix}volume")
    check_medium(medium, grid, volume.scale, settings, f"{prefix}medium")
    check_lights(light, lights, prefix, settings)
    check_depth(max_depth, settings, f"{prefix}render.max_depth" if prefix else "max_depth")


def check_scene(scene: Scene, settings: Settings, volumes: VolumeStore, where: str = "scene") -> None:
    """A whole scene: its cache's parts, the camera, and the sample limit."""
    check_camera(scene.camera, settings, f"{where}.camera")
    if scene.render.spp > settings.MAX_SPP:
        raise InputError(f"{where}.render.spp", f"{scene.render.spp} is over the limit of {settings.MAX_SPP}")
    check_cache_parts(
        scene.volume,
        scene.medium,
        scene.light,
        scene.lights,
        scene.render.max_depth,
        settings,
        volumes,
        f"{where}.",
    )
