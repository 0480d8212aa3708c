"""/v1/animations: camera paths rendered as frame jobs across workers, then an MP4."""

from __future__ import annotations

from ..harness import detail, fog_scene, job_of, png_size, wait_job


def test_an_orbit_animation_becomes_an_mp4_and_its_frames(client, fog):
    body = {
        "scene": fog_scene(fog, 32),
        "orbit": {"elevation": 10},
        "frames": 5,
        "fps": 10,
        "quality": "draft",
    }
    r = client.post("/v1/animations", json=body)
    assert r.status_code == 202, r.text
    anim = job_of(r)
    assert r.json()["kind"] == "animation"
    end = wait_job(client, anim)
    assert end["status"] == "finished", end

    video = client.get(end["result_url"])
    assert video.status_code == 200 and video.headers["content-type"] == "video/mp4"
    assert video.content[4:8] == b"ftyp"
    info = client.get(f"/v1/animations/{anim}").json()
    assert info["frames"] == 5 and info["frames_done"] == [0, 1, 2, 3, 4]
    frames = [client.get(f"/v1/animations/{anim}/frames/{i}") for i in (0, 4)]
    assert [f.status_code for f in frames] == [200, 200]
    assert png_size(frames[0].content) == (32, 32)
    assert frames[0].content != frames[1].content  # the camera moved
    outside = client.get(f"/v1/animations/{anim}/frames/5")
    assert outside.status_code == 404 and "outside 0..4" in detail(outside)


def test_keyframes_of_differing_sizes_or_too_large_are_422(client, fog):
    scene = fog_scene(fog, 16)
    a, b = dict(scene["camera"]), dict(scene["camera"]) | {"eye": [6, 2, 0]}
    body = {"scene": scene, "keyframes": [a, b | {"width": 3000}], "frames": 2, "quality": "draft"}
    r = client.post("/v1/animations", json=body)
    assert r.status_code == 422 and detail(r).startswith("keyframes[1]: image 3000x16 is over the limit")
    body["keyframes"] = [a, b | {"width": 20}]
    r = client.post("/v1/animations", json=body)
    assert r.status_code == 422 and "frames of one video share a size" in detail(r)
    # each keyframe valid, the frame between them not: an up that turns over passes through zero
    body["keyframes"] = [a | {"up": [0, 1, 0]}, a | {"up": [0, -1, 0]}]
    body["frames"] = 3
    r = client.post("/v1/animations", json=body)
    assert r.status_code == 422, r.text
    assert detail(r).startswith("keyframes[1]: frame 1, between keyframes[0] and [1], has no valid camera")


def test_bad_animation_bodies_are_422(client, fog):
    anim = {"scene": fog_scene(fog), "orbit": {}, "quality": "draft"}
    r = client.post("/v1/animations", json=anim | {"frames": 601})
    assert r.status_code == 422 and "frames: 601 is over the limit of 600" in detail(r)
    r = client.post("/v1/animations", json=anim | {"fps": 1e-7})  # (was accepted; ffmpeg then failed)
    assert r.status_code == 422 and detail(r).startswith("fps: "), r.text
    r = client.post("/v1/animations", json={k: v for k, v in anim.items() if k != "orbit"} | {"frames": 3})
    assert r.status_code == 422 and "exactly one of 'keyframes'" in detail(r)
    for path in ("/v1/animations/anim-nope", "/v1/animations/a.b", "/v1/animations/a.b/video"):
        r = client.get(path)
        assert r.status_code == 404 and "no animation" in detail(r), (path, r.text)
