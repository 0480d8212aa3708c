"""Hostile input, as a client that means harm would send it (issue 12): every case is a 4xx
within a second, no answer shows a server path or class name, nothing reaches the queue, and a
normal render right after still comes back."""

from __future__ import annotations

import json
import re
import time

import pytest

from ..harness import assert_no_leak, detail, fog_scene, png_size, rq, sparse_vdb, upload

#: Numbers that no field accepts: non-finite ones (Python's JSON reads them, 1e999 too) and
#: finite ones beyond every documented range.
BAD_NUMBERS = ["NaN", "Infinity", "-Infinity", "1e999", "-1e999", "1e308", "-1e308"]
MARK = "__hostile__"


def cache_body(vid: str) -> dict:
    return {
        "volume": {"id": vid, "scale": 1.0},
        "medium": {"density_scale": 5.0, "albedo": 0.9},
        "light": {"direction": [1.0, -1.0, 0.0], "irradiance": 1.0},
        "max_depth": 8,
        "quality": "draft",
    }


def render_body(vid: str) -> dict:
    scene = fog_scene(vid, 16)
    scene["volume"]["scale"] = 1.0
    scene["medium"]["albedo"] = 0.9
    scene["light"]["irradiance"] = 1.0
    scene["camera"]["up"] = [0.0, 1.0, 0.0]
    scene["render"] |= {"max_depth": 8, "seed": 3}
    return {"scene": scene, "quality": "draft", "exposure": 0.0}


def orbit_body(vid: str) -> dict:
    return render_body(vid) | {
        "orbit": {"radius": 6.0, "elevation": 10.0, "turns": 1.0},
        "frames": 4,
        "fps": 10.0,
    }


def keyframes_body(vid: str) -> dict:
    cam = fog_scene(vid, 16)["camera"] | {"up": [0.0, 1.0, 0.0]}
    return render_body(vid) | {"keyframes": [cam, cam | {"eye": [6.0, 2.0, 0.0]}], "frames": 4}


def numeric_leaves(data, path=()):
    """Paths to every number in a body."""
    if isinstance(data, dict):
        for k, v in data.items():
            yield from numeric_leaves(v, (*path, k))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            yield from numeric_leaves(v, (*path, i))
    elif isinstance(data, int | float) and not isinstance(data, bool):
        yield path


def with_token(body: dict, path: tuple, token: str) -> bytes:
    """The body as JSON text with the number at ``path`` written as ``token`` (NaN, 1e999...)."""
    data = json.loads(json.dumps(body))
    node = data
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = MARK
    return json.dumps(data).replace(f'"{MARK}"', token).encode()


def jobs_in_redis(svc) -> int:
    return len(rq(svc).keys("rq:job:*"))


def answer(client, method: str, path: str, **kw):
    t0 = time.perf_counter()
    r = client.request(method, path, **kw)
    return r, time.perf_counter() - t0


def check(svc, r, seconds: float, what: str) -> None:
    assert 400 <= r.status_code < 500, (what, r.status_code, r.text)
    assert seconds < 1.0, (what, seconds)
    assert_no_leak(r.text, svc)
    assert len(r.text) < 2000, (what, len(r.text))


@pytest.mark.parametrize(
    "route, make, leaves",
    [
        ("/v1/caches", cache_body, None),
        ("/v1/renders", render_body, None),
        ("/v1/animations", orbit_body, None),
        ("/v1/animations", keyframes_body, ("keyframes",)),
    ],
    ids=["caches", "renders", "orbit", "keyframes"],
)
def test_every_number_of_every_body_out_of_range_or_not_finite_is_422(svc, client, fog, route, make, leaves):
    body = make(fog)
    before = jobs_in_redis(svc)
    paths = [p for p in numeric_leaves(body) if leaves is None or p[0] in leaves]
    assert len(paths) >= 8, paths
    failures = []
    for path in paths:
        field = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path).lstrip(".")
        for token in BAD_NUMBERS:
            r, seconds = answer(
                client, "POST", route, content=with_token(body, path, token),
                headers={"content-type": "application/json"},
            )  # fmt: skip
            try:
                check(svc, r, seconds, f"{path}={token}")
                assert r.status_code == 422, r.text
                vector = re.sub(r"\[\d\]$", "", field)  # a vector's message names the vector,
                parent = vector.rpartition(".")[0]  # the camera's geometry rules name the camera
                assert detail(r).startswith((field, vector, f"{parent}: ")), (field, detail(r))
            except AssertionError as err:
                failures.append(str(err)[:300])
    assert not failures, f"{len(failures)} of {len(paths) * len(BAD_NUMBERS)} cases: " + "\n".join(
        failures[:10]
    )
    assert jobs_in_redis(svc) == before  # nothing was enqueued


