"""Volumes: the real OpenVDB files, placement to the half voxel, tiles, .vol, and bad input."""

import struct

import numpy as np
import pyopenvdb as vdb
import pytest

from cloudgraph.errors import VolumeError
from cloudgraph.procedural import box_volume, noise_volume, sphere_volume
from cloudgraph.vdb import vdb_grid_table
from cloudgraph.volume import Volume, load_volume, volume_info, write_vdb, write_vol

from ..helpers import rotated_affine

# ------------------------------------------------------------------ real files


def test_smoke1_reads_as_documented(data_dir):
    v = load_volume(data_dir / "smoke1.vdb")
    assert v.grid == "density"
    assert v.index_min == (1, 2, 1) and v.shape == (111, 222, 112)
    np.testing.assert_allclose(v.voxel_size, 1 / 2.1, rtol=1e-5)  # 0.476
    assert 0.9e6 < np.count_nonzero(v.density) <= 1049275  # active voxels per SOURCES.md
    assert 5.0 < v.density.max() < 6.0  # half floats, read through the real library


def test_blender_smoke_has_slightly_non_cubic_voxels(data_dir):
    v = load_volume(data_dir / "blender_smoke_000002.vdb")
    vs = v.voxel_size
    assert 0.13 < vs.min() < vs.max() < 0.134 and vs.max() - vs.min() > 1e-4
    assert np.count_nonzero(v.density) <= 71983


def test_fog_sphere_medium_box_is_active_bbox_grown_by_half_a_voxel(data_dir):
    v = load_volume(data_dir / "fog_sphere.vdb")
    lo, hi = v.world_bbox()
    # index bbox (-5,-4,-5)..(5,4,5), voxel 0.2, translated by (0, 2, 0) in the file
    np.testing.assert_allclose(lo, [-5.5 * 0.2, 2 - 4.5 * 0.2, -5.5 * 0.2], atol=1e-5)
    np.testing.assert_allclose(hi, [5.5 * 0.2, 2 + 4.5 * 0.2, 5.5 * 0.2], atol=1e-5)


def test_volume_scale_multiplies_world_about_the_origin(data_dir):
    a = load_volume(data_dir / "fog_sphere.vdb")
    b = load_volume(data_dir / "fog_sphere.vdb", scale=3.0)
    np.testing.assert_allclose(b.world_corners(), 3.0 * a.world_corners(), atol=1e-6)


def test_info_reports_grids_bbox_and_range(data_dir):
    info = volume_info(data_dir / "smoke1.vdb")
    assert info["grids"] == [{"name": "density", "type": "float"}]
    assert info["index_bbox"] == [[1, 2, 1], [111, 223, 112]]
    assert info["value_range"][0] == 0.0 and 5.0 < info["value_range"][1] < 6.0


# ------------------------------------------------------- round trips and placement


@pytest.mark.parametrize("half", [False, True])
def test_written_vdb_reads_back_with_its_affine_transform(tmp_path, half):
    m = rotated_affine()
    src = box_volume((3, 4, 5), density=2.0, index_min=(3, -2, 7), index_to_world=m)
    src.density[1, 2, 3] = 0.5
    write_vdb(src, tmp_path / "b.vdb", half=half)
    v = load_volume(tmp_path / "b.vdb")
    assert v.index_min == (3, -2, 7) and v.shape == (3, 4, 5)
    np.testing.assert_allclose(v.index_to_world, m, atol=1e-6)
    np.testing.assert_array_equal(v.density, src.density)
    # a corner of the medium is the corner voxel's index point minus half a voxel, mapped
    corner = m @ np.array([3 - 0.5, -2 - 0.5, 7 - 0.5, 1.0])
    assert np.min(np.linalg.norm(v.world_corners() - corner[:3], axis=1)) < 1e-6


def test_tiles_read_as_density_like_voxels(tmp_path):
    tiled = vdb.FloatGrid()
    tiled.name = "density"
    tiled.fill((0, 0, 0), (15, 15, 15), 1.5, True)  # one active tile, no leaf nodes
    assert tiled.leafCount() == 0
    dense = tiled.deepCopy()
    acc = dense.getAccessor()
    for leaf_origin in np.ndindex(2, 2, 2):  # a changed voxel turns its 8^3 tile into a leaf,
        ijk = tuple(8 * int(c) for c in leaf_origin)  # which keeps its voxels when changed back
        acc.setValueOn(ijk, 0.0)
        acc.setValueOn(ijk, 1.5)
    assert dense.leafCount() == 8 and dense.activeVoxelCount() == tiled.activeVoxelCount()
    vdb.write(str(tmp_path / "tiled.vdb"), grids=[tiled])
    vdb.write(str(tmp_path / "dense.vdb"), grids=[dense])
    a, b = load_volume(tmp_path / "tiled.vdb"), load_volume(tmp_path / "dense.vdb")
    assert a.shape == b.shape == (16, 16, 16)
    np.testing.assert_array_equal(a.density, b.density)


def test_vol_round_trip_keeps_values_and_extent(tmp_path):
    src = sphere_volume(12, density=3.0, voxel_size=0.5)
    write_vol(src, tmp_path / "s.vol")
    v = load_volume(tmp_path / "s.vol")
    np.testing.assert_array_equal(v.density, src.density)
    np.testing.assert_allclose(v.world_bbox(), src.world_bbox(), atol=1e-6)


