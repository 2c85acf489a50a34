"""L_dgrad (losses/depth_gradient.py): the rendered depth's log differences between neighbours
against the prior's. Its gradient against central differences, its invariance to a scale of
either side, that it sees a torn surface the per-pixel L_depth band lets through, the pixels it
ignores, extreme inputs, bad input."""
import numpy as np
import pytest

from render_fixtures import central_fd, wavy_depth, with_holes

from d2gs_np.losses.depth_gradient import depth_gradient_bwd, depth_gradient_fwd
from d2gs_np.losses.depth_prior import depth_prior_fwd

H, W = 9, 11


def _depth(seed=0, lo=1.5, hi=6.0):
    return wavy_depth((H, W), seed, lo, hi)


def test_gradient_matches_central_differences():
    # A prior that agrees with the render only in part, holes in both, a mask: every pair kind and
    # the 1/D factor are exercised. Central differences at h = 1e-6 on depths 1.5-6: the L1 is
    # piecewise linear in log D, so truncation is ~h^2 unless a pair's log difference lies within
    # the step's h / D < 1e-6 of 0 (none lies within 1e-5 here: checked below), rounding ~1e-16 / 1e-6 = 1e-10 against entries
    # ~1e-3..1e-1; 1e-7 relative to the largest catches a missing neighbour or factor.
    d = _depth(0)
    prior = 0.7 * d + 0.3 * np.roll(d, 3, axis=1) + 0.2
    prior, alpha = with_holes(prior, np.ones((H, W)))
    mask = np.ones((H, W))
    mask[:, :2] = 0.0
    weight = 0.37
    value, saved = depth_gradient_fwd(d, prior, alpha, mask=mask)
    r = np.log(d) - np.log(prior)
    assert np.nanmin(np.abs(np.diff(r, axis=1))) > 1e-5 and np.nanmin(np.abs(np.diff(r, axis=0))) > 1e-5
    g = depth_gradient_bwd(saved, weight)
    fd = central_fd(lambda x: weight * depth_gradient_fwd(x, prior, alpha, mask=mask)[0], d, 1e-6)
    assert np.max(np.abs(g - fd)) <= 1e-7 * np.max(np.abs(fd))
    assert np.all(g[:, :2] == 0.0) and np.all(g[~np.isfinite(prior)] == 0.0) and np.all(g[alpha < 0.5] == 0.0)


def test_value_is_the_mean_absolute_log_difference_over_pairs():
    # The obvious loop over pairs, written out.
    d = _depth(2)
    prior = d * np.exp(0.1 * np.random.default_rng(3).standard_normal((H, W)))
    prior[4, 5] = np.nan
    r = np.log(d) - np.log(prior)
    total, n = 0.0, 0
    for i in range(H):
        for j in range(W):
            for di, dj in ((0, 1), (1, 0)):
                a, b = (i, j), (i + di, j + dj)
                if b[0] < H and b[1] < W and np.isfinite(r[a]) and np.isfinite(r[b]):
                    total += abs(r[b] - r[a])
                    n += 1
    assert depth_gradient_fwd(d, prior, np.ones((H, W)))[0] == pytest.approx(total / n, rel=1e-12)


@pytest.mark.parametrize("a, b", [(1.0, 3.7), (2.5, 1.0), (1e-3, 1e4)])
def test_invariant_to_a_scale_of_either_side(a, b):
    d, prior = _depth(4), _depth(5)
    v0, s0 = depth_gradient_fwd(d, prior, np.ones((H, W)))
    v1, s1 = depth_gradient_fwd(a * d, b * prior, np.ones((H, W)))
    assert v1 == pytest.approx(v0, rel=1e-10)
    # the gradient on D scales as 1/a (dL/dD = dL/dr / D)
    assert np.allclose(depth_gradient_bwd(s1) * a, depth_gradient_bwd(s0), rtol=1e-9, atol=0)


def test_a_torn_surface_inside_the_prior_band_costs_here_and_not_in_l_depth():
    # A flat panel rendered as two patches 8 % apart in depth: within L_depth's 10 % tolerance, so
    # L_depth is 0; the pairs across the tear make L_dgrad positive, and its gradient pulls the two
    # patches together (nearer patch deeper, deeper patch nearer).
    prior = np.full((H, W), 2.0)
    d = np.full((H, W), 2.0)
    d[:, W // 2:] *= 1.08
    a = np.ones((H, W))
    assert depth_prior_fwd(d, prior, a, "depth", tolerance=0.1)[0] == 0.0
    value, saved = depth_gradient_fwd(d, prior, a)
    n = H * (W - 1) + (H - 1) * W
    assert value == pytest.approx(H * np.log(1.08) / n, rel=1e-12)
    g = depth_gradient_bwd(saved)
    assert np.all(g[:, W // 2 - 1] < 0) and np.all(g[:, W // 2] > 0)  # descent: -g moves them together
    assert np.all(g[:, : W // 2 - 1] == 0) and np.all(g[:, W // 2 + 1:] == 0)
    # the same depth step in the prior (a real edge) costs nothing
    assert depth_gradient_fwd(d, 3.0 * d, a)[0] == 0.0


def test_no_valid_pair_gives_zero_and_no_gradient():
    d = _depth(0)
    lone = np.full((H, W), np.nan)
    lone[::2, ::2] = 1.0  # valid pixels, none adjacent
    assert depth_gradient_fwd(d, lone, np.ones((H, W))) == (0.0, None)
    assert depth_gradient_bwd(None) is None
    assert depth_gradient_fwd(d, d, np.zeros((H, W))) == (0.0, None)  # transparent render
    assert depth_gradient_fwd(d, d, np.ones((H, W)), mask=np.zeros((H, W))) == (0.0, None)


def test_extreme_depths_and_priors_stay_finite():
    # Depths at the min_depth floor and huge, priors of 0 / negative / inf (ignored): finite output.
    d = _depth(0)
    d[0, 0], d[1, 1], d[2, 2] = 1e-12, 1e12, 0.0
    prior = d.copy()
    prior[3, 3], prior[4, 4], prior[5, 5] = 0.0, -1.0, np.inf
    v, s = depth_gradient_fwd(d, prior * 1.1, np.ones((H, W)))
    g = depth_gradient_bwd(s)
    assert np.isfinite(v) and v == pytest.approx(0.0, abs=1e-12) and np.all(np.isfinite(g))
    assert g[0, 0] == 0.0 and g[2, 2] == 0.0 and g[3, 3] == 0.0 and g[5, 5] == 0.0
    # float32 in, float32 cotangent out
    v32, s32 = depth_gradient_fwd(_depth(1).astype(np.float32), _depth(2).astype(np.float32),
                                  np.ones((H, W), np.float32))
    assert depth_gradient_bwd(s32).dtype == np.float32


@pytest.mark.parametrize("bad, match", [
    (dict(depth=np.ones((3,))), "depth must be an"),
    (dict(prior=np.ones((H, W + 1))), "prior must have the depth's shape"),
    (dict(alpha=np.ones((H + 1, W))), "alpha must have the depth's shape"),
    (dict(mask=np.ones((2, 2))), "mask must have the depth's shape"),
])
def test_bad_shapes_are_refused(bad, match):
    args = dict(depth=np.ones((H, W)), prior=np.ones((H, W)), alpha=np.ones((H, W)), mask=None)
    args.update(bad)
    with pytest.raises(ValueError, match=match):
        depth_gradient_fwd(args["depth"], args["prior"], args["alpha"], mask=args["mask"])
