"""The page, step 1 of one session (see conftest.py): it loads, its pure functions, a volume
uploaded, its draft cache precomputed with progress by SSE and its stats shown."""

from __future__ import annotations

import re
import time

import pytest

from .page import count_event_sources, errors_shown, shot


def test_page_loads(page, service):
    page.goto(service.url + "/")
    # no volume yet: the viewport says what to do
    page.wait_for_selector("#view-overlay:has-text('Upload a volume')")
    assert page.title() == "cloudgraph"
    assert page.inner_text("#status") == "Ready."
    assert page.locator("#volume-select option").first.inner_text().startswith("no volumes")
    assert errors_shown(page) == []
    shot(page, "01-loaded")


def test_page_modules(page):
    """The page's pure functions, run in the page: sRGB decoding and MAE, light angles, framing,
    escaping."""
    r = page.evaluate(
        """async () => {
        const im = await import('/js/imagemath.js');
        const lw = await import('/js/lightwidget.js');
        const cam = await import('/js/camera.js');
        const dom = await import('/js/dom.js');
        const img = (v) => { const d = new ImageData(2, 1); d.data.fill(255);
                             for (let i = 0; i < 8; i++) if (i % 4 < 3) d.data[i] = v; return d; };
        const cmp = im.compareImages(img(188), img(128));
        const out = { lut: [im.srgbToLinear(0), im.srgbToLinear(128), im.srgbToLinear(255)],
                      mae: cmp.mae, rel: cmp.relative, angles: [], inView: true,
                      esc: dom.escapeHtml(`<a href="x">&'`) };
        for (const ax of ['y', 'z']) {
          const d = lw.lightDirection(-35, 25, cam.AXES[ax]);
          out.angles.push(lw.anglesOf(d, cam.AXES[ax]));
          const c = new cam.OrbitCamera();
          c.axes = cam.AXES[ax];
          const box = [[-33.8, -12.4, -26.2], [19.0, 93.3, 27.1]];
          c.frame(box);
          const { forward, right, up } = c.basis();
          const t = Math.tan(c.fov * Math.PI / 360);
          for (let i = 0; i < 8; i++) {
            const p = [0, 1, 2].map((k) => box[(i >> k) & 1][k]);
            const v = cam.sub(p, c.eye());
            const z = cam.dot(v, forward);
            const x = Math.abs(cam.dot(v, right));
            const y = Math.abs(cam.dot(v, up));
            if (z <= 0 || x > z * t || y > z * t) out.inView = false;
          }
        }
        return out;
      }"""
    )
    assert (
        r["lut"][0] == 0
        and r["lut"][2] == pytest.approx(1)
        and r["lut"][1] == pytest.approx(0.2158, abs=1e-4)
    )
    # |0.5029 - 0.2158| relative to 0.2158
    assert r["mae"] == pytest.approx(0.2871, abs=1e-3) and r["rel"] == pytest.approx(1.330, abs=1e-2)
    for a in r["angles"]:
        assert a["az"] == pytest.approx(-35, abs=0.01) and a["el"] == pytest.approx(25, abs=0.01)
    assert r["inView"], "framing leaves a corner of the box out of view"
    assert r["esc"] == "&lt;a href=&quot;x&quot;&gt;&amp;&#39;"


def test_a_volume_of_several_float_grids_none_named_density_is_read_by_its_first(page):
    """A volume whose description names no default grid (api.md): the page's scenes name the
    first float grid, the one its boxes and values describe."""
    r = page.evaluate(
        """async () => {
        const s = await import('/js/scene.js');
        const grids = [{ name: 'vel', type: 'vec3s' }, { name: 'smoke', type: 'float' },
                       { name: 'heat', type: 'half' }];
        return [s.densityGrid({ grid: 'density', grids: [] }), s.densityGrid({ grid: null, grids })];
      }"""
    )
    assert r == ["density", "smoke"]


def test_upload_volume(page, data_dir):
    page.set_input_files("#volume-file", str(data_dir / "smoke1.vdb"))
    page.wait_for_selector("#upload-state.ok")
    selected = page.eval_on_selector("#volume-select", "s => s.value")
    assert re.fullmatch(r"[0-9a-f]{64}", selected)
    assert "smoke1.vdb" in page.inner_text("#volume-select")
    # the default density puts the densest voxel at optical depth 1: 1 / (5.71 * 0.476)
    assert float(page.input_value("#density")) == pytest.approx(0.368, abs=0.002)
    assert "Precompute" in page.inner_text("#view-overlay")
    assert errors_shown(page) == []
    shot(page, "02-uploaded")


def test_precompute_progress_and_stats(page):
    page.select_option("#quality", "draft")
    page.evaluate(
        """() => {
        const bar = document.querySelector('#cache-progress');
        window.__progress = [bar.value];
        new MutationObserver(() => window.__progress.push(bar.value))
          .observe(bar, { attributes: true, attributeFilter: ['value'] });
      }"""
    )
    count_event_sources(page)
    t0 = time.monotonic()
    page.click("#precompute")
    mid_shot = False
    while time.monotonic() - t0 < 120:
        values = page.evaluate("window.__progress")
        if not mid_shot and any(0 < v < 1 for v in values):
            shot(page, "03-precompute-running")
            mid_shot = True
        if page.get_attribute("#cache-state", "data-state") in ("ready", "failed"):
            break
        time.sleep(0.1)
    assert page.get_attribute("#cache-state", "data-state") == "ready", errors_shown(page)
    values = page.evaluate("window.__progress")
    intermediate = [v for v in values if 0 < v < 1]
    assert intermediate, f"the progress bar never showed a value between 0 and 100 %: {values}"
    assert values[-1] == 1.0
    assert values.index(intermediate[0]) < len(values) - 1
    assert intermediate == sorted(intermediate), f"progress went backwards: {values}"
    assert "100 %" in page.inner_text("#cache-stage")
    assert page.evaluate("window.__eventSources") == ["/v1/jobs/"], "progress did not come by SSE"
    nodes = int(page.inner_text("#cache-stats dd[data-stat=nodes]").replace(",", ""))
    edges = int(page.inner_text("#cache-stats dd[data-stat=edges]").replace(",", ""))
    assert nodes > 1000 and edges > nodes
    assert re.search(r"\d", page.inner_text("#cache-stats dd[data-stat='graph build']"))
    size = r"[\d.]+ (B|KiB|MiB|GiB)"  # the cache is a few hundred KiB since its files are packed
    assert re.fullmatch(
        rf"{size} \(graph {size}, radiance {size}\)", page.inner_text("#cache-stats dd[data-stat=bytes]")
    )
    shot(page, "04-precomputed")
