"""The page's field decoder and WebGL2 ray march, on synthetic fields, against an independent
numpy march (tests/web/fieldmaker.py). No service: the modules are served from web/."""

from __future__ import annotations

import base64
import copy

import numpy as np
import pytest

from cloudgraph.field_grid import unit_points
from cloudgraph.light_depth import FINE_POWER, TAU_POWER

from ..helpers import rotated_affine
from .browser import ARGS, chromium_path, static_page
from .fieldmaker import _sample as sample
from .fieldmaker import encode, light_depth_from_above, make_field, put_array, reference_render, rel_mae

sync_api = pytest.importorskip("playwright.sync_api")

RENDER_JS = """async ({ b64, cams, exposure, fast, mix, remix }) => {
  const { decodeField } = await import('/js/field.js');
  const { GLView } = await import('/js/glview.js');
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const field = decodeField(bytes.buffer);
  const view = new GLView(document.createElement('canvas'));
  if (mix) view.setMix(mix);  // the lights' intensities of a v1.1 field: before its upload
  view.setField(field);
  if (remix) view.setMix(remix);  // and after it (a re-mix)
  return cams.map((cam) => Array.from(view.readImage(cam, { exposure, fast }).data));
}"""


@pytest.fixture(scope="module")
def browser():
    path = chromium_path()
    if path is None:
        pytest.skip("Chromium not found (install Debian's chromium or set CLOUDGRAPH_CHROMIUM)")
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=path, args=ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def page(browser):
    pg = static_page(browser)
    yield pg
    pg.context.close()


def camera(eye, target, size=48, fov=40.0):
    return {
        "eye": list(eye),
        "target": list(target),
        "up": [0, 1, 0],
        "fov": fov,
        "width": size,
        "height": size,
    }


def render(page, field, cams, exposure=0.0, fast=False, mix=None, remix=None):
    b64 = base64.b64encode(encode(field)).decode()
    args = {"b64": b64, "cams": cams, "exposure": exposure, "fast": fast, "mix": mix, "remix": remix}
    out = page.evaluate(RENDER_JS, args)
    return [
        np.asarray(px, float).reshape(c["height"], c["width"], 4)[..., :3]
        for px, c in zip(out, cams, strict=True)
    ]


def refusal(page, field) -> str:
    """The page's decoder's message refusing ``field``, or "" where it reads it."""
    return page.evaluate(
        """async (b64) => {
        const { decodeField } = await import('/js/field.js');
        try { decodeField(Uint8Array.from(atob(b64), (c) => c.charCodeAt(0)).buffer); }
        catch (e) { return e.message; }
        return "";
      }""",
        base64.b64encode(encode(field)).decode(),
    )


def test_decode_reads_header_and_arrays(page):
    field = make_field()
    b64 = base64.b64encode(encode(field)).decode()
    r = page.evaluate(
        """async (b64) => {
        const f = await import('/js/field.js');
        const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
        const d = f.decodeField(bytes.buffer);
        const m = d.unitToWorld, w = d.worldToUnit;
        const id = [];
        for (let r = 0; r < 4; r++) for (let c = 0; c < 4; c++) {
          let s = 0; for (let k = 0; k < 4; k++) s += m[4 * r + k] * w[4 * k + c]; id.push(s);
        }
        const bad = [];
        for (const cut of [new ArrayBuffer(4), bytes.slice(0, 40).buffer]) {
          try { f.decodeField(cut); } catch (e) { bad.push(e.message); }
        }
        const wrong = bytes.slice(); wrong[0] = 88;
        try { f.decodeField(wrong.buffer); } catch (e) { bad.push(e.message); }
        const s = d.arrays.sigma_t.data;
        return { shape: d.arrays.radiance_ms.shape, sigma0: f.halfToFloat(s[s.length >> 1]),
                 step: d.step, id, bad, block: d.arrays.majorant.block,
                 half: [0x3c00, 0xc000, 0x0001].map(f.halfToFloat) };
      }""",
        b64,
    )
    raw = field["raw"]
    assert r["shape"] == list(raw["radiance_ms"].shape)
    assert r["sigma0"] == pytest.approx(float(raw["sigma_t"].reshape(-1)[raw["sigma_t"].size >> 1]))
    assert r["step"] == pytest.approx(field["header"]["step"])
    assert np.allclose(np.reshape(r["id"], (4, 4)), np.eye(4), atol=1e-9)
    assert r["half"] == [1.0, -2.0, 2**-24]
    assert r["block"] == 4
    assert "too short" in r["bad"][0] and "cut short" in r["bad"][1] and "magic" in r["bad"][2]


