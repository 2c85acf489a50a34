"""Bundle adjustment (d2gs_np.pose.bundle): Jacobian against finite differences, recovery with outliers."""
import numpy as np
import pytest

from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.evaluation.metrics import ate
from d2gs_np.pose.bundle import (BundleProblem, bundle_adjust, params_to_poses, poses_to_params,
                                  reprojection_bwd, reprojection_fwd, reprojection_jacobian)


def _world(rng, C=6, P=120):
    """Cameras on a short sideways path looking at a cloud 4-6 units ahead; all points seen by all cameras."""
    pts = np.c_[rng.uniform(-2, 2, P), rng.uniform(-1.5, 1.5, P), rng.uniform(4, 6, P)]
    poses = np.stack([se3_exp(np.r_[-0.2 * c, 0.05 * rng.standard_normal(2), 0.03 * rng.standard_normal(3)])
                      for c in range(C)])
    f, cx, cy = 200.0, 120.0, 80.0
    cam_idx = np.repeat(np.arange(C), P)
    pt_idx = np.tile(np.arange(P), C)
    r, _ = reprojection_fwd(poses_to_params(poses), pts, f, cx, cy, cam_idx, pt_idx, np.zeros((C * P, 2)))
    return poses, pts, f, cx, cy, cam_idx, pt_idx, r  # r = projections (observations of zero)


def test_jacobian_matches_central_differences():
    rng = np.random.default_rng(0)
    poses, pts, f, cx, cy, ci, pi, uv = _world(rng, C=3, P=10)
    cams = poses_to_params(poses) + 0.05 * rng.standard_normal((3, 6))  # rotation vectors away from 0
    uv = uv + rng.standard_normal(uv.shape)
    free = np.array([1, 2])
    _, saved = reprojection_fwd(cams, pts, f, cx, cy, ci, pi, uv)
    J = reprojection_jacobian(saved, free, True).toarray()

    def flat(x):
        c = cams.copy()
        c[free] = x[:12].reshape(2, 6)
        return reprojection_fwd(c, x[12:42].reshape(10, 3), x[42], cx, cy, ci, pi, uv)[0].ravel()

    x0 = np.r_[cams[free].ravel(), pts.ravel(), f]
    # central differences, h = 1e-6: truncation O(h^2 |r'''|) ~ 1e-10 px, rounding ~ 1e-16 * 200 / 1e-6 ~ 2e-8
    h = 1e-6
    Jn = np.stack([(flat(x0 + h * e) - flat(x0 - h * e)) / (2 * h) for e in np.eye(x0.size)], axis=1)
    assert np.max(np.abs(J - Jn)) < 1e-5 * max(1.0, np.max(np.abs(Jn)))
    # the backward pass is J^T v on the full parameter set
    v = rng.standard_normal(uv.shape)
    v_cams, v_pts, v_f = reprojection_bwd(saved, v)
    Jall = reprojection_jacobian(saved, np.arange(3), True).toarray()
    g = Jall.T @ v.ravel()
    np.testing.assert_allclose(np.r_[v_cams.ravel(), v_pts.ravel(), v_f], g, rtol=1e-12, atol=1e-9)


def test_bundle_adjustment_recovers_poses_with_noise_and_outliers():
    """The pipeline's procedure (d2gs_np.video.sfm): a robust solve, residuals > 3 px dropped, a second solve."""
    rng = np.random.default_rng(1)
    poses, pts, f, cx, cy, ci, pi, uv = _world(rng, P=300)
    obs = uv + 0.3 * rng.standard_normal(uv.shape)  # 0.3 px noise
    out = rng.random(len(obs)) < 0.2  # 20 % outliers: anywhere within +-40 px
    obs[out] += rng.uniform(-40, 40, (out.sum(), 2))
    start = np.stack([se3_exp(0.05 * rng.standard_normal(6)) @ T for T in poses])
    start[0] = poses[0]
    pts0 = pts + 0.2 * rng.standard_normal(pts.shape)
    base = ate(start, poses)

    def solve(loss):
        cams, P, _, info = bundle_adjust(BundleProblem(poses_to_params(start), pts0, f, cx, cy, ci, pi, obs),
                                         loss=loss, max_nfev=100)
        keep = info["residual_px"] < 3.0
        cams, _, _, info = bundle_adjust(BundleProblem(cams, P, f, cx, cy, ci[keep], pi[keep], obs[keep]),
                                         loss=loss, max_nfev=100)
        return ate(params_to_poses(cams), poses), info, keep

    err, info, keep = solve("soft_l1")
    spread = np.ptp(poses[:, :3, 3], axis=0).max()
    assert err < 0.01 * spread and err < 0.2 * base, (err, base)
    assert info["median_px"] < 0.45  # inliers fit to the noise level (median of |r| for 0.3 px: 0.35)
    assert np.mean(keep[out]) < 0.1 and np.mean(keep[~out]) > 0.9  # outliers found, inliers kept
    # plain least squares is pulled off by the outliers: the robust loss is what makes it work
    err_l2, _, _ = solve("linear")
    assert err_l2 > 2 * err


def test_bundle_adjustment_refines_the_focal_length():
    rng = np.random.default_rng(2)
    poses, pts, f, cx, cy, ci, pi, uv = _world(rng, C=8)
    prob = BundleProblem(poses_to_params(poses), pts, 1.15 * f, cx, cy, ci, pi, uv + 0.2 * rng.standard_normal(uv.shape))
    _, _, f_est, _ = bundle_adjust(prob, fixed_cams=(0,), refine_focal=True, max_nfev=200)
    assert abs(f_est / f - 1) < 0.03  # from 15 % off


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match="cams must have shape"):
        reprojection_fwd(np.zeros((2, 5)), np.zeros((1, 3)), 1.0, 0, 0, [0], [0], np.zeros((1, 2)))
    with pytest.raises(ValueError, match="index outside"):
        reprojection_fwd(np.zeros((2, 6)), np.zeros((1, 3)), 1.0, 0, 0, np.array([2]), np.array([0]), np.zeros((1, 2)))
