"""Several lights and a uniform sky (scene spec v1.1 ``lights``; docs/method.md, "Several
lights"): the spec and its errors, the keys, a sky on a thin homogeneous sphere against its
closed-form single scattering, two suns against the sum of each alone, a re-mix of intensities
with no solve and no new kernel, and sun + sky against volpath.
"""

import json

import numpy as np
import pytest

from cloudgraph.cache import CacheStore, cache_keys
from cloudgraph.errors import SceneError
from cloudgraph.metrics import bias_metrics, binned
from cloudgraph.params import build_params
from cloudgraph.precompute import precompute
from cloudgraph.procedural import sphere_volume
from cloudgraph.scene import PhaseSpec, json_schema, parse_scene

from ..helpers import (
    box_interval,
    framed_camera,
    kernels_compiled_by_the_second,
    latlong_lookup,
    pixel_rays,
    reference,
)

BASE = {"volume": {"path": "cloud.vdb"}, "camera": {"eye": [0, 0, 5], "target": [0, 0, 0]}}
TYPES = "type must be one of directional, sky, envmap, sunsky, got "
SUN = {"type": "directional", "direction": [-0.6, -0.7, -0.3], "irradiance": [1.0, 0.9, 0.8]}
SUN2 = {"type": "directional", "direction": [0.5, -0.3, -0.8], "irradiance": 0.7}
SKY = {"type": "sky", "radiance": [0.2, 0.3, 0.5]}


def lit(volume, lights, density_scale, albedo=0.9, size=32, max_depth=-1, spp=64):
    return parse_scene(
        {
            "volume": {"path": "unused.vdb"},
            "medium": {"density_scale": density_scale, "albedo": albedo},
            "lights": lights,
            "camera": framed_camera(volume, size=size),
            "render": {"spp": spp, "max_depth": max_depth},
        }
    )


def renderer(cache, volume, scene):
    from cloudgraph.render import GraphRenderer

    return GraphRenderer(cache, volume, scene)


# ------------------------------------------------------------------ the spec


@pytest.mark.parametrize(
    "extra, words",
    [
        ({"light": SUN, "lights": [SUN]}, "not both"),
        ({"lights": []}, "lights must be a list of 1 to 8 lights, got 0 of them"),
        ({"lights": [SUN] * 9}, "1 to 8 lights, got 9"),
        ({"lights": [{"type": "sky", "radiance": -1}]}, "lights.0.radiance: must be a non-negative number"),
        ({"lights": [SKY, {"type": "sky", "radiance": [1, 2]}]}, "lights.1.radiance: must be"),
        ({"lights": [SUN, {"type": "moon"}]}, f"lights.1.{TYPES}'moon'"),
        ({"lights": [{"type": {}, "radiance": 1}]}, f"lights.0.{TYPES}{{}}"),
        ({"lights": ["sun"]}, "lights.0.type must be one of"),
        ({"lights": [{"type": "directional", "direction": [0, 0, 0]}]}, "lights.0.direction: direction must"),
        ({"lights": [{"type": "sky", "direction": [0, -1, 0]}]}, "lights.0.direction: Extra inputs"),
    ],
)
def test_bad_lights_are_refused_with_the_field_named(extra, words):
    with pytest.raises(SceneError) as err:
        parse_scene({**BASE, **extra})
    assert words in str(err.value)


def test_a_v1_scene_dumps_as_before_and_a_v11_one_without_the_unused_light():
    v1 = parse_scene({**BASE, "light": SUN})
    assert "lights" not in v1.model_dump() and v1.light_list() == (v1.light,)
    v11 = parse_scene({**BASE, "lights": [SUN, SKY]})
    dumped = v11.model_dump(mode="json")
    assert "light" not in dumped and [li["type"] for li in dumped["lights"]] == ["directional", "sky"]
    assert parse_scene(dumped) == v11
    schema = json.dumps(json_schema())
    assert '"sky"' in schema and "lights" in schema


