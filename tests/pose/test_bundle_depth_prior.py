"""The depth prior's rows of the bundle adjustment (d2gs_np/pose/bundle.py ``depth_prior_rows``,
``bundle_adjust(depth=...)``) and the third round of the given poses' adjustment that uses them
(d2gs_np/pose/given.py, step 3b): Jacobian against central differences (rotations near 0 and near
pi), prior-less rows, the two solvers on the same optimum, the rotation drift the rows remove,
what the pipeline says when it leaves them out, and bad input."""
import copy

import numpy as np
import pytest

from d2gs_np.data.suite import make_suite_scene
from d2gs_np.geometry.camera import camera_center
from d2gs_np.geometry.so3 import so3_exp, so3_log
from d2gs_np.pose import bundle as B
from d2gs_np.pose.bundle import (BundleProblem, bundle_adjust, depth_prior_rows, params_to_poses, poses_to_params,
                                  reprojection_fwd)
from d2gs_np.pose.config import PoseInitConfig
from d2gs_np.pose.given import adjust_given_poses, adjusted_start, triangulate_tracks
from d2gs_np.pose.lm import robust_loss
from bundle_fixtures import schur_then_scipy
from d2gs_np.train.config import ExperimentConfig, InitConfig

F, CX, CY, W, H = 200.0, 160.0, 120.0, 320, 240


def _saved(cams, pts, ci, pi):
    return reprojection_fwd(cams, pts, F, CX, CY, ci, pi, np.zeros((len(ci), 2)))[1]


@pytest.mark.parametrize("angle", [0.4, 1e-9, np.pi - 1e-3])
def test_jacobian_matches_central_differences(angle):
    # Cameras turned by `angle` (the left Jacobian's series branch near 0, its 1 / (1 - cos) terms
    # near pi), points 3-6 in front. Rows are O(weight x 1) with O(weight / z) derivatives: central
    # differences at h = 1e-6 in float64 carry O(h^2) ~ 1e-12 truncation and ~1e-10 rounding, so
    # 1e-7 relative to the largest entry is far below any wrong term (a lost J_l or sign is O(1)).
    rng = np.random.default_rng(0)
    C, P = 3, 8
    axis = rng.normal(size=(C, 3)) * 0.05 + np.array([0.3, 0.8, 0.5])
    phi = angle * axis / np.linalg.norm(axis, axis=1, keepdims=True)  # nearby axes: all see the points
    R = so3_exp(phi)
    centres = 0.1 * rng.normal(size=(C, 3))
    X = centres[0] + np.c_[rng.uniform(-0.5, 0.5, (P, 2)), rng.uniform(3, 6, P)] @ R[0]  # ahead of camera 0
    cams = np.concatenate([phi, -np.einsum("cij,cj->ci", R, centres)], axis=1)
    ci, pi = np.repeat(np.arange(C), P), np.tile(np.arange(P), C)
    weight, log_a = 2.5, 0.3
    saved = _saved(cams, X, ci, pi)
    z = saved[3][:, 2]
    lp = np.log(np.abs(z)) + 0.1 * rng.normal(size=z.shape)
    lp[3] = np.nan  # no prior here: a zero row with zero derivatives
    r, d_cam, d_pt = depth_prior_rows(saved, lp, log_a, weight)
    assert r.shape == (C * P,) and d_cam.shape == (C * P, 6) and d_pt.shape == (C * P, 3)
    front = z > 0
    assert front.all()  # every camera sees the points in front
    zero = ~np.isfinite(lp) | ~front
    assert np.all(r[zero] == 0) and np.all(d_cam[zero] == 0) and np.all(d_pt[zero] == 0)
    np.testing.assert_allclose(r[~zero], weight * (np.log(z[~zero]) - log_a - lp[~zero]), rtol=1e-14)

    def rows(c, x):
        s = _saved(c, x, ci, pi)
        return depth_prior_rows(s, lp, log_a, weight)[0]

    h = 1e-6
    Jc = np.zeros((C * P, C, 6))
    for c in range(C):
        for k in range(6):
            e = np.zeros((C, 6))
            e[c, k] = h
            Jc[:, c, k] = (rows(cams + e, X) - rows(cams - e, X)) / (2 * h)
    Jp = np.zeros((C * P, P, 3))
    for p in range(P):
        for k in range(3):
            e = np.zeros((P, 3))
            e[p, k] = h
            Jp[:, p, k] = (rows(cams, X + e) - rows(cams, X - e)) / (2 * h)
    o = np.arange(C * P)
    scale = max(np.abs(Jc).max(), np.abs(Jp).max())
    assert np.max(np.abs(Jc[o, ci] - d_cam)) < 1e-7 * scale
    assert np.max(np.abs(Jp[o, pi] - d_pt)) < 1e-7 * scale
    # and the sparse Jacobian the SciPy solver builds from them (camera 0 fixed: its columns dropped)
    free = np.array([1, 2])
    J = B._depth_jacobian(d_cam, d_pt, ci, pi, free, C, 6 * len(free) + 3 * P).toarray()
    Jn = np.concatenate([Jc[:, free].reshape(C * P, -1), Jp.reshape(C * P, -1)], axis=1)
    assert np.max(np.abs(J - Jn)) < 1e-7 * scale


