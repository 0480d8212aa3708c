"""The page, a step of one session after step 3 (see conftest.py): a sky. With a sky the scene
has v1.1 lights (a sun and the sky): a relight on the server (the graph reused), then the
real-time view draws the sky behind the cloud, within 1 % of the server's `field` render, and
new intensities or a new sky colour re-draw it at once with no request. The sky off again
brings back the v1 cache."""

from __future__ import annotations

from .page import (
    api_requests,
    assert_realtime_is_the_server_field,
    errors_shown,
    frames_drawn,
    reset_view,
    shot,
    shown_pixels,
    wait_field_key,
    wait_rest,
)
from .test_web_3_compare_relight import MAX_FIELD_REL_MAE


def corners(pixels: list[float]) -> float:
    """Mean gray (0..255) of the shown image's four corners (64 x 64 values): the background."""
    n = int(len(pixels) ** 0.5)
    return sum(pixels[i] for i in (0, n - 1, n * (n - 1), n * n - 1)) / 4


def change(page, selector: str, value: str) -> None:
    page.fill(selector, value)
    page.dispatch_event(selector, "change")


#: The one light's field key before the sky (the last step brings it back).
BEFORE = {}


def test_a_sky_relights_then_is_drawn_behind_the_cloud_like_the_server(page):
    reset_view(page)  # (its corners show the background)
    dark = corners(shown_pixels(page))
    old_key = BEFORE["key"] = page.get_attribute("#viewport", "data-field-key")
    change(page, "#sky", "0.5")
    page.wait_for_selector("#relight-info[data-seconds]", timeout=600_000)
    new_key = page.get_attribute("#viewport", "data-field-key")
    assert new_key != old_key, "the sky's cache is another radiance key"
    wait_rest(page, frames_drawn(page) - 1)
    sky = corners(shown_pixels(page))
    assert dark < 20 and sky > dark + 50, (dark, sky)  # black behind the cloud before, the sky now
    shot(page, "08e-sky")

    assert_realtime_is_the_server_field(page, "sun + sky", MAX_FIELD_REL_MAE)


def test_new_intensities_of_the_lights_re_draw_with_no_request(page):
    key = page.get_attribute("#viewport", "data-field-key")
    with api_requests(page) as requests:
        before = corners(shown_pixels(page))
        frames = frames_drawn(page)
        change(page, "#sky", "1.5")  # brighter sky
        wait_rest(page, frames)
        brighter = corners(shown_pixels(page))
        frames = frames_drawn(page)
        change(page, "#irradiance", "2")  # a brighter sun: the same cache
        wait_rest(page, frames)
    assert page.get_attribute("#viewport", "data-field-key") == key
    assert requests == []
    assert brighter > before + 20, (before, brighter)
    assert errors_shown(page) == []
    shot(page, "08f-sky-remixed")


def test_the_sky_off_brings_back_the_one_light(page):
    change(page, "#irradiance", "1")
    change(page, "#sky", "0")
    # the one light's cache is ready: its field is downloaded again and drawn
    wait_field_key(page, BEFORE["key"])
    assert corners(shown_pixels(page)) < 20
    assert errors_shown(page) == []