def test_the_radiance_key_holds_the_lights_kinds_and_directions_not_their_intensities():
    volume = sphere_volume(8)
    params = build_params(volume, 1.0, "draft")

    def key(lights):
        return cache_keys(parse_scene({**BASE, "lights": lights}), volume, params)["radiance_key"]

    brighter = [{**SUN, "irradiance": 3.0}, {**SKY, "radiance": 0.1}]
    assert key([SUN, SKY]) == key(brighter)  # a re-mix: the same cache
    assert key([SUN, SKY]) != key([SUN])  # a sky more
    assert key([SUN]) != key([{**SUN, "direction": [0, -1, 0]}])
    assert key([SUN, SUN2]) != key([SUN2, SUN])  # components in the list's order
    # the v1 light keeps its key (its radiance has the irradiance in it)
    v1 = cache_keys(parse_scene({**BASE, "light": SUN}), volume, params)["radiance_key"]
    assert (
        v1 != key([SUN])
        and v1
        != cache_keys(parse_scene({**BASE, "light": {**SUN, "irradiance": 2.0}}), volume, params)[
            "radiance_key"
        ]
    )


# ------------------------------------------------------------------ a sky, closed form


def sky_single_scattering(camera, radius, sigma, albedo, sky, n=48) -> np.ndarray:
    """(H, W) single scattering plus background of a homogeneous ball (radius, sigma_t) under a
    uniform sky, written out here with Gauss-Legendre quadrature: along a camera chord,
    L = sky T(chord) + albedo sigma int T(t) S(|x(t)|) dt, where S(r) = sky / 2 int_-1^1
    exp(-sigma l(r, mu)) dmu and l(r, mu) = -r mu + sqrt(r^2 mu^2 - r^2 + R^2) is the distance
    from radius r to the surface at cosine mu."""
    dirs = pixel_rays(camera.eye, camera.target, camera.up, camera.fov, camera.width, camera.height)
    eye = np.asarray(camera.eye, float)
    x, w = np.polynomial.legendre.leggauss(n)
    b = dirs @ eye  # |eye + t d|^2 = t^2 + 2 b t + |eye|^2
    disc = b * b - (eye @ eye - radius * radius)
    hit = disc > 0
    root = np.sqrt(np.where(hit, disc, 0.0))
    t0, t1 = -b - root, -b + root
    ts = 0.5 * (t1 - t0)[..., None] * (x + 1.0) + t0[..., None]  # (H, W, n) along the chord
    r = np.linalg.norm(eye + ts[..., None] * dirs[..., None, :], axis=-1)
    mu = x  # the inner quadrature's nodes, over [-1, 1]
    ell = -r[..., None] * mu + np.sqrt(np.maximum(r[..., None] ** 2 * (mu**2 - 1) + radius**2, 0.0))
    S = 0.5 * (np.exp(-sigma * ell) * w).sum(axis=-1)
    inscatter = 0.5 * (t1 - t0) * (np.exp(-sigma * (ts - t0[..., None])) * S * w).sum(axis=-1)
    L = np.exp(-sigma * (t1 - t0)) + albedo * sigma * inscatter
    return sky * np.where(hit, L, 1.0)


