"""A full data volume, and one that may not be written: the job's error and the answer say so
(with the free space), no partial file is left, jobs that do not need the space go on, and the
next job is fine once there is room again.

The volumes are small tmpfs mounts, which only root can make: run as another user, the module is
skipped with that reason.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest

from ..harness import BLENDER, FOG, cache_of, fog_scene, png_size
from .faults import Launched, assert_no_leaks, cache_files, wait_status

SIZE = "1m"


def _mount(folder: Path, *options: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", ",".join((f"size={SIZE}", *options)), "tmpfs", str(folder)],
                   check=True, capture_output=True)  # fmt: skip


def _remount(folder: Path, option: str) -> None:
    subprocess.run(["mount", "-o", f"remount,{option}", str(folder)], check=True, capture_output=True)


def _fill(folder: Path, leave: int) -> Path:
    """A file that leaves about ``leave`` bytes free on the volume of ``folder``."""
    import shutil

    filler = folder / "filler.bin"
    free = shutil.disk_usage(folder).free
    with open(filler, "wb") as f:
        f.write(b"\0" * max(0, free - leave))
    return filler


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    data = tmp_path_factory.mktemp("disk")
    try:
        _mount(data / "cache")
    except (subprocess.CalledProcessError, FileNotFoundError, PermissionError) as err:
        why = getattr(err, "stderr", b"") or str(err).encode()
        pytest.skip(f"a small tmpfs cannot be mounted here (root only): {why.decode().strip()}")
    try:
        _mount(data / "volumes")
        svc = Launched(data, {"CACHE_DIR": data / "cache"}).start()
        try:
            yield svc
        finally:
            svc.stop()
    finally:
        for folder in ("volumes", "cache"):
            subprocess.run(["umount", "-l", str(data / folder)], capture_output=True)


def _no_partial_files(folder: Path) -> None:
    left = [p.name for p in folder.rglob("*") if p.name.endswith(".tmp") or p.name.startswith(".")]
    assert not left, left


def test_a_full_cache_volume_fails_the_precompute_in_words_and_the_next_job_is_fine(service):
    cache = service.data_dir / "cache"
    with service.client() as c:
        r = c.post("/v1/volumes", files={"file": (FOG.name, FOG.read_bytes())})
        assert r.status_code == 201, r.text
        vid = r.json()["id"]
        scene = fog_scene(vid, 16, density=5.0)
        filler = _fill(cache, 4096)

        r = c.post("/v1/caches", json=cache_of(scene))
        job = f"cache-{r.json()['id']}"
        t0 = time.monotonic()
        end, t1 = wait_status(c, job, 60)
        assert end["status"] == "failed", end
        assert end["error"].startswith("the cache volume is full ("), end["error"]
        assert end["error"].endswith(" free): free some space on it, or lower CLOUDGRAPH_CACHE_MAX_GB")
        assert "KiB free" in end["error"] or "bytes free" in end["error"]
        print(f"full cache volume: failed in {t1 - t0:.2f} s: {end['error']}")
        _no_partial_files(cache)
        log = service.log_text()
        assert f"job {job} failed" in log and "No space left on device" in log  # the details

        # A job that needs no room on it goes on meanwhile
        r = c.post("/v1/renders", json={"scene": scene, "integrator": "volpath"})
        assert r.status_code == 200 and png_size(r.content) == (16, 16), r.text

        filler.unlink()  # room again: asking again makes the cache, whole
        r = c.post("/v1/caches", json=cache_of(scene))
        assert r.status_code == 202, r.text
        end, _ = wait_status(c, job, 60)
        assert end["status"] == "finished", end
        assert all(p.is_file() for p in cache_files(service, end["result"]["keys"]).values())
        assert c.get(f"/v1/caches/{r.json()['id']}/field").status_code == 200
    assert_no_leaks(service)


def test_a_read_only_cache_volume_says_so(service):
    cache = service.data_dir / "cache"
    with service.client() as c:
        vid = c.get("/v1/volumes").json()[0]["id"]
        scene = fog_scene(vid, 16, density=6.5)
        _remount(cache, "ro")
        try:
            r = c.post("/v1/caches", json=cache_of(scene))
            job = f"cache-{r.json()['id']}"
            end, _ = wait_status(c, job, 60)
        finally:
            _remount(cache, "rw")
        assert end["status"] == "failed", end
        assert end["error"] == (
            "the cache volume is not writable (read-only): an operator has to make it writable"
        )
        r = c.post("/v1/caches", json=cache_of(scene))
        end, _ = wait_status(c, job, 60)
        assert end["status"] == "finished", end
    _no_partial_files(cache)
    assert_no_leaks(service)


def test_an_upload_to_a_full_uploads_volume_is_507_and_leaves_nothing(service):
    volumes = service.data_dir / "volumes"
    filler = _fill(volumes, 64 * 1024)  # room for less than the upload's copies
    try:
        with service.client() as c:
            r = c.post("/v1/volumes", files={"file": (BLENDER.name, BLENDER.read_bytes())})
            assert r.status_code == 507, r.text
            assert r.json()["detail"].startswith("the uploads volume is full ("), r.text
            assert r.json()["detail"].endswith(" free): free some space on it")
            names = [v["filename"] for v in c.get("/v1/volumes").json()]
            assert BLENDER.name not in names
        _no_partial_files(volumes)
    finally:
        filler.unlink()
    with service.client() as c:  # room again
        r = c.post("/v1/volumes", files={"file": (BLENDER.name, BLENDER.read_bytes())})
        assert r.status_code == 201, r.text
    assert_no_leaks(service)
