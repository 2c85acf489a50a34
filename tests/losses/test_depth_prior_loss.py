"""L_depth (losses/depth_prior.py): the rendered depth against a depth prior, invariant to what the
prior's kind leaves unknown (a scale for a depth, a scale and shift for a disparity). Its gradient
against central differences in both spaces, its invariances (and the shift a depth prior does
fix), the pixels it ignores, flat and extreme inputs, bad input."""
import numpy as np
import pytest

from render_fixtures import central_fd, wavy_depth, with_holes

from d2gs_np.losses.depth_prior import depth_prior_bwd, depth_prior_fwd

H, W = 9, 11


def _depth(seed=0, lo=1.5, hi=6.0):
    return wavy_depth((H, W), seed, lo, hi)


_TOL_MAP = np.where(np.arange(W)[None, :] < W // 2, 0.0, 0.05) * np.ones((H, 1))  # a pixel's own tau


@pytest.mark.parametrize("space, tol", [("depth", 0.0), ("depth", 0.05), ("metric", 0.0), ("metric", 0.05),
                                        ("disparity", 0.0), ("depth", _TOL_MAP), ("metric", _TOL_MAP)],
                         ids=["depth-0", "depth-0.05", "metric-0", "metric-0.05", "disparity", "depth-map", "metric-map"])
def test_gradient_matches_central_differences(space, tol):
    # The render's depth and a prior that agrees with it only in part: every factor of the
    # gradient is exercised. Central differences at h = 1e-6 on depths 1.5-6: truncation ~h^2
    # (0 for the L1, piecewise linear in log D: no pixel's log ratio lies within 1e-6 of the
    # frame mean here), rounding ~1e-16 / 1e-6 = 1e-10 against gradients ~1e-3..1e-1 per pixel;
    # 1e-7 relative to the largest catches a missing term (the floor's, the mean's) or factor.
    d = _depth(0)
    truth = 1.0 / d if space == "disparity" else d
    prior = 0.7 * truth + 0.3 * np.roll(truth, 3, axis=1) + 0.2
    prior, alpha = with_holes(prior, np.ones((H, W)))
    mask = np.ones((H, W))
    mask[:, :2] = 0.0
    weight = 0.37

    def value(x):
        return weight * depth_prior_fwd(x, prior, alpha, space, mask=mask, tolerance=tol)[0]

    v, saved = depth_prior_fwd(d, prior, alpha, space, mask=mask, tolerance=tol)
    assert 0.01 < v < 0.6
    if space != "disparity":
        valid = np.isfinite(prior) & (alpha >= 0.5) & (mask > 0)
        r = np.log(d[valid] / prior[valid])
        r = r - r.mean() if space == "depth" else r
        tv = np.broadcast_to(tol, (H, W))[valid]
        assert np.min(np.abs(np.abs(r) - tv)) > 1e-4  # away from the kinks
        assert np.all(tv == 0) or 0 < np.mean(np.abs(r) < tv) < 1  # some pixels within tau
    g = depth_prior_bwd(saved, weight)
    fd = central_fd(value, d, 1e-6)
    assert np.max(np.abs(g - fd)) < 1e-7 * np.max(np.abs(fd))
    ignored = ~np.isfinite(prior) | (alpha < 0.5) | (mask == 0)
    assert np.all(g[ignored] == 0.0) and np.any(g[~ignored] != 0.0)


def test_departures_within_the_tolerance_cost_nothing():
    d = _depth(11)
    alpha = np.ones((H, W))
    ripple = 0.04 * np.sin(np.arange(W) / 1.7)[None, :] * np.ones((H, 1))
    prior = 2.5 * d * np.exp(ripple)  # the ratios off by at most 4 % (+ the mean's shift)
    v, saved = depth_prior_fwd(d, prior, alpha, tolerance=0.1)
    assert v == 0.0 and np.all(depth_prior_bwd(saved) == 0.0)
    v0 = depth_prior_fwd(d, prior, alpha, tolerance=0.0)[0]
    assert v0 > 0.01
    # beyond it, the excess only: a 30 % step on half the frame
    far = prior * np.where(np.arange(W)[None, :] < W // 2, 1.0, 1.3)
    v1 = depth_prior_fwd(d, far, alpha, tolerance=0.1)[0]
    assert 0.0 < v1 < depth_prior_fwd(d, far, alpha, tolerance=0.0)[0] - 0.05
    with pytest.raises(ValueError, match="tolerance must be >= 0"):
        depth_prior_fwd(d, prior, alpha, tolerance=-0.1)


def test_a_depth_prior_fixes_the_ratios_up_to_a_scale():
    d = _depth(2)
    prior = d * np.exp(0.1 * np.sin(np.arange(W) / 2.0))[None, :]
    alpha = np.ones((H, W))
    v = depth_prior_fwd(d, prior, alpha)[0]
    assert v > 0.01
    for a in (3.0, 0.01, 1e5):  # exact in logs: log a cancels with the frame mean
        assert depth_prior_fwd(a * d, prior, alpha)[0] == pytest.approx(v, abs=1e-12)
        assert depth_prior_fwd(d, a * prior, alpha)[0] == pytest.approx(v, abs=1e-12)
    assert depth_prior_fwd(d, 4.0 * d, alpha)[0] == pytest.approx(0.0, abs=1e-12)
    # a shift changes the ratios, so it costs: a scene whose depth range is stretched is not free
    assert depth_prior_fwd(d + 2.0, d, alpha)[0] > 0.05
    assert depth_prior_fwd(d, d + 2.0, alpha)[0] > 0.05


def test_a_metric_prior_pulls_the_depth_itself_a_frame_wide_bias_included():
    d = _depth(5)
    alpha = np.ones((H, W))
    assert depth_prior_fwd(d, d, alpha, "metric")[0] == 0.0
    # 20 % too far everywhere: free for the "depth" kind, |log 1.2| - tau for "metric"
    assert depth_prior_fwd(1.2 * d, d, alpha, "depth")[0] == pytest.approx(0.0, abs=1e-12)
    v, saved = depth_prior_fwd(1.2 * d, d, alpha, "metric", tolerance=0.05)
    assert v == pytest.approx(np.log(1.2) - 0.05, rel=1e-12)
    g = depth_prior_bwd(saved)
    assert np.all(g > 0)  # every pixel pulled nearer
    np.testing.assert_allclose(g, 1.0 / (d.size * 1.2 * d), rtol=1e-12)
    # within the tolerance: nothing
    v, saved = depth_prior_fwd(1.04 * d, d, alpha, "metric", tolerance=0.05)
    assert v == 0.0 and np.all(depth_prior_bwd(saved) == 0.0)


def test_a_disparity_prior_is_matched_up_to_scale_and_shift():
    d = _depth(2)
    prior = 0.5 / d + 0.1 / _depth(3)
    alpha = np.ones((H, W))
    v = depth_prior_fwd(d, prior, alpha, "disparity")[0]
    assert v > 0.001
    # exact but for the flat floor, k mean^2 / variance of the moved side (here at most ~10^2,
    # so ~1e-10)
    for a, b in ((3.0, 0.0), (0.01, 0.005), (1e5, -7.0)):
        assert depth_prior_fwd(d / a, prior, alpha, "disparity")[0] == pytest.approx(v, abs=1e-7)
        assert depth_prior_fwd(d, a * prior + b, alpha, "disparity")[0] == pytest.approx(v, abs=1e-7)
    # a prior that is the disparity up to scale and shift costs nothing; reversed, the most
    assert depth_prior_fwd(d, 4.0 / d - 1.0, alpha, "disparity")[0] == pytest.approx(0.0, abs=1e-7)
    assert depth_prior_fwd(d, -1.0 / d, alpha, "disparity")[0] == pytest.approx(2.0, abs=1e-7)


def test_ignored_pixels_do_not_change_the_value():
    d = _depth(4)
    prior, alpha = with_holes(0.8 * d + 0.3 * _depth(5), np.ones((H, W)))
    v = depth_prior_fwd(d, prior, alpha)[0]
    assert v == depth_prior_fwd(d, np.where(alpha < 0.5, -1.0, prior), alpha)[0]  # no estimate, or no render
    other = d.copy()
    bad = ~np.isfinite(prior) | (alpha < 0.5)
    other[bad] = 100.0 * np.random.default_rng(0).random(bad.sum())
    assert depth_prior_fwd(other, prior, alpha)[0] == v


def test_flat_sides_and_too_few_pixels_are_finite():
    d = _depth(6)
    alpha = np.ones((H, W))
    flat = np.full((H, W), 3.0)
    for space, prior in (("depth", d), ("disparity", 1.0 / d)):
        # a flat render: the prior's own spread (depth) or no correlation (disparity), and a finite
        # gradient that raises the depth where the prior is far
        v, saved = depth_prior_fwd(flat, prior, alpha, space)
        g = depth_prior_bwd(saved)
        assert np.all(np.isfinite(g))
        assert v == pytest.approx(np.mean(np.abs(np.log(d) - np.log(d).mean())) if space == "depth" else 1.0, abs=1e-12)
        far = d > np.median(d)
        assert np.mean(-g[far]) > 0 > np.mean(-g[~far])
        v, saved = depth_prior_fwd(d, np.full((H, W), 0.5), alpha, space)  # a flat prior
        assert np.isfinite(v) and v > 0 and np.all(np.isfinite(depth_prior_bwd(saved)))
    # one valid pixel, or none, or a prior of zeros: no value and no gradient
    one = np.full((H, W), np.nan)
    one[2, 3] = 1.0
    assert depth_prior_fwd(d, one, alpha) == (0.0, None) and depth_prior_bwd(None) is None
    assert depth_prior_fwd(d, d, np.zeros((H, W))) == (0.0, None)
    assert depth_prior_fwd(d, np.zeros((H, W)), alpha) == (0.0, None)  # no positive depth to compare
    assert depth_prior_fwd(d, np.zeros((H, W)), alpha, "disparity") == (0.0, None)


@pytest.mark.parametrize("scale", [1e-4, 1e6])
def test_tiny_and_huge_depths_give_the_same_value_and_a_scaled_gradient(scale):
    d = _depth(7)
    prior = 0.6 * d + 0.2 * _depth(8)
    alpha = np.ones((H, W))
    v, s = depth_prior_fwd(d, prior, alpha)
    vs, ss = depth_prior_fwd(scale * d, prior, alpha, min_depth=0.0)
    assert vs == pytest.approx(v, abs=1e-12)
    np.testing.assert_allclose(depth_prior_bwd(ss) * scale, depth_prior_bwd(s), rtol=1e-6, atol=1e-12)
    # in disparity space too (1/D spans 1e-6 .. 1e4)
    vd, sd = depth_prior_fwd(scale * d, 1.0 / d, alpha, "disparity", min_depth=0.0)
    assert vd == pytest.approx(0.0, abs=1e-9) and np.all(np.isfinite(depth_prior_bwd(sd)))


def test_float32_renders_get_a_float32_gradient_close_to_float64():
    d = _depth(9)
    prior = 0.8 * d + 0.4 * _depth(10)
    alpha = np.ones((H, W))
    g64 = depth_prior_bwd(depth_prior_fwd(d, prior, alpha)[1])
    g32 = depth_prior_bwd(depth_prior_fwd(d.astype(np.float32), prior, alpha)[1])
    assert g32.dtype == np.float32
    # the float32 input rounds depths by ~6e-8 relative; the statistics are taken in float64
    np.testing.assert_allclose(g32, g64, rtol=1e-4, atol=1e-6 * np.abs(g64).max())


def test_bad_input_is_refused_with_what_to_fix():
    d = _depth(0)
    alpha = np.ones((H, W))
    with pytest.raises(ValueError, match="prior must have the depth's shape"):
        depth_prior_fwd(d, d[:-1], alpha)
    with pytest.raises(ValueError, match="depth must be an \\(h, w\\) array"):
        depth_prior_fwd(d[None], d, alpha)
    with pytest.raises(ValueError, match="space must be one of"):
        depth_prior_fwd(d, d, alpha, "inverse")
    with pytest.raises(ValueError, match="tolerance must have the depth's shape"):
        depth_prior_fwd(d, d, alpha, tolerance=np.zeros((H, W + 1)))
    with pytest.raises(ValueError, match="one number or an \\(h, w\\) map"):
        depth_prior_fwd(d, d, alpha, tolerance=np.zeros(W))
    bad = np.zeros((H, W))
    bad[2, 3] = np.nan
    with pytest.raises(ValueError, match="tolerance must be >= 0 .* at every pixel; got a map holding nan"):
        depth_prior_fwd(d, d, alpha, tolerance=bad)


def test_a_tolerance_map_is_each_pixels_own_tolerance():
    # a prior 6 % off on the left half, exact on the right ("metric": no frame mean): with tau 0.1
    # on the left nothing is pulled anywhere; with tau 0 on the left exactly the left is pulled,
    # by log 1.06 a pixel, whatever the right half's tau
    d = _depth(4)
    alpha = np.ones((H, W))
    left = np.broadcast_to(np.arange(W)[None, :] < W // 2, (H, W))
    prior = d * np.where(left, 1.06, 1.0)
    v_loose, s_loose = depth_prior_fwd(d, prior, alpha, "metric", tolerance=np.where(left, 0.1, 0.0))
    v_tight, s_tight = depth_prior_fwd(d, prior, alpha, "metric", tolerance=np.where(left, 0.0, 0.1))
    assert v_loose == 0.0 and np.all(depth_prior_bwd(s_loose) == 0.0)
    assert v_tight == pytest.approx(left.sum() * np.log(1.06) / (H * W), rel=1e-12)
    g = depth_prior_bwd(s_tight)
    assert np.all(g[left] < 0.0) and np.all(g[~left] == 0.0)  # the left pulled deeper, toward its prior
    # one number and a map holding it everywhere are the same term
    v1, s1 = depth_prior_fwd(d, prior, alpha, "depth", tolerance=0.02)
    v2, s2 = depth_prior_fwd(d, prior, alpha, "depth", tolerance=np.full((H, W), 0.02))
    assert v1 == v2 and np.array_equal(depth_prior_bwd(s1), depth_prior_bwd(s2))