def test_a_uniform_sky_on_a_thin_ball_is_its_closed_form_single_scattering(variant, tmp_path):
    n, tau_radius, albedo = 40, 0.4, 0.5
    volume = sphere_volume(n)
    radius = n / 2.0 - 1.0  # sphere_volume's (volpath reads the same: 0.1 % in the middle)
    sigma = tau_radius / radius
    scene = lit(volume, [{"type": "sky", "radiance": 1.0}], sigma, albedo, size=24, max_depth=1)
    cache = precompute(scene, volume, "draft", CacheStore(tmp_path))
    expected = sky_single_scattering(scene.camera, radius, sigma, albedo, 1.0)
    # pixels whose chords stay off the voxelised surface (its staircase moves T by 2-3 % at 0.8 R);
    # the background outside the ball
    dirs = pixel_rays(scene.camera.eye, scene.camera.target, scene.camera.up, scene.camera.fov, 24, 24)
    eye = np.asarray(scene.camera.eye)
    miss = np.linalg.norm(eye - (dirs @ eye)[..., None] * dirs, axis=-1)  # the chord's distance to the centre
    inner, outside = miss < 0.6 * radius, miss > radius + 3.0  # (pixels are 1.9 voxels wide)
    r = renderer(cache, volume, scene)
    field = r.render(scene.camera, 4, 0, "field").mean(axis=2)
    gather = r.render(scene.camera, 1024, 1, "gather").mean(axis=2)
    # without the sky's in-scattering the ball's centre would read 1 - T: 17 % below
    assert expected[inner].min() < 0.9 and np.abs(field[inner] / expected[inner] - 1).max() < 0.01
    np.testing.assert_allclose(field[outside], 1.0, rtol=1e-5)  # the sky behind the ball
    np.testing.assert_allclose(gather[outside], 1.0, rtol=1e-5)
    keep = binned(inner[..., None].astype(float), 4)[..., 0] == 1.0
    g, e = binned(gather[..., None], 4)[..., 0], binned(expected[..., None], 4)[..., 0]
    assert np.abs(g[keep] / e[keep] - 1).max() < 0.01


# ------------------------------------------------------------------ several suns, a re-mix


@pytest.fixture(scope="module")
def two_suns(variant, tmp_path_factory):
    volume = sphere_volume(24, soft=0.2)
    store = CacheStore(tmp_path_factory.mktemp("suns"))
    scenes = {
        name: lit(volume, lights, 1.0, size=24)
        for name, lights in (("both", [SUN, SUN2]), ("sun", [SUN]), ("sun2", [SUN2]))
    }
    caches = {name: precompute(s, volume, "draft", store) for name, s in scenes.items()}
    return volume, scenes, caches


def test_two_suns_are_the_sum_of_each_alone(two_suns):
    volume, scenes, caches = two_suns
    field = {n: renderer(caches[n], volume, s).render(s.camera, 4, 0, "field") for n, s in scenes.items()}
    total = field["sun"] + field["sun2"]
    m = bias_metrics(field["both"], total)
    # each component lit with its own random numbers: sampling noise of the lighting only
    assert m["binned_relMAE"] < 0.01 and abs(m["mean_ratio"] - 1) < 0.005, m
    assert field["sun"].mean() > 0.2 * total.mean() and field["sun2"].mean() > 0.2 * total.mean()


def test_with_forward_scattering_two_suns_are_still_the_sum_of_each_alone(variant, tmp_path):
    # An anisotropic phase's field keeps each sun's view terms apart (ms_shape, ms_shape_1, in
    # each sun's frame), and the render adds each in its own light: dropping one, or reading one
    # in the other's frame, moves the sum by far more than the lighting's noise (measured 0.5 %)
    volume = sphere_volume(24, soft=0.2)
    store = CacheStore(tmp_path)
    phase = {"type": "hg", "g": 0.7}

    def field(lights):
        s = lit(volume, lights, 1.0, size=24)
        s = s.model_copy(
            update={"medium": s.medium.model_copy(update={"phase": PhaseSpec.model_validate(phase)})}
        )
        cache = precompute(s, volume, "draft", store)
        return renderer(cache, volume, s).render(s.camera, 4, 0, "field"), cache

    both, cache = field([SUN, SUN2])
    assert {e.get("shape", {}).get("array") for e in cache.field.meta["lights"]} == {
        "ms_shape",
        "ms_shape_1",
    }
    total = field([SUN])[0] + field([SUN2])[0]
    m = bias_metrics(both, total)
    assert m["binned_relMAE"] < 0.015 and abs(m["mean_ratio"] - 1) < 0.01, m


