"""/v1/volumes: uploads stored by content, described, refused with a reason."""

from __future__ import annotations

import hashlib

import pytest

from ..harness import BLENDER, FOG, SMOKE, assert_no_leak, detail, upload


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
