"""Tests of the progressive-resolution schedule and the downsampled-target cache."""
from __future__ import annotations

import math

import numpy as np
import pytest

from d2gs_np.geometry.camera import make_intrinsics, scale_intrinsics, scaled_size
from d2gs_np.train.schedule import (
    SCHEDULE_KINDS,
    ScheduleConfig,
    TargetCache,
    downsample_area,
    downsample_mask,
    render_scale,
)

# Schedule values are a few float64 operations on O(1) numbers.
SCALE_ATOL = 1e-14
# Block means of O(1) values computed two ways in float64: a few ulps.
AREA_ATOL = 1e-14
# cv2.INTER_AREA uses float32 weights (1/3 -> 0.33333334): ~1e-8 relative against exact areas.
CV2_AREA_ATOL = 1e-7


@pytest.mark.parametrize("kind", SCHEDULE_KINDS)
@pytest.mark.parametrize("r0", [0.2, 0.5, 1.0])
def test_endpoints_and_monotone(kind, r0):
    total = 1000
    T = 500  # ramp_fraction 0.5
    values = np.array([render_scale(s, total, r0=r0, kind=kind) for s in range(total + 10)])
    assert values[0] == pytest.approx(r0, abs=SCALE_ATOL)
    assert values[T] == 1.0
    assert np.all(values[T:] == 1.0)
    assert np.all(np.diff(values) >= 0.0)
    assert np.all((values >= r0 - SCALE_ATOL) & (values <= 1.0))
    # approaches 1 continuously at the end of the ramp (no jump at step T): the steepest end
    # slope is inverse_sqrt's, dr/ds = (1/r0^2 - 1) / 2 = 12 for r0 = 0.2, i.e. 0.024 per step
    assert 1.0 - values[T - 1] < 0.03


def test_closed_forms_at_midpoint():
    r0 = 0.2
    mid = {k: render_scale(50, 200, r0=r0, kind=k) for k in SCHEDULE_KINDS}  # s = 0.5
    assert mid["cosine"] == pytest.approx(0.6, abs=SCALE_ATOL)
    assert mid["linear"] == pytest.approx(0.6, abs=SCALE_ATOL)
    assert mid["exponential"] == pytest.approx(math.sqrt(0.2), abs=SCALE_ATOL)
    assert mid["inverse_sqrt"] == pytest.approx(1.0 / math.sqrt(13.0), abs=SCALE_ATOL)
    # cosine: r0 + (1 - r0)(1 - cos(pi s))/2 at s = 0.25
    assert render_scale(25, 200, r0=r0) == pytest.approx(r0 + 0.8 * (1 - math.cos(math.pi / 4)) / 2, abs=SCALE_ATOL)


def test_ramp_fraction_and_config():
    assert render_scale(0, 100, ramp_fraction=0.0) == 1.0
    assert render_scale(99, 100, ramp_fraction=1.0, kind="linear") == pytest.approx(0.2 + 0.8 * 0.99)
    cfg = ScheduleConfig(r0=0.3, kind="linear", ramp_fraction=0.25)
    assert cfg.scale(10, 100) == pytest.approx(0.3 + 0.7 * 10 / 25)
    with pytest.raises(ValueError, match="kind must be one of"):
        ScheduleConfig(kind="step")
    with pytest.raises(ValueError, match="r0 must be"):
        ScheduleConfig(r0=0.0)
    with pytest.raises(ValueError, match="step must be >= 0"):
        render_scale(-1, 10)


