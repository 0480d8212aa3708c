"""The OpenAPI document is the wire's truth: every answer it does not describe is a failure of
schemathesis (``--checks all``), and a client generated from it (openapi-python-client) uploads a
volume, precomputes its cache and renders an image.

The service is this module's own (with an API key, as deployed), so that generated requests
never reach the shared one. Schemathesis runs first, on a service that holds no volume: a random
upload is never a readable volume, so no request it makes can start a job.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import re
import subprocess
import sys

import httpx
import pytest

from ..harness import FOG, KEY, cache_of, fog_scene, no_server_errors, png_size, start_service, wait_until

#: Seconds of schemathesis (all phases: coverage, fuzzing, stateful).
CHECK_S = 120

#: A body can be valid by the schema and still break a rule JSON Schema cannot state (a camera
#: whose eye is its target, a light of zero direction, a density_scale too large for the volume
#: it names): the service answers 422 naming the rule. So 422 is an accepted answer to a
#: schema-valid body, and only there; every other check keeps its defaults.
SCHEMATHESIS_TOML = """
[[operations]]
include-method = "POST"
[operations.checks.positive_data_acceptance]
expected-statuses = ["2xx", "3xx", "401", "403", "404", "409", "422", "429", "5xx"]
"""

#: openapi-python-client takes JSON as YAML. Images and videos are files to the client.
CLIENT_CONFIG = {
    "content_type_overrides": dict.fromkeys(
        ("image/png", "image/x-exr", "video/mp4"), "application/octet-stream"
    ),
    "post_hooks": [],
}


@pytest.fixture(scope="module")
def contract(tmp_path_factory):
    s = start_service(tmp_path_factory.mktemp("contract"), workers=1, API_KEYS=KEY)
    yield s
    try:
        no_server_errors(s)
    finally:
        s.stop()


@pytest.fixture(scope="module")
def document(contract) -> dict:
    r = httpx.get(f"{contract.url}/openapi.json", timeout=30)
    assert r.status_code == 200, r.text
    return r.json()


def test_every_error_answer_is_documented_with_its_real_body(document):
    assert not {"HTTPValidationError", "ValidationError"} & set(document["components"]["schemas"])
    for path, operations in document["paths"].items():
        for method, op in operations.items():
            errors = {code: r for code, r in op["responses"].items() if int(code) >= 400}
            if path.startswith("/v1/"):
                assert "401" in errors, (method, path)
            for code, r in errors.items():
                schema = r["content"]["application/json"]["schema"]
                assert schema == {"$ref": "#/components/schemas/ErrorPublic"}, (method, path, code)
    body = document["paths"]["/v1/volumes"]["post"]["requestBody"]
    form = body["content"]["multipart/form-data"]["schema"]
    assert body["required"] and form["required"] == ["file"]
    assert form["properties"]["file"]["format"] == "binary"
    assert list(document["paths"]["/metrics"]["get"]["responses"]["200"]["content"]) == ["text/plain"]


def test_options_and_unknown_methods_answer_with_allow(contract):
    with contract.client() as c:
        r = c.options("/v1/volumes")
        assert r.status_code == 204 and r.headers["allow"] == "GET, POST, OPTIONS"
        r = c.put("/v1/volumes/" + "a" * 64)
        assert r.status_code == 405 and r.headers["allow"] == "DELETE, GET"
        assert "PUT is not allowed" in r.json()["detail"]


def test_an_unknown_path_and_a_body_of_another_type_are_named(contract):
    """A path under /v1 that no route has is a 404 whatever the method (the page's mount at /
    answered a POST there with 405), and a body of a Content-Type the operation does not read a
    415 naming the one it does (``curl -d`` sends a JSON scene form-encoded: it read as "not an
    object"), before the key is checked or the body read."""
    with contract.client() as c:
        for method in ("GET", "POST", "DELETE"):
            r = c.request(method, "/v1/renderz")
            assert r.status_code == 404 and "no API route /v1/renderz" in r.json()["detail"], (method, r.text)
        scene = json.dumps(fog_scene("a" * 64)).encode()
        for path, sent, want in (
            ("/v1/renders", "application/x-www-form-urlencoded", "application/json"),
            ("/v1/caches", "text/plain", "application/json"),
            ("/v1/volumes", "application/octet-stream", "multipart/form-data"),
        ):
            r = c.post(path, content=scene, headers={"Content-Type": sent})
            assert r.status_code == 415, (path, r.text)
            assert f"Content-Type {want}, not {sent}" in r.json()["detail"]
        auth = {"Authorization": f"Bearer {KEY}"}
        r = c.post(
            "/v1/renders", content=b"{", headers={"Content-Type": "application/json; charset=utf-8"} | auth
        )
        assert r.status_code == 422  # the type is right: the JSON is not
        r = c.post("/v1/renders", content=b"{", headers={"Content-Type": "application/vnd.x+json"} | auth)
        assert r.status_code == 422 and "not valid JSON" in r.json()["detail"]  # (+json: JSON too)


def test_schemathesis_finds_no_answer_the_document_does_not_describe(contract, tmp_path):
    config = tmp_path / "schemathesis.toml"
    config.write_text(SCHEMATHESIS_TOML)
    cmd = [
        sys.executable, "-m", "schemathesis.cli", "--config-file", str(config),
        "run", f"{contract.url}/openapi.json",
        "--checks", "all",
        "--max-time", str(CHECK_S),
        "--header", f"Authorization: Bearer {KEY}",
        "--request-timeout", "30",
        "--generation-database", "none",
        "--no-color",
    ]  # fmt: skip
    run = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=CHECK_S + 300)
    out = run.stdout + run.stderr
    print(out[-4000:])  # the figures: cases generated and passed, the seed
    assert run.returncode == 0, out[-30000:]
    cases = re.search(r"(\d+) generated, (\d+) passed", out)
    assert cases and int(cases[1]) > 0, out[-4000:]