def _set(body: dict, path: str, value) -> dict:
    data = json.loads(json.dumps(body))
    *head, last = path.split(".")
    node = data
    for p in head:
        node = node[int(p)] if p.isdigit() else node[p]
    node[int(last) if last.isdigit() else last] = value
    return data


CASES = [
    # route, field path, value, status, words in the answer
    ("/v1/renders", "scene.medium.density_scale", 1000.0, 422, "optical depth across one voxel"),
    ("/v1/caches", "medium.density_scale", 1e39, 422, "medium.density_scale: must be at most"),
    ("/v1/caches", "max_depth", 10**9, 422, "max_depth: 1000000000 is over the limit of 1000"),
    ("/v1/renders", "scene.render.max_depth", 10**9, 422, "scene.render.max_depth: 1000000000 is over"),
    ("/v1/renders", "scene.light.direction", [1e308, -1e308, 0], 422, "scene.light.direction"),
    ("/v1/renders", "scene.light.direction", [1e-300, 0, 0], 422, "scene.light.direction: direction must be"),
    ("/v1/caches", "light.irradiance", [1, 1e7, 1], 422, "light.irradiance: must be at most"),
    ("/v1/caches", "volume.scale", 1e-300, 422, "volume.scale: must be within"),
    ("/v1/renders", "scene.volume.scale", 1e300, 422, "scene.volume.scale: must be within"),
    ("/v1/renders", "scene.camera.eye", [1e308, 2, 6], 422, "scene.camera.eye: components must be within"),
    ("/v1/renders", "scene.camera.up", [0, 1e-300, 0], 422, "up must be a non-zero vector"),
    ("/v1/renders", "scene.camera.up", [0, 1e-7, 0], 422, "scene.camera.up: must be a vector of length"),
    ("/v1/animations", "orbit.radius", 1e-300, 422, "orbit.radius: must be within"),
    ("/v1/animations", "orbit.radius", 1e300, 422, "orbit.radius: must be within"),
    ("/v1/renders", "scene.volume.grid", "temperature", 422, "has no grid named 'temperature'"),
    ("/v1/caches", "volume.grid", "temperature", 422, "volume.grid: the volume has no grid named"),
    ("/v1/animations", "scene.volume.grid", "temperature", 422, "scene.volume.grid"),
    ("/v1/renders", "scene.volume.id", "a.b", 404, "no volume with id 'a.b'"),
    ("/v1/caches", "volume.id", "é" * 10, 404, "no volume with id"),
    ("/v1/renders", "scene.volume.id", "f" * 100_000, 404, "(100000 characters)"),
    ("/v1/renders", "estimator", "photon", 422, "estimator: Input should be"),
    ("/v1/renders", "scene.camera.width", 100_000, 422, "scene.camera.width"),
    ("/v1/animations", "keyframes.1.width", 3000, 422, "keyframes[1]: image 3000x16 is over the limit"),
    ("/v1/animations", "frames", 10**9, 422, "frames: 1000000000 is over the limit"),
]