def test_a_new_light_list_computes_its_new_lights_only(variant, tmp_path):
    # A cache of several lights is its components' own caches side by side: a relight that adds
    # a light lights, transports and bakes that light alone, and the lights it had keep their
    # bits; the same lights in another order compute nothing
    volume = sphere_volume(24, soft=0.2)
    store = CacheStore(tmp_path)
    first = precompute(lit(volume, [SUN, SKY], 1.0, size=24), volume, "draft", store)
    assert first.stats["light_components"] == 2 and first.stats["components_reused"] == 0
    more = precompute(lit(volume, [SUN, SKY, SUN2], 1.0, size=24), volume, "draft", store)
    assert more.stats["components_reused"] == 2 and more.stats["graph_reused"]
    n = len(first.radiance) // 2  # components: the suns in order, then the sky
    np.testing.assert_array_equal(more.radiance[:n], first.radiance[:n])
    np.testing.assert_array_equal(more.radiance[2 * n :], first.radiance[n:])
    np.testing.assert_array_equal(more.field.tau_light, first.field.tau_light)
    np.testing.assert_array_equal(more.field.array("radiance_ms_2"), first.field.array("radiance_ms_1"))
    assert [c["type"] for c in more.field.meta["lights"]] == ["directional", "directional", "sky"]
    assert more.field.meta["lights"][1]["tau"] == "tau_light_1" and more.field.array("tau_light_1").max() > 1
    # the same lights from nothing: the same files, whatever the store had
    fresh = CacheStore(tmp_path / "fresh")
    precompute(lit(volume, [SUN, SKY, SUN2], 1.0, size=24), volume, "draft", fresh)
    for path in ("radiance_path", "field_path"):
        key = more.keys["radiance_key"]
        assert getattr(fresh, path)(key).read_bytes() == getattr(store, path)(key).read_bytes(), path
    swapped = precompute(lit(volume, [SKY, SUN2, SUN], 1.0, size=24), volume, "draft", store)
    assert swapped.keys["radiance_key"] != more.keys["radiance_key"]
    assert swapped.stats["components_reused"] == 3


@pytest.mark.parametrize("estimator", ["gather", "field"])
def test_new_intensities_re_mix_the_cache_with_no_new_kernel(two_suns, estimator):
    from cloudgraph.lights import Lights

    volume, scenes, caches = two_suns
    scene = scenes["both"]
    r = renderer(caches["both"], volume, scene)

    def with_intensities(e1, e2):
        lights = [{**SUN, "irradiance": e1}, {**SUN2, "irradiance": e2}]
        return Lights.of(lit(volume, lights, 1.0, size=24))

    one, two = with_intensities(1.0, 0.0), with_intensities(0.0, 1.0)
    a = r.render(scene.camera, 16, 0, estimator, one)
    (b, mixed), new = kernels_compiled_by_the_second(
        lambda: r.render(scene.camera, 16, 0, estimator, two),
        lambda: r.render(scene.camera, 16, 0, estimator, with_intensities([2.0, 1.0, 0.5], 3.0)),
    )
    assert not new, f"kernels compiled for a new mix: {new}"
    # the same random numbers in every render: linear in the intensities to rounding
    expected = a * np.array([2.0, 1.0, 0.5], np.float32) + 3.0 * b
    np.testing.assert_allclose(mixed, expected, rtol=1e-4, atol=1e-6 * expected.max())
    with pytest.raises(SceneError, match="not the cache's"):
        r.render(scene.camera, 4, 0, estimator, Lights.of(scenes["sun"]))


