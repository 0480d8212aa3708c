"""compose.yaml end to end: the image is built (cached layers: seconds after a code change), the
cluster (Redis, the API, two RQ workers on one data volume, a Dask scheduler and two Dask
workers) comes up under a project name of its own and free ports on 127.0.0.1, waits on every
healthcheck, then a real volume is uploaded, a draft cache precomputed and a small image rendered
over HTTP on the published port; a precompute during which one Dask worker is SIGKILLed ends with
the bytes of the same precompute run undisturbed in one process. The cluster and its volumes are
removed in a finalizer, whatever happens.

Skipped, with the reason, where Docker or docker-compose is missing or its daemon does not
answer, or where the base image (``make base-image``) has not been made. ``make cluster-test``
makes everything it needs (as root); ``CLOUDGRAPH_CLUSTER_TEST=0`` turns the test off.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import socket
import struct
import subprocess
import time
import zlib
from pathlib import Path

import httpx
import pytest

from ..conftest import DATA, ROOT

BASE_IMAGE = os.environ.get("BASE_IMAGE", "cloudgraph-base:bookworm")
IMAGE = os.environ.get("CLOUDGRAPH_IMAGE", "cloudgraph:latest")
FOG = DATA / "fog_sphere.vdb"  # 78 KB: a draft cache in a few seconds
BLENDER = DATA / "blender_smoke_000002.vdb"  # 300 KB: a default cache in some 10 s on 2 cores
WORKERS = 2  # RQ workers
DASK_WORKERS = 2
ARTIFACTS = ROOT / "test-artifacts" / "cluster"


def _run(*cmd: str, timeout: float = 60, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd=ROOT)


def _compose_command() -> list[str] | None:
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    if shutil.which("docker") and _run("docker", "compose", "version").returncode == 0:
        return ["docker", "compose"]
    return None


def _why_not() -> str | None:
    """Why the cluster cannot be tested here, or None."""
    if os.environ.get("CLOUDGRAPH_CLUSTER_TEST") == "0":
        return "CLOUDGRAPH_CLUSTER_TEST=0"
    if not shutil.which("docker"):
        return "docker is not installed (make cluster-test installs Debian's docker.io, as root)"
    if _compose_command() is None:
        return "docker-compose is not installed (make cluster-test installs it, as root)"
    info = _run("docker", "info", timeout=30)
    if info.returncode != 0:
        return (
            f"the Docker daemon does not answer: {info.stderr.strip()[-200:]} (make cluster-test starts it)"
        )
    if _run("docker", "image", "inspect", BASE_IMAGE).returncode != 0:
        return f"no base image {BASE_IMAGE}: make base-image makes it (root, debootstrap)"
    if not FOG.is_file():
        return f"test volume {FOG} not found (set CLOUDGRAPH_TEST_DATA)"
    return None


WHY_NOT = _why_not()
pytestmark = pytest.mark.skipif(WHY_NOT is not None, reason=f"cluster test: {WHY_NOT}")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def png_pixels(data: bytes) -> tuple[int, int, int, bytes]:
    """(width, height, channels, raw bytes) of an 8-bit, non-interlaced PNG, decoded with zlib
    and the five scanline filters (no imaging library needed)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        pos += 12 + length
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        elif kind == b"IEND":
            break
    assert header is not None, "PNG without IHDR"
    width, height, depth, color, _, _, interlace = header
    assert depth == 8 and interlace == 0, header
    channels = {0: 1, 2: 3, 4: 2, 6: 4}[color]
    raw, stride, out = zlib.decompress(idat), width * channels, bytearray()
    prev = bytearray(stride)
    for y in range(height):
        filt, line = raw[y * (stride + 1)], bytearray(raw[y * (stride + 1) + 1 : (y + 1) * (stride + 1)])
        for i in range(stride):
            a = line[i - channels] if i >= channels else 0
            b, c = prev[i], prev[i - channels] if i >= channels else 0
            if filt == 1:
                line[i] = (line[i] + a) & 255
            elif filt == 2:
                line[i] = (line[i] + b) & 255
            elif filt == 3:
                line[i] = (line[i] + (a + b) // 2) & 255
            elif filt == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        out += line
        prev = line
    return width, height, channels, bytes(out)


class Cluster:
    def __init__(self, project: str, port: int, key: str):
        self.project, self.port, self.key = project, port, key
        self.url = f"http://127.0.0.1:{port}"
        self.env = os.environ | {
            "CLOUDGRAPH_API_KEYS": key,
            "CLOUDGRAPH_PORT": str(port),
            "CLOUDGRAPH_DASHBOARD_PORT": str(free_port()),
            "CLOUDGRAPH_BIND": "127.0.0.1",
            "CLOUDGRAPH_IMAGE": IMAGE,
        }
        self.times: dict[str, float] = {}

    def compose(self, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
        cmd = [*_compose_command(), "-p", self.project, "-f", str(ROOT / "compose.yaml"), *args]
        return _run(*cmd, timeout=timeout, env=self.env)

    def containers(self) -> dict[str, str]:
        """Container id -> health status (or state, without a healthcheck)."""
        ids = self.compose("ps", "-q").stdout.split()
        if not ids:
            return {}
        fmt = "{{.Id}} {{if .State.Health}}{{.State.Health.Status}}{{else}}{{.State.Status}}{{end}}"
        out = _run("docker", "inspect", "-f", fmt, *ids).stdout.split("\n")
        return dict(line.split() for line in out if line.strip())

    def logs(self) -> str:
        return self.compose("logs", "--no-color", "--tail", "40", timeout=60).stdout[-6000:]


def remove_stale_clusters() -> None:
    """Removes the clusters (and volumes) of earlier test runs whose pytest process is gone
    (killed before its finalizer ran)."""
    label = "com.docker.compose.project"
    out = _run("docker", "ps", "-a", "--filter", f"label={label}", "--format", f'{{{{.Label "{label}"}}}}')
    for project in set(out.stdout.split()):
        pid = project.removeprefix("cgtest")
        if project.startswith("cgtest") and pid.isdigit() and not Path(f"/proc/{pid}").exists():
            Cluster(project, 0, "k-" + secrets.token_hex(16)).compose("down", "-v", "-t", "5", timeout=180)


@pytest.fixture(scope="module")
def cluster(request) -> Cluster:
    remove_stale_clusters()
    t0 = time.monotonic()
    build = _run(str(ROOT / "docker" / "build-image.sh"), timeout=1500, env=os.environ | {"QUIET": "1"})
    assert build.returncode == 0, f"image build failed:\n{build.stdout[-3000:]}\n{build.stderr[-3000:]}"
    c = Cluster(f"cgtest{os.getpid()}", free_port(), "k-" + secrets.token_hex(16))
    c.times["build_s"] = time.monotonic() - t0

    def down():
        t = time.monotonic()
        c.compose("down", "-v", "--remove-orphans", "-t", "20", timeout=180)
        c.times["down_s"] = time.monotonic() - t
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "timings.json").write_text(json.dumps(c.times, indent=1) + "\n")
        print(f"\ncluster timings: {c.times}")

    request.addfinalizer(down)  # before `up`: a half-started cluster is removed as well
    t0 = time.monotonic()
    up = c.compose("up", "-d", "--no-build")
    assert up.returncode == 0, f"docker-compose up failed:\n{up.stderr[-3000:]}\n{c.logs()}"
    deadline, states = time.monotonic() + 240, {}
    while time.monotonic() < deadline:
        states = c.containers()
        if len(states) == 3 + WORKERS + DASK_WORKERS and all(s == "healthy" for s in states.values()):
            break
        assert "unhealthy" not in states.values() and "exited" not in states.values(), (states, c.logs())
        time.sleep(1)
    else:
        pytest.fail(f"the cluster was not healthy in 240 s: {states}\n{c.logs()}")
    c.times["up_healthy_s"] = time.monotonic() - t0
    return c


def test_compose_requires_api_keys():
    """Without CLOUDGRAPH_API_KEYS the compose file refuses to start anything, and says why."""
    env = {k: v for k, v in os.environ.items() if k != "CLOUDGRAPH_API_KEYS"}
    r = _run(*_compose_command(), "-f", str(ROOT / "compose.yaml"), "config", env=env)
    assert r.returncode != 0
    assert "CLOUDGRAPH_API_KEYS" in r.stdout + r.stderr


def test_cluster_uploads_precomputes_and_renders(cluster: Cluster):
    t0 = time.monotonic()
    # Published on the loopback interface only.
    port = cluster.compose("port", "api", "8000").stdout.strip()
    assert port == f"127.0.0.1:{cluster.port}", port

    headers = {"Authorization": f"Bearer {cluster.key}"}
    with httpx.Client(base_url=cluster.url, headers=headers, timeout=60) as http:
        assert http.get("/v1/volumes", headers={"Authorization": ""}).status_code == 401
        ready = http.get("/readyz")
        assert ready.status_code == 200 and ready.json()["workers"] == WORKERS, ready.text

        with open(FOG, "rb") as f:
            up = http.post("/v1/volumes", files={"file": (FOG.name, f)})
        assert up.status_code == 201, up.text
        vid = up.json()["id"]

        medium, light = {"density_scale": 5.0}, {"direction": [1, -1, 0]}
        body = {"volume": {"id": vid}, "medium": medium, "light": light, "quality": "draft"}
        pre = http.post("/v1/caches", json=body)
        assert pre.status_code in (200, 202), pre.text
        cid, deadline = pre.json()["id"], time.monotonic() + 300
        while (cache := http.get(f"/v1/caches/{cid}").json())["status"] not in ("finished", "failed"):
            assert time.monotonic() < deadline, f"precompute did not end in 300 s: {cache}"
            time.sleep(0.5)
        assert cache["status"] == "finished", cache
        assert cache["stats"]["nodes"] > 0, cache
        cluster.times["precompute_s"] = time.monotonic() - t0

        t1 = time.monotonic()
        camera = {"eye": [0, 2, 6], "target": [0, 2, 0], "fov": 30, "width": 48, "height": 40}
        scene = {"volume": {"id": vid}, "medium": medium, "light": light, "camera": camera}
        scene["render"] = {"spp": 4}
        render = http.post(
            "/v1/renders", json={"scene": scene, "integrator": "graph", "format": "png", "quality": "draft"}
        )
        assert render.status_code == 200, render.text
        assert render.headers["content-type"] == "image/png"
        cluster.times["render_s"] = time.monotonic() - t1
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "render.png").write_bytes(render.content)
    width, height, channels, pixels = png_pixels(render.content)
    assert (width, height) == (48, 40)
    assert any(pixels), "the render is black"
    assert len(set(pixels)) > 4, "the render is flat: no fog sphere in it"

    # Both workers see the cache on the one data volume.
    listings = {
        cluster.compose("exec", "-T", "--index", str(i), "worker", "find", "/data/cache", "-type", "f").stdout
        for i in range(1, WORKERS + 1)
    }
    assert len(listings) == 1 and listings.pop().strip(), "the workers do not share /data/cache"
    cluster.times["test_s"] = time.monotonic() - t0


