"""Request and response bodies. Scenes are scene spec v1 with ``volume.id`` in place of a path."""

from __future__ import annotations

from enum import StrEnum
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from cloudgraph.options import ESTIMATORS, INTEGRATORS, PHASE_ESTIMATORS, QUALITIES
from cloudgraph.scene import (
    MAX_LIGHTS,
    CameraSpec,
    Light,
    LightSpec,
    MediumSpec,
    Scene,
    VolumeSpec,
    check_light_list,
)

from .validation import first_non_finite

# The API's enums come from the engine's tuples (one source of truth).
Quality = Literal[QUALITIES]
Integrator = Literal[INTEGRATORS]
Estimator = Literal[ESTIMATORS]


class _Body(BaseModel):
    """A request body: no unknown fields, and every number finite (checked on the raw input, so
    that the answer names the field before any other rule looks at it)."""

    model_config = ConfigDict(extra="forbid")

    @model_validator(mode="before")
    @classmethod
    def _finite(cls, data):
        found = first_non_finite(data)
        if found is not None:
            raise ValueError(f"{found[0]}: must be a finite number, got {found[1]}")
        return data


def check_phase_estimator(scene: Scene, integrator: str, estimator: str) -> None:
    """An anisotropic phase needs an estimator that renders it (options.PHASE_ESTIMATORS)."""
    phase = scene.medium.phase
    if integrator == "graph" and not phase.isotropic and estimator not in PHASE_ESTIMATORS:
        raise ValueError(
            f"estimator: {estimator!r} renders the isotropic phase only, and scene.medium.phase is "
            f"{phase.type!r}; use {' or '.join(repr(e) for e in PHASE_ESTIMATORS)}"
        )


class CacheCreate(_Body):
    """What a radiance cache depends on: the volume, the medium, the light (or v1.1's lights) and
    the depth."""

    volume: VolumeSpec
    medium: MediumSpec = MediumSpec()
    light: LightSpec = LightSpec()
    lights: tuple[Light, ...] | None = Field(
        None,
        min_length=1,
        max_length=MAX_LIGHTS,
        description="v1.1: the lights (directional, sky, envmap, sunsky) instead of 'light'; their "
        "intensities are mixed at render time, so any intensities of the same lights are this cache",
    )
    max_depth: int = Field(-1, ge=-1)
    quality: Quality = "default"

    @model_validator(mode="before")
    @classmethod
    def _light_list(cls, data):
        return check_light_list(data)

    def light_id(self) -> dict:
        """What the cache's id holds of its light: the v1 light, or the v1.1 lights' kinds and
        directions (intensities are mixed at render time: lights.py)."""
        if self.lights is None:
            return self.light.model_dump()
        kinds = [{"type": li.type} for li in self.lights]
        for kind, li in zip(kinds, self.lights, strict=True):
            if li.type == "directional":
                kind["direction"] = list(li.unit_direction())
            if li.type == "envmap":  # an uploaded map's id: the sha256 of its bytes
                kind["id"] = li.id
            if li.type == "sunsky":  # its sun's direction and colour, and its sky: not its scales
                kind.update(sun_direction=list(li.unit_sun_direction()), up=list(li.unit_up()))
                kind.update(turbidity=li.turbidity, ground_albedo=li.ground_albedo)
        return {"lights": kinds}

    def light_part(self) -> dict:
        """The scene's light fields of the cache's precompute job."""
        if self.lights is None:
            return {"light": self.light.model_dump(mode="json")}
        return {"lights": [li.model_dump(mode="json") for li in self.lights]}


class RenderCreate(_Body):
    scene: Scene
    integrator: Integrator = "graph"
    estimator: Estimator = Field("gather", description="the graph integrator's camera stage")
    format: Literal["png", "exr"] = "png"
    quality: Quality = "default"
    exposure: float = Field(0.0, ge=-20, le=20, description="PNG exposure in stops")

    @model_validator(mode="after")
    def _phase(self) -> RenderCreate:
        check_phase_estimator(self.scene, self.integrator, self.estimator)
        return self


class Orbit(_Body):
    """Cameras on a circle around the scene camera's target, in the plane normal to ``up``."""

    radius: float | None = Field(None, gt=0, description="default: the scene camera's distance to the target")
    elevation: float = Field(20.0, ge=-89, le=89, description="degrees above the orbit plane")
    turns: float = Field(1.0, gt=0, le=10)


