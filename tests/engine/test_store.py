"""Least-recently-used eviction of the cache store."""

import os
import time

from cloudgraph.store import evict_lru


def test_eviction_removes_oldest_until_under_budget_and_keeps_recent_and_cleans_dead_tmp(tmp_path):
    now = time.time()
    files = {}
    for i, age in enumerate([5000, 4000, 3000, 10]):  # seconds since last use
        p = tmp_path / "graphs" / f"{i}.npz"
        p.parent.mkdir(exist_ok=True)
        p.write_bytes(b"x" * 100)
        os.utime(p, (now - age, now - age))
        files[i] = p
    dead = tmp_path / "graphs" / ".3.abc.tmp"
    dead.write_bytes(b"half")
    os.utime(dead, (now - 5000, now - 5000))
    fresh = tmp_path / "graphs" / ".4.def.tmp"
    fresh.write_bytes(b"being written")
    # a shared precompute's chunk result, however old, belongs to its run (worker/chunks.py)
    chunk = tmp_path / "runs" / "cache-1.ab" / "3-0.npz"
    chunk.parent.mkdir(parents=True)
    chunk.write_bytes(b"x" * 100)
    os.utime(chunk, (now - 9000, now - 9000))
    removed = evict_lru(tmp_path, max_bytes=250, min_age_s=300)
    assert sorted(removed) == [files[0], files[1]]
    assert files[2].exists() and files[3].exists() and chunk.exists()
    assert not dead.exists() and fresh.exists()
    # over budget, but the rest is recent: kept
    assert evict_lru(tmp_path, max_bytes=0, min_age_s=2000) == [files[2]] and files[3].exists()
