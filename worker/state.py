"""Per-process warm state: settings, stores, and recently used volumes and renderers (bounded)."""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from functools import lru_cache

from cloudgraph.cache import CacheStore
from cloudgraph.errors import SceneError
from cloudgraph.scene import Scene
from cloudgraph.store import VolumeStore
from cloudgraph.volume import Volume, load_volume
from cloudgraph_service.settings import Settings


class LRU:
    """A small least-recently-used map, bounded by entry count; thread-safe."""

    def __init__(self, size: int):
        self.size, self._d, self._lock = size, OrderedDict(), threading.Lock()

    def get(self, key):
        """The value under ``key`` (now the most recently used), or None."""
        with self._lock:
            if key in self._d:
                self._d.move_to_end(key)
                return self._d[key]
        return None

    def get_or_make(self, key, make):
        with self._lock:
            if key in self._d:
                self._d.move_to_end(key)
                return self._d[key]
        value = make()
        with self._lock:
            self._d[key] = value
            while len(self._d) > self.size:
                self._d.popitem(last=False)
        return value


class WorkerState:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.volumes = VolumeStore(settings.volumes_dir)
        self.caches = CacheStore(settings.cache_dir)
        # a sunsky light's sky maps (cloudgraph/sunsky.py) beside the caches, unless set
        os.environ.setdefault("CLOUDGRAPH_SKY_DIR", str(settings.cache_dir / "skies"))
        self._volumes = LRU(max(2, settings.WORKER_RENDERERS))
        self.renderers = LRU(settings.WORKER_RENDERERS)

    def volume(self, scene: Scene) -> Volume:
        """The scene's volume (by uploaded id), kept loaded."""
        v = scene.volume
        path = self.volumes.path(v.id) if v.id else None
        if path is None:
            raise SceneError(f"volume {v.id!r} is not stored (upload it with POST /v1/volumes)")
        return self._volumes.get_or_make((v.id, v.grid, v.scale), lambda: load_volume(path, v.grid, v.scale))


@lru_cache(maxsize=1)
def state() -> WorkerState:
    return WorkerState(Settings.from_env())
