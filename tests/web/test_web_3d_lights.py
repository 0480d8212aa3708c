"""The page, a step of one session after the phase's (see conftest.py): several lights. A
second sun and a sky make the scene's lights v1.1 ``lights``: a relight on the server (the graph
reused), then the real-time view draws both suns and the sky within 1 % of the server's `field`
render. Each light's intensity and colour re-mix the view at once with no request. An uploaded
environment map lights the cloud and is drawn behind it, like the server draws it. Removing
the sun, the sky and the map again brings back the one light's cache."""

from __future__ import annotations

import numpy as np

from .page import (
    api_requests,
    assert_orbit_holds,
    assert_realtime_is_the_server_field,
    errors_shown,
    frames_drawn,
    reset_view,
    shot,
    shown_pixels,
    wait_field_key,
    wait_relit,
    wait_rest,
)
from .test_web_3_compare_relight import MAX_FIELD_REL_MAE
from .test_web_3b_sky import change, corners

#: The one light's field key before (the last step brings it back).
BEFORE = {}


def cloud_mean(pixels: list[float], cloud: np.ndarray) -> float:
    """Mean gray over the view's cloud pixels (a mask); the sky around it does not re-mix."""
    return float(np.asarray(pixels)[cloud].mean())


def test_a_second_sun_and_a_sky_relight_then_are_drawn_like_the_server(page):
    reset_view(page)
    old_key = BEFORE["key"] = page.get_attribute("#viewport", "data-field-key")
    page.click("#sun-add")
    row = "#sun-list .sun-row:nth-child(1)"
    change(page, f"{row} input[data-label='sun 2 azimuth']", "120")
    change(page, f"{row} input[data-label='sun 2 elevation']", "-20")  # from below, the other side
    change(page, f"{row} input[data-label='sun 2 irradiance']", "1.5")
    change(page, "#sky", "0.3")
    wait_relit(page, old_key)
    shot(page, "08i-two-suns-and-a-sky")
    assert_realtime_is_the_server_field(page, "two suns + sky", MAX_FIELD_REL_MAE)


def test_each_light_s_intensity_and_colour_re_mix_with_no_request(page):
    key = page.get_attribute("#viewport", "data-field-key")
    with api_requests(page) as requests:
        shown = np.asarray(shown_pixels(page))
        cloud = np.abs(shown - corners(list(shown))) > 8  # not the sky behind it
        assert cloud.mean() > 0.05, "the cloud is in view"
        before = cloud_mean(shown, cloud)
        frames = frames_drawn(page)
        change(page, "#sun-list input[data-label='sun 2 irradiance']", "0")  # the second sun off
        wait_rest(page, frames)
        without = cloud_mean(shown_pixels(page), cloud)
        frames = frames_drawn(page)
        change(page, "#sun-list input[data-label='sun 2 irradiance']", "8")
        page.fill("#sun-list input[type=color]", "#ff8000")  # an orange second sun, twice as bright
        page.dispatch_event("#sun-list input[type=color]", "input")
        wait_rest(page, frames)
        brighter = cloud_mean(shown_pixels(page), cloud)
    assert page.get_attribute("#viewport", "data-field-key") == key
    assert requests == []
    # (means over the cloud's pixels: the sky's own intensity is not changed here)
    assert without < before - 3 and brighter > before + 3, (without, before, brighter)
    assert errors_shown(page) == []
    shot(page, "08j-second-sun-re-mixed")
    # the server's field in the new mix (the same cache, other intensities) is the page's
    assert_realtime_is_the_server_field(page, "re-mixed suns", MAX_FIELD_REL_MAE)


def test_an_uploaded_environment_map_lights_the_cloud_and_is_drawn_behind_it(page, tmp_path):
    from cloudgraph.image import write_exr

    h, w = 32, 64
    v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w, indexing="ij")
    rgb = 0.3 * np.stack([1 + 0.8 * np.sin(2 * np.pi * u), 1 + 0.6 * np.cos(2 * np.pi * u), 0.5 + v], -1)
    write_exr(rgb.astype(np.float32), tmp_path / "around.exr")
    old_key = page.get_attribute("#viewport", "data-field-key")
    page.set_input_files("#env-file", str(tmp_path / "around.exr"))
    page.wait_for_selector("#env-state.ok, #env-state.failed")
    assert page.get_attribute("#env-state", "class") == "ok", errors_shown(page)
    assert page.input_value("#env-select") != ""  # the upload is chosen: a relight
    wait_relit(page, old_key)
    shot(page, "08k-environment-map")
    assert_realtime_is_the_server_field(page, "two suns + sky + map", MAX_FIELD_REL_MAE)

    with api_requests(page) as requests:
        before = corners(shown_pixels(page))
        frames = frames_drawn(page)
        change(page, "#env-scale", "3")  # a brighter map: the same cache
        wait_rest(page, frames)
        brighter = corners(shown_pixels(page))
    assert requests == []
    assert brighter > before + 20, (before, brighter)


def test_several_lights_hold_the_frame_rate_while_orbiting(page):
    # two suns (three more fetches a step at rest), a sky and a map: moving frames march the
    # one packed texture, whatever the lights
    assert_orbit_holds(page, "two suns + sky + map")


def test_removing_the_sun_the_sky_and_the_map_brings_back_the_one_light(page):
    page.click("#sun-list .sun-row button")
    change(page, "#env-scale", "1")
    page.select_option("#env-select", "")
    change(page, "#sky", "0")
    wait_field_key(page, BEFORE["key"])
    assert page.eval_on_selector_all("#sun-list .sun-row", "rows => rows.length") == 0
    assert corners(shown_pixels(page)) < 20  # no sky behind the cloud
    assert errors_shown(page) == []
