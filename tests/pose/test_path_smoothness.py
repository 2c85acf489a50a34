"""The camera path's smoothness prior of the bundle adjustment (d2gs_np/pose/bundle.py
``path_smoothness_fwd``): Jacobian against central differences, zero on a constant-velocity path,
the two solvers on the same cost, the covariance it tightens, stiff and bad input."""
import numpy as np
import pytest

from d2gs_np.geometry.camera import camera_center
from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.pose import bundle as B
from d2gs_np.pose.bundle import (BundleProblem, bundle_adjust, camera_covariance, params_to_poses,
                                  path_smoothness_fwd, pose_prior_fwd, poses_to_params, reprojection_fwd)
from d2gs_np.pose.lm import robust_loss
from bundle_fixtures import schur_then_scipy

F, CX, CY = 200.0, 120.0, 80.0


def _line_path(rng, C, step=0.2):
    """Cameras whose centres lie on a line at equal steps (turned at random): second difference 0."""
    R = [se3_exp(np.r_[0.0, 0.0, 0.0, 0.05 * rng.standard_normal(3)])[:3, :3] for _ in range(C)]
    centres = np.c_[step * np.arange(C), 0.02 * np.arange(C), np.zeros(C)]
    T = np.tile(np.eye(4), (C, 1, 1))
    for k in range(C):
        T[k, :3, :3] = R[k]
        T[k, :3, 3] = -R[k] @ centres[k]
    return T


def test_jacobian_matches_central_differences():
    # rotation vectors of 0.3-1 rad, and one exactly 0 (the left Jacobian's series branch).
    # h = 1e-6 on residuals of size ~1 / sigma = 10: truncation O(h^2) ~ 1e-11, rounding ~ 1e-16 x 10 / 1e-6
    # ~ 1e-9; 1e-7 relative to the largest entry holds both with room
    rng = np.random.default_rng(0)
    cams = rng.standard_normal((5, 6)) * np.r_[0.6, 0.6, 0.6, 1.0, 1.0, 1.0]
    cams[2, :3] = 0.0
    sigma = 0.1
    r, J = path_smoothness_fwd(cams, sigma)
    assert r.shape == (3, 3) and J.shape == (3, 3, 3, 6)
    free = np.arange(5)
    _, Jd = B._smooth_dense(cams, free, sigma)
    h = 1e-6
    x0 = cams.ravel()
    flat = lambda x: path_smoothness_fwd(x.reshape(5, 6), sigma)[0].ravel()
    Jn = np.stack([(flat(x0 + h * e) - flat(x0 - h * e)) / (2 * h) for e in np.eye(x0.size)], axis=1)
    assert np.max(np.abs(Jd - Jn)) < 1e-7 * np.max(np.abs(Jn))
    # a fixed camera's columns are dropped, the rest unchanged
    free2 = np.array([0, 1, 3, 4])
    _, Jd2 = B._smooth_dense(cams, free2, sigma)
    cols = (6 * free2[:, None] + np.arange(6)).ravel()
    np.testing.assert_array_equal(Jd2, Jd[:, cols])


def test_zero_on_a_constant_velocity_path_and_not_off_it():
    rng = np.random.default_rng(1)
    T = _line_path(rng, 6)
    r, _ = path_smoothness_fwd(poses_to_params(T), 0.01)
    assert np.max(np.abs(r)) < 1e-12
    # one centre moved by d: the three rows around it see d, -2d, d (in units of sigma)
    T2 = T.copy()
    d = np.array([0.0, 0.003, 0.0])
    T2[3, :3, 3] -= T2[3, :3, :3] @ d
    np.testing.assert_allclose(camera_center(T2)[3] - camera_center(T)[3], d, atol=1e-15)
    r2, _ = path_smoothness_fwd(poses_to_params(T2), 0.01)
    np.testing.assert_allclose(r2, np.stack([np.zeros(3), d, -2 * d, d]) / 0.01, atol=1e-9)


def test_short_paths_and_bad_input():
    r, J = path_smoothness_fwd(np.zeros((2, 6)), 0.1)
    assert r.shape == (0, 3) and J.shape == (0, 3, 3, 6)
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="smoothness sigma"):
            path_smoothness_fwd(np.zeros((4, 6)), bad)
    with pytest.raises(ValueError, match=r"shape \(C, 6\)"):
        path_smoothness_fwd(np.zeros((4, 5)), 0.1)