# The cache of a scene, built in the worker container by one process alone (no Dask), in a store
# of its own (argv[2]); prints its keys, as JSON
_UNDISTURBED = """
import json, sys
from cloudgraph.mitsuba_scene import set_variant
from cloudgraph.cache import CacheStore
from cloudgraph.precompute import precompute
from cloudgraph.scene import parse_scene
from cloudgraph.store import VolumeStore
from cloudgraph.volume import load_volume
set_variant()
body = json.loads(sys.argv[1])
path = str(VolumeStore("/data/volumes").path(body["volume"]["id"]))
camera = {"eye": [30, 0, 5], "target": [0, 0, 5], "up": [0, 0, 1]}  # the cache does not depend on it
scene = {"medium": body["medium"], "light": body["light"], "volume": {"path": path}, "camera": camera}
scene = parse_scene(scene)
store = CacheStore(sys.argv[2])
keys = precompute(scene, load_volume(path), body["quality"], store).keys
print(json.dumps(keys))
"""

# The sha256 of a cache's files in a store of the worker container, as JSON
_DIGESTS = """
import hashlib, json, sys
from cloudgraph.cache import CacheStore
store, keys = CacheStore(sys.argv[1]), json.loads(sys.argv[2])
paths = {"graph": store.graph_path(keys["graph_key"]), "radiance": store.radiance_path(keys["radiance_key"]),
         "field": store.field_path(keys["radiance_key"])}
print(json.dumps({k: hashlib.sha256(p.read_bytes()).hexdigest() for k, p in paths.items()}))
"""


