"""Fixtures of the service tests: real processes (tests/harness.py), nothing mocked.

``svc`` is one whole service (redis-server, one worker, uvicorn) shared by the test files of this
folder; tests that need a service of their own (no worker, API keys, small limits, faults)
start one. Every service checks at its end that no request was answered with a 500.
"""

from __future__ import annotations

import pytest

from ..harness import BLENDER, FOG, no_server_errors, start_service, upload


@pytest.fixture(scope="session")
def svc(tmp_path_factory):
    s = start_service(tmp_path_factory.mktemp("svc"), workers=1)
    yield s
    try:
        no_server_errors(s)
    finally:
        s.stop()


@pytest.fixture(scope="session")
def client(svc):
    with svc.client() as c:
        yield c


@pytest.fixture(scope="session")
def uploads(client) -> dict:
    """The first upload of each test volume (their answers, checked in test_volumes)."""
    return {p.name: upload(client, p) for p in (FOG, BLENDER)}


@pytest.fixture(scope="session")
def fog(uploads) -> str:
    return uploads[FOG.name].json()["id"]


@pytest.fixture(scope="session")
def blender(uploads) -> str:
    return uploads[BLENDER.name].json()["id"]


@pytest.fixture(scope="module")
def idle(tmp_path_factory):
    """No worker at first, a 1 MiB upload limit and room for four waiting jobs."""
    s = start_service(tmp_path_factory.mktemp("idle"), workers=0, MAX_UPLOAD_MB=1, MAX_QUEUED=4)
    yield s
    try:
        no_server_errors(s)
    finally:
        s.stop()
