"""The page, step 2 of one session (see conftest.py): the real-time (WebGL2) view of the cache
drawn in the page, orbiting at a frame rate, zoom, pan, fly and keyframes."""

from __future__ import annotations

import re
import time

import pytest

from .page import (
    assert_orbit_adapts,
    camera,
    errors_shown,
    frames_drawn,
    mean_abs,
    orbit,
    shot,
    shown_pixels,
    wait_rest,
)


def test_realtime_view_draws_the_field(page):
    """With WebGL2 the page draws the cache's field itself, at full size once at rest."""
    wait_rest(page, 0)
    vp = page.eval_on_selector("#viewport", "v => ({...v.dataset})")
    assert vp["renderer"] == "webgl" and re.fullmatch(r"[0-9a-f]{64}", vp["fieldKey"]), vp
    width = page.eval_on_selector("#view-canvas", "c => c.width")
    assert int(vp["internal"]) == width >= 256
    info = page.inner_text("#view-info")
    assert info.startswith("WebGL2") and "rest" in info and re.search(r"field \d+×\d+×\d+", info)
    assert "this page draws the cache's radiance field" in page.inner_text("#view-mode")
    pixels = shown_pixels(page)
    assert max(pixels) > 20, "the real-time view of the smoke is black"
    assert page.is_hidden("#view-img") and page.is_hidden("#view-overlay")
    assert errors_shown(page) == []
    shot(page, "05-realtime")
    print(f"rest: {width} px drawn in {int(vp['restMs']) / 1000:.2f} s; {info}")


def test_realtime_orbit_holds_frame_rate(page):
    """Orbiting draws the moving camera's frames within the frame budget (page.py's
    assert_orbit_adapts: its rate is measured, its levels asserted), never below 128 px inside,
    and the full size again at rest."""
    before = shown_pixels(page)
    full = int(page.get_attribute("#viewport", "data-internal"))
    r = orbit(page, ms=3000, dx=150)
    frames = frames_drawn(page)
    assert_orbit_adapts(page, "one sun", r)
    shot(page, "06-orbiting")
    wait_rest(page, frames - 1)
    assert int(page.get_attribute("#viewport", "data-internal")) == full
    after = shown_pixels(page)
    diff = mean_abs(before, after)
    assert diff > 1.0, f"the image hardly changed after orbiting (mean |diff| {diff:.3f} of 255)"
    assert "yaw -" in page.inner_text("#camera-info")
    assert errors_shown(page) == []
    shot(page, "06-orbited")


def test_zoom_pan_fly_and_keyframes(page):
    box = page.locator("#viewport").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    eye0, target0, d0 = camera(page)

    page.mouse.move(x, y)
    page.mouse.wheel(0, -300)  # wheel up: closer
    page.wait_for_function(f"JSON.parse(document.querySelector('#camera-info').dataset.eye)[0] !== {eye0[0]}")
    _, target1, d1 = camera(page)
    assert d1 < 0.9 * d0 and target1 == target0

    for how in ("shift", "right"):
        page.mouse.move(x, y)
        if how == "shift":
            page.keyboard.down("Shift")
        page.mouse.down(button="left" if how == "shift" else "right")
        page.mouse.move(x + 60, y + 30, steps=5)
        page.mouse.up(button="left" if how == "shift" else "right")
        if how == "shift":
            page.keyboard.up("Shift")
        _, target2, d2 = camera(page)
        assert target2 != target1, f"{how}-drag did not pan"
        assert d2 == pytest.approx(d1, rel=1e-3)
        target1 = target2

    page.focus("#viewport")
    eye3, target3, d3 = camera(page)
    page.keyboard.down("w")
    time.sleep(0.4)
    page.keyboard.up("w")
    eye4, target4, d4 = camera(page)
    forward = [(t - e) / d3 for t, e in zip(target3, eye3, strict=True)]
    moved = sum((a - b) * f for a, b, f in zip(target4, target3, forward, strict=True))
    assert moved > 0.05 * d3, "W did not fly forward"
    assert d4 == pytest.approx(d3, rel=1e-3)
    page.keyboard.press("ArrowLeft")
    assert camera(page)[1] != target4

    # keyframes: fewer than two is refused in words; two are listed
    page.check("#anim-path-keys")
    page.click("#anim-add-key")
    assert page.inner_text("#anim-keys-count") == "1 keyframe"
    page.click("#anim-run")
    page.wait_for_selector("#errors li:has-text('at least 2 keyframes')")
    page.click("#errors li .dismiss")
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x - 80, y, steps=4)
    page.mouse.up()
    page.click("#anim-add-key")
    assert page.locator("#anim-keys-list li").count() == 2
    assert page.inner_text("#anim-keys-count") == "2 keyframes"
    wait_rest(page, frames_drawn(page) - 1)
    assert errors_shown(page) == []
    shot(page, "07-moved-keyframes")