def test_bad_input_is_named():
    rng = np.random.default_rng(1)
    cams = np.c_[0.01 * rng.normal(size=(2, 3)), np.zeros((2, 3))]
    X = np.c_[rng.uniform(-1, 1, (5, 2)), np.full(5, 4.0)]
    ci, pi = np.repeat([0, 1], 5), np.tile(np.arange(5), 2)
    saved = _saved(cams, X, ci, pi)
    lp = np.zeros(10)
    with pytest.raises(ValueError, match="one entry per observation"):
        depth_prior_rows(saved, lp[:9], 0.0, 1.0)
    for a, w in ((np.nan, 1.0), (np.inf, 1.0), (0.0, 0.0), (0.0, -1.0), (0.0, np.nan)):
        with pytest.raises(ValueError, match="log scale must be finite and its weight > 0"):
            depth_prior_rows(saved, lp, a, w)
    prob = BundleProblem(cams, X, F, CX, CY, ci, pi, np.zeros((10, 2)))
    for solver in ("scipy", "schur"):
        with pytest.raises(ValueError, match="one log depth per observation"):
            bundle_adjust(prob, solver=solver, depth=(lp[:7], 0.0, 1.0))
    for bad in (-1.0, np.nan):
        with pytest.raises(ValueError, match="depth_prior_weight"):
            PoseInitConfig(depth_prior_weight=bad)


def _drift_world(seed=0, C=8, P=150, drift_deg=0.8, noise_px=0.2):
    """A lateral path (0.1 per frame) past points 3-9 deep; the given poses are the true ones with a
    rotation about the vertical axis that drifts linearly over the clip by ``drift_deg`` (the suite's
    slow drift), and tracks of every point in every frame (``noise_px`` of noise). A linear yaw drift
    on a lateral path moves every point's disparity alike: a near-gauge of the tracks."""
    rng = np.random.default_rng(seed)
    centres = np.c_[0.1 * np.arange(C), 0.01 * rng.normal(size=C), np.zeros(C)]
    R = so3_exp(np.c_[0.01 * rng.normal(size=(C, 3))])
    poses = np.tile(np.eye(4), (C, 1, 1))
    poses[:, :3, :3] = R
    poses[:, :3, 3] = -np.einsum("cij,cj->ci", R, centres)
    z = rng.uniform(3, 9, P)
    X = np.c_[rng.uniform(-0.45, 0.45, P) * z + 0.35, rng.uniform(-0.35, 0.35, P) * z, z]
    ci, pi = np.repeat(np.arange(C), P), np.tile(np.arange(P), C)
    uv, saved = reprojection_fwd(poses_to_params(poses), X, F, CX, CY, ci, pi, np.zeros((C * P, 2)))
    inside = (uv[:, 0] > 2) & (uv[:, 0] < W - 3) & (uv[:, 1] > 2) & (uv[:, 1] < H - 3)
    assert inside.all()
    obs = uv + noise_px * rng.normal(size=uv.shape)
    yaw = np.deg2rad(drift_deg) * (np.arange(C) / (C - 1) - 0.5)
    given = poses.copy()
    for c in range(C):
        Rd = so3_exp(np.array([0.0, yaw[c], 0.0]))
        given[c, :3, :3] = Rd @ R[c]
        given[c, :3, 3] = -given[c, :3, :3] @ centres[c]
    return poses, given, X, ci, pi, obs, saved[3][:, 2]


def _depth_maps(ci, obs, z_true, C, factor):
    """Per frame a depth map that holds ``factor`` x the true depth in each observed pixel's 2 x 2
    bilinear neighbourhood (NaN elsewhere, and where two observations' neighbourhoods meet)."""
    maps = np.full((C, H, W), np.nan)
    count = np.zeros((C, H, W), dtype=int)
    for c, (u, v), z in zip(ci, obs, z_true):
        i, j = int(np.floor(v - 0.5)), int(np.floor(u - 0.5))  # the taps of bilinear_fwd (centres at +0.5)
        maps[c, i:i + 2, j:j + 2] = factor * z
        count[c, i:i + 2, j:j + 2] += 1
    maps[count > 1] = np.nan
    return list(maps)


