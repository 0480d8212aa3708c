"""Stored things that go missing or half-made: a cache whose field (or graph) file is gone is not
finished and is rebuilt when asked for again; an animation whose video is gone answers 410; an
upload whose client or API died is not stored and leaves no temporary file; and a request without
a key is refused before its body is read.
"""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from pathlib import Path

import httpx
import pytest

from ..harness import FOG, KEY, cache_of, detail, fog_scene, job_of, wait_until
from .faults import Launched, _children, _cmdline, assert_no_leaks, cache_files, wait_status

AUTH = {"Authorization": f"Bearer {KEY}"}


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = Launched(tmp_path_factory.mktemp("storage"), {"API_KEYS": KEY}).start()
    yield svc
    svc.stop()


@pytest.fixture(scope="module")
def fog(service) -> str:
    with service.client(headers=AUTH) as c:
        with open(FOG, "rb") as f:
            r = c.post("/v1/volumes", files={"file": (FOG.name, f)})
        assert r.status_code == 201, r.text
        return r.json()["id"]


def _finished_cache(c, body: dict) -> tuple[str, dict]:
    r = c.post("/v1/caches", json=body)
    cid = r.json()["id"]
    end, _ = wait_status(c, f"cache-{cid}", 120)
    assert end["status"] == "finished", end
    return cid, c.get(f"/v1/caches/{cid}").json()


def test_an_animation_whose_video_or_frame_was_removed_answers_410_not_500(service, fog):
    body = {"scene": fog_scene(fog, 16), "orbit": {}, "frames": 2, "fps": 10, "quality": "draft"}
    with service.client(headers=AUTH) as c:
        r = c.post("/v1/animations", json=body)
        assert r.status_code == 202, r.text
        anim = job_of(r)
        end, _ = wait_status(c, anim, 120)
        assert end["status"] == "finished", end
        folder = service.data_dir / "outputs" / "animations" / anim
        video, frame = folder / "video.mp4", next(folder.glob("frame_*.png"))
        assert video.is_file()
        video.unlink()
        frame.unlink()
        r = c.get(f"/v1/animations/{anim}/video")
        assert r.status_code == 410, r.text
        assert detail(r) == f"the video of animation {anim} is gone; start the animation again"
        index = int(frame.stem.split("_")[1])
        r = c.get(f"/v1/animations/{anim}/frames/{index}")
        assert r.status_code == 410, r.text
        assert detail(r) == f"frame {index} of animation {anim} is gone; start the animation again"


@pytest.mark.parametrize("lost", ["field", "graph"])
def test_a_cache_that_lost_a_file_is_not_finished_and_asking_again_rebuilds_only_that(service, fog, lost):
    body = cache_of(fog_scene(fog, density=3.0 if lost == "field" else 3.5))
    with service.client(headers=AUTH) as c:
        cid, cache = _finished_cache(c, body)
        files = cache_files(service, cache["keys"])
        whole = {k: p.read_bytes() for k, p in files.items()}
        files[lost].unlink()

        r = c.get(f"/v1/caches/{cid}/field")
        assert r.status_code == (410 if lost == "field" else 200), r.text
        r = c.get(f"/v1/caches/{cid}")
        assert r.status_code == 200 and r.json()["status"] == "failed", r.text
        assert r.json()["error"] == (
            f"the {lost} of cache {cid} is gone (evicted or removed); "
            "ask for the cache again (POST /v1/caches) to rebuild"
        )
        t0 = time.monotonic()
        r = c.post("/v1/caches", json=body)
        assert r.status_code == 202, r.text
        assert r.json()["id"] == cid and r.json()["status"] in ("queued", "running")
        end, t1 = wait_status(c, f"cache-{cid}", 120)
        assert end["status"] == "finished", end
        stats = end["result"]["stats"]
        field = c.get(f"/v1/caches/{cid}/field", headers={"Accept-Encoding": "gzip"})
        again = c.post("/v1/caches", json=body)

    print(f"{lost} rebuilt in {t1 - t0:.2f} s")
    assert stats["radiance_reused"] is True  # no transport: a relight-sized job at most
    assert stats["graph_reused"] is (lost != "graph")
    assert {k: p.read_bytes() for k, p in files.items()} == whole  # the same bytes again
    assert field.status_code == 200
    assert again.status_code == 200 and again.json()["status"] == "finished"
    assert_no_leaks(service)


def _post_raw(port: int, path: str, headers: dict, body_size: int, chunk: int = 1 << 16):
    """Sends a request with a ``body_size`` body from a thread, as a client that reads while it
    sends (curl does); returns (status line, seconds to it, bytes sent by then)."""
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    head = f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Length: {body_size}\r\n"
    head += "".join(f"{k}: {v}\r\n" for k, v in headers.items()) + "\r\n"
    sent = {"n": 0}

    def send():
        try:
            s.sendall(head.encode())
            block = b"\0" * chunk
            while sent["n"] < body_size:
                s.sendall(block)
                sent["n"] += len(block)
        except OSError:  # the server closed: it has answered
            pass

    t0 = time.monotonic()
    threading.Thread(target=send, daemon=True).start()
    data = b""
    while b"\r\n" not in data:
        more = s.recv(4096)
        if not more:
            break
        data += more
    took = time.monotonic() - t0
    s.close()
    return data.split(b"\r\n", 1)[0].decode(), took, sent["n"]


