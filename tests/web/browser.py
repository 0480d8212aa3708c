"""Headless Chromium for the web tests: where it is, how it is launched, a fresh page, and the
page's own modules served straight from web/ (no service) for tests of pure page code."""

from __future__ import annotations

import mimetypes
import os
import shutil
from pathlib import Path

from ..harness import ROOT

CHROMIUM = os.environ.get("CLOUDGRAPH_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
# --disable-gpu: no GPU on the test machines; WebGL2 still runs on SwiftShader (software).
ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
# The page's fallback: Chromium with WebGL switched off entirely.
NO_WEBGL_ARGS = [*ARGS, "--disable-webgl"]
WEB = ROOT / "web"
STATIC_ORIGIN = "http://cloudgraph.test"
TIMEOUT_MS = 60_000


def chromium_path() -> str | None:
    return CHROMIUM if Path(CHROMIUM).exists() else None


def new_page(browser, width: int = 1400, height: int = 950):
    context = browser.new_context(viewport={"width": width, "height": height})
    pg = context.new_page()
    pg.set_default_timeout(TIMEOUT_MS)
    pg.problems = []
    pg.on("pageerror", lambda e: pg.problems.append(f"page error: {e}"))
    pg.on("console", lambda m: m.type == "error" and pg.problems.append(f"console: {m.text}"))
    return pg


def static_page(browser):
    """A blank page at STATIC_ORIGIN whose /js/*.js are web/'s files, for importing modules."""
    pg = new_page(browser)

    def serve(route):
        path = route.request.url[len(STATIC_ORIGIN) :].split("?")[0]
        if path in ("", "/"):
            route.fulfill(status=200, content_type="text/html", body="<!doctype html><title>t</title>")
            return
        file = (WEB / path.lstrip("/")).resolve()
        if WEB.resolve() not in file.parents or not file.is_file():
            route.fulfill(status=404, body="not found")
            return
        kind = mimetypes.guess_type(file.name)[0] or "application/octet-stream"
        if file.suffix == ".js":
            kind = "text/javascript"
        route.fulfill(status=200, content_type=kind, body=file.read_bytes())

    pg.context.route(f"{STATIC_ORIGIN}/**", serve)
    pg.goto(STATIC_ORIGIN + "/")
    return pg
