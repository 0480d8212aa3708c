"""Helpers for the web tests that drive the page in a real service (tests/web/test_web_*.py):
screenshots, the errors shown, waiting for a frame or a cache, reading what the viewport shows,
orbiting, the camera, and a page opened on smoke1's draft cache."""

from __future__ import annotations

import base64
import contextlib
import json
import math

from ..harness import ROOT

ARTIFACTS = ROOT / "test-artifacts" / "web"

# Gray values at 64x64 of an image source (an <img> or an ImageBitmap), drawn through a canvas.
GRAY_64_JS = """function gray64(src) {
  const c = document.createElement('canvas');
  c.width = 64; c.height = 64;
  const ctx = c.getContext('2d');
  ctx.drawImage(src, 0, 0, 64, 64);
  const d = ctx.getImageData(0, 0, 64, 64).data;
  const out = [];
  for (let i = 0; i < d.length; i += 4) out.push((d[i] + d[i + 1] + d[i + 2]) / 3);
  return out;
}"""

# ... of the viewport image, in the page.
PIXELS_JS = "() => { " + GRAY_64_JS + " return gray64(document.querySelector('#view-img')); }"


def shot(page, name: str) -> None:
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"), full_page=True)


def errors_shown(page) -> list[str]:
    return page.locator("#errors li .msg").all_inner_texts()


def count_event_sources(page) -> None:
    """Records the paths of the EventSources that the page opens from now on."""
    page.evaluate(
        """() => {
        window.__eventSources = [];
        const Original = window.EventSource;
        window.EventSource = class extends Original {
          constructor(url, init) {
            super(url, init);
            window.__eventSources.push(new URL(url, location.href).pathname.replace(/[^/]+\\/events$/, ''));
          }
        };
      }"""
    )


def wait_final(page, after_frame: int) -> None:
    """Waits for the server viewer's final (256 px, 4 passes) image after ``after_frame``."""
    page.wait_for_function(
        f"""() => {{
          const img = document.querySelector('#view-img');
          return Number(img.dataset.frame || 0) > {after_frame} && img.dataset.final === '1'
            && !document.querySelector('#viewport').dataset.busy;
        }}"""
    )


def frames_drawn(page) -> int:
    return int(page.get_attribute("#viewport", "data-frames") or 0)


def wait_rest(page, after_frames: int) -> None:
    """Waits for the real-time view's full-size frame at rest, drawn after ``after_frames`` (the
    exact march at 640 px in strips: 10-30 s of a software GPU sharing two cores with the service,
    more while the machine is loaded; a wait, not a judged time)."""
    page.wait_for_function(
        f"""() => {{
          const v = document.querySelector('#viewport');
          return v.dataset.renderer === 'webgl' && v.dataset.state === 'rest'
            && Number(v.dataset.frames || 0) > {after_frames};
        }}""",
        timeout=180_000,
    )


def reset_view(page) -> None:
    """Back to the home view, drawn at rest. A step that reads the view's corners or the cloud's
    pixels starts here: the camera an earlier step's orbit left turned by as many pointer events
    as the loaded machine delivered."""
    frames = frames_drawn(page)
    page.click("#view-reset")
    wait_rest(page, frames)


# ... of a PNG (given as base64), decoded in the page.
PNG_PIXELS_JS = (
    "async (b64) => { "
    + GRAY_64_JS
    + """
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  return gray64(await createImageBitmap(new Blob([bytes], { type: 'image/png' })));
}"""
)


def shown_pixels(page) -> list[float]:
    """Gray values of what the viewport shows (a screenshot: a WebGL canvas cannot be read
    back once it has been shown)."""
    png = page.locator("#viewport").screenshot()
    return page.evaluate(PNG_PIXELS_JS, base64.b64encode(png).decode())


