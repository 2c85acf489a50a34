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


# ---- fuse_depth_maps: the priors fused over the frames

def _rig(n=8, tilt=0.0):
    """n cameras 2 % of the depth apart along x, all facing a plane at depth 5 (``tilt``: its
    depth rising by that much per unit of x); the true depth map of each frame."""
    from d2gs_np.geometry.camera import make_intrinsics
    K = make_intrinsics(30.0, 30.0, W / 2, H / 2)
    poses, depths = [], []
    cols = np.arange(W) + 0.5
    rows = np.arange(H) + 0.5
    for i in range(n):
        T = np.eye(4)
        cx = 0.1 * (i - (n - 1) / 2)
        T[0, 3] = -cx  # the camera at (cx, 0, 0), looking down +z
        poses.append(T)
        # ray through a pixel: x = cx + (u - W/2) / f * z; the plane z = 5 + tilt * x
        a = (cols[None, :] - W / 2) / 30.0 + 0.0 * rows[:, None]
        depths.append((5.0 + tilt * cx) / (1.0 - tilt * a))
    return poses, [K] * n, depths


def _smooth_noise(rng, sigma):
    import cv2
    f = cv2.GaussianBlur(rng.normal(size=(H, W)), (0, 0), 4.0)
    return sigma * f / f.std()


def test_fused_maps_keep_an_exact_plane_and_average_independent_errors():
    from d2gs_np.scene.depth_prior import fuse_depth_maps
    poses, Ks, depths = _rig(tilt=0.2)
    # exact maps stay exact: the bilinear read of a slanted plane's log depth errs by its curvature
    # over a pixel, (tilt a / f)^2 / 8 ~ 1e-6 here; 1e-5 relative is the bound
    fused, info = fuse_depth_maps(depths, poses, Ks)
    for f, d in zip(fused, depths):
        assert np.nanmax(np.abs(f / d - 1.0)) < 1e-5
    assert info["views"] == 8 and info["fused_share"] > 0.9
    # independent smooth 10 % log errors per frame: the fused error's RMS near 0.1 / sqrt(8) ~ 0.035,
    # for the pixels every frame sees (the middle); 0.6 x the unfused RMS bounds it with room for the
    # edges' fewer views and the 2-sigma gate
    rng = np.random.default_rng(1)
    noisy = [d * np.exp(_smooth_noise(rng, 0.1)) for d in depths]
    fused, _ = fuse_depth_maps(noisy, poses, Ks, gate=0.5)
    mid = (slice(None), slice(W // 4, 3 * W // 4))
    before = np.sqrt(np.mean([np.mean(np.log(n / d)[mid] ** 2) for n, d in zip(noisy, depths)]))
    after = np.sqrt(np.mean([np.mean(np.log(f / d)[mid] ** 2) for f, d in zip(fused, depths)]))
    assert after < 0.6 * before, (before, after)
    # an error the frames share is not removed: the same field on every frame stays as it is
    shared = _smooth_noise(rng, 0.1)
    same = [d * np.exp(shared) for d in depths]
    fused, _ = fuse_depth_maps(same, poses, Ks, gate=0.5)
    after = np.sqrt(np.mean([np.mean(np.log(f / d)[mid] ** 2) for f, d in zip(fused, depths)]))
    assert after > 0.8 * np.sqrt(np.mean(shared[mid] ** 2))


def test_fusion_leaves_out_a_frame_off_by_more_than_the_gate_and_the_unusable_pixels():
    from d2gs_np.scene.depth_prior import fuse_depth_maps
    poses, Ks, depths = _rig(n=4)  # a fronto-parallel plane: the bilinear read is exact
    maps = [d.copy() for d in depths]
    maps[1] = 2.0 * maps[1]  # a frame twice too far (another surface): |log 2| > 0.3
    maps[2] = 1.1 * maps[2]  # one 10 % too far: within the gate, averaged in
    keep = np.ones((H, W), bool)
    keep[:, :5] = False  # frame 0's left columns may not be fused
    fused, _ = fuse_depth_maps(maps, poses, Ks, usable=[keep, None, None, None])
    inner = (slice(None), slice(W // 3, 2 * W // 3))  # seen by every frame
    np.testing.assert_allclose(fused[0][inner], depths[0][inner] * 1.1 ** (1 / 3), rtol=1e-12)
    np.testing.assert_array_equal(fused[0][:, :5], maps[0][:, :5])
    # a frame without a map is neither fused nor read; a NaN pixel stays NaN
    maps[3] = None
    maps[0][0, W // 2] = np.nan
    fused, _ = fuse_depth_maps(maps, poses, Ks)
    assert fused[3] is None and np.isnan(fused[0][0, W // 2])
    np.testing.assert_allclose(fused[0][1:, inner[1]], depths[0][1:, inner[1]] * 1.1 ** 0.5, rtol=1e-12)


def test_fusion_ignores_points_behind_another_camera_and_refuses_bad_input():
    from d2gs_np.scene.depth_prior import fuse_depth_maps
    poses, Ks, depths = _rig(n=2)
    back = np.diag([-1.0, 1.0, -1.0, 1.0])  # frame 1 turned round: the plane is behind it
    fused, info = fuse_depth_maps(depths, [poses[0], back @ poses[1]], Ks)
    np.testing.assert_array_equal(fused[0], depths[0])
    assert info["fused_share"] == 0.0 and np.all(np.isfinite(fused[1]))
    with pytest.raises(ValueError, match="gate must be > 0"):
        fuse_depth_maps(depths, poses, Ks, gate=0.0)
    with pytest.raises(ValueError, match="need as many poses"):
        fuse_depth_maps(depths, poses[:1], Ks)
    with pytest.raises(ValueError, match="mask 0 has shape"):
        fuse_depth_maps(depths, poses, Ks, usable=[np.ones((2, 2), bool), None])
