"""The pose solver (d2gs_np/pose/gauss_newton.py, docs/method.md §5): exact Jacobians against
central finite differences, recovery of known poses, agreement with scipy.optimize.least_squares,
and the stiff cases (rank deficiency, outliers, a frame without matches, invalid depths, a large
initial error, a huge damping)."""
import numpy as np
import pytest
from scipy.optimize import least_squares

from d2gs_np.constants import LM_DAMPING_MAX
from d2gs_np.geometry.camera import camera_center
from d2gs_np.geometry.se3 import se3_exp, se3_interpolate, se3_inverse, se3_log
from d2gs_np.geometry.so3 import so3_log
from d2gs_np.pose import gauss_newton as gn
from d2gs_np.pose.config import ROBUST_LOSSES, GaussNewtonConfig
from d2gs_np.pose.lm import SCIPY_LOSS

K = np.array([[120.0, 0.0, 80.0], [0.0, 120.0, 45.0], [0.0, 0.0, 1.0]])
# Central differences with h = 1e-6 in float64: truncation ~h^2 |third derivative| ~ 1e-12 |J| and
# rounding ~1e-16 |f| / h ~ 1e-10 |f| (|f| <= ~1e3 px, |J| ~ 1e3 for the residuals, O(1) for the
# mid pose): 1e-6 relative to max |J| leaves a margin of 10-100 over both.
FD_STEP = 1e-6
FD_REL_TOL = 1e-6


def _project(T, X):
    Xc = X @ T[:3, :3].T + T[:3, 3]
    p = Xc @ K.T
    return p[:, :2] / p[:, 2:], Xc[:, 2]


def _scene(n=4, num_points=120, seed=0, points=None, spread=1e-3):
    """True mid poses along a short path, endpoints +-spread around them, and world points."""
    rng = np.random.default_rng(seed)
    mids = np.stack([se3_exp(np.r_[0.15 * k, 0.02 * k, 0.0, 0.0, 0.03 * k, 0.01 * k]) for k in range(n)])
    d = [rng.normal(0, spread, 6) for _ in range(n)]
    starts = np.stack([se3_exp(-d[k]) @ mids[k] for k in range(n)])
    ends = np.stack([se3_exp(d[k]) @ mids[k] for k in range(n)])
    if points is None:
        points = np.c_[rng.uniform(-2.5, 2.5, (num_points, 2)), rng.uniform(4.0, 7.0, num_points)]
    return mids, starts, ends, points


def _pairs(mids, X, gaps=(1, 2)):
    out = []
    n = len(mids)
    for k in range(n):
        for g in gaps:
            j = k + g
            if j < n:
                pk, dk = _project(mids[k], X)
                pj, dj = _project(mids[j], X)
                out.append(gn.pair_observations(k, j, pk, pj, dk, dj))
    return out


def _perturb(starts, ends, sigma_rot, sigma_t, seed=1, fixed=(0,)):
    rng = np.random.default_rng(seed)
    P = np.stack([np.eye(4) if k in fixed else se3_exp(np.r_[rng.normal(0, sigma_t, 3), rng.normal(0, sigma_rot, 3)])
                  for k in range(len(starts))])
    return P @ starts, P @ ends


def _problem(n=4, sigma_rot=0.01, sigma_t=0.03, seed=0, **kw):
    mids, starts, ends, X = _scene(n, seed=seed, **kw)
    s, e = _perturb(starts, ends, sigma_rot, sigma_t, seed=seed + 1)
    return mids, gn.PoseProblem(s, e, np.stack([K] * n), _pairs(mids, X))


def _mid_error(res, mids):
    return max(np.abs(se3_log(res.mids[k] @ se3_inverse(mids[k]))).max() for k in range(len(mids)))


def _fd_jacobian(problem, x, h):
    J = np.zeros((len(problem.residuals(x, 100.0, 1e-3, False)[0]), len(x)))
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        J[:, i] = (problem.residuals(x + e, 100.0, 1e-3, False)[0] - problem.residuals(x - e, 100.0, 1e-3, False)[0]) / (2 * h)
    return J


@pytest.mark.parametrize("scale", [0.0, 1e-2, 0.2])
def test_jacobian_matches_central_differences(scale):
    # scale 0: every angle is exactly 0 apart from the 1e-3 spread (series branches); 1e-2 takes
    # the log's closed form (spread change > 1e-3); 0.2 rad larger rotations.
    _, prob = _problem(n=3)
    x = np.random.default_rng(5).normal(0, 1, prob.num_params) * scale
    r, J = prob.residuals(x, 100.0, 1e-3)
    assert np.all(np.isfinite(J))
    Jfd = _fd_jacobian(prob, x, FD_STEP)
    assert np.abs(J - Jfd).max() <= FD_REL_TOL * np.abs(J).max()


