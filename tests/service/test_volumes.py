"""/v1/volumes: uploads stored by content, described, refused with a reason."""

from __future__ import annotations

import hashlib

import pytest

from ..harness import BLENDER, FOG, SMOKE, assert_no_leak, cache_of, detail, fog_scene, upload, wait_job


def test_an_upload_is_stored_under_the_sha256_of_its_bytes_and_described(client, uploads):
    first = uploads[FOG.name]
    assert first.status_code == 201, first.text
    vid = first.json()["id"]
    assert vid == hashlib.sha256(FOG.read_bytes()).hexdigest()
    assert first.headers["location"] == f"/v1/volumes/{vid}"

    again = upload(client, FOG, name="renamed.vdb")
    assert again.status_code == 200, again.text
    assert again.json()["id"] == vid

    r = client.get(f"/v1/volumes/{vid}")
    assert r.status_code == 200
    info = r.json()
    assert [(g["name"], g["type"]) for g in info["grids"]] == [("density", "float")]
    grid = info["grids"][0]  # what the density_scale check needs, read at upload
    assert grid["value_max"] == pytest.approx(info["value_range"][1])
    assert grid["voxel_size"] == pytest.approx([0.2] * 3, rel=1e-6) and grid["dims"] == [11, 9, 11]
    assert info["index_bbox"] == [[-5, -4, -5], [5, 4, 5]]
    assert info["voxel_size"] == pytest.approx([0.2] * 3, rel=1e-6)
    assert info["bytes"] == FOG.stat().st_size and info["format"] == "vdb"

    r = client.get("/v1/volumes")
    assert r.status_code == 200
    listed = {v["id"]: v for v in r.json()}
    assert {vid, uploads[BLENDER.name].json()["id"]} <= set(listed)
    assert uploads[BLENDER.name].status_code == 201


def test_a_vdb_of_several_float_grids_none_named_density_is_stored_and_scenes_name_one(client, tmp_path):
    # (a simulation's export: the smoke's density under another name, and its temperature)
    import numpy as np
    import pyopenvdb as vdb

    smoke = vdb.read(str(FOG), "density")
    smoke.name = "smoke"
    heat = vdb.FloatGrid()
    heat.name = "temperature"
    heat.copyFromArray(np.full((4, 4, 4), 300.0, np.float32))
    path = tmp_path / "sim.vdb"
    vdb.write(str(path), grids=[smoke, heat])
    r = upload(client, path)
    assert r.status_code == 201, r.text
    info = r.json()
    assert info["grid"] is None  # no grid a scene reads unless it names one
    grids = {g["name"]: g for g in info["grids"]}
    assert grids["temperature"]["value_max"] == 300.0 and grids["temperature"]["dims"] == [4, 4, 4]
    assert grids["smoke"]["value_max"] == pytest.approx(info["value_range"][1])  # (described: the first)
    body = cache_of(fog_scene(info["id"]))
    r = client.post("/v1/caches", json=body)
    assert r.status_code == 422, r.text
    assert "volume.grid" in r.text and "is required" in detail(r) and "'temperature'" in detail(r)
    body["volume"]["grid"] = "smoke"
    r = client.post("/v1/caches", json=body)
    assert r.status_code in (200, 202), r.text
    assert wait_job(client, r.json()["job"].removeprefix("/v1/jobs/"))["status"] == "finished"


def test_a_file_that_is_no_volume_is_422_naming_the_upload(svc, client, tmp_path):
    bad = tmp_path / "notes.vdb"
    bad.write_text("not a volume at all")
    r = upload(client, bad)
    assert r.status_code == 422, r.text
    assert "notes.vdb is neither an OpenVDB" in detail(r)
    assert_no_leak(r.text, svc)
    empty = tmp_path / "empty.vdb"
    empty.write_bytes(b"")
    r = upload(client, empty)
    assert r.status_code == 422 and "upload is empty" in detail(r)
    r = client.post("/v1/volumes", files={"other": ("a.vdb", b"x")})
    assert r.status_code == 422 and "multipart form field named 'file'" in detail(r)
    r = client.post("/v1/volumes", data={"name": "x"})  # (a form, not multipart)
    assert r.status_code == 415 and "Content-Type multipart/form-data, not application/x-www" in detail(r)


def test_unknown_volumes_are_404(client):
    for path in ("/v1/volumes/" + "a" * 64, "/v1/volumes/" + "g" * 64, "/v1/volumes/a.b"):
        r = client.get(path)
        assert r.status_code == 404 and "no volume with id" in detail(r), (path, r.text)
        assert client.delete(path).status_code == 404


def test_an_upload_over_the_size_limit_is_413(idle):
    with idle.client() as c:
        r = upload(c, SMOKE)  # 2.5 MB
        assert r.status_code == 413, r.text
        assert "upload is over the limit of 1 MiB" in detail(r)
        assert c.get("/v1/volumes").json() == []
        stored = idle.data_dir / "volumes"  # refused before a byte was written
        assert not stored.exists() or not [p for p in stored.iterdir() if p.is_file()]
