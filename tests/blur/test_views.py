"""Tests of the virtual-view counts (d2gs_np.blur.views): the "scale" and "length" schedules keep
neighbouring views within their spacing, the blur length in pixels, a frame's count by schedule,
and the backward's stratified draw of views."""
from __future__ import annotations

import numpy as np
import pytest

from d2gs_np.blur.config import BlurConfig
from d2gs_np.blur.views import backward_subset, blur_length_px, frame_views, views_at_scale, views_for_length
from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.gaussians import init_params


# ---------------------------------------------------------------------------------------------
# Virtual views per render scale (BlurConfig.n_schedule)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [2, 3, 5, 8, 16, 33])
def test_views_at_scale_keep_the_pixel_spacing_of_full_resolution(n):
    for r in np.linspace(0.05, 1.0, 96):
        m = views_at_scale(n, float(r), "scale")
        assert 2 <= m <= n
        # spacing of m views over a blur r*L long is at most the full-resolution spacing L / (n - 1) ...
        assert r / (m - 1) <= 1.0 / (n - 1) + 1e-12
        # ... and one view fewer would not be (m is the least such count), except at the floor of 2
        if m > 2:
            assert r / (m - 2) > 1.0 / (n - 1)
    assert views_at_scale(n, 1.0, "scale") == n
    assert views_at_scale(n, 0.3, "fixed") == n


def test_views_at_scale_examples_and_errors():
    assert [views_at_scale(8, r, "scale") for r in (0.2, 0.5, 1.0)] == [3, 5, 8]
    assert views_at_scale(1, 0.2, "scale") == 1  # no blur model stays a single sharp view
    for bad in (0.0, -0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="scale"):
            views_at_scale(8, bad, "scale")
    with pytest.raises(ValueError, match="n schedule"):
        views_at_scale(8, 0.5, "linear")



# ---------------------------------------------------------------------------------------------
# Virtual views per blur length (BlurConfig.n_schedule = "length")
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [3, 5, 8, 16])
@pytest.mark.parametrize("spacing", [0.5, 1.0, 2.5])
def test_views_for_length_keep_neighbouring_views_within_the_spacing(n, spacing):
    for L in np.linspace(0.0, 40.0, 161):
        m = views_for_length(n, float(L), spacing)
        assert 2 <= m <= n
        if m < n:  # not capped: the gap is at most the spacing, and one view fewer would exceed it
            assert L / (m - 1) <= spacing + 1e-12
            if m > 2:
                assert L / (m - 2) > spacing
    assert views_for_length(n, 1e6, spacing) == n


def test_views_for_length_examples_and_errors():
    assert [views_for_length(8, L, 1.0) for L in (0.0, 1.0, 2.5, 7.0, 20.0)] == [2, 2, 4, 8, 8]
    assert views_for_length(1, 50.0) == 1 and views_for_length(2, 50.0) == 2
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="length_px"):
            views_for_length(8, bad)
    with pytest.raises(ValueError, match="spacing_px"):
        views_for_length(8, 3.0, 0.0)
    with pytest.raises(ValueError, match="views_for_length"):
        views_at_scale(8, 0.5, "length")


