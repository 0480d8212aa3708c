"""The page, step 3 of one session (see conftest.py): the real-time view against the server's
render, the server's final frame at rest, a relight, and the graph compared with volpath."""

from __future__ import annotations

import re

from .page import compare_realtime, errors_shown, frames_drawn, orbit, shot, wait_rest

#: The real-time view against the server's `field` render of the same camera, at rest: the two
#: march the same rays (the server's at the pixels' centres too; measured 0.00-0.01 % in every
#: comparison of the page session, 0.25 % at most while the server's positions were jittered)
MAX_FIELD_REL_MAE = 0.002


def test_compare_realtime_with_server_field(page):
    """At rest the page's view is the server's `field` render of the same camera and size,
    within MAX_FIELD_REL_MAE; the comparison with volpath is shown beside it."""
    result = compare_realtime(page)
    rel, rel_volpath, text = float(result["relMae"]), float(result["relMaeVolpath"]), result["text"]
    print(f"real-time vs server field: relMAE {rel:.4f}; vs volpath 8 spp {rel_volpath:.4f}")
    assert 0 <= rel < MAX_FIELD_REL_MAE, text
    assert 0 < rel_volpath < 1, text
    assert "real-time vs server field: relMAE" in text and "real-time vs volpath 8 spp" in text
    shot(page, "08a-compare-realtime")


def test_final_frame_at_rest(page):
    """The toggle asks the server for a gather frame at rest, shown over the real-time view
    until the camera moves."""
    page.check("#final-toggle")
    page.wait_for_selector("#viewport[data-final='1']", timeout=120_000)
    assert page.is_visible("#view-img")
    assert page.eval_on_selector("#view-img", "i => i.naturalWidth") == 256
    assert "final: server gather 256×256 px" in page.inner_text("#view-info")
    shot(page, "08b-final")
    frames = frames_drawn(page)
    orbit(page, ms=300, dx=-20)
    assert page.get_attribute("#viewport", "data-final") is None and page.is_hidden("#view-img")
    page.uncheck("#final-toggle")
    wait_rest(page, frames)
    assert page.get_attribute("#viewport", "data-final") is None
    assert errors_shown(page) == []


def test_relight_keeps_old_field_then_swaps(page):
    """A new light starts a relight (the graph reused); the old field is drawn meanwhile and
    the new one replaces it, with the time it took shown."""
    old_key = page.get_attribute("#viewport", "data-field-key")
    page.fill("#light-az", "60")
    page.dispatch_event("#light-az", "change")
    page.wait_for_selector("#relight-info:has-text('Relighting on the server')")
    # meanwhile: still the real-time view of the old field, and it still follows the camera
    frames = frames_drawn(page)
    orbit(page, ms=400, dx=30)
    # the viewport and the relight note read at one instant (the relight may end between two reads)
    vp, seconds = page.evaluate(
        "() => [{...document.querySelector('#viewport').dataset},"
        " document.querySelector('#relight-info').dataset.seconds ?? null]"
    )
    assert vp["renderer"] == "webgl" and int(vp["frames"]) > frames
    relit = vp["fieldKey"] != old_key  # a very quick relight may be done already
    assert relit or seconds is None
    shot(page, "08c-relighting")
    page.wait_for_selector("#relight-info[data-seconds]", timeout=600_000)
    seconds = float(page.get_attribute("#relight-info", "data-seconds"))
    assert 0 < seconds < 600
    assert "Relit in" in page.inner_text("#relight-info")
    new_key = page.get_attribute("#viewport", "data-field-key")
    assert re.fullmatch(r"[0-9a-f]{64}", new_key) and new_key != old_key
    assert page.inner_text("#cache-stats dd[data-stat='graph build']") == "reused"
    wait_rest(page, frames_drawn(page) - 1)
    assert errors_shown(page) == []
    shot(page, "08d-relit")
    print(f"relight: {seconds:.2f} s from the light change to the new field drawn")


def test_compare_graph_with_volpath(page):
    page.select_option("#compare-size", "64")
    page.fill("#compare-graph-spp", "8")
    page.fill("#compare-volpath-spp", "8")
    page.click("#compare-run")
    page.wait_for_selector(".compare-out[data-state=done], .compare-out[data-state=failed]")
    assert page.get_attribute(".compare-out", "data-state") == "done", errors_shown(page)
    mae = float(page.get_attribute("#compare-canvas", "data-mae"))
    text = page.inner_text("#compare-mae")
    relative = float(re.search(r"([\d.]+) % of the volpath mean", text).group(1))
    assert mae > 0 and 0 < relative < 100, text
    page.select_option("#compare-view", "diff")
    shot(page, "08-compare")
    page.select_option("#compare-view", "split")
