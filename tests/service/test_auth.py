"""API keys: with CLOUDGRAPH_API_KEYS set, every /v1 route needs one; health routes never do."""

from __future__ import annotations

from ..harness import FOG, KEY, detail, no_server_errors, start_service


def test_with_api_keys_v1_needs_the_key_and_health_does_not(tmp_path):
    s = start_service(tmp_path / "auth", workers=0, API_KEYS=f"{KEY},another-key-0123456789")
    try:
        with s.client() as c:
            r = c.get("/v1/volumes")
            assert r.status_code == 401, r.text
            assert r.headers["www-authenticate"] == "Bearer"
            assert "send 'Authorization: Bearer <key>'" in detail(r)
            for auth in ("Bearer wrong-key-wrong-key", f"Basic {KEY}", KEY, "Bearer", f"Bearer {KEY[:-1]}"):
                r = c.get("/v1/volumes", headers={"Authorization": auth})
                assert r.status_code == 401, auth
            with open(FOG, "rb") as f:
                assert c.post("/v1/volumes", files={"file": ("fog.vdb", f)}).status_code == 401
            assert c.get("/v1/jobs/x", headers={"Authorization": "Bearer nope"}).status_code == 401
            assert c.get("/v1/caches/" + "0" * 32 + "/field").status_code == 401

            good = {"Authorization": f"Bearer {KEY}"}
            assert c.get("/v1/volumes", headers=good).json() == []
            with open(FOG, "rb") as f:
                r = c.post("/v1/volumes", files={"file": ("fog.vdb", f)}, headers=good)
            assert r.status_code == 201, r.text
            r = c.get("/v1/volumes", headers={"Authorization": "Bearer another-key-0123456789"})
            assert r.status_code == 200 and len(r.json()) == 1
            assert c.get("/v1/jobs/x", headers=good).status_code == 404
            assert c.get("/v1/caches/" + "0" * 32 + "/field", headers=good).status_code == 404

            assert c.get("/healthz").status_code == 200
            assert c.get("/readyz").status_code == 503  # no worker; but not 401
            assert c.get("/metrics").status_code == 200
        no_server_errors(s)
    finally:
        s.stop()


def test_without_api_keys_v1_needs_none(client):
    assert client.get("/v1/volumes").status_code == 200
    assert client.get("/v1/volumes", headers={"Authorization": "Bearer anything"}).status_code == 200