def test_blur_length_of_a_sideways_camera_shift_is_f_times_shift_over_depth():
    K = np.array([[100.0, 0.0, 40.0], [0.0, 100.0, 30.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-0.3, 0.3, (500, 2)), np.full(500, 2.0)]  # a fronto-parallel plane, depth 2
    Ts, Te = np.eye(4), np.eye(4)
    Te[0, 3] = 0.05  # 5 cm sideways: every point moves f * 0.05 / 2 = 2.5 px
    assert blur_length_px(pts, pts, Ts, Te, K, 80, 60) == pytest.approx(2.5, rel=1e-12)
    assert blur_length_px(pts, pts, Ts, Ts, K, 80, 60) == 0.0  # zero-length exposure
    # an object moving 0.1 to the side under a still camera: 5 px
    assert blur_length_px(pts, pts + [0.1, 0.0, 0.0], Ts, Ts, K, 80, 60) == pytest.approx(5.0, rel=1e-12)
    # points behind either camera or outside the image do not count; none left gives 0
    behind = pts * [1, 1, -1]
    assert blur_length_px(behind, behind, Ts, Te, K, 80, 60) == 0.0
    far_off = pts + [10.0, 0.0, 0.0]
    assert blur_length_px(far_off, far_off, Ts, Te, K, 80, 60) == 0.0
    assert blur_length_px(np.zeros((0, 3)), np.zeros((0, 3)), Ts, Te, K, 80, 60) == 0.0
    # one stray point at the camera does not decide the length (99th percentile)
    stray = np.vstack([pts, [[0.0, 0.0, 1e-3]]])
    assert blur_length_px(stray, stray, Ts, Te, K, 80, 60) == pytest.approx(2.5, rel=1e-9)
    with pytest.raises(ValueError, match="means_start"):
        blur_length_px(pts, pts[:3], Ts, Te, K, 80, 60)



def test_frame_views_follow_the_schedule_and_the_longer_of_the_static_and_dynamic_blurs():
    K = np.array([[100.0, 0.0, 40.0], [0.0, 100.0, 30.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-0.3, 0.3, (200, 2)), np.full(200, 2.0)]  # fronto-parallel, depth 2
    movers = np.c_[rng.uniform(-0.2, 0.2, (20, 2)), np.full(20, 2.0)]
    deform = DeformConfig(degree=1, order=1)
    scene = init_params(plane, np.full((200, 3), 0.5), movers, np.full((20, 3), 0.5), deform)
    scene["dynamic.deform_means"][:, 0, 0] = 1.0  # the movers slide sideways, 1 unit per unit time
    static = {k: v for k, v in scene.items() if k.startswith("static.")}
    T, still = np.eye(4), np.zeros(6)
    shift = np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0])  # 5 cm sideways: f * 0.05 / 2 = 2.5 px

    def views(params, xi_end, tau, width=80, config=BlurConfig(num_virtual=8)):
        return frame_views(params, 0.5, tau, T, still, xi_end, K * (width / 80), width, 60 * width // 80, 80,
                           config, deform)

    assert views(static, still, 0.1) == 2  # no blur: the smallest n > 1
    assert views(static, shift, 0.1) == views_for_length(8, 2.5, 1.0) == 4
    # the movers blur by 50 px per unit time at depth 2 (5 px over tau = 0.1), plus the camera's
    # 2.5 px: the longer of the static and the dynamic blur decides
    assert views(scene, still, 0.0) == 2
    assert views(scene, still, 0.1) == views_for_length(8, 5.0, 1.0) == 6
    assert views(scene, shift, 0.02) == views_for_length(8, 2.5 + 1.0, 1.0) == 5  # the movers' blur
    assert views(scene, -shift, 0.02) == views_for_length(8, 2.5, 1.0) == 4  # the static blur (movers: 1.5 px)
    assert views(scene, shift, 0.1, config=BlurConfig(num_virtual=8, n_schedule="fixed"), width=40) == 8
    assert views(scene, shift, 0.1, config=BlurConfig(num_virtual=8, n_schedule="scale"), width=40) == \
        views_at_scale(8, 0.5, "scale") == 5


# ---------------------------------------------------------------------------------------------
# Backward through a subset of the views (BlurConfig.backward_views)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n, m", [(8, 2), (8, 3), (7, 3), (5, 2), (2, 1), (9, 4)])
def test_backward_subset_draws_one_view_per_run_weighted_by_the_run(n, m):
    rng = np.random.default_rng(0)
    edges = (np.arange(m + 1) * n) // m
    counts = np.zeros(n)
    for _ in range(400):
        idx, w = backward_subset(n, m, rng)
        assert idx.shape == w.shape == (m,)
        for j in range(m):  # one view from each run of neighbours, weighted by the run's share
            assert edges[j] <= idx[j] < edges[j + 1]
            assert w[j] == pytest.approx((edges[j + 1] - edges[j]) / n, rel=1e-15)
        assert w.sum() == pytest.approx(1.0, rel=1e-15)
        counts[idx] += 1
    assert np.all(counts > 0)  # every view is drawn sometimes
    assert set(np.diff(edges)) <= {n // m, -(-n // m)}  # runs as equal as they can be


@pytest.mark.parametrize("m", [0, 8, 11])
def test_backward_subset_of_all_views_is_the_exact_backward(m):
    idx, w = backward_subset(8, m, np.random.default_rng(0))
    np.testing.assert_array_equal(idx, np.arange(8))
    np.testing.assert_array_equal(w, np.full(8, 1 / 8))


def test_backward_subset_refuses_bad_counts():
    rng = np.random.default_rng(0)
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="views in the backward"):
            backward_subset(8, bad, rng)

