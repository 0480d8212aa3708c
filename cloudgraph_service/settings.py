"""Service settings, one class, read from the environment (``CLOUDGRAPH_*``) at start-up."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

#: Keys that must never guard a service (the template's placeholders and common words).
_PLACEHOLDER_KEYS = {"changeme", "changethis", "secret", "password"}


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
    """Limits and locations shared by the API and the workers (api.md, "Settings")."""

    DATA_DIR: Path = Path("data")
    CACHE_DIR: Path | None = None  # CLOUDGRAPH_CACHE_DIR, else DATA_DIR/cache
    REDIS_URL: str = "redis://127.0.0.1:6379/0"
    API_KEYS: tuple[str, ...] = field(default_factory=tuple)
    QUEUE: str = "cloudgraph"
    MAX_UPLOAD_MB: int = 512
    MAX_BODY_KB: int = 256  # JSON request bodies
    MAX_VOXELS: int = 256 * 1024 * 1024  # densified voxels of any grid of an upload
    MAX_IMAGE_SIDE: int = 2048
    MAX_SPP: int = 4096
    MAX_FRAMES: int = 600
    MAX_DEPTH: int = 1000  # scattering events, when not -1 (unbounded, converged)
    MAX_VOXEL_TAU: float = 100.0  # optical depth across one voxel at the densest point
    MAX_QUEUED: int = 200  # jobs waiting; beyond this, 429 with Retry-After
    SYNC_MAX_PIXELS: int = 512 * 512  # renders up to this size come back in the response
    SYNC_WAIT_S: float = 60.0
    JOB_TIMEOUT_S: int = 3600  # a job's budget: past it, the job is stopped and failed for good
    JOB_RETRIES: int = 2  # reruns of a job whose worker died under it (never for errors)
    HEARTBEAT_S: int = 30  # a worker silent this long (plus a grace) is presumed dead
    UPLOAD_CHECK_S: float = 120.0  # reading an upload (in a child process) may take this long
    CACHE_MAX_GB: float = 20.0
    WORKER_RENDERERS: int = 4  # loaded radiance caches kept per worker
    WORKER_THREADS: int = 0  # Dr.Jit threads per worker process (0: one per core)

    @classmethod
    def from_env(cls) -> Settings:
        """The settings from ``CLOUDGRAPH_*`` variables; refuses placeholder API keys.

        Raises:
            ValueError: a variable that does not parse, or a short or placeholder API key.
        """
        keys = tuple(k.strip() for k in os.environ.get("CLOUDGRAPH_API_KEYS", "").split(",") if k.strip())
        for k in keys:
            if len(k) < 16 or k.lower() in _PLACEHOLDER_KEYS:
                raise ValueError(
                    "CLOUDGRAPH_API_KEYS holds a placeholder or short key; use 16+ random characters"
                )
        d = cls()
        cache_dir = _env("CACHE_DIR", None, Path)
        return cls(
            DATA_DIR=Path(_env("DATA_DIR", d.DATA_DIR, Path)).resolve(),
            CACHE_DIR=cache_dir.resolve() if cache_dir else None,
            REDIS_URL=_env("REDIS_URL", d.REDIS_URL),
            API_KEYS=keys,
            QUEUE=_env("QUEUE", d.QUEUE),
            MAX_UPLOAD_MB=_env("MAX_UPLOAD_MB", d.MAX_UPLOAD_MB, int),
            MAX_BODY_KB=_env("MAX_BODY_KB", d.MAX_BODY_KB, int),
            MAX_VOXELS=_env("MAX_VOXELS", d.MAX_VOXELS, int),
            MAX_IMAGE_SIDE=_env("MAX_IMAGE_SIDE", d.MAX_IMAGE_SIDE, int),
            MAX_SPP=_env("MAX_SPP", d.MAX_SPP, int),
            MAX_FRAMES=_env("MAX_FRAMES", d.MAX_FRAMES, int),
            MAX_DEPTH=_env("MAX_DEPTH", d.MAX_DEPTH, int),
            MAX_VOXEL_TAU=_env("MAX_VOXEL_TAU", d.MAX_VOXEL_TAU, float),
            MAX_QUEUED=_env("MAX_QUEUED", d.MAX_QUEUED, int),
            SYNC_MAX_PIXELS=_env("SYNC_MAX_PIXELS", d.SYNC_MAX_PIXELS, int),
            SYNC_WAIT_S=_env("SYNC_WAIT_S", d.SYNC_WAIT_S, float),
            JOB_TIMEOUT_S=_env("JOB_TIMEOUT_S", d.JOB_TIMEOUT_S, int),
            JOB_RETRIES=_env("JOB_RETRIES", d.JOB_RETRIES, int),
            HEARTBEAT_S=_env("HEARTBEAT_S", d.HEARTBEAT_S, int),
            UPLOAD_CHECK_S=_env("UPLOAD_CHECK_S", d.UPLOAD_CHECK_S, float),
            CACHE_MAX_GB=_env("CACHE_MAX_GB", d.CACHE_MAX_GB, float),
            WORKER_RENDERERS=_env("WORKER_RENDERERS", d.WORKER_RENDERERS, int),
            WORKER_THREADS=_env("WORKER_THREADS", d.WORKER_THREADS, int),
        )

    @property
    def volumes_dir(self) -> Path:
        return self.DATA_DIR / "volumes"

    @property
    def cache_dir(self) -> Path:
        return self.CACHE_DIR or self.DATA_DIR / "cache"

    @property
    def outputs_dir(self) -> Path:
        return self.DATA_DIR / "outputs"
