"""Edge refinement of ``field`` frames at few samples a pixel (cloudgraph/edges.py): which
pixels are refined, where their rays go, and the refined frame against the antialiased one,
with no kernel compiled for a moved camera."""

import numpy as np

from cloudgraph.edges import (
    REFINE_MAX,
    REFINE_RUN,
    edge_pixels,
    refine_lanes,
    refined,
    spread_lanes,
    strata_positions,
)
from cloudgraph.metrics import bias_metrics

from ..helpers import LIGHT, framed_camera, kernels_compiled_by_the_second


def _frame(y: np.ndarray) -> np.ndarray:
    return np.repeat(y[..., None], 3, axis=-1)


def test_a_step_and_a_thin_rim_bend_and_a_steep_smooth_gradient_does_not():
    h, w = 12, 32  # (7 of 32 columns bend: under the cap)
    y = np.ones((h, w))
    y[:, :6] = np.linspace(0.0, 1.0, 6)  # a ramp of 0.2 a pixel: steeper than the threshold
    y[:, 16] = 1.5  # a thin bright rim: the frame's bright end (the threshold 0.15)
    y[:, 20:] = 0.0  # a step down
    mask = edge_pixels(_frame(y))
    cols = np.nonzero(mask.any(axis=0))[0].tolist()
    # the ramp's inside is straight: only its ends bend (0, against the border repeated past
    # it, and 5, at the plateau); the rim with its two neighbours; both sides of the step
    assert cols == [0, 5, 15, 16, 17, 19, 20]
    assert mask[:, cols].all()  # whole columns: the frame is the same along them


def test_a_dark_frame_has_no_edges_and_a_busy_one_refines_its_sharpest_quarter():
    assert not edge_pixels(np.zeros((8, 8, 3))).any()
    rng = np.random.default_rng(1)
    y = rng.random((40, 40))
    mask = edge_pixels(_frame(y))
    assert mask.sum() == int(REFINE_MAX * y.size)
    p = np.pad(y, 1, mode="edge")
    bend = np.abs(p[1:-1, 2:] + p[1:-1, :-2] - 2 * y)  # (along rows: a lower bound of the bend)
    assert bend[mask].mean() > bend[~mask].mean()
    assert not edge_pixels(_frame(y[:1, :1])).any()  # one pixel: a quarter of it is none


def test_strata_positions_are_the_centres_of_each_refined_pixels_strata():
    mask = np.zeros((4, 5), bool)
    mask[1, 2] = mask[3, 0] = True
    pos = strata_positions(mask, side=3)
    assert pos.shape == (18, 2) and pos.dtype == np.float32
    u = np.array([1, 3, 5]) / 6
    np.testing.assert_allclose(pos[:9, 0], np.tile(2 + u, 3) / 5, rtol=1e-6)  # x fastest
    np.testing.assert_allclose(pos[:9, 1], np.repeat(1 + u, 3) / 4, rtol=1e-6)
    np.testing.assert_allclose(pos[9:, 0], np.tile(0 + u, 3) / 5, rtol=1e-6)
    np.testing.assert_allclose(pos[9:, 1], np.repeat(3 + u, 3) / 4, rtol=1e-6)


def test_at_one_sample_a_pixel_the_middle_stratum_is_the_frames_own_ray():
    mask = np.zeros((4, 5), bool)
    mask[1, 2] = mask[3, 0] = True
    every, without = strata_positions(mask, side=3), strata_positions(mask, side=3, centre=True)
    assert without.shape == (16, 2)
    # the pixel's centre, where a frame of one sample a pixel put its ray, is left out, the
    # other eight kept in order
    keep = np.arange(18) % 9 != 4
    np.testing.assert_array_equal(without, every[keep])
    np.testing.assert_allclose(every[~keep], [[2.5 / 5, 1.5 / 4], [0.5 / 5, 3.5 / 4]], rtol=1e-6)
    image = np.full((4, 5, 3), 9.0, np.float32)
    out = refined(image, mask, np.zeros((16, 3)), centre=True)  # its own value is one sample of 9
    np.testing.assert_allclose(out[mask], 1.0, rtol=1e-6)
    assert refine_lanes(8, 8, centre=True) == 16 * 8 and refine_lanes(8, 8) == 16 * 9


