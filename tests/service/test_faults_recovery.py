"""Every part of `make run`'s service can die alone: the worker process, its supervisor, Redis
(SIGTERM and SIGKILL) and the API, each killed in the middle of a precompute and of a render.
The launcher starts the dead part again and the others stay up; the job completes with the
bytes of an undisturbed run, within 5 s of the dead part being back; nothing leaks.
"""

from __future__ import annotations

import os
import re
import signal
import time

import httpx
import pytest
from rq import Worker
from rq.job import Job

from ..harness import FOG, cache_of, fog_scene, upload, wait_until
from .faults import (
    PRECOMPUTE_STAGES,
    Launched,
    assert_no_leaks,
    cache_files,
    hold_at_stage,
    wait_status,
)

#: (part, signal): what each case kills.
FAULTS = [
    ("worker", signal.SIGKILL),
    ("supervisor", signal.SIGKILL),
    ("redis", signal.SIGTERM),
    ("redis", signal.SIGKILL),
    ("api", signal.SIGKILL),
]
IDS = [f"{part}-{signal.Signals(sig).name}" for part, sig in FAULTS]
#: Seconds from the dead part being back to the job's end (the issue's bound).
RECOVERY_S = 5.0
#: The render the render cases make: long enough (a few tens of ms) to be caught in the middle.
RENDER = {"width": 96, "spp": 32}


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    # Every render a job (none answered in the request), so that each can be caught running
    svc = Launched(tmp_path_factory.mktemp("faults"), {"SYNC_MAX_PIXELS": 0}).start()
    yield svc
    took = svc.stop(signal.SIGINT, group=True)  # Ctrl-C: every process ends
    print(f"stopped by Ctrl-C in {took:.2f} s")
    assert took < 20, took


@pytest.fixture(scope="module")
def fog(service) -> str:
    with service.client() as c:
        r = upload(c, FOG)
        assert r.status_code == 201, r.text
        return r.json()["id"]


def _back(svc: Launched, part: str, old: dict[str, int]) -> float:
    """Waits until the killed ``part`` runs again (a new process that answers); the monotonic
    time it did."""

    def answers() -> bool:
        pids = svc.pids()
        if part in ("worker", "supervisor"):  # a new worker process, registered with RQ
            new = pids.get("worker", old["worker"])
            return new != old["worker"] and any(w.pid == new for w in Worker.all(connection=svc.redis()))
        if pids.get(part, old[part]) == old[part]:
            return False
        if part == "redis":
            try:
                return bool(svc.redis().ping())
            except Exception:
                return False
        return _get(svc, "/healthz") == 200

    wait_until(answers, 60, f"{part} did not come back", interval=0.02)
    return time.monotonic()


def _get(svc: Launched, path: str) -> int:
    try:
        return httpx.get(f"{svc.url}{path}", timeout=2).status_code
    except httpx.HTTPError:
        return 0


def _kill(svc: Launched, part: str, sig: int, held: int) -> dict[str, int]:
    """Kills ``part`` while the worker process ``held`` is paused, then lets that go on (unless
    it died with it); returns the pids from before."""
    old = svc.pids()
    assert old["worker"] == held
    os.kill(old[part], sig)
    if part not in ("worker", "supervisor"):
        os.kill(held, signal.SIGCONT)
    return old


def _outcome(svc: Launched, part: str, old: dict[str, int], restarts: int) -> None:
    """The others stayed up, the dead part was started again (logged once per restart)."""
    now = svc.pids()
    for other in ("redis", "api", "supervisor"):
        if other != part:
            assert now[other] == old[other], (other, old, now)
    name = "worker 1" if part in ("worker", "supervisor") else part
    # (anywhere in a line: another process's output, Mitsuba's colour reset, may precede it)
    mark = re.compile(rf"cloudgraph: {re.escape(name)} \(pid \d+\) exited")
    lines = [ln for ln in svc.log_text().splitlines() if mark.search(ln)]
    assert len(lines) == restarts, lines
    if part == "supervisor":
        assert f"(pid {old['supervisor']}) exited with status 137; starting it again in" in lines[-1]


_killed: dict[str, int] = {}  # restarts logged so far, by launcher name


def _count(part: str) -> int:
    if part in ("redis", "api", "supervisor"):
        key = "worker 1" if part == "supervisor" else part
        _killed[key] = _killed.get(key, 0) + 1
    return _killed.get("worker 1" if part in ("worker", "supervisor") else part, 0)


