"""Service settings, one class, read from the environment (``CLOUDGRAPH_*``) at start-up.

Each setting is declared once, with its type and default; ``CLOUDGRAPH_<NAME>`` overrides it (an
empty variable counts as unset). Nothing here is built at import time: the API, the workers and
the upload check each call :meth:`Settings.from_env` at their entry point.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from cloudgraph import options

ENV_PREFIX = "CLOUDGRAPH_"
#: Keys that must never guard a service (the template's placeholders and common words).
_PLACEHOLDER_KEYS = {"changeme", "changethis", "secret", "password"}
_MIN_KEY_LENGTH = 16
#: pydantic's error types for a value that is not a number, as the settings' errors name them.
_NOT_A = {"int_parsing": "int", "int_from_float": "int", "int_type": "int", "float_parsing": "float"}


class Settings(BaseSettings):
    """Limits and locations shared by the API and the workers (api.md, "Settings")."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        case_sensitive=True,
        env_ignore_empty=True,
        frozen=True,
        validate_default=True,  # DATA_DIR's default is made absolute too
    )

    DATA_DIR: Path = Path("data")  # absolute once read (relative to the working directory)
    CACHE_DIR: Path | None = None  # CLOUDGRAPH_CACHE_DIR, else DATA_DIR/cache
    REDIS_URL: str = "redis://127.0.0.1:6379/0"
    # Comma-separated in the environment; empty: no key is asked for
    API_KEYS: Annotated[tuple[str, ...], NoDecode] = Field((), repr=False)
    QUEUE: str = "cloudgraph"
    MAX_UPLOAD_MB: int = 512
    MAX_BODY_KB: int = 256  # JSON request bodies
    MAX_VOXELS: int = 256 * 1024 * 1024  # densified voxels of any grid of an upload
    MAX_IMAGE_SIDE: int = 2048
    MAX_SPP: int = 4096
    MAX_FRAMES: int = 600
    MAX_DEPTH: int = 1000  # scattering events, when not -1 (unbounded, converged)
    MAX_VOXEL_TAU: float = options.MAX_VOXEL_TAU  # optical depth across one voxel at the densest point
    MAX_QUEUED: int = 200  # jobs waiting; beyond this, 429 with Retry-After
    SYNC_MAX_PIXELS: int = 512 * 512  # renders up to this size come back in the response
    SYNC_WAIT_S: float = 60.0
    JOB_TIMEOUT_S: int = 3600  # a job's budget: past it, the job is stopped and failed for good
    JOB_RETRIES: int = 2  # reruns of a job whose worker died under it (never for errors)
    HEARTBEAT_S: int = 30  # a worker silent this long (plus a grace) is presumed dead
    UPLOAD_CHECK_S: float = 120.0  # reading an upload (in a child process) may take this long
    CACHE_MAX_GB: float = 20.0
    WORKER_RENDERERS: int = 4  # loaded radiance caches kept per worker
    WORKER_THREADS: int = 0  # Dr.Jit threads per worker process (0: one per core; 1 counts as 2)
    DASK_SCHEDULER: str | None = None  # tcp://HOST:8786: precomputes run there (docs/cluster.md)

    @field_validator("DATA_DIR", "CACHE_DIR")
    @classmethod
    def _absolute(cls, path: Path | None) -> Path | None:
        return None if path is None else path.resolve()

    @field_validator("API_KEYS", mode="before")
    @classmethod
    def _split_keys(cls, value):
        if isinstance(value, str):
            return tuple(k.strip() for k in value.split(",") if k.strip())
        return value

    @field_validator("API_KEYS")
    @classmethod
    def _no_placeholder_keys(cls, keys: tuple[str, ...]) -> tuple[str, ...]:
        for k in keys:
            if len(k) < _MIN_KEY_LENGTH or k.lower() in _PLACEHOLDER_KEYS:
                raise ValueError(
                    f"holds a placeholder or short key; use {_MIN_KEY_LENGTH}+ random characters"
                )
        return keys

    @classmethod
    def from_env(cls) -> Settings:
        """The settings from ``CLOUDGRAPH_*`` variables; refuses placeholder API keys.

        Raises:
            ValueError: a variable that does not parse, or a short or placeholder API key, in one
                line that names the variable (never an API key's value).
        """
        try:
            return cls()
        except ValidationError as err:
            raise ValueError("; ".join(_one_line(e) for e in err.errors())) from None

    @property
    def volumes_dir(self) -> Path:
        return self.DATA_DIR / "volumes"

    @property
    def environments_dir(self) -> Path:
        return self.DATA_DIR / "environments"

    @property
    def cache_dir(self) -> Path:
        return self.CACHE_DIR or self.DATA_DIR / "cache"

    @property
    def outputs_dir(self) -> Path:
        return self.DATA_DIR / "outputs"


def _one_line(error: dict) -> str:
    """One of pydantic's errors as the variable's name and what is wrong with it."""
    name = ENV_PREFIX + ".".join(str(p) for p in error["loc"][:1])
    if name == ENV_PREFIX + "API_KEYS":  # a key's value is a secret: never echoed
        return f"{name} {error['msg'].removeprefix('Value error, ')}"
    raw = error.get("input")
    if error["type"] in _NOT_A:
        return f"{name}={raw!r} is not a valid {_NOT_A[error['type']]}"
    return f"{name}={raw!r}: {error['msg']}"