def test_a_request_without_a_key_is_refused_before_its_body_is_read(service):
    boundary = "x" * 16
    form = {"Content-Type": f"multipart/form-data; boundary={boundary}"}
    status, took, sent = _post_raw(service.port, "/v1/volumes", form, 50 * 2**20)
    print(f"unauthenticated 50 MB upload: {status} in {took * 1000:.0f} ms, {sent / 2**20:.1f} MB sent")
    assert status == "HTTP/1.1 401 Unauthorized", status
    assert took < 0.5, took
    assert sent < 50 * 2**20  # answered before the body was in

    with service.client() as c:
        # A client that sends the whole body before it reads gets the 401 too
        t0 = time.monotonic()
        r = c.post("/v1/volumes", files={"file": ("big.vdb", b"\0" * (50 * 2**20))})
        print(f"... sent whole first: {r.status_code} in {time.monotonic() - t0:.2f} s")
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer", r.text
        # Malformed JSON without a key: 401, not 422; with the key, the 422 names the fault
        r = c.post("/v1/caches", content=b"{not json", headers={"Content-Type": "application/json"})
        assert r.status_code == 401, r.text
        assert detail(r) == "missing or wrong API key: send 'Authorization: Bearer <key>'"
        r = c.post("/v1/caches", content=b"{not json", headers={"Content-Type": "application/json"} | AUTH)
        assert r.status_code == 422 and "not valid JSON" in detail(r), r.text
    assert_no_leaks(service)


def _check_process(api: int) -> int | None:
    """The volume check that the API process ``api`` runs, if one runs."""
    for c in _children().get(api, []):
        if "server.volume_check" in _cmdline(c):
            return c
    return None


def _upload_in_background(svc: Launched, name: str):
    """Starts an upload of the fog volume from a thread; (thread, its answer box)."""
    box: dict = {}

    def go():
        try:
            with svc.client(headers=AUTH) as c, open(FOG, "rb") as f:
                box["r"] = c.post("/v1/volumes", files={"file": (name, f)})
        except httpx.HTTPError as err:
            box["err"] = err

    t = threading.Thread(target=go, daemon=True)
    t.start()
    return t, box


def _stored(svc: Launched) -> list[str]:
    with svc.client(headers=AUTH) as c:
        return [v["filename"] for v in c.get("/v1/volumes").json()]


def test_an_upload_whose_api_dies_during_the_check_is_not_stored_and_leaves_nothing(service, fog):
    (service.data_dir / "volumes").mkdir(exist_ok=True)
    api = service.pids()["api"]
    thread, box = _upload_in_background(service, "orphan.vdb")
    check = wait_until(lambda: _check_process(api), 30, "no volume check started", interval=0.005)
    os.kill(check, signal.SIGSTOP)  # held mid-check
    incoming = list((service.data_dir / "volumes").glob(".incoming.*.tmp"))
    assert incoming, "the upload was not spooled"
    os.kill(api, signal.SIGKILL)
    os.kill(check, signal.SIGCONT)  # it dies with its API, or ends at once if it had not yet asked
    wait_until(lambda: not Path(f"/proc/{check}").exists(), 5, "the check outlived its API")
    thread.join(30)
    assert "err" in box  # its client saw the API die
    t_back = wait_until(lambda: service.pids().get("api", api) != api and _healthy(service), 60, "no API")
    assert t_back
    assert "orphan.vdb" not in _stored(service)
    assert not [p for p in incoming if p.exists()]  # swept when the API started again
    assert_no_leaks(service)


def _healthy(svc: Launched) -> bool:
    try:
        return httpx.get(f"{svc.url}/healthz", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def test_an_upload_whose_client_goes_away_during_the_check_is_not_stored(service, fog):
    api = service.pids()["api"]
    s = socket.create_connection(("127.0.0.1", service.port), timeout=10)
    boundary = "b" * 24
    payload = FOG.read_bytes()
    body = (
        (
            f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="left.vdb"\r\n'
            "Content-Type: application/octet-stream\r\n\r\n"
        ).encode()
        + payload
        + f"\r\n--{boundary}--\r\n".encode()
    )
    s.sendall(
        (
            f"POST /v1/volumes HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {KEY}\r\n"
            f"Content-Type: multipart/form-data; boundary={boundary}\r\nContent-Length: {len(body)}\r\n\r\n"
        ).encode()
        + body
    )
    check = wait_until(lambda: _check_process(api), 30, "no volume check started", interval=0.005)
    os.kill(check, signal.SIGSTOP)  # held mid-check, while its client leaves
    s.close()
    t0 = time.monotonic()
    wait_until(lambda: not Path(f"/proc/{check}").exists(), 5, "the check went on without its client")
    print(f"client gone: check stopped in {time.monotonic() - t0:.2f} s")
    time.sleep(0.3)
    assert "left.vdb" not in _stored(service)
    assert service.pids()["api"] == api
    assert_no_leaks(service)
