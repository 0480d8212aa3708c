"""The page, a step of one session after the sky's (see conftest.py): forward scattering. A
Henyey-Greenstein phase is another graph (its similarity-scaled medium's): the page asks for a
precompute, then draws the new field, whose L_ms depends on the view (api.md, ``ms_shape``),
within 1 % of the server's `field` render of the same camera. The isotropic phase again brings
back the cache it had."""

from __future__ import annotations

from .page import (
    assert_orbit_holds,
    assert_realtime_is_the_server_field,
    errors_shown,
    frames_drawn,
    shot,
    wait_field_key,
    wait_rest,
)
from .test_web_3_compare_relight import MAX_FIELD_REL_MAE

#: The isotropic cache's field key (the last step brings it back).
BEFORE = {}


def test_a_forward_scattering_cloud_is_drawn_like_the_server_draws_it(page):
    wait_rest(page, frames_drawn(page) - 1)
    BEFORE["key"] = page.get_attribute("#viewport", "data-field-key")
    page.select_option("#phase-type", "hg")
    page.fill("#phase-g", "0.85")
    page.dispatch_event("#phase-g", "change")
    page.wait_for_selector("#view-overlay:has-text('Precompute')")  # another graph: asked for
    page.click("#precompute")
    page.wait_for_selector("#cache-state[data-state=ready], #cache-state[data-state=failed]", timeout=600_000)
    assert page.get_attribute("#cache-state", "data-state") == "ready", errors_shown(page)
    page.wait_for_function(
        f"() => {{ const k = document.querySelector('#viewport').dataset.fieldKey;"
        f" return k && k !== '{BEFORE['key']}'; }}",
        timeout=120_000,
    )
    wait_rest(page, frames_drawn(page) - 1)
    shot(page, "08h-forward-scattering")
    assert_realtime_is_the_server_field(page, "g = 0.85", MAX_FIELD_REL_MAE)


def test_the_forward_scattering_view_holds_its_frame_rate_while_orbiting(page):
    # an anisotropic field's moving frames read two textures a step (the packed one and the suns'
    # transmittance): the frame budget lowers their resolution and lengthens their step, never
    # below 128 px
    assert_orbit_holds(page, "g = 0.85")


def test_the_isotropic_phase_brings_back_its_cache(page):
    page.select_option("#phase-type", "isotropic")
    page.dispatch_event("#phase-type", "change")
    wait_field_key(page, BEFORE["key"])
    assert errors_shown(page) == []