def _problem(seed, C=7, P=120, noise=0.3):
    rng = np.random.default_rng(seed)
    poses = _line_path(rng, C, step=0.25)
    pts = np.c_[rng.uniform(-2, 2, P), rng.uniform(-1.5, 1.5, P), rng.uniform(4, 6, P)]
    ci, pi = np.repeat(np.arange(C), P), np.tile(np.arange(P), C)
    uv, _ = reprojection_fwd(poses_to_params(poses), pts, F, CX, CY, ci, pi, np.zeros((C * P, 2)))
    obs = uv + noise * rng.standard_normal(uv.shape)
    start = np.stack([se3_exp(np.r_[0.03 * rng.standard_normal(3), 0.01 * rng.standard_normal(3)]) @ T
                      for T in poses])
    return poses, pts, ci, pi, obs, start, pts + 0.05 * rng.standard_normal(pts.shape)


def test_schur_and_scipy_reach_the_same_optimum_with_the_smoothness():
    # as test_bundle_schur's comparison: SciPy started at the Schur solver's optimum (prior and
    # smoothness on, no camera fixed) finds no lower cost and does not move it (1e-10 / 1e-5, the
    # bounds justified there); the reported cost is the cost recomputed from scratch
    poses, pts, ci, pi, obs, start, pts0 = _problem(2)
    prior = (poses_to_params(start), 0.05, np.deg2rad(1.0))
    kw = dict(fixed_cams=(), loss="soft_l1", f_scale=1.0, tol=1e-12, prior=prior, smooth=0.01)
    prob = BundleProblem(poses_to_params(start), pts0, F, CX, CY, ci, pi, obs)
    c1, p1, f1, i1 = schur_then_scipy(prob, kw)
    r = np.r_[reprojection_fwd(c1, p1, F, CX, CY, ci, pi, obs)[0].ravel(),
              pose_prior_fwd(c1, prior[0], prior[1], prior[2])[0].ravel(), path_smoothness_fwd(c1, 0.01)[0].ravel()]
    assert i1["cost"] == pytest.approx(0.5 * float(np.sum(robust_loss(r ** 2, "soft_l1")[0])), rel=1e-12)
    # and it is a different optimum from the one without the rows
    c0, _, _, i0 = bundle_adjust(prob, solver="schur", max_nfev=200, **{**kw, "smooth": None})
    assert np.max(np.abs(c0 - c1)) > 1e-4


def test_smoothness_pulls_the_path_straight_and_tightens_the_covariance():
    # a true constant-velocity path seen through 1 px of noise by few points: the smoothness (consistent
    # with the truth) lowers the centres' error against the truth, and their covariance
    poses, pts, ci, pi, obs, start, pts0 = _problem(3, P=25, noise=1.0)
    prior = (poses_to_params(start), 0.05, np.deg2rad(1.0))
    prob = BundleProblem(poses_to_params(start), pts0, F, CX, CY, ci, pi, obs)
    err, var = [], []
    for smooth in (None, 0.002):
        c, p, _, _ = bundle_adjust(prob, solver="schur", fixed_cams=(), prior=prior, smooth=smooth, max_nfev=100)
        ce, cg = camera_center(params_to_poses(c)), camera_center(poses)
        second = ce[:-2] - 2 * ce[1:-1] + ce[2:]
        err.append(np.sqrt(np.mean(np.sum(second ** 2, axis=1))))
        Sigma, _ = camera_covariance(BundleProblem(c, p, F, CX, CY, ci, pi, obs), c, p, (), "soft_l1", 1.0, prior,
                                     smooth)
        var.append(np.trace(Sigma))
        assert np.all(np.isfinite(Sigma))
    assert np.max(np.abs(cg[:-2] - 2 * cg[1:-1] + cg[2:])) < 1e-12
    assert err[1] < 0.3 * err[0], err
    assert var[1] < var[0], var


def test_a_stiff_smoothness_keeps_an_exact_problem_exact():
    # noise-free observations of a constant-velocity path: a smoothness 1e4 times stiffer than the
    # pixels (sigma 1e-6 per frame squared) agrees with the truth, and the solution is still the truth
    poses, pts, ci, pi, obs, start, pts0 = _problem(4, noise=0.0)
    prior = (poses_to_params(poses), 0.05, 0.01)
    prob = BundleProblem(poses_to_params(start), pts0, F, CX, CY, ci, pi, obs)
    cams, _, _, info = bundle_adjust(prob, solver="schur", fixed_cams=(), prior=prior, smooth=1e-6, max_nfev=200,
                                     tol=1e-14)
    assert np.all(np.isfinite(cams))
    np.testing.assert_allclose(params_to_poses(cams), poses, atol=1e-6)