@pytest.mark.parametrize("affine", ["box", "rotated"])
def test_march_matches_numpy_reference(page, affine):
    """The shader's image of a synthetic field is the numpy march's, within 2.5 % relMAE, from
    outside the box and from inside it, with exposure."""
    if affine == "box":
        field = make_field()
    else:
        m = rotated_affine() * 1.0
        m[:3, :3] *= 8
        field = make_field(unit_to_world=m)
    lo, hi = (np.asarray(v) for v in field["header"]["world_bbox"])
    c = (lo + hi) / 2
    r = np.linalg.norm(hi - lo)
    cams = [
        camera(c + r * np.array([0.3, 0.4, 1.2]), c),
        camera(c + r * np.array([-1.1, -0.2, 0.3]), c + 0.05 * r, size=40, fov=55),
        camera(c + 0.05 * r, c + r * np.array([1, 0.1, 0.2]), size=32, fov=90),  # inside the box
    ]
    images = render(page, field, cams, exposure=1.0)
    for cam, img in zip(cams, images, strict=True):
        ref = reference_render(field, cam, exposure=1.0)
        assert ref.mean() > 5, "the reference image is black: a useless test"
        err = rel_mae(img, ref)
        # the per-pixel jitter leaves a little unbiased noise on the rough synthetic medium
        assert err < 0.025, f"relMAE {err:.4f} for camera {cam}"
        assert img.mean() == pytest.approx(ref.mean(), rel=0.01)


@pytest.mark.parametrize("grid", ["tau_power", "no tau_power", "fine"])
def test_tau_light_is_interpolated_as_the_header_says(page, grid):
    """Between grid points the page reads tau_light as the server's field does: interpolating
    exp(-tau_power tau), or tau itself where the header has no tau_power (a field of before
    it), on the field's grid or on one twice as fine (light_depth.py). A tau_light that steps
    between 0 and 6 from texel to texel tells the readings apart."""
    field = make_field()
    shape = np.array(field["values"]["tau_light"].shape) * (2 if grid == "fine" else 1)
    x = np.arange(shape[2])
    put_array(field, "tau_light", np.broadcast_to(6.0 * (x % 2), shape).astype(np.float32), 0.01)
    field["header"]["tau_power"] = FINE_POWER if grid == "fine" else TAU_POWER
    if grid == "no tau_power":
        del field["header"]["tau_power"]
    other = copy.deepcopy(field)
    other["header"]["tau_power"] = 0.0 if grid != "no tau_power" else TAU_POWER
    lo, hi = (np.asarray(v) for v in field["header"]["world_bbox"])
    c, r = (lo + hi) / 2, np.linalg.norm(hi - lo)
    cam = camera(c + r * np.array([0.3, 0.4, 1.2]), c)
    (img,) = render(page, field, [cam], exposure=1.0)
    ref = reference_render(field, cam, exposure=1.0)
    assert rel_mae(img, ref) < 0.025
    assert rel_mae(reference_render(other, cam, exposure=1.0), ref) > 0.1  # the other reading


def test_a_fine_tau_grid_is_drawn_still_and_moving(page):
    """A tau_light twice as fine as the density grid (light_depth.py): the exact march reads it
    at its own resolution, the moving camera's texture at each voxel's centre (the mean of the
    eight fine texels around it in exp(-tau_power tau))."""
    field = make_field()
    light_depth_from_above(field, fine=True)
    assert field["values"]["tau_light"].shape == tuple(2 * n for n in field["values"]["sigma_t"].shape)
    lo, hi = (np.asarray(v) for v in field["header"]["world_bbox"])
    c, r = (lo + hi) / 2, np.linalg.norm(hi - lo)
    cam = camera(c + r * np.array([0.3, 0.4, 1.2]), c)
    ref = reference_render(field, cam, exposure=1.0)
    assert ref.mean() > 5, "the reference image is black: a useless test"
    for fast, tol in ((False, 0.025), (True, 0.03)):
        (img,) = render(page, field, [cam], exposure=1.0, fast=fast)
        assert rel_mae(img, ref) < tol, f"fast={fast}"
    # the moving texture's light at each voxel's centre: the fine grid read there
    got = page.evaluate(
        """async (b64) => {
        const { decodeField } = await import('/js/field.js');
        const { voxelTransmittance } = await import('/js/fieldtex.js');
        const field = decodeField(Uint8Array.from(atob(b64), (c) => c.charCodeAt(0)).buffer);
        const { tau_light, sigma_t } = field.arrays;
        return Array.from(voxelTransmittance(tau_light, field.tauPower, sigma_t.shape));
      }""",
        base64.b64encode(encode(field)).decode(),
    )
    nz, ny, nx = field["values"]["sigma_t"].shape
    q = np.exp(-FINE_POWER * field["values"]["tau_light"])
    expected = sample(q, unit_points((nx, ny, nz))) ** (1 / FINE_POWER)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-6)