class AnimationCreate(_Body):
    scene: Scene
    keyframes: list[CameraSpec] | None = Field(None, description="cameras passed through, evenly in time")
    orbit: Orbit | None = None
    frames: int = Field(24, ge=1)
    fps: float = Field(24.0, ge=1, le=120)  # (ffmpeg refuses a frame rate far below 1)
    integrator: Integrator = "graph"
    estimator: Estimator = "gather"
    quality: Quality = "default"
    exposure: float = Field(0.0, ge=-20, le=20)

    @model_validator(mode="after")
    def _one_path(self) -> AnimationCreate:
        if (self.keyframes is None) == (self.orbit is None):
            raise ValueError("give exactly one of 'keyframes' (2 or more cameras) or 'orbit'")
        if self.keyframes is not None and len(self.keyframes) < 2:
            raise ValueError("keyframes needs at least 2 cameras")
        check_phase_estimator(self.scene, self.integrator, self.estimator)
        return self


class JobStatus(StrEnum):
    queued = "queued"
    waiting = "waiting"  # on another job (a render on its precompute, a video on its frames)
    running = "running"
    finished = "finished"
    failed = "failed"
    canceled = "canceled"


class JobPublic(BaseModel):
    id: str
    kind: str
    status: JobStatus
    stage: str | None = None
    fraction: float = 0.0
    result_url: str | None = None
    result: dict | None = None
    error: str | None = None
    created_at: float | None = None


class AnimationPublic(JobPublic):
    """An animation's job, with the frames rendered so far."""

    frames: int = Field(description="frames asked for")
    frames_done: list[int] = Field(description="indices of the frames already rendered")


class GridPublic(BaseModel):
    """One grid of an uploaded volume. A float grid of a .vdb (and a .vol's one grid) carries
    the densest value and voxel size that the density_scale limit is computed from."""

    name: str
    type: str = Field(description="value type: 'float' and 'half' grids hold densities")
    dims: list[int] | None = Field(None, description="active bounding box size, voxels per axis")
    value_max: float | None = None
    voxel_size: list[float] | None = Field(None, description="world units per voxel, per axis")


class VolumePublic(BaseModel):
    """An uploaded volume; its id is the sha256 of the file's bytes."""

    id: str = Field(pattern="^[0-9a-f]{64}$")
    filename: str
    bytes: int
    format: Literal["vdb", "vol"]
    created: float = Field(description="upload time, seconds since the epoch")
    grids: list[GridPublic]
    grid: str | None = Field(
        description="the density grid scenes use when they name none: 'density', else the only float "
        "grid; null where there are several and none is named 'density' (a scene must name one)"
    )
    index_bbox: list[list[int]] = Field(
        description="[[x, y, z] min, [x, y, z] max], index space, of `grid` (null: of the first float grid)"
    )
    world_bbox: list[list[float]] = Field(description="[[x, y, z] min, [x, y, z] max], world units, of it")
    voxel_size: list[float] = Field(description="world units per voxel, per axis, of it")
    value_range: list[float] = Field(description="[min, max] of it")
    active_fraction: float = Field(description="fraction of its bounding box's voxels above 0")


class EnvironmentPublic(BaseModel):
    """An uploaded environment map (lat-long OpenEXR); its id is the sha256 of the file's bytes."""

    id: str = Field(pattern="^[0-9a-f]{64}$")
    filename: str
    bytes: int
    format: Literal["exr"]
    created: float = Field(description="upload time, seconds since the epoch")
    width: int = Field(description="pixels; twice the height (lat-long)")
    height: int
    channels: int


class CachePublic(BaseModel):
    """A radiance cache and its precompute: ``keys`` and ``stats`` once it has finished."""

    id: str = Field(pattern="^[0-9a-f]{32}$")
    status: JobStatus
    stage: str | None = None
    fraction: float = 0.0
    job: str = Field(description="the precompute job's URL: /v1/jobs/cache-<id>")
    keys: dict | None = None
    stats: dict | None = None
    error: str | None = None


class HealthPublic(BaseModel):
    status: Literal["ok"]


class ReadyPublic(BaseModel):
    status: Literal["ready"]
    workers: int = Field(description="live workers")
    stuck: int = Field(description="live workers past their job's budget")


def binary(*media_types: str) -> dict:
    """The OpenAPI ``content`` of a response that is a file's bytes, in any of ``media_types``."""
    return {m: {"schema": {"type": "string", "format": "binary"}} for m in media_types}
