"""Service settings, one class, read from the environment (``CLOUDGRAPH_*``) at start-up."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path


def _env(name: str, default, cast=str):
    raw = os.environ.get(f"CLOUDGRAPH_{name}")
    if raw is None or raw == "":
        return default
    try:
        return cast(raw)
    except ValueError:
        raise ValueError(f"CLOUDGRAPH_{name}={raw!r} is not a valid {cast.__name__}") from None


@dataclass(frozen=True)
class Settings:
    """Limits and locations shared by the API and the workers."""

    DATA_DIR: Path = Path("data")
    REDIS_URL: str = "redis://127.0.0.1:6379/0"
    API_KEYS: tuple[str, ...] = field(default_factory=tuple)
    QUEUE: str = "cloudgraph"
    MAX_UPLOAD_MB: int = 512
    MAX_IMAGE_SIDE: int = 2048
    MAX_SPP: int = 4096
    MAX_FRAMES: int = 600
    MAX_QUEUED: int = 200  # jobs waiting; beyond this, 429 with Retry-After
    SYNC_MAX_PIXELS: int = 512 * 512  # renders up to this size come back in the response
    SYNC_WAIT_S: float = 60.0
    JOB_TIMEOUT_S: int = 3600
    JOB_RETRIES: int = 2
    HEARTBEAT_S: int = 30  # a worker silent this long (plus its job's grace) is presumed dead
    CACHE_MAX_GB: float = 20.0
    WORKER_RENDERERS: int = 4  # loaded radiance caches kept per worker

    @classmethod
    def from_env(cls) -> Settings:
        keys = tuple(k.strip() for k in os.environ.get("CLOUDGRAPH_API_KEYS", "").split(",") if k.strip())
        for k in keys:
            if len(k) < 16 or k.lower() in {"changeme", "changethis", "secret", "password"}:
                raise ValueError(
                    "CLOUDGRAPH_API_KEYS holds a placeholder or short key; use 16+ random characters"
                )
        d = cls()
        return cls(
            DATA_DIR=Path(_env("DATA_DIR", d.DATA_DIR, Path)).resolve(),
            REDIS_URL=_env("REDIS_URL", d.REDIS_URL),
            API_KEYS=keys,
            QUEUE=_env("QUEUE", d.QUEUE),
            MAX_UPLOAD_MB=_env("MAX_UPLOAD_MB", d.MAX_UPLOAD_MB, int),
            MAX_IMAGE_SIDE=_env("MAX_IMAGE_SIDE", d.MAX_IMAGE_SIDE, int),
            MAX_SPP=_env("MAX_SPP", d.MAX_SPP, int),
            MAX_FRAMES=_env("MAX_FRAMES", d.MAX_FRAMES, int),
            MAX_QUEUED=_env("MAX_QUEUED", d.MAX_QUEUED, int),
            SYNC_MAX_PIXELS=_env("SYNC_MAX_PIXELS", d.SYNC_MAX_PIXELS, int),
            SYNC_WAIT_S=_env("SYNC_WAIT_S", d.SYNC_WAIT_S, float),
            JOB_TIMEOUT_S=_env("JOB_TIMEOUT_S", d.JOB_TIMEOUT_S, int),
            JOB_RETRIES=_env("JOB_RETRIES", d.JOB_RETRIES, int),
            HEARTBEAT_S=_env("HEARTBEAT_S", d.HEARTBEAT_S, int),
            CACHE_MAX_GB=_env("CACHE_MAX_GB", d.CACHE_MAX_GB, float),
            WORKER_RENDERERS=_env("WORKER_RENDERERS", d.WORKER_RENDERERS, int),
        )

    @property
    def volumes_dir(self) -> Path:
        return self.DATA_DIR / "volumes"

    @property
    def cache_dir(self) -> Path:
        return self.DATA_DIR / "cache"

    @property
    def outputs_dir(self) -> Path:
        return self.DATA_DIR / "outputs"
