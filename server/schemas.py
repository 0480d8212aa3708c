"""Request and response bodies. Scenes are scene spec v1 with ``volume.id`` in place of a path."""

from __future__ import annotations

from enum import StrEnum
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from cloudgraph.options import ESTIMATORS, INTEGRATORS, QUALITIES
from cloudgraph.scene import CameraSpec, LightSpec, MediumSpec, Scene, VolumeSpec

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


class CacheCreate(_Body):
    """What a radiance cache depends on: the volume, the medium, the light and the depth."""

    volume: VolumeSpec
    medium: MediumSpec = MediumSpec()
    light: LightSpec = LightSpec()
    max_depth: int = Field(-1, ge=-1)
    quality: Quality = "default"


class RenderCreate(_Body):
    scene: Scene
    integrator: Integrator = "graph"
    estimator: Estimator = Field("gather", description="the graph integrator's camera stage")
    format: Literal["png", "exr"] = "png"
    quality: Quality = "default"
    exposure: float = Field(0.0, ge=-20, le=20, description="PNG exposure in stops")


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
    fps: float = Field(24.0, gt=0, le=120)
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
