"""A page of its own on the session's service (after the session's steps, see conftest.py): a
Disney-sized field's memory in the page."""

from __future__ import annotations

from .browser import new_page
from .fieldmaker import encode, light_depth_from_above, make_field
from .page import errors_shown, open_scene

#: The Disney cloud at 1/16 resolution: its field's grid.
DISNEY_16 = (154, 86, 126)


def test_disney_sized_field_fits_in_memory(browser, service, data_dir):
    """A field the size of Disney 1/16's (126x86x154 voxels, its multiple scattering at the same
    resolution and its tau_light at twice it, its sun's L_ms over its light factor, as the bake
    makes it) is drawn with at most 64 MB
    of textures and 200 MB of page memory: the JS heap after loading plus the GPU textures."""
    field = make_field(shape=DISNEY_16, block=8, ms_coarsen=1)
    light_depth_from_above(field, fine=True)
    field["header"]["ms_light"] = {"power": [0.1, 0.1, 0.1], "range": 1.25}  # (the sun's L_ms apart)
    # (uncompressed: Chromium does not gunzip a response that a test fulfils)
    body = encode(field)
    pg = new_page(browser)
    try:
        pg.route(
            "**/v1/caches/*/field",
            lambda route: route.fulfill(
                status=200,
                headers={"Content-Type": "application/octet-stream"},
                body=body,
            ),
        )
        open_scene(pg, service, data_dir)
        pg.wait_for_selector("#viewport[data-renderer=webgl][data-state=rest]")
        info = pg.inner_text("#view-info")
        assert "field 126×86×154" in info, info
        gpu = int(pg.get_attribute("#viewport", "data-texture-bytes"))
        cdp = pg.context.new_cdp_session(pg)
        cdp.send("HeapProfiler.collectGarbage")
        cdp.send("Performance.enable")
        metrics = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
        heap = metrics["JSHeapUsedSize"]
        print(f"Disney-sized field: JS heap {heap / 2**20:.1f} MiB, textures {gpu / 2**20:.1f} MiB")
        assert gpu <= 64 * 2**20, gpu
        assert heap + gpu <= 200e6, (heap, gpu)
        assert errors_shown(pg) == []
    finally:
        pg.context.close()
