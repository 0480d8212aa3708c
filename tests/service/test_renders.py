"""/v1/renders: small renders on a ready cache come back directly; others wait on their cache."""

from __future__ import annotations

import pytest

from cloudgraph.options import ESTIMATORS

from ..harness import cache_of, detail, fog_scene, job_of, png_size, rq_job, wait_job


def _ready(client, scene) -> dict:
    r = client.post("/v1/caches", json=cache_of(scene))
    assert r.status_code in (200, 202), r.text
    end = wait_job(client, f"cache-{r.json()['id']}")
    assert end["status"] == "finished", end
    return client.get(f"/v1/caches/{r.json()['id']}").json()


def test_renders_on_a_ready_cache_come_back_in_the_response(client, fog):
    scene = fog_scene(fog, width=40, height=24)
    _ready(client, scene)

    png = client.post("/v1/renders", json={"scene": scene, "quality": "draft"})
    assert png.status_code == 200, png.text
    assert png.headers["content-type"] == "image/png"
    assert png_size(png.content) == (40, 24)
    assert float(png.headers["x-render-seconds"]) >= 0
    job = client.get(f"/v1/jobs/{png.headers['x-job-id']}").json()
    assert job["kind"] == "render" and job["status"] == "finished"
    assert client.get(job["result_url"]).content == png.content

    exr = client.post("/v1/renders", json={"scene": scene, "quality": "draft", "format": "exr"})
    assert exr.status_code == 200, exr.text
    assert exr.headers["content-type"] == "image/x-exr"
    assert exr.content[:4] == b"\x76\x2f\x31\x01"  # the OpenEXR magic number
    assert b"dataWindow" in exr.content[:1024]

    vp = client.post("/v1/renders", json={"scene": fog_scene(fog, 16), "integrator": "volpath"})
    assert vp.status_code == 200, vp.text
    assert png_size(vp.content) == (16, 16)


def test_a_field_render_over_http_returns_an_image_and_its_own_time(client, fog):
    scene = fog_scene(fog, width=48, height=32, spp=1)
    cache = _ready(client, scene)
    if "field_bytes" not in (cache["stats"] or {}):
        pytest.skip("the engine's precompute does not bake a radiance field yet (issue 8)")
    r = client.post("/v1/renders", json={"scene": scene, "quality": "draft", "estimator": "field"})
    assert r.status_code == 200, r.text
    assert png_size(r.content) == (48, 32)
    seconds = float(r.headers["x-render-seconds"])
    assert 0 < seconds < 30
    gather = client.post("/v1/renders", json={"scene": scene, "quality": "draft"})
    assert gather.status_code == 200 and gather.content != r.content  # another estimator ran


def test_a_render_before_its_cache_waits_on_the_precompute(svc, client, fog):
    scene = fog_scene(fog, 24, density=4.0)  # a cache nobody has asked for
    r = client.post("/v1/renders", json={"scene": scene, "quality": "draft"})
    assert r.status_code == 202, r.text
    render = job_of(r)
    assert r.json()["kind"] == "render" and r.json()["status"] in ("waiting", "queued", "running")

    cache = client.post("/v1/caches", json=cache_of(scene))  # the render started it
    assert cache.status_code in (200, 202) and cache.json()["status"] != "canceled"
    end = wait_job(client, render)
    assert end["status"] == "finished", end
    assert wait_job(client, f"cache-{cache.json()['id']}")["status"] == "finished"
    assert rq_job(svc, render).started_at >= rq_job(svc, f"cache-{cache.json()['id']}").ended_at
    img = client.get(end["result_url"])
    assert img.status_code == 200 and img.headers["content-type"] == "image/png"
    assert png_size(img.content) == (24, 24)


@pytest.mark.parametrize(
    "mutate, status, words",
    [
        (
            lambda b: b["scene"]["camera"].update(fov=0),
            422,
            "scene.camera.fov: Input should be greater than 0",
        ),
        (lambda b: b["scene"]["camera"].update(width=0), 422, "scene.camera.width: Input should be greater"),
        (lambda b: b["scene"]["camera"].update(eye=[0, 2, 0]), 422, "eye and target must differ"),
        (lambda b: b["scene"]["camera"].update(width=3000), 422, "image 3000x32 is over the limit of 2048"),
        (lambda b: b["scene"]["render"].update(spp=5000), 422, "scene.render.spp: 5000 is over the limit"),
        (lambda b: b["scene"]["medium"].update(density_scale=-1), 422, "scene.medium.density_scale"),
        (lambda b: b["scene"]["volume"].update(id="0" * 64), 404, "upload it with POST /v1/volumes"),
        (lambda b: b.update(integrator="photon"), 422, "integrator: Input should be 'volpath' or 'graph'"),
        (lambda b: b.update(estimator="photon"), 422, "estimator: Input should be 'gather'"),
        (lambda b: b.update(colour="red"), 422, "colour: Extra inputs are not permitted"),
        (lambda b: b.pop("scene"), 422, "scene: Field required"),
    ],
)
def test_a_bad_render_body_gets_a_4xx_that_says_what_is_wrong(client, fog, mutate, status, words):
    body = {"scene": fog_scene(fog), "quality": "draft"}
    mutate(body)
    r = client.post("/v1/renders", json=body)
    assert r.status_code == status, r.text
    assert words in detail(r)


def test_the_estimators_offered_are_the_engines(client, fog):
    r = client.post("/v1/renders", json={"scene": fog_scene(fog), "estimator": "nope"})
    assert r.status_code == 422
    assert all(repr(e) in detail(r) for e in ESTIMATORS), detail(r)


