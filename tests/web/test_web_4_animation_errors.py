"""The page, step 4 and last of one session (see conftest.py): an animation played and
downloaded, bad uploads shown in words, and no unexpected page error in the whole session."""

from __future__ import annotations

from .page import errors_shown, shot


def test_animation_plays(page, service):
    page.check("#anim-path-orbit")
    page.fill("#anim-frames", "4")
    page.fill("#anim-fps", "8")
    page.fill("#anim-size", "64")
    page.fill("#anim-spp", "4")
    page.click("#anim-run")
    page.wait_for_function(
        """() => {
          const v = document.querySelector('#anim-video');
          return (v.getAttribute('src') && (v.readyState >= 2 || v.duration > 0))
            || /failed|cancelled/.test(document.querySelector('#anim-stage').textContent);
        }""",
        timeout=120_000,
    )
    assert "done" in page.inner_text("#anim-stage"), errors_shown(page)
    state = page.evaluate(
        "() => { const v = document.querySelector('#anim-video'); "
        "return {ready: v.readyState, duration: v.duration, w: v.videoWidth}; }"
    )
    assert state["ready"] >= 2 and state["duration"] > 0 and state["w"] == 64, state
    page.evaluate("() => document.querySelector('#anim-video').play()")
    page.wait_for_function("document.querySelector('#anim-video').currentTime > 0")
    href = page.get_attribute("#anim-download", "href")
    assert page.is_visible("#anim-download")
    with service.client() as client:
        r = client.get(href)
    assert r.status_code == 200
    assert r.headers["content-type"] == "video/mp4"
    assert r.content[4:8] == b"ftyp"
    shot(page, "09-animation")


def test_bad_upload_shows_error(page, tmp_path):
    bad = tmp_path / "bad.vdb"
    bad.write_text("this is not a volume\n")
    page.set_input_files("#volume-file", str(bad))
    page.wait_for_selector("#errors li")
    message = errors_shown(page)[0]
    assert "bad.vdb" in message and "422" in message
    assert "bad.vdb is neither an OpenVDB" in message and ".tmp" not in message
    assert page.is_visible("#errors")
    assert "failed" in page.inner_text("#upload-state")
    shot(page, "10-bad-upload")

    # a file name is user text: it reaches the page as text, never as markup
    page.set_input_files(
        "#volume-file",
        files=[{"name": '<img id="pwned" src="x">.vdb', "mimeType": "text/plain", "buffer": b"nope"}],
    )
    page.wait_for_function("document.querySelectorAll('#errors li').length >= 2")
    assert page.locator("#pwned").count() == 0
    assert '<img id="pwned" src="x">.vdb' in errors_shown(page)[0]
    # the volume chosen before is still selected and the viewport still works
    assert "smoke1.vdb" in page.inner_text("#volume-select option:checked")
    shot(page, "11-bad-upload-name")


def test_no_unexpected_page_errors(page):
    # the expected failures above are answered 422 (logged by Chromium as failed resources)
    unexpected = [p for p in page.problems if "status of 422" not in p]
    assert unexpected == []
