"""Henyey-Greenstein phase functions (scene spec v1.1 ``medium.phase``; docs/method.md,
"Anisotropic scattering"): the spec and its errors, the keys, Mitsuba's reference and the phase's
sampling, single scattering against the closed form in a slab (the field's and volpath's into the
light), g = 0 as the isotropic scene, the field's view terms summed toward each camera, and the
estimators that refuse the phase. The anisotropic cache against volpath and the field's walks:
test_phase_field.py.
"""

import numpy as np
import pytest

from cloudgraph.cache import CacheStore, cache_keys
from cloudgraph.errors import SceneError
from cloudgraph.metrics import bias_metrics, binned
from cloudgraph.params import build_params
from cloudgraph.precompute import precompute
from cloudgraph.procedural import box_volume, sphere_volume
from cloudgraph.scene import PhaseSpec, json_schema, parse_scene

from ..helpers import (
    box_interval,
    graph_renderer,
    hg,
    pixel_rays,
    with_phase,
)

BASE = {"volume": {"path": "cloud.vdb"}, "camera": {"eye": [0, 0, 5], "target": [0, 0, 0]}}


# ------------------------------------------------------------------ the spec


@pytest.mark.parametrize(
    "phase, words",
    [
        ({"type": "hg", "g": 0.96}, "g must be in [-0.95, 0.95]"),
        ({"type": "hg", "g": -1.0}, "g must be in [-0.95, 0.95]"),
        ({"type": "hg"}, "g is required"),
        ({"type": "hg", "g": "forward"}, "g must be a finite number"),
        ({"type": "hg2", "g": [0.8], "weight": 0.5}, "two asymmetries"),
        ({"type": "hg2", "g": [0.8, 0.99], "weight": 0.5}, "g[1] must be in"),
        ({"type": "hg2", "g": [0.8, -0.3]}, "weight is required"),
        ({"type": "hg2", "g": [0.8, -0.3], "weight": 1.5}, "weight must be in [0, 1]"),
        ({"type": "mie"}, "type must be one of isotropic, hg, hg2"),
        ({"type": "isotropic", "g": 0.5}, "takes no g"),
        ({"type": "hg", "g": 0.5, "lobes": 2}, "unknown field 'lobes'"),
    ],
)
def test_bad_phases_are_refused_with_the_field_named(phase, words):
    with pytest.raises(SceneError) as err:
        parse_scene({**BASE, "medium": {"phase": phase}})
    assert "medium.phase" in str(err.value) and words in str(err.value)


def test_a_v1_medium_is_isotropic_and_dumps_as_before():
    s = parse_scene({**BASE, "medium": {"density_scale": 2.0, "albedo": 0.8}})
    assert s.medium.phase.isotropic and s.medium.phase.type == "isotropic"
    assert s.medium.model_dump() == {"density_scale": 2.0, "albedo": 0.8}  # request hashes unchanged
    assert s.medium.graph_medium() == (2.0, (0.8, 0.8, 0.8))
    hg2 = parse_scene({**BASE, "medium": {"phase": {"type": "hg2", "g": [0.85, -0.3], "weight": 0.8}}})
    assert hg2.medium.model_dump()["phase"] == {"type": "hg2", "g": (0.85, -0.3), "weight": 0.8}
    assert hg2.medium.phase.mean_cosine() == pytest.approx(0.8 * 0.85 - 0.2 * 0.3)


def test_similarity_scaling_keeps_absorption_and_reduced_scattering():
    # sigma_t' = sigma_t (1 - a g), albedo' = a (1 - g) / (1 - a g): sigma_a' = sigma_a and
    # sigma_s' = sigma_s (1 - g)
    s = parse_scene(
        {**BASE, "medium": {"density_scale": 3.0, "albedo": 0.8, "phase": {"type": "hg", "g": 0.85}}}
    )
    scale, albedo = s.medium.graph_medium()
    assert scale * albedo[0] == pytest.approx(3.0 * 0.8 * (1 - 0.85))
    assert scale * (1 - albedo[0]) == pytest.approx(3.0 * 0.2)
    # An RGB albedo: one grey sigma_t' (from the mean albedo), each channel's absorption exact
    rgb = parse_scene(
        {
            **BASE,
            "medium": {"density_scale": 3.0, "albedo": [1.0, 0.9, 0.8], "phase": {"type": "hg", "g": 0.6}},
        }
    )
    scale, albedo = rgb.medium.graph_medium()
    assert scale == pytest.approx(3.0 * (1 - 0.9 * 0.6))
    np.testing.assert_allclose(
        scale * (1 - np.array(albedo)), 3.0 * (1 - np.array([1.0, 0.9, 0.8])), atol=1e-12
    )


