"""A real running service for integration tests: redis-server, worker processes and uvicorn.

Nothing is mocked: each piece is the program `make run` starts, on free ports, with its data in
a temporary folder.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

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
        w = subprocess.Popen(
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
        wait_until(lambda: _get_ok(f"{self.url}/healthz"), 30, "the API did not start")

    def wait_ready(self, timeout: float = 60) -> None:
        wait_until(lambda: _get_ok(f"{self.url}/readyz"), timeout, "no worker became ready")

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


def _get_ok(url: str) -> bool:
    try:
        return httpx.get(url, timeout=2).status_code == 200
    except httpx.HTTPError:
        return False
