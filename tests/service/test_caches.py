"""/v1/caches: one precompute per cache, progress as events; the radiance field for browsers."""

from __future__ import annotations

import gzip
import json
import struct
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from cloudgraph.cache import CacheStore

from ..harness import (
    FOG,
    blender_cache,
    cache_of,
    detail,
    fog_scene,
    job_of,
    rq,
    rq_job,
    sse,
    upload,
    wait_job,
)


def test_a_precompute_streams_its_stages_then_the_cache_has_a_graph(client, blender):
    r = client.post("/v1/caches", json=blender_cache(blender))
    assert r.status_code == 202, r.text
    body = r.json()
    job = job_of(r)
    assert body["job"] == f"/v1/jobs/{job}" and job == f"cache-{body['id']}"
    assert body["status"] in ("queued", "running")

    events = sse(client, job)
    names = [e for e, _ in events]
    assert names[-1] == "end" and set(names[:-1]) == {"progress"}, names
    progress = [d for e, d in events if e == "progress"]
    fractions = [d["fraction"] for d in progress]
    assert fractions == sorted(fractions), fractions
    stages = [d["stage"] for d in progress if d["status"] == "running"]
    assert {"reinforce", "lighting", "transport"} & set(stages), stages  # several stages seen
    assert len(set(stages)) >= 2, stages
    end = events[-1][1]
    assert end["status"] == "finished" and end["fraction"] == 1.0 and end["stage"] == "done"

    r = client.get(f"/v1/caches/{body['id']}")
    assert r.status_code == 200
    cache = r.json()
    assert cache["status"] == "finished"
    assert cache["stats"]["nodes"] > 1000 and cache["stats"]["edges"] > cache["stats"]["nodes"]
    assert {"volume_id", "graph_key", "radiance_key"} <= set(cache["keys"])

    again = client.post("/v1/caches", json=blender_cache(blender))
    assert again.status_code == 200 and again.json()["id"] == body["id"]
    assert "location" not in again.headers


def test_the_same_cache_asked_for_at_once_is_one_precompute(svc, client, fog):
    body = cache_of(fog_scene(fog, density=6.0))

    def post(_):
        with svc.client() as c:
            return c.post("/v1/caches", json=body)

    with ThreadPoolExecutor(6) as pool:
        answers = list(pool.map(post, range(6)))
    assert {a.status_code for a in answers} <= {200, 202}, [a.text for a in answers]
    assert len({a.json()["id"] for a in answers}) == 1
    assert len({a.json()["job"] for a in answers}) == 1
    job = answers[0].json()["job"].removeprefix("/v1/jobs/")
    assert wait_job(client, job)["status"] == "finished"

    again = client.post("/v1/caches", json=body)
    assert again.status_code == 200 and again.json()["status"] == "finished"
    time.sleep(0.5)  # a duplicate in the queue would have run by now
    assert len(rq_job(svc, job).results()) == 1  # one execution
    assert rq(svc).llen("rq:queue:cloudgraph") == 0


def _field_body(raw: bytes) -> tuple[dict, bytes]:
    """(header, whole body) of a decompressed field (api.md, "The radiance field")."""
    assert raw[:8] == b"CGFIELD1", raw[:16]
    (n,) = struct.unpack("<I", raw[8:12])
    return json.loads(raw[12 : 12 + n].decode()), raw


def test_a_finished_caches_field_comes_gzipped_with_an_etag_and_is_cached_for_ever(svc, client, fog):
    scene = fog_scene(fog, density=6.0)
    r = client.post("/v1/caches", json=cache_of(scene))
    cid = r.json()["id"]
    end = wait_job(client, f"cache-{cid}")
    assert end["status"] == "finished", end
    cache = client.get(f"/v1/caches/{cid}").json()
    if "field_bytes" not in (cache["stats"] or {}):
        pytest.skip("the engine's precompute does not bake a radiance field yet (issue 8)")
    key = cache["keys"]["radiance_key"]

    # httpx would decompress for us: ask for the bytes as they travel
    r = client.get(f"/v1/caches/{cid}/field", headers={"Accept-Encoding": "gzip"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/octet-stream"
    assert r.headers["content-encoding"] == "gzip"
    assert r.headers["etag"] == f'"{key}"'
    assert r.headers["cache-control"] == "public, max-age=31536000, immutable"
    stored = CacheStore(svc.data_dir / "cache").field_path(key)
    assert int(r.headers["content-length"]) == stored.stat().st_size  # sent as stored
    header, body = _field_body(r.content)  # decoded by httpx from Content-Encoding
    assert header["format"] == "cloudgraph-field" and header["version"] == 1
    assert header["radiance_key"] == key
    for name, a in header["arrays"].items():
        assert a["offset"] % 16 == 0, name
        size = 2 if a["dtype"] == "float16" else 4
        count = 1
        for n in a["shape"]:
            count *= n
        assert a["offset"] + size * count <= len(body), name
    with client.stream("GET", f"/v1/caches/{cid}/field") as raw:
        compressed = b"".join(raw.iter_raw())
    assert compressed == stored.read_bytes() and gzip.decompress(compressed) == body

    same = client.get(f"/v1/caches/{cid}/field", headers={"If-None-Match": f'"{key}"'})
    assert same.status_code == 304 and same.content == b""
    assert same.headers["etag"] == f'"{key}"'
    listed = client.get(f"/v1/caches/{cid}/field", headers={"If-None-Match": f'"x", W/"{key}"'})
    assert listed.status_code == 304
    other = client.get(f"/v1/caches/{cid}/field", headers={"If-None-Match": '"something-else"'})
    assert other.status_code == 200


def test_the_field_of_an_unknown_or_unfinished_cache_is_404_or_409(client, idle):
    for cid in ("0" * 32, "a.b", "x" * 500, "é"):
        r = client.get(f"/v1/caches/{cid}/field")
        assert r.status_code == 404, (cid, r.text)
        assert "start one with POST /v1/caches" in detail(r)
    with idle.client() as c:  # no worker: the precompute stays queued
        vid = upload(c, FOG).json()["id"]
        r = c.post("/v1/caches", json=cache_of(fog_scene(vid)))
        assert r.status_code == 202, r.text
        r = c.get(f"/v1/caches/{r.json()['id']}/field")
        assert r.status_code == 409 and "is queued, not finished" in detail(r)