def test_the_schema_documents_the_phase():
    medium = json_schema()["$defs"]["MediumSpec"]["properties"]
    assert "phase" in medium
    phase = json_schema()["$defs"]["PhaseSpec"]["properties"]
    assert phase["type"]["enum"] == ["isotropic", "hg", "hg2"]


def test_keys_carry_the_phase_and_isotropic_keys_stay():
    volume = sphere_volume(16)
    params = build_params(volume, 0.3, "draft")
    doc = {**BASE, "medium": {"density_scale": 0.3, "albedo": 0.9}}
    iso = cache_keys(parse_scene(doc), volume, params)
    g0 = cache_keys(
        parse_scene({**doc, "medium": {**doc["medium"], "phase": {"type": "hg", "g": 0.0}}}), volume, params
    )
    assert g0 == iso  # g = 0 is the isotropic phase: same graph, same radiance
    hg5 = parse_scene({**doc, "medium": {**doc["medium"], "phase": {"type": "hg", "g": 0.5}}})
    blend = parse_scene(
        {**doc, "medium": {**doc["medium"], "phase": {"type": "hg2", "g": [0.7, 0.1], "weight": 2 / 3}}}
    )
    k5, kb = cache_keys(hg5, volume, params), cache_keys(blend, volume, params)
    assert k5["graph_key"] != iso["graph_key"] and k5["radiance_key"] != iso["radiance_key"]
    # the same mean cosine: the same similarity-scaled graph, but radiance of its own
    assert kb["graph_key"] == k5["graph_key"] and kb["radiance_key"] != k5["radiance_key"]


# ------------------------------------------------------------------ Mitsuba's reference, sampling


@pytest.mark.parametrize(
    "phase",
    [{"type": "hg", "g": 0.7}, {"type": "hg", "g": -0.4}, {"type": "hg2", "g": [0.85, -0.3], "weight": 0.8}],
)
def test_the_volpath_phase_is_the_spec_s(variant, phase):
    import mitsuba as mi

    from cloudgraph.mitsuba_scene import phase_dict

    spec = PhaseSpec.model_validate(phase)
    p = mi.load_dict(phase_dict(spec))
    mu = np.linspace(-1, 1, 9)
    mei = mi.MediumInteraction3f()
    mei.wi = mi.Vector3f(0, 0, -1)  # Mitsuba's wi points back along the ray (d = +z)
    mei.sh_frame = mi.Frame3f(mei.wi)
    # wo, toward where light comes from, at cosine mu with the ray: mu is the scattering cosine
    wo = mi.Vector3f(np.sqrt(1 - mu**2), 0 * mu, mu)
    value = np.array(p.eval_pdf(mi.PhaseFunctionContext(), mei, wo)[1])
    expected = sum(w * hg(g, mu) for w, g in spec.lobes())
    np.testing.assert_allclose(value, expected, rtol=1e-4)


def test_phase_sampling_follows_the_phase(variant):
    import drjit as dr
    import mitsuba as mi

    from cloudgraph.phase import hg_phase, sample_phase

    lobes = PhaseSpec(type="hg2", g=(0.85, -0.3), weight=0.8).lobes()
    n = 1 << 18
    rng = mi.PCG32(n, initstate=7, initseq=dr.arange(mi.UInt64, n))
    d = dr.normalize(mi.Vector3f(0.3, -0.5, 0.8))
    w = sample_phase(lobes, d, rng)
    mu = np.array(dr.dot(w, d))
    assert np.allclose(np.array(dr.norm(w)), 1, atol=1e-5)
    edges = np.linspace(-1, 1, 41)
    counts = np.histogram(mu, edges)[0]
    # the expected share of each bin: 2 pi int p dmu, on a fine grid
    fine = np.linspace(-1, 1, 40 * 64 + 1)
    p = np.array(hg_phase(lobes, mi.Float(fine)))
    mass = 2 * np.pi * np.add.reduceat((p[:-1] + p[1:]) / 2 * np.diff(fine), np.arange(0, 40 * 64, 64))
    assert mass.sum() == pytest.approx(1, rel=1e-3)
    sigma = np.sqrt(n * mass)
    assert np.all(np.abs(counts - n * mass) < 5 * sigma + 2)
    # and the mean cosine is g_eff
    assert mu.mean() == pytest.approx(0.8 * 0.85 - 0.2 * 0.3, abs=0.005)


