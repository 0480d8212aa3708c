"""A real running service for integration tests: redis-server, worker processes and uvicorn.

Nothing is mocked: each piece is the program `make run` starts, on free ports, with its data in
a temporary folder.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from .conftest import DATA  # the real test volumes

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Service:
    """Handles on the processes of a running service."""

    data_dir: Path
    env: dict
    redis_port: int
    api_port: int
    redis: subprocess.Popen | None = None
    api: subprocess.Popen | None = None
    workers: list[subprocess.Popen] = field(default_factory=list)
    logs: list = field(default_factory=list)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.api_port}"

    def client(self, **kw) -> httpx.Client:
        return httpx.Client(base_url=self.url, **{"timeout": 120, **kw})

    def _log(self, name: str):
        f = open(self.data_dir / f"{name}.log", "ab")  # noqa: SIM115  (closed in stop())
        self.logs.append(f)
        return f

    def start_redis(self) -> None:
        (self.data_dir / "redis").mkdir(parents=True, exist_ok=True)
        self.redis = subprocess.Popen(
            [
                shutil.which("redis-server") or "/usr/bin/redis-server",
                "--port",
                str(self.redis_port),
                "--bind",
                "127.0.0.1",
                "--dir",
                str(self.data_dir / "redis"),
                "--appendonly",
                "yes",
                "--appendfsync",
                "always",
                "--save",
                "",
            ],
            stdout=self._log("redis"),
            stderr=subprocess.STDOUT,
        )
        wait_until(lambda: _ping(self.redis_port), 10, "redis-server did not start")

    def stop_redis(self) -> None:
        self.redis.terminate()
        self.redis.wait(10)

    def start_worker(self) -> subprocess.Popen:
        w = subprocess.Popen(  # the supervisor; it starts and watches the worker process
            [sys.executable, "-m", "worker"],
            cwd=ROOT,
            env=self.env,
            stdout=self._log(f"worker{len(self.workers)}"),
            stderr=subprocess.STDOUT,
        )
        self.workers.append(w)
        return w

    def start_api(self) -> None:
        self.api = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "uvicorn",
                "--factory",
                "server.main:create_app",
                "--host",
                "127.0.0.1",
                "--port",
                str(self.api_port),
                "--log-level",
                "warning",
            ],
            cwd=ROOT,
            env=self.env,
            stdout=self._log("api"),
            stderr=subprocess.STDOUT,
        )
        wait_until(lambda: get_ok(f"{self.url}/healthz"), 30, "the API did not start")

    def wait_ready(self, timeout: float = 60) -> None:
        """Until every worker started is alive (counted by /readyz)."""

        def all_alive():
            try:
                r = httpx.get(f"{self.url}/readyz", timeout=2)
            except httpx.HTTPError:
                return False
            return r.status_code == 200 and r.json()["workers"] >= len(self.workers)

        wait_until(all_alive, timeout, f"not all {len(self.workers)} workers became ready")

    def stop(self) -> None:
        for p in [self.api, *self.workers, self.redis]:
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in [self.api, *self.workers, self.redis]:
            if p is not None:
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
        for f in self.logs:
            f.close()


def start_service(data_dir: Path, workers: int = 1, **settings) -> Service:
    """Starts redis, ``workers`` workers and the API; ``settings`` become CLOUDGRAPH_* variables."""
    data_dir.mkdir(parents=True, exist_ok=True)
    redis_port, api_port = free_port(), free_port()
    env = {
        **os.environ,
        "CLOUDGRAPH_DATA_DIR": str(data_dir),
        "CLOUDGRAPH_REDIS_URL": f"redis://127.0.0.1:{redis_port}/0",
        "PYTHONUNBUFFERED": "1",
    }
    env.update({f"CLOUDGRAPH_{k}": str(v) for k, v in settings.items()})
    svc = Service(data_dir, env, redis_port, api_port)
    try:
        svc.start_redis()
        for _ in range(workers):
            svc.start_worker()
        svc.start_api()
        if workers:
            svc.wait_ready()
    except BaseException:
        svc.stop()
        raise
    return svc


def wait_until(predicate, timeout: float, message: str, interval: float = 0.1):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise TimeoutError(message)


def _ping(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5) as s:
            s.sendall(b"PING\r\n")
            return s.recv(16).startswith(b"+PONG")
    except OSError:
        return False


def get_ok(url: str) -> bool:
    try:
        return httpx.get(url, timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


# ------------------------------------------------------------------ helpers for service tests

FOG = DATA / "fog_sphere.vdb"  # 78 KB: a draft cache in well under a second
BLENDER = DATA / "blender_smoke_000002.vdb"  # 300 KB: a draft cache in a few seconds, every stage
SMOKE = DATA / "smoke1.vdb"  # 2.5 MB: long precomputes
KEY = "k3y-for-tests-0123456789abcdef"
TERMINAL = ("finished", "failed", "canceled")


def fog_scene(
    vid: str, width: int = 32, height: int | None = None, spp: int = 4, density: float = 5.0
) -> dict:
    """The fog sphere (centre (0, 2, 0), radius 1.1), seen from the side."""
    camera = {"eye": [0, 2, 6], "target": [0, 2, 0], "fov": 30, "width": width, "height": height or width}
    return {
        "volume": {"id": vid},
        "medium": {"density_scale": density},
        "light": {"direction": [1, -1, 0]},
        "camera": camera,
        "render": {"spp": spp},
    }


def smoke_scene(vid: str, density: float, width: int = 32) -> dict:
    """smoke1.vdb (a 110 x 220 x 110 plume, y up) from the front."""
    camera = {"eye": [-7, 40, 160], "target": [-7, 40, 0], "fov": 45, "width": width, "height": width}
    return {
        "volume": {"id": vid},
        "medium": {"density_scale": density},
        "light": {"direction": [0.55, -0.25, -0.8]},
        "camera": camera,
        "render": {"spp": 4},
    }


def blender_cache(vid: str, density: float = 6.0) -> dict:
    """A /v1/caches body for the Blender smoke (z up, about 7 x 7 x 10.5 units)."""
    return {
        "volume": {"id": vid},
        "medium": {"density_scale": density},
        "light": {"direction": [0.3, 0.2, -1]},
        "quality": "draft",
    }


def cache_of(scene: dict, quality: str = "draft") -> dict:
    """The /v1/caches body of a scene's cache."""
    return {k: scene[k] for k in ("volume", "medium", "light")} | {"quality": quality}


