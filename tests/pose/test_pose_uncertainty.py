"""How well a bundle adjustment determined each camera (pose.bundle.camera_covariance,
relative_rotation_std): against the dense inverse of the same normal equations, and its
behaviour with more data, a free gauge and a camera no point sees."""
import numpy as np
import pytest

from d2gs_np.geometry.so3 import so3_exp
from d2gs_np.pose.bundle import (BundleProblem, bundle_adjust, camera_covariance, pose_prior_fwd, poses_to_params,
                                  relative_rotation_std, reprojection_fwd, reprojection_jacobian)
from d2gs_np.pose.lm import robust_loss


def _problem(rng, C=5, P=40, unseen=(), noise_px=0.5):
    """Cameras on a short arc looking at points 4-6 units ahead, observations with pixel noise."""
    poses = []
    for c in range(C):
        T = np.eye(4)
        T[:3, :3] = so3_exp(np.array([0.01 * c, 0.06 * (c - C / 2), 0.0]))
        T[:3, 3] = -T[:3, :3] @ np.array([0.25 * (c - C / 2), 0.02 * c, 0.0])
        poses.append(T)
    cams = poses_to_params(np.stack(poses))
    X = rng.uniform([-2, -1, 4], [2, 1, 6], size=(P, 3))
    f, cx, cy = 200.0, 120.0, 70.0
    seen = [c for c in range(C) if c not in unseen]
    ci = np.repeat(seen, P)
    pi = np.tile(np.arange(P), len(seen))
    uv, _ = reprojection_fwd(cams, X, f, cx, cy, ci, pi, np.zeros((len(ci), 2)))
    uv = uv + noise_px * rng.standard_normal(uv.shape)
    return BundleProblem(cams, X, f, cx, cy, ci, pi, uv)


def _dense_covariance(prob, cams, pts, fixed, loss, f_scale, prior):
    """The obvious way: every residual row (data and prior) in one dense Jacobian, H = J^T W J over
    cameras and points together, inverted whole; the free cameras' block."""
    C = cams.shape[0]
    free = np.array([c for c in range(C) if c not in set(fixed)])
    r, saved = reprojection_fwd(cams, pts, prob.focal, prob.cx, prob.cy, prob.cam_idx, prob.pt_idx, prob.uv)
    J = reprojection_jacobian(saved, free, False).toarray()
    w = robust_loss((r / f_scale) ** 2, loss)[1].ravel()
    H = J.T @ (w[:, None] * J)
    if prior is not None:
        rp, Jp = pose_prior_fwd(cams[free], prior[0][free], prior[1], prior[2])
        wp = robust_loss((rp / f_scale) ** 2, loss)[1]
        for i in range(len(free)):
            H[6 * i:6 * i + 6, 6 * i:6 * i + 6] += Jp[i].T @ (wp[i][:, None] * Jp[i])
    nc = 6 * len(free)
    return np.linalg.inv(H)[:nc, :nc], H


def test_camera_covariance_is_the_dense_inverse_of_the_same_normal_equations():
    rng = np.random.default_rng(0)
    prob = _problem(rng)
    prior = (prob.cams + 0.003 * rng.standard_normal(prob.cams.shape), 0.1, np.radians(1.0))
    cams, pts, _, _ = bundle_adjust(prob, fixed_cams=(), loss="soft_l1", f_scale=1.0, max_nfev=30, prior=prior,
                                    solver="schur")
    Sigma, free = camera_covariance(prob, cams, pts, (), "soft_l1", 1.0, prior)
    dense, H = _dense_covariance(prob, cams, pts, (), "soft_l1", 1.0, prior)
    np.testing.assert_array_equal(free, np.arange(5))
    # Two float64 solutions of one SPD system (the Schur complement against the whole inverse):
    # they differ by about cond(H) x 1e-16 relative; cond(H) is below 1e9 here, so 1e-6 of the
    # largest entry leaves a factor 10 and fails for any wrong block (a missed prior or weight
    # moves entries by percents).
    assert np.linalg.cond(H) < 1e9
    np.testing.assert_allclose(Sigma, dense, rtol=0, atol=1e-6 * np.abs(dense).max())
    # two fixed cameras (the gauge and the scale held), no prior, the linear loss: the same
    Sigma1, free1 = camera_covariance(prob, cams, pts, (0, 4), "linear", 1.0, None)
    dense1, H1 = _dense_covariance(prob, cams, pts, (0, 4), "linear", 1.0, None)
    np.testing.assert_array_equal(free1, [1, 2, 3])
    assert np.linalg.cond(H1) < 1e9
    np.testing.assert_allclose(Sigma1, dense1, rtol=0, atol=1e-6 * np.abs(dense1).max())


