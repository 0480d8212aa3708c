"""The page's march with a Henyey-Greenstein phase (the field header's ``phase``): single
scattering times 4pi p(to_light . d) per pixel, as the server's ``field`` estimator takes it,
against an independent numpy march of a synthetic field (tests/web/fieldmaker.py)."""

from __future__ import annotations

import numpy as np
import pytest

from .fieldmaker import (
    add_view_terms,
    light_depth_from_above,
    make_field,
    put_array,
    reference_render,
    rel_mae,
    view_basis,
)
from .test_glview import browser, camera, page, render  # noqa: F401 (fixtures)


@pytest.mark.parametrize(
    "phase, lobes",
    [
        ({"type": "hg", "g": 0.6}, [(1.0, 0.6)]),
        ({"type": "hg2", "g": [0.8, -0.3], "weight": 0.7}, [(0.7, 0.8), (0.3, -0.3)]),
    ],
)
@pytest.mark.parametrize("fast", [False, True])
def test_the_page_weights_single_scattering_by_the_phase_per_pixel(page, phase, lobes, fast):  # noqa: F811
    field, iso = make_field(), make_field()
    for f in (field, iso):  # single scattering well above the synthetic L_ms
        f["header"]["light"]["irradiance"] = [4.0, 3.6, 3.2]
        light_depth_from_above(f)  # (moving frames interpolate exp(-tau): a continuous tau)
    field["header"]["phase"] = phase
    lo, hi = (np.asarray(v) for v in field["header"]["world_bbox"])
    c, r = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    cams = [
        camera(c + r * np.array([0.1, -1.1, 0.2]), c, fov=50),  # from below, into the light (down)
        camera(c + r * np.array([1.2, 0.1, 0.3]), c),  # from the side
    ]
    # moving frames: the packed texture holds the sun's transmittance apart, weighted by E p
    # per ray
    images = render(page, field, cams, fast=fast)
    for cam, img, plain in zip(cams, images, render(page, iso, cams), strict=True):
        ref = reference_render(field, cam, lobes=lobes)
        assert ref.mean() > 5, "the reference image is black: a useless test"
        assert rel_mae(img, ref) < 0.025
        assert rel_mae(plain, ref) > 0.1, "the phase changed little: a useless test"


@pytest.mark.parametrize("light_power", [0.0, 0.9])
def test_the_page_adds_the_view_terms_of_an_anisotropic_field(page, light_power):  # noqa: F811
    # The field of an anisotropic phase keeps how the sun's L_ms depends on the view (20
    # functions of direction, api.md): the page's march adds them per sample and clamps at 0,
    # as the server's does, against the numpy march that reads them independently; with a
    # light_power (the engine's bake) they are kept over the sun's light factor of that power.
    field, plain = make_field(), make_field()
    for f in (field, plain):
        f["header"]["phase"] = {"type": "hg", "g": 0.85}
        f["header"]["light"]["irradiance"] = [0.2, 0.18, 0.16]  # L_ms the most of the image
    if light_power:
        field["header"]["ms_light"] = {"power": [0.0, 0.0, 0.0], "range": 1.25}
        plain["header"]["ms_light"] = field["header"]["ms_light"]
    add_view_terms(field, light_power=light_power)
    lo, hi = (np.asarray(v) for v in field["header"]["world_bbox"])
    c, r = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    cams = [
        camera(c + r * np.array([0.1, -1.1, 0.2]), c, fov=50),  # from below, into the light
        camera(c + r * np.array([1.2, 0.1, 0.3]), c),  # from the side
    ]
    images = render(page, field, cams)
    for cam, img, without in zip(cams, images, render(page, plain, cams), strict=True):
        ref = reference_render(field, cam, lobes=[(1.0, 0.85)])
        assert ref.mean() > 5, "the reference image is black: a useless test"
        assert rel_mae(img, ref) < 0.025
        # (over the light factor they weigh less: 4.4 % with light_power 0.9)
        assert rel_mae(without, ref) > (0.03 if light_power else 0.1), "the view terms changed little"
        if light_power:  # the factor read as none would fail the first assertion
            del field["header"]["ms_shape"]["light_power"]
            assert rel_mae(reference_render(field, cam, lobes=[(1.0, 0.85)]), ref) > 0.05
            field["header"]["ms_shape"]["light_power"] = light_power


