"""How the service is put together: the API process never loads the renderer, server/ and
worker/ share only cloudgraph_service, and the settings are honoured by both."""

from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys

from cloudgraph_service.settings import Settings

from ..harness import (
    FOG,
    ROOT,
    cache_of,
    fog_scene,
    free_port,
    get_ok,
    start_service,
    upload,
    wait_job,
    wait_until,
)


def test_the_api_process_loads_neither_mitsuba_nor_drjit_nor_the_worker():
    code = (
        "import sys, server.main\n"
        "server.main.create_app()\n"
        "print(' '.join(m for m in ('mitsuba', 'drjit', 'scipy', 'worker', 'pyopenvdb') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", out.stdout


def _imports(package: str) -> set[str]:
    """Top-level modules that the package's files import."""
    found = set()
    for path in (ROOT / package).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split(".")[0])
    return found


def test_server_and_worker_share_only_cloudgraph_service():
    assert "worker" not in _imports("server")
    assert "server" not in _imports("worker")
    assert not {"server", "worker", "fastapi"} & _imports("cloudgraph_service")


def test_the_cache_dir_setting_is_honoured_by_the_service(tmp_path, monkeypatch):
    monkeypatch.setenv("CLOUDGRAPH_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("CLOUDGRAPH_CACHE_DIR", str(tmp_path / "elsewhere"))
    assert Settings.from_env().cache_dir == tmp_path / "elsewhere"
    monkeypatch.delenv("CLOUDGRAPH_CACHE_DIR")
    assert Settings.from_env().cache_dir == tmp_path / "data" / "cache"

    s = start_service(tmp_path / "data", workers=1, CACHE_DIR=tmp_path / "elsewhere")
    try:
        with s.client() as c:
            vid = upload(c, FOG).json()["id"]
            r = c.post("/v1/caches", json=cache_of(fog_scene(vid)))
            cache = r.json()
            assert wait_job(c, f"cache-{cache['id']}")["status"] == "finished"
            key = c.get(f"/v1/caches/{cache['id']}").json()["keys"]["radiance_key"]
            assert list((tmp_path / "elsewhere").rglob(f"{key}*")), "the radiance is not in CACHE_DIR"
            assert not (tmp_path / "data" / "cache").exists()
            field = c.get(f"/v1/caches/{cache['id']}/field")  # the API reads it from there too
            assert field.status_code == 200, field.text
    finally:
        s.stop()


def _listening(port: int) -> set[str]:
    """Local addresses (hex, as /proc/net/tcp writes them) listening on ``port``."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as f:
            for line in f.readlines()[1:]:
                local, state = line.split()[1], line.split()[3]
                addr, _, hexport = local.rpartition(":")
                if state == "0A" and int(hexport, 16) == port:
                    found.add(addr)
    return found


def test_make_run_listens_on_localhost_only_unless_told(tmp_path):
    port, redis_port = free_port(), free_port()
    env = {
        **os.environ,
        "PORT": str(port),
        "REDIS_PORT": str(redis_port),
        "WORKERS": "0",
        "CLOUDGRAPH_DATA_DIR": str(tmp_path / "data"),
    }
    env.pop("HOST", None)
    proc = subprocess.Popen(
        [str(ROOT / "bin" / "run-service")], cwd=ROOT, env=env, start_new_session=True,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        wait_until(lambda: get_ok(f"http://127.0.0.1:{port}/healthz"), 60, "make run did not start")
        assert _listening(port) == {"0100007F"}  # 127.0.0.1, nothing else
        assert _listening(redis_port) == {"0100007F"}
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(20)