# ------------------------------------------------------------------ single scattering, closed form


def slab_scene(sigma, camera, phase, max_depth=1):
    return parse_scene(
        {
            "volume": {"path": "unused.vdb"},
            "medium": {"density_scale": sigma, "albedo": 0.8, "phase": phase},
            "light": {"direction": [np.sin(np.radians(45)), 0.0, -np.cos(np.radians(45))], "irradiance": 1.5},
            "camera": {**camera, "up": [0, 1, 0]},
            "render": {"spp": 1, "max_depth": max_depth},
        }
    )


def slab_single_scattering(scene, scale: int) -> np.ndarray:
    """Single scattering in the slab [-20, 20]^2 x [-2, 2] lit through its top face, on a grid
    of rays ``scale`` times finer than the image: along a camera ray o + t d through the slab,
    tau_light = sigma (2 - z) / mu_l and the camera's transmittance exp(-sigma (t - t0)), so

        L = albedo sigma E p(mu) int_t0^t1 exp(-sigma (t - t0) - sigma (2 - o_z - t d_z) / mu_l) dt,

    mu = to_light . d (constant along the ray), in closed form."""
    cam = scene.camera
    sigma, albedo = scene.medium.density_scale, scene.medium.albedo
    E, to_light = 1.5, -np.asarray(scene.light.unit_direction())
    mu_l = to_light[2]
    o = np.asarray(cam.eye)
    d = pixel_rays(cam.eye, cam.target, cam.up, cam.fov, scale * cam.width, scale * cam.height)
    t0, t1 = box_interval(o, d, [-20, -20, -2], [20, 20, 2])
    assert np.all(t1 > t0)
    k = sigma * (1 - d[..., 2] / mu_l)  # the exponent is a - k t
    a = sigma * t0 - sigma * (2 - o[2]) / mu_l
    integral = np.exp(a - k * t0) * -np.expm1(-k * (t1 - t0)) / k
    p = sum(w * hg(g, d @ to_light) for w, g in scene.medium.phase.lobes())
    return binned((albedo * sigma * E * p * integral)[..., None], scale)[..., 0]


SLAB_VIEWS = {
    # from above: the lit face, light scattered back towards it (mu about -0.7)
    "above": (
        2.0,
        {"eye": [-3.0, 2.0, 30.0], "target": [0.0, 0.0, 2.0], "fov": 18, "width": 32, "height": 24},
    ),
    # from below, looking into the light through the slab (mu within 9 degrees of 1: the peak)
    "into the light": (
        0.5,
        {"eye": [21.2, 0.0, -21.2], "target": [0.0, 0.0, 0.0], "fov": 18, "width": 32, "height": 24},
    ),
}
#: The field's own error against the closed form, phase or not: from below, the camera sees the
#: slab's last half voxel, where the light leaves it and the field's optical depth to the light
#: is clamped to the last grid point's (the isotropic field reads 0.9-1.6 % high there too).
FIELD_RTOL = {"above": 0.01, "into the light": 0.02}


