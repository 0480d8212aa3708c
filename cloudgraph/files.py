"""Atomic file writes: the one helper every writer of the engine and the service uses."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO


@contextmanager
def atomic_writer(path: Path, sync: bool = True) -> Iterator[BinaryIO]:
    """A binary file that appears at ``path`` whole or not at all: written under a temporary name
    in the same folder, synced (unless ``sync`` is false), then renamed into place (removed if
    the writer fails)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            if sync:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_atomic(path: Path, data: bytes, sync: bool = True) -> Path:
    """``data`` at ``path``, whole or not at all (:func:`atomic_writer`)."""
    with atomic_writer(path, sync) as f:
        f.write(data)
    return Path(path)


def default_cache_dir() -> Path:
    """The engine's cache folder: $CLOUDGRAPH_CACHE_DIR, or ~/.cache/cloudgraph."""
    return Path(os.environ.get("CLOUDGRAPH_CACHE_DIR", Path.home() / ".cache" / "cloudgraph"))