def test_a_new_lights_direct_light_and_light_march_compile_no_new_kernel(variant):
    # A relight runs the bake's kernels for a new light: its direction and colour are kernel
    # parameters, not literals (tracing.opaque), so only the first light compiles them
    from cloudgraph.build import GraphBuilder
    from cloudgraph.field import field_chunk
    from cloudgraph.lighting import direct_radiance
    from cloudgraph.tracing import towards_light

    volume = sphere_volume(16)
    builder = GraphBuilder(volume, 0.5, build_params(volume, 0.5, "draft"))
    points = np.random.default_rng(0).random((256, 3)).astype(np.float32) * volume.world_bbox()[1]

    def bake_kernels(direction, irradiance):
        d = np.asarray(direction, float) / np.linalg.norm(direction)
        lit = direct_radiance(builder.field, points, d, irradiance, samples=4)
        inputs = {"points": points, "to_light": towards_light(d), "step": np.array([0.25])}
        return lit, field_chunk(builder, "field_tau", 0, inputs)[1]

    bake_kernels([0.1, 0.2, -0.9], 1.0)  # (the first launch also evaluates the medium's pending arrays)
    (first, second), new = kernels_compiled_by_the_second(
        lambda: bake_kernels(SUN["direction"], 1.0), lambda: bake_kernels(SUN2["direction"], [0.5, 0.4, 0.3])
    )
    assert not new, f"kernels compiled for a new light: {new}"
    assert np.abs(first[1] - second[1]).mean() > 0.05 * first[1].mean()  # the light did move


# ------------------------------------------------------------------ against volpath


def assert_like_volpath(volume, lights, store) -> None:
    """gather (512 spp) within 2 % binned and 1 % in mean of a 1024-spp volpath reference, the
    field within 2 % and 1.5 %, on the soft ball (default quality)."""
    scene = lit(volume, lights, 1.0, albedo=0.9)
    r = renderer(precompute(scene, volume, "default", store), volume, scene)
    ref = reference(scene, volume, spp=1024)
    gather = bias_metrics(r.render(scene.camera, 512, 1, "gather"), ref)
    field = bias_metrics(r.render(scene.camera, 4, 0, "field"), ref)
    assert gather["binned_relMAE"] < 0.02 and abs(gather["mean_ratio"] - 1) < 0.01, gather
    assert field["binned_relMAE"] < 0.02 and abs(field["mean_ratio"] - 1) < 0.015, field


def test_sun_and_sky_against_volpath(variant, tmp_path):
    # measured: gather 0.4 % / 0.998, field 0.8 % / 0.995; the sky alone would read 0.8 of it
    assert_like_volpath(sphere_volume(32, soft=0.2), [SUN, SKY], CacheStore(tmp_path))


# ------------------------------------------------------------------ environment maps


def envmaps(tmp_path) -> dict:
    """Two lat-long .exr maps written here: a constant one, and a vertical gradient (bright and
    white at the top row, +y, dim and blue at the bottom)."""
    from cloudgraph.image import write_exr

    h, w = 32, 64
    const = tmp_path / "const.exr"
    write_exr(np.full((h, w, 3), 0.7, np.float32), const)
    ramp = np.linspace(2.0, 0.2, h, dtype=np.float32)[:, None, None] * np.ones((h, w, 3), np.float32)
    gradient = tmp_path / "gradient.exr"
    write_exr(ramp * np.array([1.0, 0.9, 0.8], np.float32) ** np.linspace(0, 3, h)[:, None, None], gradient)
    return {"const": str(const), "gradient": str(gradient)}


