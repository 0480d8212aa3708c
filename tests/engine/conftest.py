"""Engine test fixtures: small scenes with their radiance caches, built once per session."""

import pytest

from cloudgraph.cache import CacheStore
from cloudgraph.precompute import precompute
from cloudgraph.procedural import noise_volume, sphere_volume

from ..helpers import medium_scene


@pytest.fixture(scope="session")
def sphere(variant, tmp_path_factory):
    """A homogeneous sphere of radius 11 voxels, optical radius 4, albedo 0.9, draft graph."""
    volume = sphere_volume(24)
    radius = 24 / 2 - 1
    scene = medium_scene(volume, density_scale=4.0 / radius)
    cache = precompute(scene, volume, "draft", CacheStore(tmp_path_factory.mktemp("sphere")))
    return {"volume": volume, "scene": scene, "cache": cache, "radius": radius, "sigma": 4.0 / radius}


@pytest.fixture(scope="session")
def cloud(variant, tmp_path_factory):
    volume = noise_volume(32, seed=7)
    scene = medium_scene(volume, density_scale=1.0 / float(volume.density.max() * volume.voxel_size.max()))
    cache = precompute(scene, volume, "draft", CacheStore(tmp_path_factory.mktemp("cloud")))
    return {"volume": volume, "scene": scene, "cache": cache}
