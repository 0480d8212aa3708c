"""The field's grids: which points of the multiple-scattering grid a bake gathers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates, maximum_filter

from cloudgraph.field_grid import read_mask


def _read_by_interpolation(dense: np.ndarray, shape, samples: int, rng) -> np.ndarray:
    """(mz, my, mx) bool: the points of a grid of ``shape`` (mx, my, mz) that trilinear
    interpolation (clamped, as a texture) gives a weight at random points of the unit cube
    where the fine grid's interpolation of ``dense`` is not zero: a brute force."""
    fine = np.array(dense.shape)
    u = rng.random((samples, 3))  # (z, y, x)
    value = map_coordinates(dense.astype(float), (u * fine - 0.5).T, order=1, mode="nearest")
    m = np.array(shape[::-1])
    c = u[value > 1e-9] * m - 0.5
    lo = np.floor(c).astype(int)
    frac = c - lo
    read = np.zeros(tuple(m), bool)
    for corner in np.ndindex(2, 2, 2):
        weight = np.prod(np.where(np.array(corner) == 1, frac, 1.0 - frac), axis=1)
        idx = np.clip(lo + np.array(corner), 0, m - 1)[weight > 1e-9]
        read[tuple(idx.T)] = True
    return read


@pytest.mark.parametrize("fine, k", [((20, 17, 23), 1), ((20, 17, 23), 2), ((31, 29, 40), 3)])
def test_the_bake_gathers_the_points_the_camera_reads_and_no_more(fine, k):
    # The field's L_ms is read by the camera's trilinear interpolation wherever the medium is;
    # the grid's points beyond that were gathered and walked for nothing (the held-out cloud's
    # 35 % more, docs/measurements.md "The gather at the points the camera reads").
    rng = np.random.default_rng(k)
    dense = np.zeros(fine, bool)
    dense[tuple(rng.integers(0, n, 40) for n in fine)] = True
    nz, ny, nx = fine
    shape = (-(-nx // k), -(-ny // k), -(-nz // k))
    mask = read_mask(dense, shape).reshape(shape[::-1])
    read = _read_by_interpolation(dense, shape, 400_000, rng)
    assert not (read & ~mask).any()  # every point read is gathered
    assert mask.sum() <= read.sum() * 1.05  # and hardly any other (where the sampled points miss
    # a corner of a weight near 0)
    if k == 1:  # at the field's own resolution: the field's points, one voxel about the medium
        np.testing.assert_array_equal(mask, maximum_filter(dense, size=3, mode="constant"))


def test_the_points_next_to_those_gathered_take_the_nearest_one_s_value():
    # The march reads L_ms at a segment's end up to a step past the medium: the grid's points
    # next to those gathered hold the nearest gathered one's value, the rest stay 0.
    from cloudgraph.field import _nearest_filled

    have = np.zeros((6, 6, 6), bool)
    have[2:4, 2:4, 2:4] = True
    values = np.where(have, np.arange(216, dtype=np.float32).reshape(6, 6, 6), 0)[..., None]
    shell = maximum_filter(have, size=3, mode="constant") & ~have
    out = _nearest_filled(values, have, shell)[..., 0]
    np.testing.assert_array_equal(out[have], values[have][:, 0])
    assert out[1, 1, 1] == values[2, 2, 2, 0] and out[4, 2, 3] == values[3, 2, 3, 0]
    assert not out[~(have | shell)].any()