# Drags on the viewport with pointer events sent from inside the page every 8 ms (a mouse's
# rate; Playwright's own mouse moves wait for a round trip each), after a real mouse press.
# Records the internal size and march step of every frame drawn meanwhile.
ORBIT_JS = """([x, y, ms, dx]) => new Promise((done) => {
  const el = document.querySelector('#viewport');
  const sizes = [];
  const steps = [];
  const obs = new MutationObserver(() => {
    sizes.push(Number(el.dataset.internal));
    steps.push(Number(el.dataset.stepScale));
  });
  obs.observe(el, { attributes: true, attributeFilter: ['data-frames'] });
  const f0 = Number(el.dataset.frames || 0);
  const t0 = performance.now();
  let i = 0;
  const id = setInterval(() => {
    i++;
    const t = performance.now() - t0;
    el.dispatchEvent(new PointerEvent('pointermove', {
      pointerId: 1, isPrimary: true, pointerType: 'mouse', buttons: 1, bubbles: true,
      clientX: x + dx * t / ms + 20 * Math.sin(i / 9), clientY: y + 15 * Math.sin(i / 13) }));
    if (t >= ms) {
      clearInterval(id);
      obs.disconnect();
      const seconds = (performance.now() - t0) / 1000;
      done({ fps: (Number(el.dataset.frames) - f0) / seconds, sizes, steps, seconds });
    }
  }, 8);
})"""


def orbit(page, ms: int = 3000, dx: float = 120) -> dict:
    box = page.locator("#viewport").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    try:
        return page.evaluate(ORBIT_JS, [x, y, ms, dx])
    finally:
        page.mouse.up()


def mean_abs(a, b) -> float:
    return sum(abs(p - q) for p, q in zip(a, b, strict=True)) / len(a)


def camera(page):
    eye = json.loads(page.get_attribute("#camera-info", "data-eye"))
    target = json.loads(page.get_attribute("#camera-info", "data-target"))
    return eye, target, math.dist(eye, target)


def open_scene(pg, service, data_dir) -> None:
    """Loads the page with smoke1 uploaded (idempotent) and precomputes its draft cache (found
    on the server when an earlier test built it)."""
    with service.client() as client, (data_dir / "smoke1.vdb").open("rb") as f:
        assert client.post("/v1/volumes", files={"file": ("smoke1.vdb", f)}).status_code in (200, 201)
    pg.goto(service.url + "/")
    pg.wait_for_selector("#volume-select option[value]:not([value=''])", state="attached")
    pg.select_option("#quality", "draft")
    pg.click("#precompute")
    pg.wait_for_selector("#cache-state[data-state=ready], #cache-state[data-state=failed]", timeout=300_000)
    assert pg.get_attribute("#cache-state", "data-state") == "ready", errors_shown(pg)


def assert_realtime_is_the_server_field(page, what: str, max_rel_mae: float) -> None:
    """The page's comparison (compare_realtime) finds its view within ``max_rel_mae`` of the
    server's `field` render of the same camera, and no error is shown."""
    result = compare_realtime(page)
    rel = float(result["relMae"])
    print(f"{what}: real-time vs server field: relMAE {rel:.4f}")
    assert 0 <= rel < max_rel_mae, result["text"]
    assert errors_shown(page) == []


def compare_realtime(page) -> dict:
    """Runs the page's "compare real-time view" at 128 px (volpath at 8 spp) and returns its
    result's data attributes (``relMae``, ``relMaeVolpath``) and ``text``; asserts it finished."""
    page.select_option("#compare-size", "128")
    page.fill("#compare-volpath-spp", "8")
    page.click("#compare-realtime")
    page.wait_for_selector("#compare-result[data-state=done], #compare-result[data-state=failed]")
    assert page.get_attribute("#compare-result", "data-state") == "done", errors_shown(page)
    result = page.eval_on_selector("#compare-result", "e => ({...e.dataset})")
    return {**result, "text": page.inner_text("#compare-result")}


def wait_relit(page, old_key: str) -> None:
    """Waits for the relight the last change started: its field (another key than ``old_key``)
    drawn at rest."""
    page.wait_for_selector("#relight-info[data-seconds]", timeout=600_000)
    page.wait_for_function(
        f"() => {{ const k = document.querySelector('#viewport').dataset.fieldKey;"
        f" return k && k !== '{old_key}'; }}",
        timeout=120_000,
    )
    wait_rest(page, frames_drawn(page) - 1)