def _client_package(document: dict, folder):
    """The client openapi-python-client generates from the service's document, imported."""
    (folder / "openapi.json").write_text(json.dumps(document))
    (folder / "client.yaml").write_text(json.dumps(CLIENT_CONFIG))
    out = folder / "cloudgraph_client"
    subprocess.run(
        [
            sys.executable, "-m", "openapi_python_client", "generate",
            "--path", str(folder / "openapi.json"),
            "--output-path", str(out),
            "--meta", "none",
            "--config", str(folder / "client.yaml"),
        ],
        check=True, capture_output=True, timeout=120,
    )  # fmt: skip
    return out


def test_a_generated_client_uploads_precomputes_and_renders(contract, document, tmp_path, monkeypatch):
    _client_package(document, tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))

    def mod(name: str):
        return importlib.import_module(f"cloudgraph_client.{name}")

    models, types = mod("models"), mod("types")
    upload, get_volume = mod("api.volumes.upload_volume"), mod("api.volumes.get_volume")
    create_cache, get_cache = mod("api.caches.create_cache"), mod("api.caches.get_cache")
    create_render, render_image = mod("api.renders.create_render"), mod("api.renders.render_image")
    get_job = mod("api.jobs.get_job")
    Client, AuthenticatedClient = mod("client").Client, mod("client").AuthenticatedClient  # noqa: N806
    client = AuthenticatedClient(base_url=contract.url, token=KEY, timeout=httpx.Timeout(120))

    # Error answers parse as the documented model
    r = get_volume.sync_detailed("a" * 64, client=Client(base_url=contract.url))
    assert r.status_code == 401 and isinstance(r.parsed, models.ErrorPublic), r.content
    r = get_volume.sync_detailed("a" * 64, client=client)
    assert r.status_code == 404 and "no volume with id" in r.parsed.detail, r.content

    # Upload: the id is the sha256 of the file's bytes
    data = FOG.read_bytes()
    with FOG.open("rb") as f:
        body = models.UploadVolumeBody(file=types.File(payload=f, file_name=FOG.name))
        r = upload.sync_detailed(client=client, body=body)
    assert r.status_code == 201, r.content
    volume = r.parsed
    assert isinstance(volume, models.VolumePublic) and volume.id == hashlib.sha256(data).hexdigest()
    described = volume.to_dict()  # as sent: the client renames the field ``bytes``
    assert (described["filename"], described["bytes"], described["format"]) == (FOG.name, len(data), "vdb")

    # Precompute a draft cache, to its end
    scene = fog_scene(volume.id, width=32, spp=4)
    r = create_cache.sync_detailed(client=client, body=models.CacheCreate.from_dict(cache_of(scene)))
    assert r.status_code in (200, 202) and isinstance(r.parsed, models.CachePublic), r.content
    cid = r.parsed.id

    def finished():
        c = get_cache.sync(cid, client=client)
        assert c.status not in (models.JobStatus.FAILED, models.JobStatus.CANCELED), c.error
        return c if c.status == models.JobStatus.FINISHED else None

    assert wait_until(finished, 180, f"cache {cid} did not finish", interval=0.2).keys is not None

    # Render on it: back at once (small, its cache ready), else through its job
    request = models.RenderCreate.from_dict({"scene": scene, "quality": "draft", "format": "png"})
    r = create_render.sync_detailed(client=client, body=request)
    assert r.status_code in (200, 202), r.content
    if r.status_code == 202:
        job = r.parsed
        assert isinstance(job, models.JobPublic)
        wait_until(
            lambda: get_job.sync(job.id, client=client).status == models.JobStatus.FINISHED,
            180,
            f"render {job.id} did not finish",
            interval=0.2,
        )
        r = render_image.sync_detailed(job.id, client=client)
        assert r.status_code == 200, r.content
    assert isinstance(r.parsed, types.File)
    assert png_size(r.parsed.payload.read()) == (32, 32)


def test_the_openapi_document_states_this_server_s_limits(tmp_path):
    # The scene spec's own bounds are the engine's (the CLI's: 4096 pixels a side, 65536 spp);
    # a server answers 422 past its settings, and its document says so
    from cloudgraph_service.settings import Settings
    from server.main import create_app

    settings = Settings(DATA_DIR=tmp_path, MAX_IMAGE_SIDE=512, MAX_SPP=100, MAX_FRAMES=50)
    schemas = create_app(settings).openapi()["components"]["schemas"]
    camera, render = schemas["CameraSpec"]["properties"], schemas["RenderSpec"]["properties"]
    assert camera["width"]["maximum"] == camera["height"]["maximum"] == 512
    assert render["spp"]["maximum"] == 100 and render["max_depth"]["maximum"] == 1000
    assert schemas["AnimationCreate"]["properties"]["frames"]["maximum"] == 50
    assert schemas["VolumeSpec"]["properties"]["scale"]["minimum"] == 1e-6
    assert all(item["maximum"] == 1e6 for item in camera["eye"]["prefixItems"])
