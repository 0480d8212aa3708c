"""Mitsuba's volpath on scenes from the spec, against analytic expectations computed in numpy."""

import subprocess
import sys

import numpy as np
import pytest

from cloudgraph.procedural import box_volume
from cloudgraph.render import render_volpath
from cloudgraph.scene import parse_scene
from cloudgraph.volume import load_volume, write_vdb

from ..helpers import box_interval, cube_volume, pixel_rays, rotated_affine


def scene_for(camera: dict, **sections) -> "parse_scene":
    doc = {"volume": {"path": "unused.vdb"}, "camera": camera}
    doc.update(sections)
    return parse_scene(doc)


def test_single_scattering_in_a_homogeneous_cube_matches_the_closed_form(variant):
    # Light falls straight down (-y) on the cube [-1, 1]^3, sigma_t = 1.2, albedo 0.7, E = 2.
    # A point p is lit through 1 - p_y of medium, so along a camera ray o + t d
    #   L = albedo sigma E / 4pi * exp(-sigma (1 - o_y)) * int_t0^t1 exp(-sigma (t - t0) + sigma t d_y) dt.
    sigma, albedo, E = 1.2, 0.7, 2.0
    cam = {"eye": [0.4, 0.3, 6.0], "target": [0.0, 0.0, 0.0], "fov": 28, "width": 48, "height": 40}
    scene = scene_for(
        cam,
        medium={"density_scale": 1.0, "albedo": albedo},
        light={"direction": [0, -1, 0], "irradiance": E},
        render={"spp": 256, "max_depth": 1, "seed": 3},
    )
    image = render_volpath(scene, cube_volume(sigma))[..., 0].astype(np.float64)

    o = np.array(cam["eye"])
    d = pixel_rays(cam["eye"], cam["target"], [0, 1, 0], cam["fov"], cam["width"], cam["height"])
    t0, t1 = box_interval(o, d, [-1, -1, -1], [1, 1, 1])
    k = sigma * (1 - d[..., 1])
    integral = np.exp(sigma * t0 * d[..., 1]) * (1 - np.exp(-k * (t1 - t0))) / k
    expected = albedo * sigma * E / (4 * np.pi) * np.exp(-sigma * (1 - o[1])) * integral
    expected = np.where(t1 > t0, expected, 0.0)

    # Compare well inside the silhouette, where a pixel's footprint does not straddle an edge.
    inner = (t1 - t0) > 0.5
    assert inner.sum() > 600
    diff = image[inner] - expected[inner]
    stderr = diff.std() / np.sqrt(diff.size)
    assert abs(diff.mean()) < 4 * stderr + 0.002 * expected[inner].mean()
    # and row by row: the fall-off with depth below the lit top face, exp(-sigma (1 - y))
    rows = inner.sum(axis=1) >= 20
    got = (image * inner).sum(axis=1)[rows] / inner.sum(axis=1)[rows]
    want = (expected * inner).sum(axis=1)[rows] / inner.sum(axis=1)[rows]
    assert want.max() / want.min() > 2.0  # the profile is steep enough to tell
    np.testing.assert_allclose(got, want, rtol=0.1)
    # where no part of a pixel sees the cube, nothing
    m0, m1 = box_interval(o, d, [-1.1, -1.1, -1.1], [1.1, 1.1, 1.1])
    assert (m1 <= m0).sum() > 100 and np.all(image[m1 <= m0] == 0.0)


def test_max_depth_zero_gives_no_light_and_more_depth_adds_energy(variant):
    cam = {"eye": [0, 0, 6.0], "target": [0, 0, 0], "fov": 25, "width": 16, "height": 16}
    means = []
    for depth in (0, 1, 4):
        scene = scene_for(cam, light={"direction": [0, -1, 0]}, render={"spp": 32, "max_depth": depth})
        means.append(render_volpath(scene, cube_volume(2.0)).mean())
    assert means[0] == 0.0 and 0 < means[1] < means[2]


def test_rotated_affine_volume_lands_at_the_expected_pixels(variant, tmp_path):
    m = rotated_affine()
    index_min, dims = np.array([3, -2, 7]), (3, 4, 5)
    write_vdb(box_volume(dims, density=3.0, index_min=tuple(index_min), index_to_world=m), tmp_path / "b.vdb")
    volume = load_volume(tmp_path / "b.vdb")
    centre = (m @ np.array([*(index_min + (np.array(dims) - 1) / 2), 1.0]))[:3]
    cam = {
        "eye": list(centre + [0.6, 0.5, 2.0]),
        "target": list(centre),
        "fov": 30,
        "width": 64,
        "height": 64,
    }
    scene = scene_for(cam, light={"direction": [0.3, -1, -0.2]}, render={"spp": 32, "max_depth": 1})
    lit = render_volpath(scene, volume)[..., 0] > 0

    # Expected: pixel-centre rays through the block in index space, [min - 0.5, max + 0.5].
    inv = np.linalg.inv(m)
    d = pixel_rays(cam["eye"], cam["target"], [0, 1, 0], cam["fov"], 64, 64)
    o_i = inv[:3, :3] @ np.asarray(cam["eye"]) + inv[:3, 3]
    d_i = d @ inv[:3, :3].T
    t0, t1 = box_interval(o_i, d_i, index_min - 0.5, index_min + np.array(dims) - 0.5)
    chord = np.where(t1 > t0, t1 - t0, 0.0)
    inside, outside = chord > 0.15 * chord.max(), chord == 0
    assert inside.sum() > 200
    assert lit[inside].mean() > 0.97  # a few deep, shadowed pixels may see no light at 32 spp
    # the only lit pixels outside are those whose footprint touches the silhouette
    grown = inside | ~outside
    grown[1:] |= grown[:-1].copy()
    grown[:-1] |= grown[1:].copy()
    grown[:, 1:] |= grown[:, :-1].copy()
    grown[:, :-1] |= grown[:, 1:].copy()
    assert not np.any(lit & ~grown)


