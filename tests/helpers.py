"""Independent expectations for tests: camera rays and ray-box chords computed in numpy."""

from __future__ import annotations

import numpy as np


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