@pytest.mark.parametrize(
    "route, field, value, status, words", CASES, ids=[f"{c[1]}={str(c[2])[:12]}" for c in CASES]
)
def test_out_of_range_values_unknown_grids_and_ids_get_a_4xx_naming_the_field(
    svc, client, fog, route, field, value, status, words
):
    make = {"/v1/caches": cache_body, "/v1/renders": render_body, "/v1/animations": keyframes_body}[route]
    if route == "/v1/animations" and field.startswith("orbit"):
        make = orbit_body
    r, seconds = answer(client, "POST", route, json=_set(make(fog), field, value))
    check(svc, r, seconds, field)
    assert r.status_code == status, r.text
    assert words in detail(r), detail(r)


@pytest.mark.parametrize("bad", ["a.b", "%C3%A9", "...", "%00", "x" * 3000, "cache-" + "0" * 32 + ".", "%20"])
def test_malformed_ids_on_every_route_are_404(svc, client, bad):
    for method, path in [
        ("GET", f"/v1/jobs/{bad}"),
        ("GET", f"/v1/jobs/{bad}/events"),
        ("POST", f"/v1/jobs/{bad}/cancel"),
        ("GET", f"/v1/renders/{bad}/image"),
        ("GET", f"/v1/animations/{bad}"),
        ("GET", f"/v1/animations/{bad}/video"),
        ("GET", f"/v1/animations/{bad}/frames/0"),
        ("GET", f"/v1/caches/{bad}"),
        ("GET", f"/v1/caches/{bad}/field"),
        ("GET", f"/v1/volumes/{bad}"),
        ("DELETE", f"/v1/volumes/{bad}"),
    ]:
        r, seconds = answer(client, method, path)
        check(svc, r, seconds, path[:60])
        assert r.status_code == 404, (path[:60], r.text)


def test_oversized_bodies_are_413_at_once_and_the_api_stays_quick(svc, client, fog):
    big = b'{"scene": {"volume": {"id": "' + b"f" * (50 * 2**20) + b'"}}}'
    r, seconds = answer(
        client, "POST", "/v1/renders", content=big, headers={"content-type": "application/json"}
    )
    check(svc, r, seconds, "50 MB body")
    assert r.status_code == 413 and "over the limit of 256 KiB" in detail(r)

    def chunks():  # no Content-Length: counted as it arrives
        yield b'{"scene": {"volume": {"id": "'
        for _ in range(64):
            yield b"f" * 2**14
        yield b'"}}}'

    r, seconds = answer(
        client, "POST", "/v1/caches", content=chunks(), headers={"content-type": "application/json"}
    )
    check(svc, r, seconds, "chunked body")
    assert r.status_code == 413, r.text

    many = keyframes_body(fog)
    many["keyframes"] = many["keyframes"] * 2000  # 4000 keyframes
    r, seconds = answer(client, "POST", "/v1/animations", json=many)
    check(svc, r, seconds, "4000 keyframes")
    assert r.status_code == 413

    t0 = time.perf_counter()
    assert client.get("/healthz").status_code == 200
    assert time.perf_counter() - t0 < 0.2


@pytest.mark.parametrize("span", [2**22, 700])
def test_a_sparse_vdb_with_a_huge_bounding_box_is_422_before_anything_is_densified(
    svc, client, tmp_path, span
):
    path = sparse_vdb(tmp_path / "two-voxels.vdb", span)
    assert path.stat().st_size < 20_000
    t0 = time.perf_counter()
    r = upload(client, path)
    seconds = time.perf_counter() - t0
    check(svc, r, seconds, f"span {span}")
    assert r.status_code == 422, r.text
    assert (
        f"two-voxels.vdb: grid 'density' has active voxels spread over a {span}x{span}x{span} box"
        in detail(r)
    )
    assert "over the limit of 268435456 (MAX_VOXELS)" in detail(r)


def test_after_all_that_a_normal_render_still_comes_back(svc, client, fog):
    r = client.post("/v1/renders", json={"scene": fog_scene(fog, 16), "integrator": "volpath"})
    assert r.status_code == 200, r.text
    assert png_size(r.content) == (16, 16)
    assert client.get("/readyz").json()["stuck"] == 0
