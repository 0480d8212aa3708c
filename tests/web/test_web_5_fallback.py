"""Pages of their own on the session's service (after the session's steps, see conftest.py):
the server renders the viewport when the page cannot (no WebGL, a broken field, a lost GPU
context)."""

from __future__ import annotations

import time

from .browser import NO_WEBGL_ARGS, chromium_path, new_page
from .page import PIXELS_JS, errors_shown, frames_drawn, mean_abs, open_scene, shot, wait_final, wait_rest


def test_fallback_without_webgl(playwright, service, data_dir):
    """Chromium without WebGL: the page says so and the server renders the viewport
    progressively (fast previews while moving, then larger and averaged passes at rest)."""
    b = playwright.chromium.launch(executable_path=chromium_path(), args=NO_WEBGL_ARGS)
    try:
        pg = new_page(b)
        open_scene(pg, service, data_dir)
        pg.wait_for_selector("#viewport[data-renderer=server]")
        assert "Real-time view unavailable: WebGL2 is disabled or unavailable" in pg.inner_text("#view-mode")
        assert "server's progressive renders" in pg.inner_text("#view-mode")
        wait_final(pg, 0)
        assert pg.eval_on_selector("#view-img", "i => i.naturalWidth") == 256
        assert pg.is_hidden("#view-canvas")
        info = pg.inner_text("#view-info")
        assert "256×256 px · 32 spp" in info and "render" in info and "round trip" in info
        before = pg.evaluate(PIXELS_JS)
        assert max(before) > 20, "the rendered smoke is black"
        frame = int(pg.get_attribute("#view-img", "data-frame"))
        assert frames_drawn(pg) == frame
        pg.evaluate(
            """() => {
            const img = document.querySelector('#view-img');
            window.__levels = [];
            new MutationObserver(() => window.__levels.push(img.dataset.level))
              .observe(img, { attributes: true, attributeFilter: ['data-frame'] });
          }"""
        )
        box = pg.locator("#viewport").bounding_box()
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        pg.mouse.move(x, y)
        pg.mouse.down()
        for i in range(1, 13):
            pg.mouse.move(x + 12 * i, y + 2 * i)
            time.sleep(0.03)
        pg.mouse.up()
        wait_final(pg, frame)
        diff = mean_abs(before, pg.evaluate(PIXELS_JS))
        assert diff > 1.0, f"the image hardly changed after orbiting (mean |diff| {diff:.3f} of 255)"
        levels = pg.evaluate("window.__levels")
        last = len(levels) - 1 - levels[::-1].index("0")
        assert levels[0] == "0" and levels[last + 1 :] == ["1", "2", "2", "2", "2"], levels
        # the real-time comparison says why it cannot run
        pg.click("#compare-realtime")
        pg.wait_for_selector("#errors li:has-text('not drawing a field')")
        shot(pg, "15-fallback-no-webgl")
        pg.context.close()
    finally:
        b.close()


def test_broken_field_falls_back_with_error(browser, service, data_dir):
    """A field that cannot be decoded is an error in words, and the server renders instead."""
    pg = new_page(browser)
    try:
        pg.route(
            "**/v1/caches/*/field",
            lambda route: route.fulfill(
                status=200, content_type="application/octet-stream", body=b"<html>" + b"oops " * 40
            ),
        )
        open_scene(pg, service, data_dir)
        pg.wait_for_selector("#errors li")
        message = errors_shown(pg)[0]
        assert "Real-time view" in message and "not a cloudgraph field" in message, message
        pg.wait_for_selector("#viewport[data-renderer=server]")
        assert "not a cloudgraph field" in pg.inner_text("#view-mode")
        wait_final(pg, 0)
        shot(pg, "16-broken-field")
    finally:
        pg.context.close()


def test_lost_gpu_context_falls_back(browser, service, data_dir):
    """When the GPU drops the WebGL context, the page says so and the server renders instead."""
    pg = new_page(browser)
    try:
        open_scene(pg, service, data_dir)
        wait_rest(pg, 0)
        pg.evaluate(
            """() => document.querySelector('#view-canvas').getContext('webgl2')
                 .getExtension('WEBGL_lose_context').loseContext()"""
        )
        pg.wait_for_selector("#viewport[data-renderer=server]")
        assert "the GPU dropped the WebGL context" in pg.inner_text("#view-mode")
        assert any("WebGL context lost" in m for m in errors_shown(pg))
        wait_final(pg, 0)
    finally:
        pg.context.close()