def test_the_field_keeps_the_map_the_server_sees_behind_the_medium(variant, tmp_path):
    # The field's background (for the page, api.md) looked up at the directions of camera rays
    # that miss the medium is the server's field render there: Mitsuba's envmap along them
    # (measured: 0.6 % of the peak at most, a 64 x 32 map resampled at 512 x 256)
    from cloudgraph.image import write_exr

    h, w = 32, 64
    v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w, indexing="ij")
    rgb = np.stack([1 + 0.8 * np.sin(2 * np.pi * u), 1 + 0.6 * np.cos(2 * np.pi * u), 0.5 + v], -1)
    write_exr(rgb.astype(np.float32), tmp_path / "map.exr")
    volume = sphere_volume(16, soft=0.2)
    envmap = {"type": "envmap", "path": str(tmp_path / "map.exr"), "scale": 0.8}
    scene = parse_scene(
        {
            "volume": {"path": "unused.vdb"},
            "medium": {"density_scale": 1.0, "albedo": 0.9},
            "lights": [SUN, envmap],
            "camera": {**framed_camera(volume, size=48), "fov": 120.0},
            "render": {"spp": 4},
        }
    )
    cache = precompute(scene, volume, "draft", CacheStore(tmp_path / "cache"))
    (entry,) = [c for c in cache.field.meta["lights"] if c["type"] == "envmap"]
    background = cache.field.array(entry["background"])
    assert background.shape == (256, 512, 3)
    image = renderer(cache, volume, scene).render(scene.camera, 4, 0, "field")
    cam = scene.camera
    d = pixel_rays(cam.eye, cam.target, cam.up, cam.fov, cam.width, cam.height).reshape(-1, 3)
    t0, t1 = box_interval(np.asarray(cam.eye, float), d, *volume.world_bbox())
    miss = t0 > t1
    assert miss.mean() > 0.3, "too few rays miss the medium: a useless test"
    page = 0.8 * latlong_lookup(background, d[miss])
    server = image.reshape(-1, 3)[miss]
    assert np.abs(page - server).max() < 0.01 * server.max(), np.abs(page - server).max()
    # the same map mirrored in u (a convention the other way round) would be far off
    assert np.abs(0.8 * latlong_lookup(background[:, ::-1], d[miss]) - server).max() > 0.2


def test_a_sun_in_the_map_is_found_by_the_map_s_own_samples(variant, tmp_path):
    # A dark map with one bright 2 x 2-texel spot: gather and the field's bake draw directions
    # from the map too, weighted by the power heuristic against their isotropic flights.
    # Measured: gather 2.3 % / 0.995 at 64 spp and field 3.7 % / 0.985, against 19 % / 0.953
    # and 22 % for the isotropic flights alone
    from cloudgraph.image import write_exr

    img = np.full((32, 64, 3), 0.05, np.float32)
    img[10:12, 20:22] = 300.0
    write_exr(img, tmp_path / "spot.exr")
    volume = sphere_volume(32, soft=0.2)
    scene = lit(volume, [{"type": "envmap", "path": str(tmp_path / "spot.exr")}], 1.0, size=32)
    r = renderer(precompute(scene, volume, "draft", CacheStore(tmp_path / "cache")), volume, scene)
    ref = reference(scene, volume, spp=1024)
    gather = bias_metrics(r.render(scene.camera, 64, 1, "gather"), ref)
    field = bias_metrics(r.render(scene.camera, 4, 0, "field"), ref)
    assert gather["binned_relMAE"] < 0.05 and abs(gather["mean_ratio"] - 1) < 0.02, gather
    assert field["binned_relMAE"] < 0.06 and abs(field["mean_ratio"] - 1) < 0.03, field


def test_several_environments_are_one_mitsuba_emitter_of_their_sum(variant, tmp_path):
    # Mitsuba takes one environment emitter a scene: volpath's reference of skies and maps
    # together sees their sum, in every direction
    import mitsuba as mi

    from cloudgraph.mitsuba_scene import envmap_emitter, scene_dict
    from cloudgraph.tracing import envmap_seen, to_jit

    maps = envmaps(tmp_path)
    lights = [
        SUN,
        SKY,
        {"type": "envmap", "path": maps["gradient"], "scale": 0.5},
        {"type": "sky", "radiance": 0.1},
    ]
    volume = sphere_volume(8)
    scene = lit(volume, lights, 1.0, size=8)
    mitsuba = mi.load_dict(scene_dict(scene, volume))
    assert len(mitsuba.emitters()) == 2  # the sun, and one environment
    rng = np.random.default_rng(0)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    seen = envmap_seen(mitsuba.environment(), to_jit(mi.Vector3f, d))
    expected = np.add(SKY["radiance"], 0.1)[:, None] + 0.5 * np.array(
        envmap_seen(envmap_emitter(maps["gradient"]), to_jit(mi.Vector3f, d))
    )
    np.testing.assert_allclose(np.array(seen), expected, rtol=1e-4)