def wait_field_key(page, key: str) -> None:
    """Waits for the field of radiance key ``key`` (one the page had before: found, not made)
    to be downloaded again and drawn at rest."""
    page.wait_for_function(
        f"() => document.querySelector('#viewport').dataset.fieldKey === '{key}'", timeout=120_000
    )
    wait_rest(page, frames_drawn(page) - 1)


@contextlib.contextmanager
def api_requests(page):
    """The URLs of the API requests (/v1/) the page makes inside the block, in a list."""
    urls = []

    def seen(request):
        if "/v1/" in request.url:
            urls.append(request.url)

    page.on("request", seen)
    try:
        yield urls
    finally:
        page.remove_listener("request", seen)


#: Frames a second the frame budget aims at while orbiting (its levels' measured cost against
#: quality.js's budget). The tests' WebGL is software (SwiftShader) on a machine shared with the
#: service: the rate is a measurement, written to ORBIT_LOG, not asserted (a timed test on a
#: shared machine is a flaky one); what is asserted is the budget's work.
TARGET_ORBIT_FPS = 20
#: Where each orbit's frame rate, sizes and steps are written (one JSON line an orbit).
ORBIT_LOG = ARTIFACTS / "orbit.jsonl"


def cheapest_level(page) -> dict:
    """The frame budget's cheapest level ({size, stepScale, cost}: quality.js's ladder)."""
    return page.evaluate("async () => (await import('/js/quality.js')).ladder(640).at(-1)")


def orbit_warm(page, what: str, min_fps: float = TARGET_ORBIT_FPS) -> None:
    """The first seconds of an orbit, not judged: two, or up to 30 while frames come slowly, as
    when a rest frame's exact march at full size, seconds on a software GPU, was still being
    drawn when the orbit began."""
    for _ in range(15):
        warm = orbit(page, ms=2000, dx=50)
        print(f"{what} orbit, first seconds: {warm['fps']:.1f} frames/s, sizes {sorted(set(warm['sizes']))}")
        if warm["fps"] >= min_fps / 2:
            break


def assert_orbit_adapts(page, what: str, r: dict) -> None:
    """An orbit's frames (``r``: orbit's) are the moving camera's, and the frame budget holds
    them: at least two a second (a frame drawn as at rest, at full size with the exact march,
    takes seconds on a software GPU), never below 128 px inside, and where they come slower than
    TARGET_ORBIT_FPS, the last half of them at the budget's cheapest level (the most it can do
    on this machine). The rate goes to ORBIT_LOG."""
    level = cheapest_level(page)
    sizes, steps = sorted(set(r["sizes"])), sorted(set(r["steps"]))
    record = {"what": what, "fps": round(r["fps"], 1), "sizes": sizes, "steps": steps}
    with ORBIT_LOG.open("a") as f:
        f.write(json.dumps(record) + "\n")
    print(f"{what} orbit: {r['fps']:.1f} frames/s, internal sizes {sizes} px, steps {steps}")
    assert r["fps"] >= 2, f"{r['fps']:.1f} frames/s while orbiting: not the moving camera's frames"
    assert r["sizes"] and min(r["sizes"]) >= 128, r["sizes"]
    if r["fps"] < TARGET_ORBIT_FPS:
        late = list(zip(r["sizes"], r["steps"], strict=True))[len(r["sizes"]) // 2 :]
        at_floor = all(size == level["size"] and step == level["stepScale"] for size, step in late)
        assert at_floor, f"{r['fps']:.1f} frames/s, the budget not at its cheapest level {level}: {late}"
    assert errors_shown(page) == []


def assert_orbit_holds(page, what: str) -> None:
    """An orbit, once the budget has found its level, adapts (assert_orbit_adapts)."""
    orbit_warm(page, what)
    assert_orbit_adapts(page, what, orbit(page, ms=3000, dx=150))
