"""Shared test helpers: camera rays and ray-box chords computed in numpy (independent
expectations), and small volumes with exactly known placement."""

from __future__ import annotations

import numpy as np

from cloudgraph.procedural import box_volume, noise_volume
from cloudgraph.render import GraphRenderer, render_volpath
from cloudgraph.scene import PhaseSpec, parse_scene


def pixel_rays(eye, target, up, fov_deg: float, width: int, height: int):
    """Pinhole rays through pixel centres, (H, W, 3) unit directions; fov along the width,
    row 0 at the top, column 0 at the left (the spec's camera, derived without Mitsuba)."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    f = (target - eye) / np.linalg.norm(target - eye)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    t = np.tan(np.radians(fov_deg) / 2)
    x = (2 * (np.arange(width) + 0.5) / width - 1) * t
    y = (1 - 2 * (np.arange(height) + 0.5) / height) * t * height / width
    d = f + x[None, :, None] * r + y[:, None, None] * u
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def box_interval(origin, dirs, lo, hi):
    """Entry and exit distances of rays origin + t dirs through the box [lo, hi] (t0 > t1: miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        a = (np.asarray(lo) - origin) * inv
        b = (np.asarray(hi) - origin) * inv
    t0 = np.nanmax(np.minimum(a, b), axis=-1)
    t1 = np.nanmin(np.maximum(a, b), axis=-1)
    return np.maximum(t0, 0.0), t1


def latlong_lookup(image: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a lat-long image (h, w, 3) at unit directions d (N, 3), as api.md
    gives the field's ``background``: u = atan2(x, -z) / 2pi (wrapped), v = acos(y) / pi, values
    at texel centres, wrapping around in u and clamped at the poles."""
    h, w = image.shape[:2]
    u = (np.arctan2(d[:, 0], -d[:, 2]) / (2 * np.pi)) % 1.0
    v = np.arccos(np.clip(d[:, 1], -1, 1)) / np.pi
    x, y = u * w - 0.5, np.clip(v * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x1, y1 = (x0 + 1) % w, np.minimum(y0 + 1, h - 1)
    x0 %= w
    top = (1 - fx) * image[y0, x0] + fx * image[y0, x1]
    bottom = (1 - fx) * image[y1, x0] + fx * image[y1, x1]
    return (1 - fy) * top + fy * bottom


def cube_volume(sigma: float, n: int = 8):
    """A homogeneous cube filling exactly [-1, 1]^3 (n voxels a side, half-voxel rule)."""
    s = 2.0 / n
    m = np.diag([s, s, s, 1.0])
    m[:3, 3] = -1.0 + 0.5 * s
    return box_volume((n, n, n), density=sigma, index_to_world=m)


def rotated_affine() -> np.ndarray:
    """A rotated, non-uniformly scaled and translated index-to-world map."""
    a, b = np.radians(30), np.radians(20)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    m = np.eye(4)
    m[:3, :3] = rz @ rx @ np.diag([0.1, 0.15, 0.12])
    m[:3, 3] = [0.3, -0.2, 0.1]
    return m


#: Light as in the bench: oblique, mostly towards -z.
LIGHT = [0.55, -0.25, -0.8]
#: A view at right angles to LIGHT: the cloud side-lit (framed_camera normalises it)
SIDE = np.cross(LIGHT, [0.0, 0.0, 1.0]).tolist()


def dense_cloud(optical_depth: float = 4.0):
    """The tests' dense cloud: a 32^3 noise cloud (seed 11) and the density scale that puts its
    densest voxel at ``optical_depth`` (a dense cloud's light falls by exp(-4) across a voxel)."""
    volume = noise_volume(32, seed=11)
    return volume, optical_depth / float(volume.density.max() * volume.voxel_size.max())


def framed_camera(volume, eye_dir=(0.6, 0.0, 0.8), size=40) -> dict:
    """A camera on ``eye_dir`` from the box centre whose view just holds the box's inscribed ball."""
    lo, hi = volume.world_bbox()
    c = (lo + hi) / 2
    dist = 2.0 * float(np.linalg.norm(hi - lo))
    fov = float(np.degrees(2 * np.arcsin(0.5 * float((hi - lo).max()) / dist)) * 1.1)
    eye = c + dist * np.asarray(eye_dir, float) / np.linalg.norm(eye_dir)
    return {
        "eye": eye.tolist(),
        "target": c.tolist(),
        "up": [0, 1, 0],
        "fov": fov,
        "width": size,
        "height": size,
    }


def medium_scene(volume, density_scale: float, albedo: float = 0.9, spp: int = 16, **camera):
    return parse_scene(
        {
            "volume": {"path": "unused.vdb"},
            "medium": {"density_scale": density_scale, "albedo": albedo},
            "light": {"direction": LIGHT, "irradiance": 1.0},
            "camera": framed_camera(volume, **camera),
            "render": {"spp": spp, "max_depth": -1, "seed": 0},
        }
    )


def reference(scene, volume, spp: int = 512) -> np.ndarray:
    """volpath with Russian roulette off, at ``spp``, another seed than the graph render's."""
    ref = scene.model_copy(update={"render": scene.render.model_copy(update={"spp": spp, "seed": 1})})
    return render_volpath(ref, volume).astype(np.float64)


def render_march(cache, volume, scene, spp: int = 16) -> np.ndarray:
    from cloudgraph.render import GraphRenderer

    renderer = GraphRenderer(cache, volume, scene, estimator="march")
    return renderer.render(scene.camera, spp).astype(np.float64)


# ------------------------------------------------------------------ shared scenes


def kernels_compiled_by_the_second(first, second):
    """(results of first() and second(), the kernels second() compiled or loaded from Dr.Jit's
    disk cache that first() did not launch)."""
    import drjit as dr

    def jit_kernels():
        return [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]

    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # clears it
        a = first()
        known = {k["hash"] for k in jit_kernels()}
        b = second()
        launched = jit_kernels()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    assert launched, "the second call launched no kernel"
    # cache_hit is also set for kernels loaded from Dr.Jit's disk cache (cache_disk), so a kernel
    # seen for the first time in this process can look like a hit: compare hashes as well.
    new = [
        {key: k[key] for key in ("hash", "size", "cache_hit", "cache_disk", "operation_count")}
        for k in launched
        if k["hash"] not in known or not k["cache_hit"] or k["cache_disk"]
    ]
    return (a, b), new


def hg(g: float, mu):
    """The Henyey-Greenstein phase, per steradian (mu: cosine between the light's travel before
    and after scattering; g > 0 forward), written out here independently of the engine."""
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * np.asarray(mu)) ** 1.5)


def with_phase(scene, phase: dict, **render):
    medium = scene.medium.model_copy(update={"phase": PhaseSpec.model_validate(phase)})
    return scene.model_copy(update={"medium": medium, "render": scene.render.model_copy(update=render)})


def graph_renderer(cache, volume, scene) -> GraphRenderer:
    return GraphRenderer(cache, volume, scene)
