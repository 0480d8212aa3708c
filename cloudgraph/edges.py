"""Edges of a noise-free frame at few samples a pixel, found and refined (numpy).

The ``field`` estimator has no noise of its own: at one sample a pixel it marches one ray
through each pixel's centre, and where a rim is thinner than a pixel (a back-lit cloud's bright
silhouette) that one ray is the pixel's value, however little of the pixel the rim covers. The
box-filtered truth averages the pixel. Such pixels bend sharply against their neighbours; they
are found on the frame itself and marched again at the centres of REFINE_SIDE x REFINE_SIDE strata,
whose mean replaces them (render.py, ``GraphRenderer.render``). docs/method.md, "Edges at a few
samples a pixel".
"""

from __future__ import annotations

import numpy as np

#: Strata per side of a refined pixel: 3 x 3 rays (2 x 2 leave the bench's back-lit rims 2-3
#: points from the antialiased image; 4 x 4 cost 40 % more for a few tenths of a point).
REFINE_SIDE = 3
#: A pixel is refined where its luminance's second difference along a row, a column or a
#: diagonal exceeds this fraction of the frame's bright end (its 99th percentile of luminance):
#: a step or a thin rim has one, a smooth gradient, however steep, has none (its pixel's centre
#: is its mean).
REFINE_CONTRAST = 0.1
#: At most this fraction of a frame's pixels is refined, those that bend most: a frame costs at
#: most 1 + REFINE_MAX REFINE_SIDE² rays a pixel (the bench's 64² frames refine 4-18 %; a
#: small cloud seen through a coarse field can bend at most pixels).
REFINE_MAX = 0.25


def edge_pixels(image: np.ndarray, contrast: float = REFINE_CONTRAST, most: float = REFINE_MAX) -> np.ndarray:
    """(H, W) bool: the pixels of an (H, W, C) frame where the luminance (the channels' mean)
    bends: |y(p - s) - 2 y(p) + y(p + s)| over ``contrast`` times the frame's 99th percentile of
    luminance, for s one pixel along a row, a column or either diagonal (the frame's border
    repeated past it); the ``most`` fraction of the pixels that bend most where more do. A frame
    without light has none."""
    image = np.asarray(image)
    # (the channels summed one by one: numpy's mean over a short last axis took 7 ms of a fresh
    # 256² frame, more than the rest of this function)
    y = sum(image[..., c].astype(np.float64) for c in range(image.shape[-1])) / image.shape[-1]
    scale = float(np.percentile(y, 99))
    if not scale > 0.0:
        return np.zeros(y.shape, bool)
    p = np.pad(y, 1, mode="edge")
    h, w = y.shape

    def shifted(dy, dx):
        return p[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]

    bend = np.zeros_like(y)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):  # four directions, as shifted views
        bend = np.maximum(bend, np.abs(shifted(dy, dx) + shifted(-dy, -dx) - 2.0 * y))
    mask = bend > contrast * scale
    cap = int(most * bend.size)
    if mask.sum() > cap:  # the sharpest first
        mask = np.zeros(bend.shape, bool)
        if cap:
            mask.flat[np.argpartition(bend.ravel(), bend.size - cap)[bend.size - cap :]] = True
    return mask


def refine_lanes(
    width: int, height: int, side: int = REFINE_SIDE, most: float = REFINE_MAX, centre: bool = False
) -> int:
    """The rays of the most a frame of width x height pixels refines (:func:`edge_pixels`);
    ``centre``: the middle stratum is the frame's own ray (:func:`strata_positions`)."""
    return max(int(most * width * height), 1) * (side * side - int(centre))


#: Lanes in a run of the refinement's rays (:func:`spread_lanes`): whole packets of the widest SIMD.
REFINE_RUN = 256


def spread_lanes(n: int, lanes: int, run: int = REFINE_RUN) -> np.ndarray:
    """(n,) the lanes of n rays in a kernel of ``lanes`` (>= n, :func:`refine_lanes`): runs of
    ``run`` consecutive lanes, the runs' starts spread evenly over the width. Dr.Jit splits a
    kernel's width among its threads in contiguous blocks; rays packed at the front would all
    fall to one thread."""
    i = np.arange(n)
    runs = -(-n // run)
    spacing = lanes // max(runs, 1)
    if spacing < run:  # (nearly every lane taken: one block of them)
        return i
    starts = np.arange(runs) * spacing // run * run
    return starts[i // run] + i % run


def strata_positions(mask: np.ndarray, side: int = REFINE_SIDE, centre: bool = False) -> np.ndarray:
    """(n side², 2) float32 film positions in [0, 1]² (x right, y down, as Mitsuba's sensors
    take them) of the centres of side x side strata in each of the n pixels of ``mask``
    (row-major), pixel after pixel. ``centre`` (an odd ``side``): without the middle stratum,
    whose centre is the pixel's, where a frame of one sample a pixel marched it already
    (n (side² - 1) positions)."""
    h, w = mask.shape
    py, px = np.nonzero(mask)
    u = (np.arange(side) + 0.5) / side
    sy, sx = np.meshgrid(u, u, indexing="ij")  # (side, side) offsets in a pixel
    if centre:
        keep = np.arange(side * side) != side * side // 2
        sy, sx = sy.reshape(-1)[keep], sx.reshape(-1)[keep]
    x = (px[:, None] + sx.reshape(1, -1)) / w
    y = (py[:, None] + sy.reshape(1, -1)) / h
    return np.stack([x.reshape(-1), y.reshape(-1)], axis=-1).astype(np.float32)


def refined(image: np.ndarray, mask: np.ndarray, samples: np.ndarray, centre: bool = False) -> np.ndarray:
    """``image`` with the pixels of ``mask`` replaced by the mean of their ``samples``: (n k, C)
    values at :func:`strata_positions` ``(mask, centre=centre)``, k per pixel (a box filter, as
    the film's); ``centre``: the pixel's own value is one more, its middle stratum's."""
    out = np.array(image, copy=True)
    n = int(mask.sum())
    values = np.asarray(samples, np.float64).reshape(n, -1, out.shape[-1])
    total, k = values.sum(axis=1), values.shape[1]
    if centre:
        total, k = total + out[mask], k + 1
    out[mask] = total / k
    return out