def _far_over_near(T, X, X_true):
    """The structure's depth warp: median depth ratio (estimate / truth) of the far third over the
    near third, in the first camera (1: the shape of the truth; scale-free)."""
    z = (X @ T[0, :3, :3].T + T[0, :3, 3])[:, 2]
    zt = X_true[:, 2]
    near, far = zt < np.quantile(zt, 1 / 3), zt > np.quantile(zt, 2 / 3)
    return np.median(z[far] / zt[far]) / np.median(z[near] / zt[near])


def _end_to_end_rot_deg(A, G):
    """The error of the rotation between the first and the last camera against the truth (deg):
    what a linear drift over the clip leaves."""
    a, b = A[-1, :3, :3] @ A[0, :3, :3].T, G[-1, :3, :3] @ G[0, :3, :3].T
    return float(np.degrees(np.linalg.norm(so3_log(a @ b.T))))


def test_the_depth_rows_remove_the_rotation_drift_the_tracks_cannot_see():
    # A 2 deg drift over the clip. Without the rows the adjustment keeps a fifth of it (its prior pulls
    # the rotations to the given ones and the tracks barely object) and warps the structure to match:
    # measured far / near depth ratio 0.963, first-to-last rotation error 2.0 -> 0.38 deg. With exact
    # priors at an unknown clip scale (x2.3) and weight 10: ratio 0.998, error 0.034 deg. The bounds
    # (warp 3 % without, 1 % with; error 0.3x) fail if the rows do nothing.
    poses, given, X, ci, pi, obs, z = _drift_world(drift_deg=2.0)
    C = len(poses)
    K = np.array([[F, 0, CX], [0, F, CY], [0, 0, 1.0]])
    maps = _depth_maps(ci, obs, z, C, 2.3)
    tracks = (ci, pi, obs, len(X))
    P0, i0 = adjust_given_poses([None] * C, None, given, K, PoseInitConfig(depth_prior_weight=10.0), tracks=tracks)
    assert "depth_prior" not in i0  # no priors given: no third round
    P1, i1 = adjust_given_poses([None] * C, None, given, K, PoseInitConfig(depth_prior_weight=10.0), tracks=tracks,
                                depth_priors=maps)
    assert i0["kept"] and i1["kept"], (i0.get("reason"), i1.get("reason"))
    dp = i1["depth_prior"]
    assert dp["observations"] > 0.8 * len(ci)  # the colliding neighbourhoods' priors are NaN, left out
    assert dp["rel_error_after"] < 0.5 * dp["rel_error_before"]
    assert i1["rounds"][-1]["depth_prior"] and len(i1["rounds"]) == len(i0["rounds"]) + 1
    # the third round keeps the second round's path length (rescaled about the mean centre)
    spread = lambda T: np.sqrt(np.mean(np.sum((camera_center(T) - camera_center(T).mean(0)) ** 2, axis=1)))
    assert spread(P1) == pytest.approx(spread(P0), rel=1e-9)
    X0, X1 = _structure(P0, ci, pi, obs, len(X)), _structure(P1, ci, pi, obs, len(X))
    warp0, warp1 = _far_over_near(P0, X0, X), _far_over_near(P1, X1, X)
    assert abs(warp0 - 1) > 0.03, warp0
    assert abs(warp1 - 1) < 0.01, warp1
    e0, e1 = _end_to_end_rot_deg(P0, poses), _end_to_end_rot_deg(P1, poses)
    assert e1 < 0.3 * e0, (e0, e1)
    assert i1["rounds"][-1]["rms_px"] < 1.0  # the pixels still fit (0.2 px noise)


def _structure(T, ci, pi, obs, P):
    """The points triangulated (linear DLT, ``triangulate_tracks``) from the tracks in the poses T:
    the structure those poses imply, independent of the adjustment's own points."""
    K = np.array([[F, 0, CX], [0, F, CY], [0, 0, 1.0]])
    X, ok = triangulate_tracks(T, K, ci, pi, obs, P, min_views=2, min_parallax_deg=0.0)
    assert ok.all()
    return X


