"""Fixtures of the web tests that drive the page in a real service (tests/web/test_web_*.py).

One service (redis-server, one worker, uvicorn), one Chromium and one page for the session;
the tests of test_web_1..4 run in order, each a step of one session: load, upload, precompute,
the real-time (WebGL2) view and orbit, compare with the server, relight, final frame, animate,
bad upload. test_web_5..7 open pages of their own afterwards: the server fallback (Chromium
launched with --disable-webgl), a broken field, a Disney-sized field's memory, and a service
with API keys. Pytest runs the files in the order of their names: run tests/web as a whole (a
later file alone finds no volume or cache on the fresh service). Chromium has no GPU here:
WebGL2 runs on SwiftShader. Screenshots of every step go to test-artifacts/web/.
(test_glview.py has a browser and a page of its own, without a service.)
"""

from __future__ import annotations

import shutil

import pytest

from ..harness import start_service
from .browser import ARGS, chromium_path, new_page
from .page import ARTIFACTS


@pytest.fixture(scope="session")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("web-service"), workers=1)
    yield svc
    svc.stop()


@pytest.fixture(scope="session")
def playwright():
    sync_api = pytest.importorskip("playwright.sync_api")
    if chromium_path() is None:
        pytest.skip("Chromium not found (install Debian's chromium or set CLOUDGRAPH_CHROMIUM)")
    shutil.rmtree(ARTIFACTS, ignore_errors=True)
    ARTIFACTS.mkdir(parents=True)
    with sync_api.sync_playwright() as pw:
        yield pw


@pytest.fixture(scope="session")
def browser(playwright):
    b = playwright.chromium.launch(executable_path=chromium_path(), args=ARGS)
    yield b
    b.close()


@pytest.fixture(scope="session")
def page(browser, service):
    pg = new_page(browser)
    yield pg
    pg.context.close()
