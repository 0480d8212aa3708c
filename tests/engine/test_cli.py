"""The command line, run as users run it: a subprocess, one line per error, no traceback."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from cloudgraph.cache import CacheStore, graph_key, volume_id
from cloudgraph.graph_file import read_graph
from cloudgraph.params import build_params
from cloudgraph.procedural import sphere_volume
from cloudgraph.volume import load_volume, write_vdb

from ..helpers import LIGHT, cube_volume, framed_camera


def cli(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "cloudgraph.cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )


@pytest.fixture
def scene_file(tmp_path):
    write_vdb(cube_volume(1.0), tmp_path / "cube.vdb")
    doc = {
        "volume": {"path": "cube.vdb"},
        "light": {"direction": [0, -1, 0]},
        "camera": {"eye": [0, 0, 6], "target": [0, 0, 0], "fov": 30, "width": 24, "height": 16},
        "render": {"spp": 8, "max_depth": 2},
    }
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    return tmp_path / "scene.json"


def test_render_writes_exr_and_png_and_compare_reads_them(scene_file, tmp_path):
    r = cli(
        "render",
        scene_file,
        "--integrator",
        "volpath",
        "--out",
        tmp_path / "a.exr",
        "--png",
        tmp_path / "a.png",
        "--exposure",
        "1",
        "--spp",
        "4",
    )
    assert r.returncode == 0, r.stderr
    assert "24x16 at 4 spp" in r.stdout
    assert (tmp_path / "a.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    r = cli("compare", tmp_path / "a.exr", tmp_path / "a.exr", "--json")
    assert r.returncode == 0, r.stderr
    m = json.loads(r.stdout)
    assert m["MAE"] == 0.0 and m["ref_mean"] > 0


def test_info_prints_the_real_smoke_grid(data_dir):
    r = cli("info", data_dir / "smoke1.vdb", "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["index_bbox"] == [[1, 2, 1], [111, 223, 112]]
    np.testing.assert_allclose(info["voxel_size"], [1 / 2.1] * 3, rtol=1e-5)


def test_info_of_several_float_grids_none_named_density_says_a_scene_must_name_one(tmp_path):
    import pyopenvdb as vdb

    smoke, heat = vdb.FloatGrid(), vdb.FloatGrid()
    smoke.name, heat.name = "smoke", "heat"
    smoke.fill((0, 0, 0), (1, 1, 1), 1.0, True)
    heat.fill((0, 0, 0), (3, 3, 3), 2.0, True)
    vdb.write(str(tmp_path / "sim.vdb"), grids=[smoke, heat])
    r = cli("info", tmp_path / "sim.vdb")
    assert r.returncode == 0, r.stderr
    said = "density grid: none named (name one with volume.grid); the figures below are of 'smoke'"
    assert said in r.stdout


def test_schema_is_json():
    r = cli("schema")
    assert r.returncode == 0 and json.loads(r.stdout)["title"] == "cloudgraph scene spec v1"


@pytest.mark.parametrize(
    "args, words",
    [
        (["info", "nowhere.vdb"], "volume file not found"),
        (["render", "nowhere.json", "--out", "x.exr"], "scene file not found"),
        (["compare", "a.exr", "b.exr"], "image not found"),
        (["render", "{scene}", "--out", "x.exr", "--spp", "0"], "--spp must be in 1..65536"),
        (["render", "{bad_scene}", "--out", "x.exr"], "camera.fov"),
        (["render", "{scene}", "--out", "{tmp}/no/such/dir/x.exr"], "error"),
        # refused before any rendering: each of these rendered first, or hung, or printed a traceback
        (["render", "{scene}", "--out", "x.txt"], "--out must name a .exr file"),
        (["render", "{scene}", "--out", "{tmp}/folder.exr"], "is a folder"),
        (["render", "{scene}", "--out", "x.exr", "--png", "y.png", "--exposure", "nan"], "--exposure"),
        (["render", "{dense}", "--out", "x.exr"], "1e+30 makes the optical depth across one voxel"),
        (["precompute", "{dense}"], "over the limit of 100; use at most"),
        (["render", "{tiny}", "--out", "x.exr"], "a voxel must be 1e-15 to 1e+15 on every axis"),
        (["render", "{env}", "--integrator", "volpath", "--out", "x.exr"], "environment map not found"),
        (["render", "{latin}", "--out", "x.exr"], "is not UTF-8 text"),
        (["render", "{deep}", "--out", "x.exr"], "nests its JSON too deeply"),
        (["precompute", "{scene}", "--cache-dir", "{scene}"], "is a file, not a folder"),
    ],
)
def test_bad_input_exits_non_zero_with_one_line(scene_file, tmp_path, args, words):
    good = json.loads(scene_file.read_text())
    scenes = {
        "bad": good | {"camera": good["camera"] | {"fov": 200}},
        "dense": good | {"medium": {"density_scale": 1e30}},  # cube of density 1, voxel 1/8
        "tiny": good | {"volume": {"path": "cube.vdb", "scale": 1e-100}},  # (in float32: 0)
        "env": {k: v for k, v in good.items() if k != "light"}
        | {"lights": [good["light"] | {"type": "directional"}, {"type": "envmap", "path": "nope.exr"}]},
    }
    for name, doc in scenes.items():
        (tmp_path / f"{name}.json").write_text(json.dumps(doc))
    (tmp_path / "latin.json").write_bytes(json.dumps(good).replace("cube", "cub\u00e9").encode("latin-1"))
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    (tmp_path / "folder.exr").mkdir()
    names = {name: tmp_path / f"{name}.json" for name in [*scenes, "latin", "deep"]}
    args = [a.format(scene=scene_file, bad_scene=names["bad"], tmp=tmp_path, **names) for a in args]
    r = cli(*args, cwd=tmp_path)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in r.stderr


def test_cli_precompute_prints_keys_and_sizes_and_render_uses_the_cache(variant, tmp_path):
    from cloudgraph.image import read_exr

    volume = sphere_volume(16)
    write_vdb(volume, tmp_path / "ball.vdb")
    doc = {
        "volume": {"path": "ball.vdb"},
        "medium": {"density_scale": 0.5, "albedo": 0.8},
        "light": {"direction": LIGHT},
        "camera": {**framed_camera(volume), "width": 32, "height": 24},
        "render": {"spp": 4},
    }
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    cache_dir = tmp_path / "cache"

    r = cli("precompute", tmp_path / "scene.json", "--quality", "draft", "--cache-dir", cache_dir)
    assert r.returncode == 0, r.stderr
    keys = dict(re.findall(r"^(volume_id|graph_key|radiance_key): ([0-9a-f]{64})$", r.stdout, re.M))
    assert set(keys) == {"volume_id", "graph_key", "radiance_key"}
    sizes = re.search(r"^nodes (\d+)\s+edges (\d+)", r.stdout, re.M)
    assert sizes, r.stdout
    assert "graph built" in r.stdout and "radiance computed" in r.stdout
    # The keys are those of the volume as read back and of the draft parameters ...
    loaded = load_volume(tmp_path / "ball.vdb")
    assert keys["volume_id"] == volume_id(loaded)
    assert keys["graph_key"] == graph_key(
        keys["volume_id"], 0.5, build_params(loaded, 0.5, "draft").to_dict()
    )
    # ... and the sizes those of the graph it stored under its key.
    graph = read_graph(CacheStore(cache_dir).graph_path(keys["graph_key"]))
    assert (graph.n_nodes, graph.counts.nnz) == (int(sizes[1]), int(sizes[2]))
    assert graph.n_nodes > 100

    r = cli(
        "render", tmp_path / "scene.json", "--integrator", "graph", "--quality", "draft",
        "--cache-dir", cache_dir, "--out", tmp_path / "g.exr",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "graph: 32x24 at 4 spp" in r.stdout
    image = read_exr(tmp_path / "g.exr")
    assert image.shape == (24, 32, 3) and np.isfinite(image).all() and image.mean() > 0
    # the field estimator: the same scene, deterministic, no noise to speak of at 4 spp
    r = cli(
        "render", tmp_path / "scene.json", "--integrator", "graph", "--estimator", "field",
        "--quality", "draft", "--cache-dir", cache_dir, "--out", tmp_path / "f.exr",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    field = read_exr(tmp_path / "f.exr")
    assert field.shape == image.shape and abs(field.mean() / image.mean() - 1) < 0.1
    # the render found the cache: nothing new was built
    assert [p.stem for p in (cache_dir / "graphs").iterdir()] == [keys["graph_key"]]
    assert [p.stem for p in (cache_dir / "radiance").iterdir()] == [keys["radiance_key"]]
    assert [p.name for p in (cache_dir / "fields").iterdir()] == [keys["radiance_key"] + ".cgf.gz"]