def test_recovers_the_true_mid_poses_from_noise_free_matches():
    mids, prob = _problem(n=5)
    before = max(np.abs(se3_log(prob.poses(np.zeros(prob.num_params))[2][k] @ se3_inverse(mids[k]))).max()
                 for k in range(5))
    res = gn.solve(prob, GaussNewtonConfig(max_iters=30))
    assert before > 1e-2
    assert res.status.startswith("converged")
    assert _mid_error(res, mids) < 1e-8
    assert res.rank == res.num_params  # noise-free points at finite depth observe every mid pose; the prior the spread
    assert res.covariance.shape == (res.num_params, res.num_params)


@pytest.mark.parametrize("robust", ["none", "huber"])
def test_scipy_least_squares_reaches_the_same_optimum(robust):
    # noisy matches, so the optimum is not the truth and both solvers must find the same one
    mids, starts, ends, X = _scene(4)
    pairs = _pairs(mids, X)
    rng = np.random.default_rng(7)
    for p in pairs:
        p.pts_k = p.pts_k + rng.normal(0, 0.5, p.pts_k.shape)
    s, e = _perturb(starts, ends, 0.01, 0.03)
    prob = gn.PoseProblem(s, e, np.stack([K] * 4), pairs)
    cfg = GaussNewtonConfig(robust=robust, robust_scale=1.0, max_iters=50, ftol=1e-14)
    res = gn.solve(prob, cfg)

    def fun(x):
        return prob.residuals(x, cfg.beta, cfg.spread_sigma, False)[0]

    def jac(x):
        return prob.residuals(x, cfg.beta, cfg.spread_sigma)[1]

    ref = least_squares(fun, np.zeros(prob.num_params), jac=jac, method="trf",
                        loss=SCIPY_LOSS[robust], f_scale=1.0, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    # scipy applies the loss to the prior rows too; there they stay far inside the Huber scale
    # (|b - a| / sigma << 1), where Huber is quadratic, so the two costs are the same function.
    prior = fun(res.x[prob.free].ravel())[3 * prob.num_matches:]
    assert np.abs(prior).max() < 1.0
    assert np.isclose(res.costs[-1], ref.cost, rtol=1e-8)
    assert np.abs(res.x[prob.free].ravel() - ref.x).max() < 1e-6


def test_cost_never_rises_from_a_five_degree_error():
    mids, starts, ends, X = _scene(5)
    s, e = _perturb(starts, ends, np.deg2rad(5.0) / np.sqrt(3), 0.2)
    prob = gn.PoseProblem(s, e, np.stack([K] * 5), _pairs(mids, X))
    res = gn.solve(prob, GaussNewtonConfig(max_iters=40))
    assert np.all(np.diff(res.costs) <= 0)
    assert _mid_error(res, mids) < 1e-6
    assert len(res.times) == len(res.costs) and np.all(np.diff(res.times) >= 0)


def test_robust_loss_recovers_the_pose_with_half_the_matches_outliers():
    mids, starts, ends, X = _scene(4, num_points=200)
    pairs = _pairs(mids, X)
    rng = np.random.default_rng(11)
    for p in pairs:
        bad = rng.random(len(p.pts_k)) < 0.5
        p.pts_k[bad] = rng.uniform([0, 0], [160, 90], (bad.sum(), 2))
    s, e = _perturb(starts, ends, 0.01, 0.03)
    prob = gn.PoseProblem(s, e, np.stack([K] * 4), pairs)
    initial = _mid_error(gn.solve(prob, GaussNewtonConfig(max_iters=0)), mids)
    err = {kind: _mid_error(gn.solve(prob, GaussNewtonConfig(robust=kind, robust_scale=1.0, beta=100.0,
                                                                max_iters=50)), mids)
           for kind in ROBUST_LOSSES}
    # measured (beta 100): initial 0.025, none 0.93, huber 0.018, cauchy 0.0017 (rad / world units, max over
    # frames); with beta 10 (the depth rows, which the outliers do not corrupt, weigh less) cauchy 0.0052
    assert err["none"] > initial  # plain least squares: the outliers pull the poses away
    assert err["cauchy"] < initial / 8  # the redescending loss recovers the pose
    assert err["huber"] < initial < err["none"] / 10  # Huber bounds each outlier's pull, but 50 % still bias it


def test_points_at_infinity_leave_translation_unobserved():
    rng = np.random.default_rng(2)
    far = np.c_[rng.uniform(-1, 1, (150, 2)) * 1e7, np.full(150, 1e7)]  # a plane at 1e7 x the baseline
    mids, starts, ends, _ = _scene(3)
    s, e = _perturb(starts, ends, 0.01, 0.03)
    prob = gn.PoseProblem(s, e, np.stack([K] * 3), _pairs(mids, far))
    res = gn.solve(prob, GaussNewtonConfig(max_iters=20))
    assert np.all(np.isfinite(res.x)) and np.all(np.isfinite(res.covariance))
    assert res.rank <= res.num_params - 3 * 2  # the mid translation of both free frames
    # rotations are still recovered
    for k in (1, 2):
        R = res.mids[k][:3, :3] @ mids[k][:3, :3].T
        assert np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)) < 1e-5


