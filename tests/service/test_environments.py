"""/v1/environments: lat-long .exr environment maps, uploaded, checked in a child process, and
used by scene spec v1.1's ``envmap`` lights over HTTP."""

from __future__ import annotations

import numpy as np
import pytest

from ..harness import detail, fog_scene, wait_job


@pytest.fixture(scope="module")
def maps(variant, tmp_path_factory) -> dict:
    """.exr files written here: a 64 x 32 gradient (bright at the top row, +y), a square one, a
    2 MiB one of noise, one too bright to scale, and a file that is not an image."""
    from cloudgraph.image import write_exr

    d = tmp_path_factory.mktemp("maps")
    ramp = np.linspace(2.0, 0.2, 32, dtype=np.float32)[:, None, None] * np.ones((32, 64, 3), np.float32)
    write_exr(ramp, d / "sky.exr")
    write_exr(np.ones((32, 32, 3), np.float32), d / "square.exr")
    write_exr(np.full((32, 64, 3), 3e38, np.float32), d / "blinding.exr")  # (inf once scaled)
    write_exr(np.random.default_rng(1).random((512, 1024, 3), dtype=np.float32), d / "big.exr")
    (d / "notes.exr").write_text("not an image")
    return {p.stem: p for p in d.iterdir()}


def put(client, path):
    with open(path, "rb") as f:
        return client.post("/v1/environments", files={"file": (path.name, f)})


def test_an_environment_map_is_stored_by_its_bytes_and_described(client, maps):
    r = put(client, maps["sky"])
    assert r.status_code in (200, 201), r.text
    info = r.json()
    assert (info["width"], info["height"], info["format"]) == (64, 32, "exr")
    assert r.headers["location"] == f"/v1/environments/{info['id']}"
    again = put(client, maps["sky"])
    assert again.status_code == 200 and again.json()["id"] == info["id"]
    assert client.get(f"/v1/environments/{info['id']}").json() == info
    assert info["id"] in [e["id"] for e in client.get("/v1/environments").json()]


@pytest.mark.parametrize(
    "name, words",
    [
        ("notes", "notes.exr is not an OpenEXR file"),
        ("square", "square.exr is 32x32: a lat-long environment map is twice as wide as high"),
        ("blinding", "blinding.exr has a pixel of radiance 3e+38, over the limit of 1e+24"),
    ],
)
def test_an_upload_that_is_not_a_lat_long_exr_is_422(client, maps, name, words):
    r = put(client, maps[name])
    assert r.status_code == 422, r.text
    assert words in detail(r)


def test_an_environment_map_over_the_size_limit_is_413(idle, maps):
    assert maps["big"].stat().st_size > 2**20
    with idle.client() as c:
        r = put(c, maps["big"])
        assert r.status_code == 413, r.text
        assert "upload is over the limit of 1 MiB" in detail(r)
        assert c.get("/v1/environments").json() == []


def test_a_scene_lit_by_an_uploaded_map_renders_and_bad_map_lights_say_why(client, fog, maps):
    untyped = {"volume": {"id": fog}, "lights": [{"direction": [1, -1, 0]}]}
    r = client.post("/v1/caches", json=untyped)
    assert r.status_code == 422 and "lights.0.type must be one of directional, sky, envmap" in detail(r), (
        r.text
    )
    eid = put(client, maps["sky"]).json()["id"]
    scene = fog_scene(fog, width=24, spp=1)
    sun = {"type": "directional", **scene.pop("light")}
    lit = {**scene, "lights": [sun, {"type": "envmap", "id": eid, "scale": 0.5}]}
    cache = client.post(
        "/v1/caches",
        json={"volume": lit["volume"], "medium": lit["medium"], "lights": lit["lights"], "quality": "draft"},
    )
    assert cache.status_code in (200, 202), cache.text
    assert wait_job(client, f"cache-{cache.json()['id']}")["status"] == "finished"
    r = client.post("/v1/renders", json={"scene": lit, "quality": "draft", "estimator": "field"})
    assert r.status_code == 200, r.text
    mean = client.get(f"/v1/jobs/{r.headers['x-job-id']}").json()["result"]["mean"]
    assert mean > 0.2  # the map behind the ball: 0.1 to 1 (scale 0.5) in every pixel that misses it

    unknown = {**scene, "lights": [{"type": "envmap", "id": "b" * 64}]}
    r = client.post("/v1/renders", json={"scene": unknown, "quality": "draft"})
    assert r.status_code == 404 and "scene.lights.0.id: no environment map with id" in detail(r), r.text
    path = {**scene, "lights": [{"type": "envmap", "path": str(maps["sky"])}]}
    r = client.post("/v1/renders", json={"scene": path, "quality": "draft"})
    assert r.status_code == 422 and "takes an uploaded environment map's 'id'" in detail(r), r.text


def test_deleted_maps_are_gone(client, maps):
    eid = put(client, maps["sky"]).json()["id"]
    assert client.delete(f"/v1/environments/{eid}").status_code == 204
    assert client.get(f"/v1/environments/{eid}").status_code == 404
    assert client.delete(f"/v1/environments/{eid}").status_code == 404