def test_a_tau_grid_of_another_resolution_is_refused_in_words(page):
    """tau_light is at sigma_t's resolution or twice it, and a finer one is read by its
    tau_power: anything else is refused with a message, not drawn wrong."""
    refusals = []
    for factor, power in ((3, FINE_POWER), (2, None)):
        field = make_field()
        shape = np.array(field["values"]["tau_light"].shape) * factor
        put_array(field, "tau_light", np.ones(shape, np.float32), 0.01)
        field["header"].pop("tau_power")
        if power:
            field["header"]["tau_power"] = power
        refusals.append(refusal(page, field))
    assert "neither at sigma_t's resolution nor at twice it" in refusals[0], refusals
    assert "needs the header's tau_power" in refusals[1], refusals


def test_moving_camera_texture_is_close(page):
    """The moving camera's single-fetch march ((sigma_t, L_in) packed in one texture, L_in
    interpolated instead of exp(-tau)) stays within 3 % of the reference."""
    field = make_field()
    lo, hi = (np.asarray(v) for v in field["header"]["world_bbox"])
    c = (lo + hi) / 2
    cams = [camera(c + np.linalg.norm(hi - lo) * np.array([0.3, 0.4, 1.2]), c)]
    (img,) = render(page, field, cams, exposure=1.0, fast=True)
    ref = reference_render(field, cams[0], exposure=1.0)
    assert rel_mae(img, ref) < 0.03


def test_field_beyond_device_limits_is_refused_in_words(page):
    r = page.evaluate(
        """async () => {
        const { GLView } = await import('/js/glview.js');
        const view = new GLView(document.createElement('canvas'));
        const grid = (n) => ({ shape: [4, 4, n] });
        const field = (n) => ({ header: {}, suns: [{ tau: 'tau_light', shape: null }], components: [],
          arrays: { sigma_t: grid(n), tau_light: grid(n), radiance_ms: { shape: [2, 2, 2, 3] },
                    majorant: { shape: [1, 1, 1] } } });
        return { max: view.maxSize, ok: view.tooLarge(field(view.maxSize)),
                 big: view.tooLarge(field(view.maxSize + 1)), bytes: view.tooLarge(field(64), 100) };
      }"""
    )
    assert r["ok"] == ""
    assert f"exceeds this device's 3D texture limit of {r['max']}" in r["big"]
    assert "MiB of textures" in r["bytes"]


def test_quality_ladder_and_controller(page):
    """Levels cost less and less, never below 128 px; slow frames move down at once to a level
    that fits, frames that keep up with the display creep back up."""
    r = page.evaluate(
        """async () => {
        const q = await import('/js/quality.js');
        const levels = q.ladder(640);
        const c = new q.QualityController(640);
        const first = c.current();
        for (let i = 0; i < 3; i++) c.report(200, c.current().cost);  // 200 ms frames
        const slow = c.current();
        const ups = [];
        for (let i = 0; i < 60; i++) { c.report(16.7, c.current().cost); ups.push(c.current().cost); }
        return { levels, first, slow, ups };
      }"""
    )
    costs = [lv["cost"] for lv in r["levels"]]
    assert costs == sorted(costs, reverse=True) and len(set(costs)) == len(costs)
    assert r["levels"][0] == {"size": 640, "stepScale": 1, "cost": 640 * 640}
    assert min(lv["size"] for lv in r["levels"]) == 128 and r["levels"][-1]["stepScale"] >= 4
    # a 200 ms frame: the cost that fits 16 ms is about 1/12 of it
    assert r["slow"]["cost"] <= r["first"]["cost"] * 1.15 * 16.7 / 200 * 1.01
    assert r["ups"][-1] == r["levels"][0]["cost"], "frames at the display's rate did not creep up"


def test_ms_light_factor_is_multiplied_back_as_the_header_says(page):
    """A field's L_ms held over its sun's light factor (header ``ms_light``: field.py)
    is drawn times exp(-min(P tau_light, range)) per channel, at rest and moving, as the numpy
    march reads it; the image without the factor differs, and a bad ms_light is refused."""
    field = make_field()
    light_depth_from_above(field, fine=True)
    field["header"]["ms_light"] = {"power": [0.3, 0.6, 1.2], "range": 1.25}
    lo, hi = (np.asarray(v) for v in field["header"]["world_bbox"])
    c, r = (lo + hi) / 2, np.linalg.norm(hi - lo)
    cam = camera(c + r * np.array([0.3, 0.4, 1.2]), c)
    ref = reference_render(field, cam, exposure=1.0)
    plain = copy.deepcopy(field)
    del plain["header"]["ms_light"]
    assert rel_mae(reference_render(plain, cam, exposure=1.0), ref) > 0.05  # the factor shows
    for fast, tol in ((False, 0.025), (True, 0.03)):
        (img,) = render(page, field, [cam], exposure=1.0, fast=fast)
        assert rel_mae(img, ref) < tol, f"fast={fast}"
    field["header"]["ms_light"] = {"power": [0.3, 0.6], "range": 1.25}
    message = refusal(page, field)
    assert "ms_light" in message, message