@pytest.mark.parametrize(("part", "sig"), FAULTS, ids=IDS)
def test_a_part_killed_mid_precompute_comes_back_and_the_cache_is_the_undisturbed_one(
    service, fog, part, sig
):
    density = 4.0 + FAULTS.index((part, sig)) * 0.25  # a cache of its own
    body = {
        "volume": {"id": fog},
        "medium": {"density_scale": density},
        "light": {"direction": [1, -1, 0]},
        "quality": "draft",
    }
    redis = service.redis()
    with service.client() as c:
        # The undisturbed run, then its files and job removed, so that the precompute runs again
        r = c.post("/v1/caches", json=body)
        job_id = f"cache-{r.json()['id']}"
        end, _ = wait_status(c, job_id, 120, svc=service)
        assert end["status"] == "finished", end
        files = cache_files(service, end["result"]["keys"])
        undisturbed = {k: p.read_bytes() for k, p in files.items()}
        for p in files.values():
            p.unlink()
        Job.fetch(job_id, connection=redis).delete()

        def submit() -> str:
            r = c.post("/v1/caches", json=body)
            assert r.status_code == 202, r.text
            return f"cache-{r.json()['id']}"

        job_id, stage, held = hold_at_stage(service, submit, PRECOMPUTE_STAGES)
        assert stage in PRECOMPUTE_STAGES
        t_kill = time.monotonic()
        old = _kill(service, part, sig, held)
        t_back = _back(service, part, old)
        end, t_done = wait_status(c, job_id, 120, svc=service)

    assert end["status"] == "finished", end
    assert t_done - t_back < RECOVERY_S, (t_back - t_kill, t_done - t_back)
    print(f"{part}/{signal.Signals(sig).name} at {stage}: back in {t_back - t_kill:.2f} s, "
          f"job done {t_done - t_back:.2f} s later")  # fmt: skip
    assert {k: p.read_bytes() for k, p in files.items()} == undisturbed
    job = Job.fetch(job_id, connection=redis)
    ran_again = part in ("worker", "supervisor")
    assert job.retries_left == (1 if ran_again else 2), job.retries_left  # put back once, or never
    _outcome(service, part, old, _count(part))
    assert_no_leaks(service)


@pytest.fixture(scope="module")
def render_scene(service, fog) -> dict:
    scene = fog_scene(fog, RENDER["width"], spp=RENDER["spp"], density=6.0)
    with service.client() as c:  # its cache, ready
        r = c.post("/v1/caches", json=cache_of(scene))
        end, _ = wait_status(c, f"cache-{r.json()['id']}", 120, svc=service)
        assert end["status"] == "finished", end
    return scene


def _render(c, scene: dict) -> str:
    r = c.post("/v1/renders", json={"scene": scene, "quality": "draft"})
    assert r.status_code == 202, r.text
    return r.json()["id"]


@pytest.mark.parametrize(("part", "sig"), FAULTS, ids=IDS)
def test_a_part_killed_mid_render_comes_back_and_the_image_is_the_undisturbed_one(
    service, render_scene, part, sig
):
    redis = service.redis()
    with service.client() as c:
        first = _render(c, render_scene)
        end, _ = wait_status(c, first, 120, svc=service)
        assert end["status"] == "finished", end
        undisturbed = c.get(end["result_url"]).content

        job_id, stage, held = hold_at_stage(service, lambda: _render(c, render_scene), ("render",))
        assert stage == "render"
        t_kill = time.monotonic()
        old = _kill(service, part, sig, held)
        t_back = _back(service, part, old)
        end, t_done = wait_status(c, job_id, 120, svc=service)
        assert end["status"] == "finished", end
        image = c.get(end["result_url"])

    assert t_done - t_back < RECOVERY_S, (t_back - t_kill, t_done - t_back)
    print(f"{part}/{signal.Signals(sig).name} mid-render: back in {t_back - t_kill:.2f} s, "
          f"job done {t_done - t_back:.2f} s later")  # fmt: skip
    assert image.status_code == 200 and image.content == undisturbed
    job = Job.fetch(job_id, connection=redis)
    assert job.retries_left == (1 if part in ("worker", "supervisor") else 2), job.retries_left
    _outcome(service, part, old, _count(part))
    assert_no_leaks(service)