def test_the_page_reads_each_view_term_of_degree_3(page):  # noqa: F811
    # degree 3's six terms (channels 14-19, api.md) alone on a positive L_ms, seen from two
    # sides: the page against the numpy march within 0.3 % (measured 0.02-0.03 %), where leaving
    # any one of them out moves the image by 0.8-3.6 %
    field = make_field()
    field["header"]["phase"] = {"type": "hg", "g": 0.85}
    field["header"]["light"]["irradiance"] = [0.2, 0.18, 0.16]
    add_view_terms(field)
    name = field["header"]["ms_shape"]["array"]
    terms = field["values"][name]
    lum = field["values"]["radiance_ms"].mean(axis=-1)
    terms[..., :14] = 0.0
    terms[..., 14:] = lum[..., None] * np.array([1, -3, 3, -3, 2, 1]) / 60.0
    put_array(field, name, terms, np.maximum(np.abs(terms).reshape(-1, 20).max(axis=0), 1e-6) / 1000.0)
    lo, hi = (np.asarray(v) for v in field["header"]["world_bbox"])
    c, r = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    cams = [camera(c + r * np.array([1.2, 0.1, 0.3]), c), camera(c + r * np.array([0.2, 0.3, -1.2]), c)]
    without = np.zeros(6)
    for cam, img in zip(cams, render(page, field, cams), strict=True):
        ref = reference_render(field, cam, lobes=[(1.0, 0.85)])
        assert ref.mean() > 5, "the reference image is black: a useless test"
        assert rel_mae(img, ref) < 0.003
        for k in range(6):
            kept = field["values"][name].copy()
            field["values"][name][..., 14 + k] = 0.0
            without[k] = max(without[k], rel_mae(reference_render(field, cam, lobes=[(1.0, 0.85)]), ref))
            field["values"][name] = kept
    assert np.all(without > 0.006), without


@pytest.mark.parametrize(
    "phase, lobes",
    [
        ({"type": "hg", "g": 0.85}, [(1.0, 0.85)]),
        ({"type": "hg2", "g": [0.8, -0.3], "weight": 0.7}, [(0.7, 0.8), (0.3, -0.3)]),
    ],
)
def test_the_page_adds_the_sun_s_light_in_its_beam_in_closed_form(page, phase, lobes):  # noqa: F811
    # A field whose header has ms_forward (api.md): the march adds the sun's light of its first
    # orders still in its beam, sum_n e^-tau (albedo tau)^n / n! p^(n+1)(to_light . d), to each
    # shaped sun's L_ms, as the server's does, against the numpy march (its own lobe products)
    field, without = make_field(), make_field()
    for f in (field, without):
        f["header"]["phase"] = phase
        f["header"]["light"]["irradiance"] = [0.5, 0.45, 0.4]
        light_depth_from_above(f)
        add_view_terms(f)
    field["header"]["ms_forward"] = 2
    lo, hi = (np.asarray(v) for v in field["header"]["world_bbox"])
    c, r = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    cams = [
        camera(c + r * np.array([0.1, -1.1, 0.2]), c, fov=50),  # from below, into the light
        camera(c + r * np.array([1.2, 0.1, 0.3]), c),  # from the side
    ]
    for cam, img, plain in zip(cams, render(page, field, cams), render(page, without, cams), strict=True):
        ref = reference_render(field, cam, lobes=lobes)
        assert ref.mean() > 5, "the reference image is black: a useless test"
        assert rel_mae(img, ref) < 0.025
        assert rel_mae(plain, ref) > 0.05, "the beam's light changed little: a useless test"


def test_the_view_terms_are_the_engine_s_functions_of_direction():
    # The page's and the numpy march's functions (written out) are the engine's (phase.py's
    # derivatives of Legendre polynomials), term by term
    from cloudgraph.phase import light_frame, shape_basis

    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    frame = light_frame([0.3, -0.8, 0.5])
    local = d @ frame.T
    engine = np.stack(shape_basis(*local.T), axis=1)
    np.testing.assert_allclose(view_basis(d, frame), engine, atol=1e-12)


def test_the_scene_panel_reads_the_phase_as_the_spec_has_it(page):  # noqa: F811
    r = page.evaluate(
        """async () => {
        const { readPhase } = await import('/js/scene.js');
        const input = (value, label) => {
          const el = document.createElement('input');
          el.value = value;
          el.dataset.label = label;
          return el;
        };
        const controls = (type, g, g2 = '-0.3', weight = '0.8') => ({
          type: { value: type }, g: input(g, 'phase g'), g2: input(g2, 'phase g2'),
          weight: input(weight, 'phase weight') });
        const errors = [];
        for (const c of [controls('hg', '0.99'), controls('hg2', '0.5', '-0.3', '1.5'), controls('hg', '')]) {
          try { readPhase(c); } catch (e) { errors.push(e.message); }
        }
        return { iso: readPhase(controls('isotropic', 'x')), hg: readPhase(controls('hg', '0.85')),
                 hg2: readPhase(controls('hg2', '0.85')), errors };
      }"""
    )
    assert r["iso"] is None  # left out of the medium: a v1 scene and its cache
    assert r["hg"] == {"type": "hg", "g": 0.85}
    assert r["hg2"] == {"type": "hg2", "g": [0.85, -0.3], "weight": 0.8}
    assert r["errors"] == [
        "phase g: must be between -0.95 and 0.95",
        "phase weight: must be between 0 and 1",
        "phase g: enter a number",
    ]