def test_tiled_grid_renders_like_the_same_grid_with_tiles_filled(variant, tmp_path):
    import pyopenvdb as vdb

    tiled = vdb.FloatGrid()
    tiled.name = "density"
    tiled.fill((0, 0, 0), (15, 15, 15), 0.2, True)
    filled = tiled.deepCopy()
    acc = filled.getAccessor()
    for origin in np.ndindex(2, 2, 2):
        ijk = tuple(8 * int(c) for c in origin)
        acc.setValueOn(ijk, 0.0)
        acc.setValueOn(ijk, 0.2)
    vdb.write(str(tmp_path / "t.vdb"), grids=[tiled])
    vdb.write(str(tmp_path / "f.vdb"), grids=[filled])
    cam = {"eye": [30, 20, 40], "target": [7.5, 7.5, 7.5], "fov": 40, "width": 24, "height": 24}
    scene = scene_for(cam, light={"direction": [-1, -1, 0]}, render={"spp": 8, "seed": 1})
    a = render_volpath(scene, load_volume(tmp_path / "t.vdb"))
    b = render_volpath(scene, load_volume(tmp_path / "f.vdb"))
    assert a.mean() > 0
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", ["smoke1", "blender_smoke_000002"])
def test_real_clouds_render_finite_and_inside_their_bbox(variant, data_dir, name):
    volume = load_volume(data_dir / f"{name}.vdb")
    lo, hi = volume.world_bbox()
    c = (lo + hi) / 2
    cam = {
        "eye": list(c + [0, 0, 2.5 * np.linalg.norm(hi - lo)]),
        "target": list(c),
        "fov": 30,
        "width": 32,
        "height": 32,
    }
    density_scale = 1.0 / (volume.density.max() * volume.voxel_size.max())  # densest voxel: optical depth 1
    scene = scene_for(
        cam,
        medium={"density_scale": float(density_scale)},
        light={"direction": [1, -1, 0]},
        render={"spp": 4, "max_depth": 8},
    )
    image = render_volpath(scene, volume)
    assert np.isfinite(image).all() and image.mean() > 1e-4
    assert image[0, 0].sum() == 0 and image[-1, -1].sum() == 0  # corners see past the cloud


def test_a_camera_inside_the_medium_sees_through_it(variant):
    # The camera inside the cube [-1, 1]^3 of a pure absorber (sigma_t 1.2, albedo 0) under a
    # uniform sky of radiance 1: each pixel is exp(-sigma t_exit). Mitsuba's rays start in the
    # sensor's medium, none unless the scene gives it: without it they read 1, unattenuated.
    sigma = 1.2
    cam = {"eye": [0.2, 0.1, -0.3], "target": [0.5, 0.3, 1.0], "fov": 70, "width": 24, "height": 20}
    scene = scene_for(
        cam,
        medium={"density_scale": 1.0, "albedo": 0.0},
        lights=[{"type": "sky", "radiance": 1.0}],
        render={"spp": 1024, "seed": 1},
    )
    image = render_volpath(scene, cube_volume(sigma))[..., 0].astype(np.float64)  # (delta tracking)
    d = pixel_rays(cam["eye"], cam["target"], [0, 1, 0], cam["fov"], cam["width"], cam["height"])
    _, t1 = box_interval(np.array(cam["eye"]), d, [-1, -1, -1], [1, 1, 1])
    expected = np.exp(-sigma * t1)
    assert expected.max() < 0.5  # every ray crosses more than half an optical depth
    assert abs(image.mean() / expected.mean() - 1) < 0.01, (image.mean(), expected.mean())
    np.testing.assert_allclose(image, expected, atol=0.07)  # 5 sigma of 1024 draws of 0 or 1


def test_one_worker_thread_counts_as_two_so_exr_files_are_written_and_read(tmp_path):
    # With Dr.Jit's pool at one thread, Mitsuba's EXR writer waits for ever (Mitsuba 3.9.1,
    # Dr.Jit 1.5): a worker set to one thread hung every EXR render. In a process of its own,
    # whose pool this test may set.
    out = tmp_path / "a.exr"
    code = (
        "import numpy as np\n"
        "from cloudgraph.image import read_exr, write_exr\n"
        "from cloudgraph.mitsuba_scene import set_threads, set_variant\n"
        "set_variant()\n"
        "assert set_threads(1) == 2\n"
        f"write_exr(np.ones((4, 4, 3), np.float32), {str(out)!r})\n"
        f"print(read_exr({str(out)!r}).sum())\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "48.0", r.stderr