def test_points_on_a_line_are_rank_deficient_but_finite():
    t = np.linspace(-2, 2, 100)
    line = np.c_[t, 0.3 * t, 5.0 + 0.5 * t]
    mids, starts, ends, _ = _scene(3)
    s, e = _perturb(starts, ends, 0.01, 0.03)
    prob = gn.PoseProblem(s, e, np.stack([K] * 3), _pairs(mids, line))
    res = gn.solve(prob, GaussNewtonConfig(max_iters=20))
    assert np.all(np.isfinite(res.x)) and np.all(np.isfinite(res.mids))
    assert res.rank < res.num_params
    assert res.costs[-1] <= res.costs[0]


def test_a_frame_without_matches_is_left_where_it_was():
    mids, starts, ends, X = _scene(4)
    pairs = [p for p in _pairs(mids, X) if 3 not in (p.k, p.j)]
    s, e = _perturb(starts, ends, 0.01, 0.03)
    prob = gn.PoseProblem(s, e, np.stack([K] * 4), pairs)
    res = gn.solve(prob, GaussNewtonConfig(max_iters=30))
    assert np.all(np.isfinite(res.x)) and np.all(res.x[3] == 0.0)
    assert res.rank == res.num_params - 6  # frame 3's mid pose: only the spread prior sees it
    assert _mid_error(gn.GaussNewtonResult(**{**res.__dict__, "mids": res.mids[:3]}), mids[:3]) < 1e-8


def test_zero_and_negative_depths_are_dropped_and_reported():
    mids, starts, ends, X = _scene(3)
    pk, dk = _project(mids[0], X)
    pj, dj = _project(mids[1], X)
    dk[:5] = 0.0
    dk[5:8] = -1.0
    dj[8:10] = np.nan
    obs = gn.pair_observations(0, 1, pk, pj, dk, dj)
    assert obs.dropped == 10 and len(obs.pts_k) == len(X) - 10
    assert np.all(obs.depth_k > 0)
    prob = gn.PoseProblem(starts, ends, np.stack([K] * 3), [obs])
    res = gn.solve(prob)
    assert res.dropped == 10 and res.num_matches == len(X) - 10


def test_depth_maps_are_read_bilinearly_at_pixel_centres():
    D = np.arange(12.0).reshape(3, 4)
    assert gn.sample_depth(D, [[0.5, 0.5]])[0] == 0.0  # the centre of pixel (0, 0)
    assert np.isclose(gn.sample_depth(D, [[1.0, 0.5]])[0], 0.5)
    assert np.isclose(gn.sample_depth(D, [[1.5, 1.5]])[0], 5.0)
    assert np.isnan(gn.sample_depth(D, [[-1.0, 0.5]])[0])


def test_huge_damping_stays_finite():
    mids, prob = _problem(n=3)
    res = gn.solve(prob, GaussNewtonConfig(damping_init=1e300, max_iters=5))
    assert np.all(np.isfinite(res.x)) and np.all(np.isfinite(res.damping))
    assert max(res.damping) <= LM_DAMPING_MAX
    assert np.all(np.diff(res.costs) <= 0)
    assert gn._solve_damped(np.eye(3) * 1e300, np.ones(3), LM_DAMPING_MAX).tolist() == pytest.approx([0.0] * 3, abs=1e-300)


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="starts"):
        gn.PoseProblem(np.zeros((2, 3, 3)), np.zeros((2, 4, 4)), np.stack([K] * 2), [])
    mids, starts, ends, X = _scene(2)
    with pytest.raises(ValueError, match="pair"):
        gn.PoseProblem(starts, ends, np.stack([K] * 2), [gn.pair_observations(0, 5, [[1, 1]], [[1, 1]], [1], [1])])
    with pytest.raises(ValueError, match="x0"):
        gn.solve(gn.PoseProblem(starts, ends, np.stack([K] * 2), []), x0=np.zeros(3))