def test_area_downsample_is_block_mean_for_integer_factors():
    rng = np.random.default_rng(0)
    img = rng.uniform(size=(24, 36, 3))
    for f in (2, 3, 4):
        out = downsample_area(img, 36 // f, 24 // f)
        block = img.reshape(24 // f, f, 36 // f, f, 3).mean(axis=(1, 3))
        np.testing.assert_allclose(out, block, rtol=0, atol=AREA_ATOL)
        assert out.dtype == np.float64
    gray = rng.uniform(size=(8, 8))
    np.testing.assert_allclose(downsample_area(gray, 4, 4), gray.reshape(4, 2, 4, 2).mean(axis=(1, 3)),
                               atol=AREA_ATOL)
    many = rng.uniform(size=(8, 8, 7)).astype(np.float32)  # > 4 channels, float32 kept
    out = downsample_area(many, 4, 4)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, many.reshape(4, 2, 4, 2, 7).mean(axis=(1, 3)), atol=1e-6)


def test_area_downsample_non_integer_matches_cv2_and_preserves_mean():
    import cv2

    rng = np.random.default_rng(1)
    img = rng.uniform(size=(30, 50, 3))
    out = downsample_area(img, 17, 11)
    assert out.shape == (11, 17, 3)
    np.testing.assert_allclose(out, cv2.resize(img, (17, 11), interpolation=cv2.INTER_AREA), atol=CV2_AREA_ATOL)
    # area resampling conserves the image mean (each input pixel's area is shared out exactly)
    np.testing.assert_allclose(out.mean(axis=(0, 1)), img.mean(axis=(0, 1)), atol=1e-12)
    with pytest.raises(ValueError, match="only shrinks"):
        downsample_area(img, 60, 30)


def test_mask_downsample_marks_any_moving_pixel():
    mask = np.zeros((8, 8), bool)
    mask[0, 0] = True  # a single moving pixel in the top-left 4x4 block
    low = downsample_mask(mask, 2, 2)
    np.testing.assert_array_equal(low, [[True, False], [False, False]])
    np.testing.assert_array_equal(downsample_mask(mask, 2, 2, threshold=0.5), np.zeros((2, 2), bool))


def test_target_cache():
    rng = np.random.default_rng(2)
    images = [rng.uniform(size=(20, 30, 3)) for _ in range(3)]
    masks = [rng.uniform(size=(20, 30)) > 0.7 for _ in range(3)]
    K = make_intrinsics(25.0, 24.0, 15.0, 10.0)
    cache = TargetCache(images, masks, K, max_entries=4)
    t = cache.get(1, 0.5)
    assert (t.width, t.height) == scaled_size(30, 20, 0.5) == (15, 10)
    assert cache.get(1, 0.5) is t  # same object on the second call
    np.testing.assert_allclose(t.image, images[1].reshape(10, 2, 15, 2, 3).mean(axis=(1, 3)), atol=AREA_ATOL)
    np.testing.assert_array_equal(t.mask, masks[1].reshape(10, 2, 15, 2).any(axis=(1, 3)))
    np.testing.assert_allclose(t.K, scale_intrinsics(K, 0.5, 0.5))
    full = cache.get(0, 1.0)
    assert full.image is images[0] and full.width == 30
    # a slightly different scale with the same rounded size hits the same entry
    assert cache.get(1, 0.51) is t
    # least-recently-used eviction beyond max_entries
    for s in (0.3, 0.4, 0.6, 0.7):
        cache.get(2, s)
    assert len(cache) == 4
    assert cache.get(1, 0.5) is not t
    with pytest.raises(ValueError, match="frame_index must be in"):
        cache.get(3, 0.5)
    with pytest.raises(ValueError, match="scale must be"):
        cache.get(0, 0.0)


# ------------------------------------------------------------- time-budgeted progress
def test_progress_without_a_budget_is_the_step_fraction_and_schedule_step_is_exact():
    from d2gs_np.train.schedule import schedule_step, training_progress

    for step in (0, 1, 499, 1000):
        assert training_progress(step, 1e9, 1000) == min(step / 1000, 1.0)
        assert schedule_step(step, 1e9, 1000) == step  # seconds ignored without a budget


def test_progress_with_a_budget_follows_whichever_ends_the_run_first():
    from d2gs_np.train.schedule import schedule_step, training_progress

    # the budget binds: 10 of 1000 steps in 30 of 60 s is half way
    assert training_progress(10, 30.0, 1000, 60.0) == 0.5
    assert schedule_step(10, 30.0, 1000, 60.0) == 500
    # the steps bind: 900 steps in 6 of 60 s
    assert training_progress(900, 6.0, 1000, 60.0) == 0.9
    assert schedule_step(900, 6.0, 1000, 60.0) == 900
    # over budget: clamped to the end, never past total_steps; at time 0 exactly the step
    assert training_progress(10, 120.0, 1000, 60.0) == 1.0 and schedule_step(10, 120.0, 1000, 60.0) == 1000
    assert schedule_step(0, 0.0, 1000, 60.0) == 0
    with pytest.raises(ValueError, match="time_budget"):
        training_progress(1, 1.0, 10, 0.0)
    with pytest.raises(ValueError, match="total_steps"):
        training_progress(1, 1.0, 0)