@pytest.mark.parametrize("view", SLAB_VIEWS)
@pytest.mark.parametrize(
    "phase", [{"type": "hg", "g": 0.85}, {"type": "hg2", "g": [0.85, -0.3], "weight": 0.8}]
)
def test_hg_single_scattering_in_a_slab_matches_the_closed_form(variant, tmp_path, view, phase):
    # max_depth 1: the field holds single scattering only and its march is deterministic, so
    # every pixel must match, and its phase factor (per ray, constant along it) exactly: the
    # ratio to the isotropic field's image is the closed forms' ratio. gather's exact event is
    # checked on its mean and binned image.
    sigma, camera = SLAB_VIEWS[view]
    m = np.eye(4)
    m[:3, 3] = [-19.5, -19.5, -1.5]
    volume = box_volume((40, 40, 4), density=1.0, index_to_world=m)
    scene, iso = slab_scene(sigma, camera, phase), slab_scene(sigma, camera, {"type": "isotropic"})
    store = CacheStore(tmp_path)
    cache = precompute(scene, volume, "draft", store)
    r = graph_renderer(cache, volume, scene)
    expected = slab_single_scattering(scene, 8)
    field = r.render(scene.camera, spp=64, estimator="field")[..., 0]
    np.testing.assert_allclose(field, expected, rtol=FIELD_RTOL[view])
    field_iso = graph_renderer(precompute(iso, volume, "draft", store), volume, iso).render(
        iso.camera, spp=64, estimator="field"
    )[..., 0]
    np.testing.assert_allclose(field / field_iso, expected / slab_single_scattering(iso, 8), rtol=0.003)
    gather = r.render(scene.camera, spp=256, estimator="gather")[..., 0]
    assert abs(gather.mean() / expected.mean() - 1) < 0.015
    assert bias_metrics(gather[..., None], expected[..., None])["binned_relMAE"] < 0.03


def test_volpath_single_scattering_into_the_light_matches_the_closed_form(variant):
    # The reference's sign of g: looking into the light, g = 0.85 scatters ~80x the isotropic
    # phase towards the camera; the opposite sign would give 1/2000 of it.
    from cloudgraph.render import render_volpath

    sigma, camera = SLAB_VIEWS["into the light"]
    m = np.eye(4)
    m[:3, 3] = [-19.5, -19.5, -1.5]
    volume = box_volume((40, 40, 4), density=1.0, index_to_world=m)
    scene = slab_scene(sigma, {**camera, "width": 16, "height": 12}, {"type": "hg", "g": 0.85})
    scene = scene.model_copy(update={"render": scene.render.model_copy(update={"spp": 256})})
    image = render_volpath(scene, volume)[..., 0]
    expected = slab_single_scattering(scene, 8)
    assert abs(image.mean() / expected.mean() - 1) < 0.02


# ------------------------------------------------------------------ g = 0, and other estimators


def test_zero_asymmetry_renders_the_isotropic_images(sphere):
    volume, scene, cache = sphere["volume"], sphere["scene"], sphere["cache"]
    for phase in ({"type": "hg", "g": 0.0}, {"type": "hg2", "g": [0.0, 0.0], "weight": 0.3}):
        zero = with_phase(scene, phase)
        assert (
            cache_keys(zero, volume, build_params(volume, scene.medium.density_scale, "draft")) == cache.keys
        )
        for estimator in ("gather", "field", "march"):
            a = graph_renderer(cache, volume, scene).render(scene.camera, 4, seed=3, estimator=estimator)
            b = graph_renderer(cache, volume, zero).render(zero.camera, 4, seed=3, estimator=estimator)
            assert np.array_equal(a, b), estimator


def test_a_nearly_isotropic_hg_is_within_noise_of_the_isotropic_image(sphere, tmp_path):
    # g = 0.01 runs the phase's own code: a similarity-scaled graph (sigma_t 0.9 % lower), the
    # phase's sampling and weights
    volume, scene = sphere["volume"], sphere["scene"]
    near = with_phase(scene, {"type": "hg", "g": 0.01})
    cache = precompute(near, volume, "draft", CacheStore(tmp_path))
    assert cache.keys["graph_key"] != sphere["cache"].keys["graph_key"]
    a = graph_renderer(sphere["cache"], volume, scene).render(scene.camera, 256, seed=1).astype(np.float64)
    b = graph_renderer(cache, volume, near).render(near.camera, 256, seed=2).astype(np.float64)
    m = bias_metrics(b, a)
    # Measured: mean ratio 0.997, binned relMAE 1.0 % (both images' noise)
    assert abs(m["mean_ratio"] - 1) < 0.01 and m["binned_relMAE"] < 0.025