# ------------------------------------------------------------------------- the pose prior
def _prior_problem(n=4, sigma=(0.05, 0.02), prior="true", depth_factor=1.0, seed=0):
    mids, starts, ends, X = _scene(n, seed=seed)
    s, e = _perturb(starts, ends, 0.01, 0.03, seed=seed + 1)
    pairs = _pairs(mids, X)
    for p in pairs:
        p.depth_k, p.depth_j = p.depth_k * depth_factor, p.depth_j * depth_factor
    G = {"true": mids, "start": np.stack([se3_interpolate(a, b, 0.5) for a, b in zip(s, e)]), "none": None}[prior]
    return mids, gn.PoseProblem(s, e, np.stack([K] * n), pairs, prior_poses=G, prior_sigma=sigma)


@pytest.mark.parametrize("prior", ["true", "start"])  # "start": M = G at x = 0, the log at the identity
@pytest.mark.parametrize("scale", [0.0, 1e-2, 0.2])
def test_pose_prior_jacobian_matches_central_differences(prior, scale):
    _, prob = _prior_problem(n=3, prior=prior)
    x = np.random.default_rng(6).normal(0, 1, prob.num_params) * scale
    r, J = prob.residuals(x, 100.0, 1e-3)
    assert r.shape[0] == 3 * prob.num_matches + 12 * len(prob.free) and np.all(np.isfinite(J))
    Jfd = _fd_jacobian(prob, x, FD_STEP)
    assert np.abs(J - Jfd).max() <= FD_REL_TOL * np.abs(J).max()
    if prior == "start" and scale == 0.0:
        assert np.abs(r[-6 * len(prob.free):]).max() < 1e-12  # at the prior poses the prior rows vanish


def test_pose_prior_rows_are_centre_and_rotation_errors_over_sigma():
    mids, prob = _prior_problem(n=3, sigma=(0.05, 0.02))
    r, _ = prob.residuals(np.zeros(prob.num_params), 100.0, 1e-3, False)
    start_mids = prob.poses(np.zeros(prob.num_params))[2]
    for i, k in enumerate(prob.free):
        rows = r[3 * prob.num_matches + 6 * len(prob.free) + 6 * i:][:6]
        assert np.allclose(rows[:3], (camera_center(start_mids[k]) - camera_center(mids[k])) / 0.05, atol=1e-10)
        angle = np.linalg.norm(so3_log(start_mids[k][:3, :3] @ mids[k][:3, :3].T))
        assert np.isclose(np.linalg.norm(rows[3:]), angle / 0.02, rtol=1e-9, atol=1e-12)


def test_pose_prior_pulls_toward_the_given_poses_when_depths_are_biased():
    """Depths 30 % too small (a scene whose render is biased near): the data alone want a
    trajectory 0.7x its size; a tight prior on the given (here true) poses keeps it."""
    def size(mids):
        c = camera_center(mids)
        return np.linalg.norm(c - c[0], axis=1).sum()
    mids, free = _prior_problem(n=5, prior="none", depth_factor=0.7)
    _, held = _prior_problem(n=5, prior="true", depth_factor=0.7, sigma=(1e-3, 1e-3))
    cfg = GaussNewtonConfig(max_iters=40)
    true_spread = size(mids)
    r_free, r_held = gn.solve(free, cfg), gn.solve(held, cfg)
    assert size(r_free.mids) / true_spread < 0.8
    assert abs(size(r_held.mids) / true_spread - 1) < 0.02
    assert r_held.rank == r_held.num_params and np.all(np.isfinite(r_held.covariance))


def test_pose_prior_bad_inputs_are_named():
    mids, starts, ends, X = _scene(3)
    with pytest.raises(ValueError, match="prior_poses"):
        gn.PoseProblem(starts, ends, np.stack([K] * 3), _pairs(mids, X), prior_poses=mids[:2])
    with pytest.raises(ValueError, match="prior_sigma"):
        gn.PoseProblem(starts, ends, np.stack([K] * 3), _pairs(mids, X), prior_poses=mids, prior_sigma=(0.0, 1.0))
