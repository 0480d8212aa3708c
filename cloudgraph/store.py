"""Content-addressed storage of uploaded volumes and environment maps, least-recently-used
eviction, and the temporary files that dead writers leave.

A volume's id is the sha256 of its file's bytes, so the same file uploaded twice is one volume.
Files are written under a temporary name and renamed into place. An upload's temporary files
carry their writer's tag (:func:`writer_tag`: its host and process), so that whoever sweeps a
shared folder knows which of them no live process can still be writing.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import socket
import tempfile
import time
from pathlib import Path
from typing import BinaryIO

from .errors import VolumeError
from .files import atomic_writer
from .scene import envmap_problem
from .vdb import VDB_MAGIC
from .volume import volume_info

CHUNK = 1 << 20


class VolumeStore:
    """Uploaded volumes: ``<root>/<id>.vdb|.vol`` with ``<id>.json`` describing it."""

    #: What is stored, in the words of its errors.
    WHAT = "a .vdb or .vol file"

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def describe(self, tmp: str) -> tuple[dict, str]:
        """(info, extension) of an upload's bytes in ``tmp``.

        Raises:
            VolumeError: not a readable volume.
        """
        with open(tmp, "rb") as f:
            head = f.read(8)
        ext = ".vdb" if len(head) == 8 and int.from_bytes(head, "little") == VDB_MAGIC else ".vol"
        info = volume_info(tmp)
        del info["path"]
        return info, ext

    def put(self, stream: BinaryIO, max_bytes: int, filename: str = "", tag: str = "") -> tuple[dict, bool]:
        """Stores an upload after checking that it is a readable volume.

        Args:
            tag: the writer's tag (:func:`writer_tag`) that the temporary copy carries: the
                process whose death makes it stale (:func:`sweep_temporaries`); this one's when
                empty.

        Returns:
            (info, created): created is False when the same bytes were stored before.

        Raises:
            VolumeError: over ``max_bytes``, empty, or not a readable volume.
        """
        h = hashlib.sha256()
        size = 0
        fd, tmp = self.temporary("upload", tag)
        try:
            with os.fdopen(fd, "wb") as f:
                while chunk := stream.read(CHUNK):
                    size += len(chunk)
                    if size > max_bytes:
                        raise VolumeError(f"upload is over the limit of {max_bytes // 2**20} MiB")
                    h.update(chunk)
                    f.write(chunk)
            if size == 0:
                raise VolumeError(f"upload is empty: send {self.WHAT} in the multipart field 'file'")
            vid = h.hexdigest()
            if self.info(vid) is not None:
                return self.info(vid), False
            try:
                info, ext = self.describe(tmp)
            except VolumeError as err:  # name the upload, not the temporary file
                name = Path(filename).name or "the upload"
                raise VolumeError(str(err).replace(tmp, name)) from None
            info.update(
                {
                    "id": vid,
                    "filename": Path(filename).name,
                    "bytes": size,
                    "format": ext[1:],
                    "created": time.time(),
                }
            )
            os.replace(tmp, self.root / f"{vid}{ext}")
            with atomic_writer(self.root / f"{vid}.json") as f:
                f.write(json.dumps(info).encode())
            return info, True
        finally:
            Path(tmp).unlink(missing_ok=True)

    def temporary(self, kind: str, tag: str = "") -> tuple[int, str]:
        """(fd, path) of a new temporary file in the store, ``.<kind>.<tag>.<random>.tmp``."""
        self.root.mkdir(parents=True, exist_ok=True)
        return tempfile.mkstemp(dir=self.root, prefix=f".{kind}.{tag or writer_tag()}.", suffix=".tmp")

    def info(self, vid: str) -> dict | None:
        if not _is_hex_id(vid):
            return None
        p = self.root / f"{vid}.json"
        return json.loads(p.read_text()) if p.is_file() else None

    def path(self, vid: str) -> Path | None:
        info = self.info(vid)
        return None if info is None else self.root / f"{vid}.{info['format']}"

    def list(self) -> list[dict]:
        if not self.root.is_dir():
            return []
        out = [json.loads(p.read_text()) for p in self.root.glob("*.json")]
        return sorted(out, key=lambda i: i.get("created", 0))

    def delete(self, vid: str) -> bool:
        info = self.info(vid)
        if info is None:
            return False
        (self.root / f"{vid}.json").unlink(missing_ok=True)
        (self.root / f"{vid}.{info['format']}").unlink(missing_ok=True)
        return True


#: The largest environment map taken, in pixels (a 8192 x 4096 map).
MAX_ENVMAP_PIXELS = 8192 * 4096


class EnvironmentStore(VolumeStore):
    """Uploaded environment maps (lat-long OpenEXR, width twice the height): ``<root>/<id>.exr``
    with ``<id>.json`` describing it; read with Mitsuba's own reader, the one its ``envmap``
    and the engine use."""

    WHAT = "a lat-long .exr file"

    def describe(self, tmp: str) -> tuple[dict, str]:
        with open(tmp, "rb") as f:
            if f.read(4) != b"\x76\x2f\x31\x01":
                raise VolumeError(f"{tmp} is not an OpenEXR file (send a lat-long .exr environment map)")
        import mitsuba as mi
        import numpy as np

        if mi.variant() is None:
            mi.set_variant("scalar_rgb")
        try:
            bitmap = mi.Bitmap(tmp)
        except Exception as err:  # Mitsuba's reader raises RuntimeError with the file's problem
            raise VolumeError(
                f"{tmp} cannot be read as an OpenEXR image: {str(err).splitlines()[-1]}"
            ) from None
        width, height = bitmap.size()
        if width * height > MAX_ENVMAP_PIXELS:
            raise VolumeError(f"{tmp} has {width}x{height} pixels, over the limit of 8192x4096")
        if width != 2 * height:
            raise VolumeError(
                f"{tmp} is {width}x{height}: a lat-long environment map is twice as wide as high"
            )
        problem = envmap_problem(np.array(bitmap, np.float32))
        if problem:
            raise VolumeError(f"{tmp} {problem}")
        return {"width": int(width), "height": int(height), "channels": int(bitmap.channel_count())}, ".exr"


def _is_hex_id(s: str) -> bool:
    return len(s) == 64 and all(c in "0123456789abcdef" for c in s)


def evict_lru(root: str | Path, max_bytes: int, min_age_s: float = 300.0) -> list[Path]:
    """Deletes the least recently used files under ``root`` until they total at most ``max_bytes``.

    Temporary files of killed writers older than ``min_age_s`` are removed too. Files used in
    the last ``min_age_s`` seconds are kept whatever the total, so a cache that a
    job has just written or read is never removed under it; readers load whole files, and a
    deleted file stays readable to whoever has it open.
    """
    now = time.time()
    for tmp in Path(root).rglob(".*.tmp"):  # left by a writer that was killed mid-write
        try:
            if now - tmp.stat().st_mtime > min_age_s:
                tmp.unlink()
        except FileNotFoundError:
            pass
    files = [
        p
        for pat in ("*.npz", "*.cgf.gz")
        for p in Path(root).rglob(pat)
        if p.is_file() and "runs" not in p.relative_to(root).parts  # a shared run's own files
    ]
    stats = [(p, p.stat()) for p in files]
    total = sum(s.st_size for _, s in stats)
    removed = []
    for p, s in sorted(stats, key=lambda ps: ps[1].st_mtime):
        if total <= max_bytes:
            break
        if now - s.st_mtime < min_age_s:
            continue
        p.unlink(missing_ok=True)
        total -= s.st_size
        removed.append(p)
    return removed


# ------------------------------------------------------------ temporary files of dead writers
#: A temporary file of the stores: ``.<kind>.<host>-<pid>.<random>.tmp`` (VolumeStore.temporary).
#: Untagged temporary files (an older version's) untouched this long are stale.
UNTAGGED_AGE_S = 600.0
_TAGGED = re.compile(r"\.(?P<kind>[a-z]+)\.(?P<host>[0-9a-f]+)-(?P<pid>\d+)\.[^.]+\.tmp")


def host_id() -> str:
    """This host, as writer tags and worker names carry it: its boot and PID namespace, hashed,
    so that a process id read from a tag is one of this host's (containers that share a
    hostname, or a machine, differ here)."""
    parts = []
    for p in ("/proc/sys/kernel/random/boot_id", "/proc/self/ns/pid"):
        try:
            parts.append(Path(p).read_text().strip() if p.endswith("id") else os.readlink(p))
        except OSError:
            parts.append(socket.gethostname())
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:10]


def writer_tag(pid: int | None = None) -> str:
    """``<host>-<pid>``: the writer of a temporary file (this process unless ``pid``)."""
    return f"{host_id()}-{pid or os.getpid()}"


def process_alive(pid: int | None, since: float | None = None) -> bool:
    """Whether process ``pid`` of this host still runs (no zombie) and is the one that was there
    at ``since`` (Unix time): a process started later under a reused id is not it. True where
    it cannot be told (no /proc)."""
    if not pid:
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    except OSError:
        return True
    fields = stat.rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
    if fields[0] in ("Z", "X"):
        return False
    try:
        lines = Path("/proc/stat").read_text().splitlines()
        boot = next(float(line.split()[1]) for line in lines if line.startswith("btime"))
        started = boot + int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, StopIteration, ValueError, IndexError):
        return True
    return since is None or started <= since + 2.0  # btime and clock ticks: a second or so


def sweep_temporaries(root: str | Path, max_age_s: float = 24 * 3600) -> list[Path]:
    """Removes the temporary files in ``root`` (not below) whose writer is gone: the tagged ones
    of this host whose process has ended, those of any host untouched for ``max_age_s``, and
    untagged ones (of an older version) untouched for ``UNTAGGED_AGE_S``.

    Returns:
        The files removed.
    """
    here, now, removed = host_id(), time.time(), []
    for p in Path(root).glob(".*.tmp"):
        m = _TAGGED.fullmatch(p.name)
        try:
            mtime = p.stat().st_mtime
        except FileNotFoundError:
            continue
        if m is None:  # untagged: written before writers were named
            stale = now - mtime > min(max_age_s, UNTAGGED_AGE_S)
        else:
            mine = m["host"] == here
            stale = (mine and not process_alive(int(m["pid"]), mtime)) or now - mtime > max_age_s
        if stale:
            p.unlink(missing_ok=True)
            removed.append(p)
    return removed
