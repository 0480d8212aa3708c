"""Content-addressed storage of uploaded volumes, and least-recently-used eviction.

A volume's id is the sha256 of its file's bytes, so the same file uploaded twice is one volume.
Files are written under a temporary name and renamed into place.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time
from pathlib import Path
from typing import BinaryIO

from .errors import VolumeError
from .files import atomic_writer
from .vdb import VDB_MAGIC
from .volume import volume_info

CHUNK = 1 << 20


class VolumeStore:
    """Uploaded volumes: ``<root>/<id>.vdb|.vol`` with ``<id>.json`` describing it."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def put(self, stream: BinaryIO, max_bytes: int, filename: str = "") -> tuple[dict, bool]:
        """Stores an upload after checking that it is a readable volume.

        Returns:
            (info, created): created is False when the same bytes were stored before.

        Raises:
            VolumeError: over ``max_bytes``, empty, or not a readable volume.
        """
        self.root.mkdir(parents=True, exist_ok=True)
        h = hashlib.sha256()
        size = 0
        fd, tmp = tempfile.mkstemp(dir=self.root, prefix=".upload.", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                while chunk := stream.read(CHUNK):
                    size += len(chunk)
                    if size > max_bytes:
                        raise VolumeError(f"upload is over the limit of {max_bytes // 2**20} MiB")
                    h.update(chunk)
                    f.write(chunk)
            if size == 0:
                raise VolumeError("upload is empty: send a .vdb or .vol file in the multipart field 'file'")
            vid = h.hexdigest()
            if self.info(vid) is not None:
                return self.info(vid), False
            with open(tmp, "rb") as f:
                head = f.read(8)
            ext = ".vdb" if len(head) == 8 and int.from_bytes(head, "little") == VDB_MAGIC else ".vol"
            try:
                info = volume_info(tmp)
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
            del info["path"]
            os.replace(tmp, self.root / f"{vid}{ext}")
            with atomic_writer(self.root / f"{vid}.json") as f:
                f.write(json.dumps(info).encode())
            return info, True
        finally:
            Path(tmp).unlink(missing_ok=True)

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