def test_refined_pixels_are_their_samples_mean_and_the_rest_are_kept():
    image = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    mask = np.zeros((2, 3), bool)
    mask[0, 1] = mask[1, 2] = True
    samples = np.concatenate([np.full((4, 3), 10.0), np.tile([[1.0, 2.0, 3.0], [3.0, 4.0, 5.0]], (2, 1))])
    out = refined(image, mask, samples)
    np.testing.assert_array_equal(out[0, 1], [10.0, 10.0, 10.0])
    np.testing.assert_array_equal(out[1, 2], [2.0, 3.0, 4.0])
    np.testing.assert_array_equal(out[~mask], image[~mask])


def _back_lit(volume, size=40):
    from cloudgraph.scene import CameraSpec

    return CameraSpec(**framed_camera(volume, eye_dir=LIGHT, size=size))


def test_one_sample_field_frames_are_refined_where_the_rim_is_thinner_than_a_pixel(sphere):
    from cloudgraph.render import GraphRenderer

    volume, scene, cache = sphere["volume"], sphere["scene"], sphere["cache"]
    r = GraphRenderer(cache, volume, scene, estimator="field")
    back = _back_lit(volume)
    antialiased = r.render(back, spp=64, seed=1)
    plain = r.render(back, spp=1, seed=1, refine=False)
    sharp = r.render(back, spp=1, seed=1)
    mask = edge_pixels(plain)
    # Measured: 1.02 % binned relMAE against the 64-sample frame, 0.23 % refined (a quarter of
    # the pixels, the cap: this small sphere through a draft field bends at many)
    assert 0 < mask.mean() <= REFINE_MAX
    np.testing.assert_array_equal(sharp[~mask], plain[~mask])
    before = bias_metrics(plain, antialiased)["binned_relMAE"]
    after = bias_metrics(sharp, antialiased)["binned_relMAE"]
    assert before > 0.007
    assert after < 0.004 and after < 0.35 * before
    # 9 samples a pixel are not refined again
    np.testing.assert_array_equal(r.render(back, spp=9, seed=1), r.render(back, spp=9, seed=1, refine=False))


def test_refining_a_moved_camera_launches_only_kernels_already_compiled(sphere):
    from cloudgraph.render import GraphRenderer

    volume, scene = sphere["volume"], sphere["scene"]
    r = GraphRenderer(sphere["cache"], volume, scene, estimator="field")
    back = _back_lit(volume)
    moved = back.model_copy(update={"eye": (30.0, 25.0, 45.0), "fov": 35.0})
    (first, second), new = kernels_compiled_by_the_second(
        lambda: r.render(back, spp=1, seed=1), lambda: r.render(moved, spp=1, seed=2)
    )
    a, b = r.render(back, 1, 1, refine=False), r.render(moved, 1, 2, refine=False)
    assert edge_pixels(a).sum() != edge_pixels(b).sum() > 0  # both refined, other ray counts
    assert np.abs(first - second).mean() > 0.1 * first.mean()  # the view did change
    assert not new, f"kernels compiled for the moved camera: {new}"


def test_the_refinements_rays_are_spread_over_the_kernels_width_in_whole_runs():
    for n, lanes in ((1, 9), (700, 9000), (5000, 147456), (1000, 1000), (1000, 1100)):
        lane = spread_lanes(n, lanes)
        assert len(np.unique(lane)) == n and lane.min() >= 0 and lane.max() < lanes
        assert np.all(np.diff(lane[: min(n, REFINE_RUN)]) == 1)  # a run is consecutive lanes
    lane = spread_lanes(5000, 147456)
    # Dr.Jit gives each thread a contiguous block of the width: each half holds about half
    assert abs(int((lane < 147456 // 2).sum()) - 2500) <= 2 * REFINE_RUN