def test_relative_rotation_std_takes_out_the_common_turn():
    rng = np.random.default_rng(1)
    F = 4
    A = rng.standard_normal((6 * F, 6 * F))
    Sigma = A @ A.T * 1e-4
    free = np.array([0, 2, 3, 5])
    rel = relative_rotation_std(Sigma, free, 6)
    assert np.isnan(rel[1]) and np.isnan(rel[4])
    # the obvious way: the linear map delta_i - mean_j delta_j on the rotation rows, applied to Sigma
    M = np.zeros((3 * F, 6 * F))
    for i in range(F):
        for j in range(F):
            M[3 * i:3 * i + 3, 6 * j:6 * j + 3] = (i == j) * np.eye(3) - np.eye(3) / F
    C = M @ Sigma @ M.T
    expect = [np.sqrt(np.trace(C[3 * i:3 * i + 3, 3 * i:3 * i + 3]) / 3) for i in range(F)]
    np.testing.assert_allclose(rel[free], expect, rtol=1e-12)
    # a turn of every camera alike (the gauge) adds nothing, however large
    g = np.zeros(6 * F)
    g[(6 * np.arange(F)[:, None] + np.arange(3)).ravel()] = np.tile([1.0, -2.0, 0.5], F)
    np.testing.assert_allclose(relative_rotation_std(Sigma + 1e3 * np.outer(g, g), free, 6)[free], expect, rtol=1e-7)
    assert np.all(np.isnan(relative_rotation_std(np.zeros((0, 0)), np.zeros(0, dtype=int), 3)))


def test_twice_the_observations_leave_the_uncertainty_over_root_two():
    # The same observations given twice (linear loss, no prior, two cameras fixed: the gauge and
    # the scale held) double H exactly, so every standard deviation falls by sqrt(2).
    rng = np.random.default_rng(2)
    prob = _problem(rng)
    cams, pts, _, _ = bundle_adjust(prob, fixed_cams=(0, 4), loss="linear", max_nfev=30, solver="schur")
    Sigma, free = camera_covariance(prob, cams, pts, (0, 4), "linear", 1.0, None)
    twice = BundleProblem(prob.cams, prob.points, prob.focal, prob.cx, prob.cy, np.r_[prob.cam_idx, prob.cam_idx],
                          np.r_[prob.pt_idx, prob.pt_idx], np.r_[prob.uv, prob.uv])
    Sigma2, _ = camera_covariance(twice, cams, pts, (0, 4), "linear", 1.0, None)
    np.testing.assert_allclose(Sigma2, Sigma / 2, rtol=0, atol=1e-9 * np.abs(Sigma).max())
    rel, rel2 = relative_rotation_std(Sigma, free, 5), relative_rotation_std(Sigma2, free, 5)
    np.testing.assert_allclose(rel2[free], rel[free] / np.sqrt(2), rtol=1e-6)
    assert np.all(rel[free] > 0)


def test_a_free_gauge_and_an_unseen_camera_give_finite_uncertainties():
    rng = np.random.default_rng(3)
    # no prior, no fixed camera: S is singular (7 gauge directions); inverted on its range
    prob = _problem(rng)
    Sigma, free = camera_covariance(prob, prob.cams, prob.points, (), "linear", 1.0, None)
    assert np.all(np.isfinite(Sigma))
    assert np.all(np.isfinite(relative_rotation_std(Sigma, free, 5)))
    # a camera no point sees, held by the prior alone: its rotation is as uncertain as the prior
    # says, so its relative std is at least (1 - 1/F) sigma_r (the mean's share taken out), and the
    # cameras the points see are better determined
    prob = _problem(rng, unseen=(2,))
    sigma_r = np.radians(1.0)
    prior = (prob.cams, 0.1, sigma_r)
    Sigma, free = camera_covariance(prob, prob.cams, prob.points, (), "soft_l1", 1.0, prior)
    rel = relative_rotation_std(Sigma, free, 5)
    assert np.all(np.isfinite(rel))
    # (0.95: the prior measures the rotation's log against the prior, the parameter is its
    # rotation vector; their Jacobian J_l differs from I by about |phi|^2 / 12 at |phi| <= 0.15)
    assert rel[2] >= 0.95 * (1 - 1 / 5) * sigma_r
    # the seen cameras: their own share is small; the unseen one's turn, through the mean, adds
    # sigma_r / F to each (measured 0.37-0.45 sigma_r in all)
    assert np.all(rel[[0, 1, 3, 4]] < 0.6 * rel[2])