def test_the_field_s_view_terms_are_summed_toward_each_camera_with_no_new_kernel(sphere, tmp_path):
    # The march reads one channel per sun: the view terms' sum toward the camera, made per camera
    # at the view grid's points (FieldTextures.look_from). Against numpy's sum of the file's
    # terms at the directions from the eye, and a moved camera compiles nothing.
    from cloudgraph.field_grid import to_world, unit_points
    from cloudgraph.phase import shape_basis

    from ..helpers import kernels_compiled_by_the_second

    volume, scene = sphere["volume"], with_phase(sphere["scene"], {"type": "hg", "g": 0.85})
    cache = precompute(scene, volume, "draft", CacheStore(tmp_path))
    r = graph_renderer(cache, volume, scene)
    moved = scene.camera.model_copy(update={"eye": (30.0, 25.0, 45.0), "fov": 35.0})
    (first, second), new = kernels_compiled_by_the_second(
        lambda: r.render(scene.camera, spp=4, estimator="field"),
        lambda: r.render(moved, spp=4, estimator="field"),
    )
    assert np.abs(first - second).mean() > 0.1 * first.mean() and not new, new

    field = cache.field
    entry = field.meta["ms_shape"]
    terms = field.array(entry["array"])
    x = to_world(np.asarray(field.meta["unit_to_world"], float), unit_points(terms.shape[2::-1]))
    d = x - np.asarray(moved.eye)
    d /= np.linalg.norm(d, axis=1, keepdims=True)

    def summed(d):  # sum_i c_i B_i(d) at the view grid's points
        basis = np.stack(shape_basis(*(d @ np.asarray(e) for e in entry["frame"])), axis=1)
        return (terms.reshape(-1, terms.shape[-1]) * basis).sum(axis=1)

    expected = summed(d)
    got = np.array(r.integrator("field").field.view_sum[0].tensor()).ravel()
    scale = np.abs(expected).max()
    assert scale > 0
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5 * scale)
    assert np.abs(got - summed(-d)).max() > 0.1 * scale  # (facing the camera, not away)


@pytest.mark.parametrize("estimator", ["free_flight", "march"])
def test_estimators_without_the_phase_refuse_it(sphere, estimator):
    volume, scene, cache = sphere["volume"], sphere["scene"], sphere["cache"]
    hg_scene = with_phase(scene, {"type": "hg", "g": 0.5})
    with pytest.raises(SceneError, match=f"estimator '{estimator}' renders the isotropic phase only"):
        graph_renderer(cache, volume, hg_scene).render(hg_scene.camera, 1, estimator=estimator)


def test_the_walks_a_point_keeps_follow_what_a_camera_sees_of_it(variant, monkeypatch):
    # A point of the walked grid that is outside the medium (read only in the cells at its
    # edge) keeps OUTSIDE_SHARE of its walks, one deeper than DEEP_TAU along every axis
    # DEEP_SHARE, the rest all of them; the bake divides each point's sums by the walks it kept.
    import drjit as dr
    import mitsuba as mi

    import cloudgraph.field_ms as field_ms
    from cloudgraph.tracing import DensityField

    volume = sphere_volume(32)  # a ball of radius 15 voxels, density 1 a voxel
    medium = DensityField.from_volume(volume, 1.0)
    lo, hi = volume.world_bbox()
    c, r = (lo + hi) / 2, (hi[0] - lo[0]) / 2
    points = np.array([c, c + [0.6 * r, 0, 0], c + [0.99 * r, 0, 0]], np.float32)  # deep, near, out
    monkeypatch.setattr(field_ms, "OUTSIDE_SHARE", 0.5)
    monkeypatch.setattr(field_ms, "DEEP_SHARE", 0.25)
    monkeypatch.setattr(field_ms, "DEEP_TAU", 10.0)
    k = 16
    kept = field_ms._walks_kept(medium, mi.Point3f(*points.T), k, 3 * k, 0.5 * volume.voxel_size[0])
    taken = np.array(dr.block_sum(mi.Float(kept), k))
    assert taken.tolist() == [4.0, 16.0, 8.0]  # (optical depth to the box: about 16, 6 and 0)
