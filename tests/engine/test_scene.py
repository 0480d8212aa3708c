"""Scene spec v1: validation a person can act on, path resolution, the exported schema."""

import json

import pytest

from cloudgraph.errors import SceneError
from cloudgraph.scene import json_schema, load_scene, parse_scene

BASE = {
    "volume": {"path": "cloud.vdb"},
    "camera": {"eye": [0, 0, 5], "target": [0, 0, 0]},
}


def with_(path: str, value):
    doc = json.loads(json.dumps(BASE))
    *parents, leaf = path.split(".")
    node = doc
    for p in parents:
        node = node.setdefault(p, {})
    node[leaf] = value
    return doc


def test_defaults_fill_a_minimal_scene():
    s = parse_scene(BASE)
    assert s.render.spp == 64 and s.render.max_depth == -1
    assert s.medium.albedo_rgb() == (1.0, 1.0, 1.0)
    assert s.light.unit_direction() == (0.0, -1.0, 0.0)


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("camera.width", 0, "camera.width"),
        ("camera.height", 4097, "camera.height"),
        ("render.spp", 0, "render.spp"),
        ("render.spp", 65537, "render.spp"),
        ("camera.fov", 0, "camera.fov"),
        ("camera.fov", 180, "camera.fov"),
        ("light.direction", [0, 0, 0], "non-zero"),
        ("camera.up", [0, 0, 0], "up must be a non-zero"),
        ("camera.target", [0, 0, 5], "eye and target must differ"),
        ("camera.up", [0, 0, 1], "parallel"),
        ("medium.density_scale", -1, "medium.density_scale"),
        ("medium.albedo", 1.5, "medium.albedo"),
        ("medium.albedo", [0.5, 0.5, -0.1], "medium.albedo"),
        ("render.max_depth", -2, "render.max_depth"),
        ("camera.colour", 1, "camera.colour"),
    ],
)
def test_invalid_fields_are_named_in_the_error(field, value, words):
    with pytest.raises(SceneError) as err:
        parse_scene(with_(field, value))
    assert words in str(err.value)


def test_volume_needs_exactly_one_source():
    with pytest.raises(SceneError, match="exactly one"):
        parse_scene(with_("volume", {"path": "a.vdb", "id": "abc"}))


def test_rgb_albedo_and_irradiance_are_kept_per_channel():
    s = parse_scene(with_("medium.albedo", [0.9, 0.8, 0.7]))
    assert s.medium.albedo_rgb() == (0.9, 0.8, 0.7)


def test_volume_path_is_relative_to_the_scene_file(tmp_path):
    (tmp_path / "sub").mkdir()
    f = tmp_path / "sub" / "scene.json"
    f.write_text(json.dumps(BASE))
    assert load_scene(f).volume.path == str(tmp_path / "sub" / "cloud.vdb")


def test_bad_json_and_missing_file_get_clear_errors(tmp_path):
    f = tmp_path / "s.json"
    f.write_text("{nope")
    with pytest.raises(SceneError, match="not valid JSON: .* line 1"):
        load_scene(f)
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene(tmp_path / "missing.json")


def test_schema_lists_every_section():
    schema = json_schema()
    assert set(schema["required"]) == {"volume", "camera"}
    assert {"volume", "medium", "light", "camera", "render"} <= set(schema["properties"])


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_numbers_are_refused_with_the_field_named(value):
    with pytest.raises(SceneError, match="density_scale"):
        parse_scene({"volume": {"path": "a.vdb"}, "medium": {"density_scale": value}})