def test_schur_and_scipy_reach_the_same_optimum_with_the_depth_rows():
    # As test_path_smoothness's comparison: SciPy started at the Schur solver's optimum (prior and
    # depth rows on, no camera fixed) finds no lower cost and does not move it (1e-10 relative cost,
    # 1e-5 in the unknowns: the bounds justified there); the reported cost is recomputed from
    # scratch; and the optimum differs from the one without the rows.
    poses, given, X, ci, pi, obs, z = _drift_world(seed=2, C=6, P=60)
    rng = np.random.default_rng(3)
    lp = np.log(1.7 * z) + 0.02 * rng.normal(size=z.shape)
    lp[::11] = np.nan
    depth = (lp, np.log(1 / 1.7), 3.0)
    prior = (poses_to_params(given), 0.05, np.deg2rad(1.0))
    kw = dict(fixed_cams=(), loss="soft_l1", f_scale=1.0, tol=1e-12, prior=prior, depth=depth)
    prob = BundleProblem(poses_to_params(given), X + 0.05 * rng.normal(size=X.shape), F, CX, CY, ci, pi, obs)
    c1, p1, f1, i1 = schur_then_scipy(prob, kw)
    rp, saved = reprojection_fwd(c1, p1, F, CX, CY, ci, pi, obs)
    rows = np.r_[rp.ravel(), B.pose_prior_fwd(c1, *prior)[0].ravel(), depth_prior_rows(saved, *depth)[0]]
    assert i1["cost"] == pytest.approx(0.5 * float(np.sum(robust_loss(rows ** 2, "soft_l1")[0])), rel=1e-12)
    # the reported residuals are the reprojection's only
    assert i1["rms_px"] == pytest.approx(float(np.sqrt(np.mean(np.sum(rp ** 2, axis=1)))), rel=1e-12)
    c0, _, _, _ = bundle_adjust(prob, solver="schur", max_nfev=200, **{**kw, "depth": None})
    assert np.max(np.abs(c0 - c1)) > 1e-4


def test_all_nan_priors_leave_the_poses_and_say_why():
    poses, given, X, ci, pi, obs, z = _drift_world(seed=4, C=6, P=80)
    K = np.array([[F, 0, CX], [0, F, CY], [0, 0, 1.0]])
    tracks = (ci, pi, obs, len(X))
    cfg = PoseInitConfig(depth_prior_weight=1.0)
    P0, i0 = adjust_given_poses([None] * 6, None, given, K, PoseInitConfig(), tracks=tracks)
    P1, i1 = adjust_given_poses([None] * 6, None, given, K, cfg, tracks=tracks,
                                depth_priors=[np.full((H, W), np.nan)] * 5 + [None])
    assert i1["depth_prior"]["observations"] == 0 and "fewer than min_points" in i1["depth_prior"]["reason"]
    np.testing.assert_array_equal(P1, P0)
    assert len(i1["rounds"]) == len(i0["rounds"])
    with pytest.raises(ValueError, match="one map \\(or None\\) per frame"):
        adjust_given_poses([None] * 6, None, given, K, cfg, tracks=tracks, depth_priors=[None] * 5)


def test_adjusted_start_says_when_it_leaves_the_rows_out():
    # photo_room at 160 x 90, 8 frames, blurry, the suite's noisy poses and its modelled video prior
    notes = []
    with_prior = make_suite_scene("photo_room", seed=0, depth_prior="video", width=160, height=90, num_frames=8,
                                  num_test_views=0)
    assert with_prior.has_depth_prior
    plain = copy.deepcopy(with_prior)
    plain.frames[3].depth_prior = None
    cfg = ExperimentConfig(pose_init=PoseInitConfig(depth_prior_weight=1.0))
    adjusted_start(plain, cfg, notes.append)
    assert "depth prior rows left out (the scene has no depth priors)" in notes[-1]
    adjusted_start(with_prior, ExperimentConfig(pose_init=PoseInitConfig(depth_prior_weight=1.0),
                                                init=InitConfig(depth_prior_space="disparity")), notes.append)
    assert "depth prior rows left out (init.depth_prior_space = disparity" in notes[-1]
    start = adjusted_start(with_prior, cfg, notes.append)
    assert "depth prior rows on" in notes[-1] and start.poses is not None
    # off (the default): no rows, nothing said of them
    adjusted_start(with_prior, ExperimentConfig(), notes.append)
    assert "depth prior rows" not in notes[-1]


def test_a_point_at_or_behind_the_camera_gets_a_zero_row():
    # z <= 0 has no log depth: the row and its derivatives are 0 (finite), the others unchanged
    cams = np.zeros((1, 6))
    X = np.array([[0.1, 0.0, 4.0], [0.0, 0.0, 0.0], [0.2, 0.1, -3.0], [0.0, 0.1, 1e-300]])
    ci, pi = np.zeros(4, dtype=int), np.arange(4)
    with np.errstate(invalid="ignore"):  # the reprojection of the point at the centre is 0 / 0
        saved = _saved(cams, X, ci, pi)
    r, d_cam, d_pt = depth_prior_rows(saved, np.log([2.0, 2.0, 2.0, 2.0]), 0.5, 2.0)
    assert np.all(np.isfinite(r)) and np.all(np.isfinite(d_cam)) and np.all(np.isfinite(d_pt))
    np.testing.assert_allclose(r[0], 2.0 * (np.log(4.0) - 0.5 - np.log(2.0)), rtol=1e-14)
    assert np.all(r[1:3] == 0) and np.all(d_cam[1:3] == 0) and np.all(d_pt[1:3] == 0)
    assert np.isfinite(r[3])  # a depth of 1e-300 is in front: its row is large but finite
