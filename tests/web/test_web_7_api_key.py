"""A page on a service of its own with API keys: 401 in words, the key field, progress by
polling and the video fetched with the key."""

from __future__ import annotations

import pytest

from ..harness import start_service
from .browser import new_page
from .page import count_event_sources, errors_shown, shot, wait_rest

KEY = "web-test-key-0123456789abcdef"


@pytest.fixture(scope="module")
def key_service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("web-key-service"), workers=1, API_KEYS=KEY)
    yield svc
    svc.stop()


def test_api_key_polling_and_video_download(browser, key_service, data_dir):
    """With keys on the server: 401 in words, the key field, progress by polling (EventSource
    cannot send the header) and the video fetched with the key."""
    pg = new_page(browser)
    try:
        pg.goto(key_service.url + "/")
        pg.wait_for_selector("#errors li")
        message = errors_shown(pg)[0]
        assert "401" in message and "API key" in message
        shot(pg, "12-key-missing")

        pg.fill("#api-key", KEY)
        pg.click("#api-key-form button[type=submit]")
        pg.wait_for_selector("#api-key-state[data-state=set]")
        assert pg.evaluate("localStorage.getItem('cloudgraph.apiKey')") == KEY
        pg.set_input_files("#volume-file", str(data_dir / "fog_sphere.vdb"))
        pg.wait_for_selector("#upload-state.ok")
        assert errors_shown(pg) == []

        pg.evaluate(
            """() => {
            const bar = document.querySelector('#cache-progress');
            window.__progress = [];
            new MutationObserver(() => window.__progress.push(bar.value))
              .observe(bar, { attributes: true, attributeFilter: ['value'] });
          }"""
        )
        count_event_sources(pg)
        pg.click("#precompute")
        pg.wait_for_selector("#cache-state[data-state=ready], #cache-state[data-state=failed]")
        assert pg.get_attribute("#cache-state", "data-state") == "ready", errors_shown(pg)
        assert pg.evaluate("window.__eventSources") == []
        assert pg.evaluate("window.__progress")[-1] == 1.0
        assert int(pg.inner_text("#cache-stats dd[data-stat=nodes]").replace(",", "")) > 0
        wait_rest(pg, 0)
        shot(pg, "13-key-viewport")

        pg.fill("#anim-frames", "2")
        pg.fill("#anim-size", "32")
        pg.fill("#anim-spp", "2")
        pg.click("#anim-run")
        pg.wait_for_function(
            """() => {
              const v = document.querySelector('#anim-video');
              return (v.getAttribute('src') && v.readyState >= 2)
                || /failed|cancelled/.test(document.querySelector('#anim-stage').textContent);
            }""",
            timeout=120_000,
        )
        assert "done" in pg.inner_text("#anim-stage"), errors_shown(pg)
        assert pg.get_attribute("#anim-video", "src").startswith("blob:")
        assert pg.get_attribute("#anim-download", "href").startswith("blob:")
        assert errors_shown(pg) == [message] or errors_shown(pg) == []
        shot(pg, "14-key-animation")
    finally:
        pg.context.close()
