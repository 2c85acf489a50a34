"""Depth priors aligned to static points (scene/depth_prior.py): exact recovery, outliers, and
the cases that cannot be aligned (too few points, a constant prior, a prior of the other kind)."""
import numpy as np
import pytest

from d2gs_np.scene.depth_prior import align_depth_prior, align_depth_scale, fit_scale_shift

# Noise-free data: the centred normal equations recover a and b to rounding, ~1e-15 relative on
# values of order 1; 1e-10 leaves room for the division by the spread of x.
EXACT_TOL = 1e-10
H, W = 30, 40


def _plane_depth():
    """A floor-like depth map: 2 at the bottom row to 6 at the top, so static points span depths."""
    rows = np.arange(H, dtype=np.float64)[:, None]
    return np.broadcast_to(6.0 - 4.0 * rows / (H - 1), (H, W)).copy()


def _points(rng, depth, n):
    uv = np.stack([rng.uniform(0, W, n), rng.uniform(0, H, n)], axis=1)
    z = depth[np.floor(uv[:, 1]).astype(int), np.floor(uv[:, 0]).astype(int)]
    return uv, z


def test_fit_scale_shift_is_exact_on_a_line_and_ignores_a_third_of_outliers():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.1, 2.0, 300)
    y = 0.7 * x + 0.25
    a, b, inl = fit_scale_shift(x, y)
    assert abs(a - 0.7) < EXACT_TOL and abs(b - 0.25) < EXACT_TOL and inl.all()
    bad = rng.random(300) < 1 / 3
    y_bad = np.where(bad, rng.uniform(-3, 3, 300), y + 1e-3 * rng.normal(size=300))
    a, b, inl = fit_scale_shift(x, y_bad)
    # 1e-3 noise on 200 good points: the refit's scale error ~ 1e-3 / (spread of x sqrt 200) ~ 1e-4
    assert abs(a - 0.7) < 2e-3 and abs(b - 0.25) < 2e-3
    assert inl[~bad].mean() > 0.95 and inl[bad].mean() < 0.1


@pytest.mark.parametrize("x", [np.full(50, 0.4), np.array([1.0, 1.0])])
def test_a_prior_that_does_not_vary_has_no_scale(x):
    # rank-deficient: every x equal (a constant prior), or fewer than three points
    assert fit_scale_shift(x, np.linspace(0.1, 0.2, x.size)) is None


def test_a_disparity_prior_is_aligned_to_the_points_exactly():
    rng = np.random.default_rng(1)
    depth = _plane_depth()
    prior = 3.0 / depth + 0.4  # a disparity up to the scale 3 and the shift 0.4
    prior[5, 7] = np.nan
    uv, z = _points(rng, depth, 200)
    aligned, info = align_depth_prior(prior, uv, z, "disparity", min_points=20)
    assert np.isnan(aligned[5, 7])  # no estimate stays no estimate
    ok = np.isfinite(prior)
    np.testing.assert_allclose(aligned[ok], depth[ok], rtol=EXACT_TOL)
    assert abs(info["scale"] - 1 / 3.0) < EXACT_TOL and info["rel_error"] < EXACT_TOL and info["points"] == 200


def test_a_depth_prior_with_a_shift_is_aligned_in_depth_space():
    rng = np.random.default_rng(2)
    depth = _plane_depth()
    uv, z = _points(rng, depth, 100)
    aligned, info = align_depth_prior(0.5 * depth - 0.3, uv, z, "depth", min_points=20)
    np.testing.assert_allclose(aligned, depth, rtol=EXACT_TOL)


def test_a_depth_given_as_a_disparity_is_refused_with_the_setting_to_change():
    rng = np.random.default_rng(3)
    depth = _plane_depth()
    uv, z = _points(rng, depth, 100)
    aligned, info = align_depth_prior(depth.copy(), uv, z, "disparity", min_points=20)
    assert aligned is None and info["scale"] < 0
    assert "is the prior a depth? (InitConfig.depth_prior_space = 'depth')" in info["reason"]


def test_too_few_points_or_a_constant_prior_leave_the_frame_unaligned():
    rng = np.random.default_rng(4)
    depth = _plane_depth()
    uv, z = _points(rng, depth, 10)
    aligned, info = align_depth_prior(1.0 / depth, uv, z, "disparity", min_points=20)
    assert aligned is None and "10 static points" in info["reason"]
    uv, z = _points(rng, depth, 100)
    aligned, info = align_depth_prior(np.full((H, W), 0.3), uv, z, "disparity", min_points=20)
    assert aligned is None and "does not vary" in info["reason"]
    # points outside the image, behind the camera or at a NaN prior pixel do not count
    uv_out = np.concatenate([uv, [[-1.0, 3.0], [W + 0.5, 2.0]]])
    z_out = np.concatenate([z, [4.0, 4.0]])
    z_out[0] = -1.0
    prior = 1.0 / depth
    cell = np.floor(uv[1, ::-1]).astype(int)
    prior[cell[0], cell[1]] = np.nan
    in_cell = np.all(np.floor(uv[1:, ::-1]).astype(int) == cell, axis=1).sum()  # point 1 and any sharing its pixel
    _, info = align_depth_prior(prior, uv_out, z_out, "disparity", min_points=20)
    assert info["points"] == 100 - 1 - in_cell


def test_a_video_prior_gets_one_scale_for_the_clip_despite_wrong_points():
    rng = np.random.default_rng(5)
    depths = [_plane_depth() * s for s in (1.0, 1.1, 0.9)]
    priors = [d / 2.5 for d in depths]  # depth up to the clip's scale 2.5
    uvs, zs = [], []
    for d in depths:
        uv, z = _points(rng, d, 80)
        wrong = rng.random(80) < 0.3  # points at a wrong depth (mismatched stereo)
        zs.append(np.where(wrong, z * rng.uniform(0.3, 3.0, 80), z))
        uvs.append(uv)
    scale, info = align_depth_scale(priors, uvs, zs, min_points=20)
    # the median ignores the 30 % wrong: exactly 2.5 when the right points are the majority on both sides
    assert abs(scale - 2.5) < 1e-9 and info["points"] == 240
    assert align_depth_scale(priors, [u[:5] for u in uvs], [z[:5] for z in zs], min_points=20)[0] is None