def test_a_dask_worker_sigkilled_mid_precompute_leaves_the_bytes_undisturbed(cluster: Cluster):
    t0 = time.monotonic()

    def in_worker(code: str, *args: str, timeout: float = 300) -> dict:
        r = cluster.compose("exec", "-T", "worker", "python", "-c", code, *args, timeout=timeout)
        assert r.returncode == 0, r.stderr[-3000:]
        return json.loads(r.stdout.strip().splitlines()[-1])

    headers = {"Authorization": f"Bearer {cluster.key}"}
    with httpx.Client(base_url=cluster.url, headers=headers, timeout=60) as http:
        with open(BLENDER, "rb") as f:
            up = http.post("/v1/volumes", files={"file": (BLENDER.name, f)})
        assert up.status_code in (200, 201), up.text
        body = {
            "volume": {"id": up.json()["id"]},
            "medium": {"density_scale": 6.0},
            "light": {"direction": [0.3, 0.2, -1]},
            "quality": "default",
        }
        keys = in_worker(_UNDISTURBED, json.dumps(body), "/tmp/undisturbed")
        undisturbed = in_worker(_DIGESTS, "/tmp/undisturbed", json.dumps(keys))
        cluster.times["undisturbed_s"] = time.monotonic() - t0

        t1 = time.monotonic()
        pre = http.post("/v1/caches", json=body)
        assert pre.status_code == 202, pre.text
        cid, deadline = pre.json()["id"], time.monotonic() + 300
        while (cache := http.get(f"/v1/caches/{cid}").json())["stage"] != "reinforce":
            assert cache["status"] not in ("finished", "failed"), f"it ended before any kill: {cache}"
            assert time.monotonic() < deadline, cache
            time.sleep(0.05)
        victim = cluster.compose("ps", "-q", "dask-worker").stdout.split()[0]
        killed = _run("docker", "kill", "--signal", "KILL", victim)
        assert killed.returncode == 0, killed.stderr
        cluster.times["killed_at_s"] = time.monotonic() - t1
        while (cache := http.get(f"/v1/caches/{cid}").json())["status"] not in ("finished", "failed"):
            assert time.monotonic() < deadline, f"precompute did not end in 300 s: {cache}"
            time.sleep(0.5)
        assert cache["status"] == "finished", cache
        assert cache["keys"] == keys
        cluster.times["killed_precompute_s"] = time.monotonic() - t1
    # The scheduler saw the worker go, and the cache is the bytes of the undisturbed run
    scheduler_log = cluster.compose("logs", "--no-color", "dask-scheduler", timeout=60).stdout
    assert "Remove worker" in scheduler_log, scheduler_log[-3000:]
    assert in_worker(_DIGESTS, "/data/cache", json.dumps(keys)) == undisturbed