@pytest.mark.parametrize(
    "light, words",
    [
        ({"type": "envmap"}, "give exactly one of 'path'"),
        ({"type": "envmap", "path": "a.exr", "id": "b"}, "give exactly one of 'path'"),
        ({"type": "envmap", "path": "a.exr", "scale": -1}, "lights.0.scale"),
    ],
)
def test_bad_envmaps_are_refused_with_the_field_named(light, words):
    with pytest.raises(SceneError) as err:
        parse_scene({**BASE, "lights": [light]})
    assert words in str(err.value)


def test_an_envmap_path_is_relative_to_the_scene_file_and_must_be_readable(variant, tmp_path):
    from cloudgraph.lights import Lights
    from cloudgraph.mitsuba_scene import envmap_emitter

    scene = parse_scene({**BASE, "lights": [{"type": "envmap", "path": "sky.exr"}]}, base_dir=tmp_path)
    assert scene.lights[0].path == str(tmp_path / "sky.exr")
    with pytest.raises(SceneError, match="cannot read the environment map"):
        Lights.of(scene).key()
    (tmp_path / "sky.exr").write_bytes(b"not an image")
    with pytest.raises(SceneError, match="cannot read the environment map"):
        envmap_emitter(str(tmp_path / "sky.exr"))
    # radiance that a scale of up to 1e6 takes past float32 (it rendered inf), or none at all
    from cloudgraph.image import write_exr
    from cloudgraph.mitsuba_scene import load_mitsuba_scene

    for name, value, words in (
        ("hot", 3e38, r"radiance 3e\+38, over the limit of 1e\+24"),
        ("nan", np.nan, "non-finite"),
    ):
        write_exr(np.full((8, 16, 3), value, np.float32), tmp_path / f"{name}.exr")
        bad = parse_scene({**BASE, "lights": [{"type": "envmap", "path": f"{name}.exr"}]}, base_dir=tmp_path)
        with pytest.raises(SceneError, match=words):  # the engine's reader (lighting, the bake)
            envmap_emitter(bad.lights[0].path)
        with pytest.raises(SceneError, match=words):  # volpath's scene
            load_mitsuba_scene(bad, sphere_volume(8))


def test_a_constant_envmap_is_the_uniform_sky_of_its_radiance(variant, tmp_path):
    volume = sphere_volume(24, soft=0.2)
    maps, store = envmaps(tmp_path), CacheStore(tmp_path / "cache")
    images = {}
    for name, light in (
        ("sky", {"type": "sky", "radiance": 0.7}),
        ("map", {"type": "envmap", "path": maps["const"]}),
    ):
        scene = lit(volume, [light], 1.0, size=24)
        images[name] = renderer(precompute(scene, volume, "draft", store), volume, scene).render(
            scene.camera, 4, 0, "field"
        )
    m = bias_metrics(images["map"], images["sky"])
    # the same light: its nodes lit by importance-sampled directions instead of uniform ones
    assert m["binned_relMAE"] < 0.01 and abs(m["mean_ratio"] - 1) < 0.005, m


def test_a_sun_and_an_envmap_against_volpath(variant, tmp_path):
    # measured: gather 0.5 % / 0.999, field 0.9 % / 0.995; with the map upside down gather reads 21 %
    envmap = {"type": "envmap", "path": envmaps(tmp_path)["gradient"], "scale": 0.5}
    assert_like_volpath(sphere_volume(32, soft=0.2), [SUN, envmap], CacheStore(tmp_path / "cache"))