def test_procedural_volumes_are_deterministic():
    np.testing.assert_array_equal(noise_volume(32, seed=3).density, noise_volume(32, seed=3).density)
    assert not np.array_equal(noise_volume(32, seed=3).density, noise_volume(32, seed=4).density)
    s = sphere_volume(20)
    assert s.density[10, 10, 10] == 1.0 and s.density[0, 0, 0] == 0.0


def test_named_grid_else_density_else_only_float_grid(tmp_path):
    g1, g2, vel = vdb.FloatGrid(), vdb.FloatGrid(), vdb.Vec3SGrid()
    g1.name, g2.name, vel.name = "smoke", "heat", "vel"
    g1.fill((0, 0, 0), (1, 1, 1), 1.0, True)
    g2.fill((0, 0, 0), (3, 3, 3), 2.0, True)
    vel.fill((0, 0, 0), (1, 1, 1), (1, 0, 0), True)
    vdb.write(str(tmp_path / "two.vdb"), grids=[g1, g2, vel])
    vdb.write(str(tmp_path / "one.vdb"), grids=[g2, vel])
    assert load_volume(tmp_path / "two.vdb", grid="heat").shape == (4, 4, 4)
    assert load_volume(tmp_path / "one.vdb").grid == "heat"
    with pytest.raises(VolumeError, match="name one with volume.grid"):
        load_volume(tmp_path / "two.vdb")
    # described all the same (an upload is stored): no default grid, the boxes of the first
    info = volume_info(tmp_path / "two.vdb")
    assert info["grid"] is None and [g["name"] for g in info["grids"]] == ["smoke", "heat", "vel"]
    assert info["index_bbox"] == [[0, 0, 0], [1, 1, 1]] and info["value_range"] == [1.0, 1.0]
    assert volume_info(tmp_path / "one.vdb")["grid"] == "heat"


# -------------------------------------------------------------------- bad input


def _single_grid_file(tmp_path) -> bytes:
    g = vdb.FloatGrid()
    g.name = "density"
    g.fill((0, 0, 0), (7, 7, 7), 1.0, True)
    vdb.write(str(tmp_path / "one.vdb"), grids=[g])
    return (tmp_path / "one.vdb").read_bytes()


def _as_double_grid(raw: bytes) -> bytes:
    """Renames the one grid's type to double; every later absolute offset moves by one byte."""
    old, new = b"\x10\x00\x00\x00Tree_float_5_4_3", b"\x11\x00\x00\x00Tree_double_5_4_3"
    i = raw.index(old) + len(old)
    parent_len = struct.unpack_from("<I", raw, i)[0]
    j = i + 4 + parent_len
    offsets = struct.pack("<qqq", *(o + 1 for o in struct.unpack_from("<qqq", raw, j)))
    return raw[: raw.index(old)] + new + raw[i:j] + offsets + raw[j + 24 :]


@pytest.mark.parametrize(
    "case, message",
    [
        ("missing", "volume file not found"),
        ("text", "neither an OpenVDB"),
        ("truncated", "truncated or corrupt"),
        ("corrupt", "truncated or corrupt"),
        ("no_grid", "no grid named 'temperature'; its grids: 'density' (float)"),
        ("vector", "holds vec3s values; density needs a scalar float grid"),
        ("empty", "is empty"),
        ("too_big", "over the limit of 1000 voxels"),
        ("double", "'density' (double) have a type this OpenVDB build cannot read"),
        ("vol_truncated", "the .vol file is truncated"),
        ("negative", "holds no positive value"),  # (accepted, then a build with no nodes)
        ("vol_zero", "holds no positive value"),
    ],
)
def test_bad_volume_input_gets_one_clear_error(tmp_path, monkeypatch, data_dir, case, message):
    path, grid = tmp_path / "v.vdb", None
    raw = _single_grid_file(tmp_path)
    if case == "text":
        path.write_text("hello, not a volume\n")
    elif case == "truncated":
        path.write_bytes((data_dir / "smoke1.vdb").read_bytes()[:100_000])
    elif case == "corrupt":
        path.write_bytes(raw[:8] + b"\xff" * (len(raw) - 8))
    elif case == "no_grid":
        path.write_bytes(raw)
        grid = "temperature"
    elif case == "vector":
        vel = vdb.Vec3SGrid()
        vel.name = "density"
        vel.fill((0, 0, 0), (1, 1, 1), (1, 0, 0), True)
        vdb.write(str(path), grids=[vel])
    elif case == "empty":
        g = vdb.FloatGrid()
        g.name = "density"
        vdb.write(str(path), grids=[g])
    elif case == "too_big":
        path.write_bytes(raw)  # 8^3 = 512 voxels
        monkeypatch.setenv("CLOUDGRAPH_MAX_VOXELS", "1000")
        path = data_dir / "fog_sphere.vdb"  # 11 x 9 x 11 = 1089 voxels
    elif case == "double":
        path.write_bytes(_as_double_grid(raw))
        assert vdb_grid_table(path) == [("density", "Tree_double_5_4_3")]
    elif case == "negative":
        g = vdb.FloatGrid()
        g.name = "density"
        g.fill((0, 0, 0), (3, 3, 3), -5.0, True)
        vdb.write(str(path), grids=[g])
    elif case == "vol_zero":
        path = tmp_path / "v.vol"
        write_vol(Volume(np.zeros((4, 4, 4), np.float32), (0, 0, 0), np.eye(4), "density"), path)
    elif case == "vol_truncated":
        path = tmp_path / "v.vol"
        write_vol(sphere_volume(8), path)
        path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(VolumeError) as err:
        load_volume(path, grid=grid)
    assert message in str(err.value)
    assert "\n" not in str(err.value)