def upload(client, path, name: str | None = None):
    with open(path, "rb") as f:
        return client.post("/v1/volumes", files={"file": (name or Path(path).name, f)})


def job_of(response) -> str:
    """The job id from a 202's Location header."""
    location = response.headers["location"]
    assert location.startswith("/v1/jobs/"), location
    return location.removeprefix("/v1/jobs/")


def wait_job(client, job_id: str, timeout: float = 180) -> dict:
    def ended():
        r = client.get(f"/v1/jobs/{job_id}")
        assert r.status_code == 200, r.text
        return r.json() if r.json()["status"] in TERMINAL else None

    return wait_until(ended, timeout, f"job {job_id} did not end in {timeout} s", interval=0.1)


def wait_stage(client, job_id: str, timeout: float = 120) -> dict:
    """The job once it runs and has reported a stage of its own."""

    def running():
        j = client.get(f"/v1/jobs/{job_id}").json()
        assert j["status"] not in TERMINAL, j
        return j if j["status"] == "running" and j["stage"] not in (None, "queued") else None

    return wait_until(running, timeout, f"job {job_id} never started", interval=0.05)


def sse(client, job_id: str) -> list[tuple[str, dict]]:
    """(event, data) pairs of a job's event stream, read to its end."""
    out, event = [], None
    with client.stream("GET", f"/v1/jobs/{job_id}/events") as r:
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/event-stream")
        for line in r.iter_lines():
            if line.startswith("event: "):
                event = line.removeprefix("event: ")
            elif line.startswith("data: "):
                out.append((event, json.loads(line.removeprefix("data: "))))
    return out


def png_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n", data[:16]
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def rq(svc: Service):
    from redis import Redis

    return Redis(port=svc.redis_port)


def rq_job(svc: Service, job_id: str):
    from rq.job import Job

    return Job.fetch(job_id, connection=rq(svc))


def no_server_errors(svc: Service) -> None:
    """No request to this service was answered with a 500 (the API counts every answer; the 503s
    of /readyz and of a Redis outage are meant)."""
    with svc.client() as c:
        metrics = c.get("/metrics").text
    counted = [ln for ln in metrics.splitlines() if ln.startswith("cloudgraph_http_requests_total{")]
    assert counted, metrics
    assert not [ln for ln in counted if 'status="500"' in ln], counted


def cache_files(svc: Service) -> set:
    return {p.relative_to(svc.data_dir) for p in (svc.data_dir / "cache").rglob("*") if p.is_file()}


def detail(r) -> str:
    body = r.json()
    assert isinstance(body.get("detail"), str), body
    return body["detail"]


#: What an answer must never show: server paths, exception class names, tracebacks.
_LEAKS = re.compile(
    r"(?<![\w.])/(tmp|work|home|root|usr|var|opt|srv)/|Traceback|File \"|"
    r"\b[A-Z]\w*(Error|Exception)\b|\bcloudgraph\.\w|\bworker\.\w|\brq\.\w|\bpydantic"
)


def assert_no_leak(text: str, svc: Service | None = None) -> None:
    """``text`` (an answer or a job's error) holds no server path, class name or traceback."""
    assert not _LEAKS.search(text), text
    if svc is not None:
        assert str(svc.data_dir) not in text, text


def sparse_vdb(path: Path, span: int, value: float = 1.0) -> Path:
    """A .vdb of two active voxels ``span`` apart on each axis: a few KB on disk, a
    ``span``^3 box dense."""
    import pyopenvdb as vdb

    g = vdb.FloatGrid()
    g.name = "density"
    acc = g.getAccessor()
    acc.setValueOn((0, 0, 0), value)
    acc.setValueOn((span - 1, span - 1, span - 1), value)
    vdb.write(str(path), grids=[g])
    return path


def stuck_forever() -> None:
    """A job that never ends and cannot be interrupted from inside, as native code that holds on
    (a Dr.Jit kernel in a loop): the alarm of RQ's own timeout is blocked. Only being killed from
    outside stops it."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM, signal.SIGTERM, signal.SIGINT})
    while True:
        time.sleep(3600)


def fails_with_a_path() -> None:
    """A job whose error, as raised, names a server path and a class: neither may reach a client."""
    raise RuntimeError(f"cannot open {ROOT}/data/secret/volume.vdb: KeyError in cloudgraph.volume")
