"""The page, a step of one session after several lights' (see conftest.py): the model's sun and
sky (Hosek-Wilkie, Mitsuba's ``sunsky``). "Sun & sky" turns the sun into the model's sun and
sky, a v1.1 ``sunsky`` light: a relight on the server (the graph reused), then the real-time
view draws the sky behind the cloud within 1 % of the server's `field` render. The sun's scale
(Irradiance) and the sky's re-mix the view at once with no request: the field keeps the
model's sun colour. Off again brings back the one light's cache."""

from __future__ import annotations

import numpy as np

from .page import (
    api_requests,
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
from .test_web_3b_sky import change, corners
from .test_web_3d_lights import cloud_mean

#: The one light's field key before (the last step brings it back).
BEFORE = {}
#: The real-time view against the server's `field` render here: 1 % (the issue's bound), not
#: MAX_FIELD_REL_MAE. The model's sky steps to black at the horizon, and the page reads that
#: step from the field's background (the map resampled at 512 x 256, read bilinearly) where the
#: server reads the map: the pixels on the horizon differ (measured 0.58 %, mean ratio 1.000;
#: the cloud itself as closely as in the other steps).
MAX_SKY_REL_MAE = 0.01


def test_the_model_s_sun_and_sky_relight_then_are_drawn_like_the_server(page):
    reset_view(page)
    dark = corners(shown_pixels(page))
    old_key = BEFORE["key"] = page.get_attribute("#viewport", "data-field-key")
    page.check("#sunsky")
    wait_relit(page, old_key)
    sky = corners(shown_pixels(page))
    assert dark < 20 and sky > dark + 20, (dark, sky)  # black behind the cloud before, the sky now
    shot(page, "08l-sun-and-sky")
    assert_realtime_is_the_server_field(page, "the model's sun and sky", MAX_SKY_REL_MAE)


def test_the_model_s_sun_and_sky_scales_re_mix_with_no_request(page):
    key = page.get_attribute("#viewport", "data-field-key")
    with api_requests(page) as requests:
        shown = np.asarray(shown_pixels(page))
        cloud = np.abs(shown - corners(list(shown))) > 8  # not the sky behind it
        assert cloud.mean() > 0.05, "the cloud is in view"
        before, sky = cloud_mean(shown, cloud), corners(list(shown))
        frames = frames_drawn(page)
        change(page, "#irradiance", "0")  # the sun off: the sky alone lights the cloud
        wait_rest(page, frames)
        without = cloud_mean(shown_pixels(page), cloud)
        frames = frames_drawn(page)
        change(page, "#sky-scale", "2")
        wait_rest(page, frames)
        brighter = corners(shown_pixels(page))
    assert page.get_attribute("#viewport", "data-field-key") == key
    assert requests == []
    assert without < before - 3 and brighter > sky + 10, (without, before, sky, brighter)
    assert errors_shown(page) == []
    shot(page, "08m-sun-and-sky-re-mixed")
    # the server's field in the new mix (the same cache, other scales) is the page's
    assert_realtime_is_the_server_field(page, "the model's sky alone", MAX_SKY_REL_MAE)


def test_the_model_off_brings_back_the_one_light(page):
    change(page, "#irradiance", "1")
    change(page, "#sky-scale", "1")
    page.uncheck("#sunsky")
    wait_field_key(page, BEFORE["key"])
    assert corners(shown_pixels(page)) < 20  # no sky behind the cloud
    assert errors_shown(page) == []