def test_malformed_bodies_get_a_422_that_says_what_is_wrong(client):
    r = client.post("/v1/renders", content=b'{"scene": ', headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert detail(r) == "the body is not valid JSON: Expecting value at character 10"
    r = client.post("/v1/renders", content=b"[1]", headers={"content-type": "application/json"})
    assert r.status_code == 422 and detail(r).startswith("the request body: Input should be a valid dict")


def test_unknown_renders_are_404(client):
    for path in ("/v1/renders/render-nope/image", "/v1/renders/a.b/image", "/v1/renders/%C3%A9/image"):
        r = client.get(path)
        assert r.status_code == 404 and "no render job" in detail(r), (path, r.text)


def test_a_scene_of_lights_renders_and_new_intensities_are_the_same_cache(client, fog):
    # scene spec v1.1: a sun and a uniform sky; the sky is seen behind the fog ball
    scene = fog_scene(fog, width=24, spp=1)
    scene.pop("light")
    scene["lights"] = [{"type": "directional", "direction": [1, -1, 0]}, {"type": "sky", "radiance": 0.5}]
    body = {k: scene[k] for k in ("volume", "medium", "lights")} | {"quality": "draft"}
    r = client.post("/v1/caches", json=body)
    assert r.status_code in (200, 202), r.text
    assert wait_job(client, f"cache-{r.json()['id']}")["status"] == "finished"
    sun = body["lights"][0]
    brighter = {**body, "lights": [{**sun, "irradiance": 3.0}, {"type": "sky", "radiance": 1.0}]}
    again = client.post("/v1/caches", json=brighter)
    assert again.status_code == 200 and again.json()["id"] == r.json()["id"]  # a re-mix: the same cache

    def mean(lights) -> float:
        req = {"scene": {**scene, "lights": lights}, "quality": "draft", "estimator": "field"}
        img = client.post("/v1/renders", json=req)
        assert img.status_code == 200, img.text
        return client.get(f"/v1/jobs/{img.headers['x-job-id']}").json()["result"]["mean"]

    # the field is linear in the intensities: the sky alone doubled doubles its image
    dark_sun = {**scene["lights"][0], "irradiance": 0.0}
    sky = mean([dark_sun, {"type": "sky", "radiance": 0.5}])
    assert sky > 0 and abs(mean([dark_sun, {"type": "sky", "radiance": 1.0}]) / sky - 2) < 1e-3
    assert mean(scene["lights"]) > sky  # and the sun adds to it


def test_a_sunsky_renders_and_its_scales_are_the_same_cache(client, fog):
    # scene spec v1.1: the model's sun and sky; new scales re-mix the cache, a new haze is another
    scene = fog_scene(fog, width=24, spp=1)
    scene.pop("light")
    sunsky = {"type": "sunsky", "sun_direction": [1, 1, 0], "turbidity": 3}
    body = {k: scene[k] for k in ("volume", "medium")} | {"lights": [sunsky], "quality": "draft"}
    r = client.post("/v1/caches", json=body)
    assert r.status_code in (200, 202), r.text
    assert wait_job(client, f"cache-{r.json()['id']}")["status"] == "finished"
    rescaled = {**body, "lights": [{**sunsky, "sun_scale": 2.0, "sky_scale": 0.5}]}
    assert client.post("/v1/caches", json=rescaled).json()["id"] == r.json()["id"]
    hazy = {**body, "lights": [{**sunsky, "turbidity": 6}]}
    assert client.post("/v1/caches", json=hazy).json()["id"] != r.json()["id"]

    def mean(light) -> float:
        req = {"scene": {**scene, "lights": [light]}, "quality": "draft", "estimator": "field"}
        img = client.post("/v1/renders", json=req)
        assert img.status_code == 200, img.text
        return client.get(f"/v1/jobs/{img.headers['x-job-id']}").json()["result"]["mean"]

    # linear in each part's scale: the sky alone doubled doubles its image, and the sun adds
    sky = mean({**sunsky, "sun_scale": 0.0})
    assert sky > 0 and abs(mean({**sunsky, "sun_scale": 0.0, "sky_scale": 2.0}) / sky - 2) < 1e-3
    assert mean(sunsky) > 1.2 * sky


@pytest.mark.parametrize(
    "lights, words",
    [
        ([{"type": "sky", "radiance": -1}], "lights.0.radiance: must be a non-negative number"),
        ([{"type": "sun"}], "lights.0.type must be one of directional, sky, envmap, sunsky, got 'sun'"),
        ([{"type": "sunsky", "turbidity": 12}], "lights.0.turbidity: Input should be less than or equal"),
        ([{"type": "sunsky", "sun_direction": [1, -1, 0]}], "lights.0.sun_direction must point above"),
        ([{"type": "sunsky", "sun_direction": [0, 2e6, 0]}], "scene.lights.0.sun_direction"),
        ([{"type": "sky", "radiance": 2e6}], "scene.lights.0.radiance: must be at most"),
        ([{"type": "directional", "direction": [0, 2e6, 0]}], "scene.lights.0.direction"),
        ([{"type": "envmap", "path": "/etc/passwd"}], "scene.lights.0.path: the HTTP API takes an uploaded"),
    ],
)
def test_bad_lights_get_a_422_naming_the_light(client, fog, lights, words):
    scene = fog_scene(fog)
    scene.pop("light")
    r = client.post("/v1/renders", json={"scene": {**scene, "lights": lights}, "quality": "draft"})
    assert r.status_code == 422, r.text
    assert words in detail(r)
    both = client.post("/v1/renders", json={"scene": {**fog_scene(fog), "lights": lights}})
    assert both.status_code == 422
