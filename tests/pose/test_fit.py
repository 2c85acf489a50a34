"""Test-view pose refinement on a frozen scene (d2gs_np/pose/fit.py, d2gs eval --test-pose-opt)."""
import numpy as np
import pytest

from d2gs_np.geometry.se3 import se3_exp, se3_inverse, se3_log
from d2gs_np.pose.config import PoseFitConfig
from d2gs_np.pose.fit import fit_pose
from d2gs_np.render import render_fwd

W, H = 64, 48
K = np.array([[60.0, 0.0, W / 2], [0.0, 60.0, H / 2], [0.0, 0.0, 1.0]])


def _scene(seed=0, n=1500):
    """Small opaque Gaussians with random colours on a plane 3 units in front of the identity camera."""
    rng = np.random.default_rng(seed)
    means = np.c_[rng.uniform(-2.0, 2.0, n), rng.uniform(-1.5, 1.5, n), 3.0 + rng.uniform(-0.05, 0.05, n)]
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    scales = np.full((n, 3), 0.04)
    return dict(means=means, quats=quats, scales=scales, opacities=np.full(n, 0.9), colors=rng.uniform(0, 1, (n, 3)))


def _render(ri, T):
    return render_fwd(**ri, cam_T_world=T, K=K, width=W, height=H, background=np.zeros(3))[0]["image"]


def _err(T, T_ref):
    xi = se3_log(T @ se3_inverse(T_ref))
    return np.linalg.norm(xi[:3]), np.degrees(np.linalg.norm(xi[3:]))


def test_a_perturbed_pose_is_pulled_back_to_the_one_that_rendered_the_target():
    ri = _scene()
    T_true = np.eye(4)
    target = _render(ri, T_true)
    T0 = se3_exp(np.array([0.02, -0.015, 0.01, 0.004, -0.006, 0.003])) @ T_true  # 2 cm, 0.45 deg
    t0, r0 = _err(T0, T_true)
    pose, info = fit_pose(ri, T0, K, W, H, target, config=PoseFitConfig(steps=150, lr=1e-3))
    t1, r1 = _err(pose, T_true)
    assert info["mse"][info["best_step"]] < 0.05 * info["mse"][0]
    assert t1 < 0.2 * t0 and r1 < 0.2 * r0
    np.testing.assert_allclose(se3_exp(info["xi"]) @ T0, pose, atol=1e-12)


def test_zero_steps_and_the_true_pose_stay_where_they_are():
    ri = _scene()
    target = _render(ri, np.eye(4))
    T0 = se3_exp(np.array([0.01, 0.0, 0.0, 0.0, 0.002, 0.0]))
    pose, info = fit_pose(ri, T0, K, W, H, target, config=PoseFitConfig(steps=0))
    assert np.array_equal(pose, T0) and info["mse"].shape == (1,) and info["best_step"] == 0
    # at the optimum (zero error) no step can lower the error: the start is returned
    pose, info = fit_pose(ri, np.eye(4), K, W, H, target, config=PoseFitConfig(steps=5))
    assert info["mse"][0] == 0.0 and info["best_step"] == 0 and np.array_equal(pose, np.eye(4))


def test_never_returns_a_pose_that_scores_worse_than_the_start():
    ri = _scene(1)
    target = np.random.default_rng(2).uniform(0, 1, (H, W, 3))  # no pose explains noise
    T0 = np.eye(4)
    pose, info = fit_pose(ri, T0, K, W, H, target, config=PoseFitConfig(steps=20, lr=5e-2))
    assert info["mse"][info["best_step"]] == info["mse"].min() <= info["mse"][0]
    r = _render(ri, pose) - target
    assert np.mean(r * r) == pytest.approx(info["mse"][info["best_step"]], rel=1e-12)


def test_a_view_that_sees_nothing_stays_finite_and_unmoved():
    ri = _scene()
    behind = np.diag([1.0, -1.0, -1.0, 1.0])  # a half turn about x: the plane is behind the camera
    target = np.zeros((H, W, 3))
    pose, info = fit_pose(ri, behind, K, W, H, target, config=PoseFitConfig(steps=10))
    assert np.all(np.isfinite(info["mse"])) and info["mse"][0] == 0.0
    np.testing.assert_array_equal(pose, behind)


def test_bad_input_is_refused():
    ri = _scene()
    target = _render(ri, np.eye(4))
    with pytest.raises(ValueError, match="target must have shape"):
        fit_pose(ri, np.eye(4), K, W, H, target[:-1])
    bad = target.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fit_pose(ri, np.eye(4), K, W, H, bad)
    sheared = np.eye(4)
    sheared[0, 1] = 0.3
    with pytest.raises(ValueError):
        fit_pose(ri, sheared, K, W, H, target)
