"""Errors as people see them: what went wrong, never where (no server path, class name or
traceback). The full error stays in the log, under the job id."""

from __future__ import annotations

import errno
import os
import re
import shutil
from collections.abc import Mapping
from pathlib import Path

from cloudgraph.errors import CloudgraphError

#: An absolute path: what a message must not show (the API's own routes, /v1/..., are fine).
_PATH = re.compile(r"(?<![\w.~:/])/(?!v1/)(?:[^\s'\"/,;:()]+/)*[^\s'\",;:()]+")
_VOLUME_FILE = re.compile(r"\.(vdb|vol)$")


class PayloadError(ValueError):
    """A job's payload that its job function refuses (a field missing, unknown or of the wrong
    type: a sender of another version, or a bug). Not the client's to fix: the log keeps this
    message, the client reads that an internal error ended the job (:func:`public_message`)."""


def scrub(text: str) -> str:
    """``text`` with every absolute path replaced: a volume file by "the volume", others by
    "a server file"."""

    def name(m: re.Match) -> str:
        return "the volume" if _VOLUME_FILE.search(m.group(0)) else "a server file"

    return _PATH.sub(name, text)


def shown(value: str, limit: int = 80) -> str:
    """A client's id or name as an answer may echo it: quoted, and cut short when long."""
    return (
        repr(value) if len(value) <= limit else repr(value[: limit // 2]) + f"... ({len(value)} characters)"
    )


#: errno values of a write that found no room, and of one that may not write at all.
_FULL = {errno.ENOSPC, errno.EDQUOT}
_UNWRITABLE = {errno.EROFS: "read-only", errno.EACCES: "permission denied", errno.EPERM: "permission denied"}
#: Free bytes under which a volume whose write failed is taken as full: numpy and zipfile report
#: a short write as an OSError without errno ("67632 requested and 50144 written").
NEARLY_FULL = 2**20


def _size(n: int) -> str:
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} bytes"


def _free(path: Path) -> int | None:
    """Free bytes on the file system of ``path`` (or of its nearest existing parent)."""
    for p in (path, *path.parents):
        try:
            return shutil.disk_usage(p).free
        except OSError:
            continue
    return None


def storage_message(err: BaseException, volumes: Mapping[str, Path]) -> str | None:
    """What a failed write says to people, naming the volume it failed on: full (with its free
    space) or not writable; None for an error that is not about storage.

    Args:
        err: the exception (an OSError when it is about storage).
        volumes: the service's data folders by the name a message gives them ("cache": the
            cache volume). The folder of the failed file (``err.filename``) picks the name;
            without a file name, the fullest folder does.
    """
    if not isinstance(err, OSError) or not volumes:
        return None
    folders = {name: Path(p) for name, p in volumes.items()}
    named = None
    if err.filename:  # the deepest folder that holds the file
        f = Path(str(err.filename))
        holders = [n for n, p in folders.items() if f == p or p in f.parents]
        named = max(holders, key=lambda n: len(folders[n].parts), default=None)
    free = {n: _free(p) for n, p in folders.items()}
    if err.errno in _UNWRITABLE:
        closed = [n for n, p in folders.items() if p.is_dir() and not os.access(p, os.W_OK)]
        name = named or next(iter(closed or folders))
        why = _UNWRITABLE[err.errno]
        return f"the {name} volume is not writable ({why}): an operator has to make it writable"
    if err.errno in _FULL or err.errno is None:
        known = {n: b for n, b in free.items() if b is not None}
        name = named or min(known, key=known.get, default=None)
        if name is None or (err.errno is None and (known.get(name) or 0) >= NEARLY_FULL):
            return None  # an errno-less OSError on a volume with room: not a storage error
        left = f"{_size(known[name])} free" if name in known else "no space left"
        hint = ", or lower CLOUDGRAPH_CACHE_MAX_GB" if name == "cache" else ""
        return f"the {name} volume is full ({left}): free some space on it{hint}"
    return None


def public_message(err: BaseException, job_id: str, volumes: Mapping[str, Path] | None = None) -> str:
    """What a job's or request's error says to its client.

    Args:
        err: the exception.
        job_id: the job it ended, named so that the log's details can be found.
        volumes: the service's data folders by name (:func:`storage_message`), so that a write
            that found its volume full or read-only says so.

    Returns:
        The message of a domain error (the caller's to fix) without paths, or of a full or
        unwritable volume; for anything else, a sentence that names the job and points to the
        log.
    """
    if isinstance(err, CloudgraphError):
        return scrub(str(err))
    if (storage := storage_message(err, volumes or {})) is not None:
        return storage
    return f"an internal error ended job {job_id}; the service log has the details under that id"
