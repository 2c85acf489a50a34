"""Tests of the virtual poses of an exposure (d2gs_np.blur.virtual_poses): the sub-frame offsets
and times, Eq. 9's geodesic, n = 1 and zero spread giving the estimate itself, and the
hand-derived endpoint derivative against central finite differences."""
from __future__ import annotations

import numpy as np
import pytest

import render_fixtures as rf
from d2gs_np.blur.virtual_poses import (
    exposure_offsets,
    knot_weights,
    subframe_times,
    three_knot_poses,
    three_knot_poses_bwd,
    three_knot_poses_fwd,
    virtual_poses,
    virtual_poses_bwd,
    virtual_poses_fwd,
)
from d2gs_np.geometry import matrix_grad_to_left_tangent, se3_exp, se3_interpolate, se3_inverse, se3_log

# Virtual poses: smooth closed forms of O(1); step 1e-6 gives truncation ~1e-12 and round-off
# ~1e-10 on a loss of size ~10; wrong Jacobian terms are O(1e-2..1).
POSE_FD_STEP = 1e-6
POSE_FD_ATOL = 1e-8
# Geodesic identities evaluated two ways in float64 (exp/log round trips of O(1) matrices).
POSE_ATOL = 1e-12


def _random_pose(rng):
    return se3_exp(rng.normal(size=6))


def test_offsets_and_times():
    np.testing.assert_array_equal(exposure_offsets(1), [0.5])
    np.testing.assert_array_equal(exposure_offsets(5), [0.0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(subframe_times(0.3, 0.2, 3), [0.2, 0.3, 0.4], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(subframe_times(0.3, 0.2, 1), [0.3])


def test_virtual_poses_endpoints_and_midpoint():
    rng = np.random.default_rng(1)
    T_hat = _random_pose(rng)
    xs, xe = 0.3 * rng.normal(size=6), 0.3 * rng.normal(size=6)
    T_s, T_e = se3_exp(xs) @ T_hat, se3_exp(xe) @ T_hat
    n = 9
    poses = virtual_poses(T_hat, xs, xe, n)
    assert poses.shape == (n, 4, 4)
    np.testing.assert_allclose(poses[0], T_s, atol=POSE_ATOL)  # u = 0
    np.testing.assert_allclose(poses[-1], T_e, atol=POSE_ATOL)  # u = 1
    mid = poses[n // 2]  # u = 0.5: equidistant along the geodesic
    np.testing.assert_allclose(se3_log(se3_inverse(mid) @ T_s), -se3_log(se3_inverse(mid) @ T_e), atol=POSE_ATOL)
    # every virtual pose is Eq. 9, T_s exp(u log(T_s^-1 T_e)), evaluated by the geometry module
    np.testing.assert_allclose(poses, se3_interpolate(T_s, T_e, exposure_offsets(n)), atol=POSE_ATOL)


def test_virtual_poses_n1_and_zero_spread_are_the_estimate():
    rng = np.random.default_rng(2)
    T_hat = _random_pose(rng)
    xs, xe = rng.normal(size=6), rng.normal(size=6)
    np.testing.assert_array_equal(virtual_poses(T_hat, xs, xe, 1), T_hat[None])  # xi ignored
    zero = np.zeros(6)
    np.testing.assert_array_equal(virtual_poses(T_hat, zero, zero, 8), np.broadcast_to(T_hat, (8, 4, 4)))
    v_s, v_e = virtual_poses_bwd(virtual_poses_fwd(T_hat, xs, xe, 1)[1], rng.normal(size=(1, 6)))
    np.testing.assert_array_equal(v_s, 0.0)
    np.testing.assert_array_equal(v_e, 0.0)


def _axis(rng):
    a = rng.normal(size=3)
    return a / np.linalg.norm(a)


def _pose_cases():
    rng = np.random.default_rng(3)
    x = 0.4 * rng.normal(size=6)
    a = _axis(rng)
    half = 0.5 * (np.pi - 1e-3)  # start and end 1e-3 rad short of a half turn apart
    return {
        "generic": (0.4 * rng.normal(size=6), 0.4 * rng.normal(size=6)),
        "zero_length": (x, x.copy()),
        "zero": (np.zeros(6), np.zeros(6)),
        "tiny": (x, x + 1e-9 * rng.normal(size=6)),
        "near_pi": (np.r_[0.2 * rng.normal(size=3), -half * a], np.r_[0.2 * rng.normal(size=3), half * a]),
        "large_endpoints": (np.r_[rng.normal(size=3), 2.5 * _axis(rng)], np.r_[rng.normal(size=3), 2.0 * _axis(rng)]),
    }


@pytest.mark.parametrize("name", list(_pose_cases()))
@pytest.mark.parametrize("n", [2, 5, 8])
def test_virtual_poses_gradient_matches_fd(name, n):
    xs, xe = _pose_cases()[name]
    rng = np.random.default_rng(4)
    T_hat = _random_pose(rng)
    if name == "near_pi":  # the relative rotation really is ~pi (not wrapped to a short way round)
        delta = se3_log(se3_inverse(se3_exp(xs)) @ se3_exp(xe))
        assert abs(np.linalg.norm(delta[3:]) - (np.pi - 1e-3)) < 1e-9
    Wt = rng.normal(size=(n, 4, 4))
    Wt[:, 3, :] = 0.0  # loss = sum_i <Wt_i, T(u_i)> over the rigid part

    def loss(a, b):
        return float(np.sum(Wt * virtual_poses(T_hat, a, b, n)))

    poses, saved = virtual_poses_fwd(T_hat, xs, xe, n)
    g = np.stack([matrix_grad_to_left_tangent(poses[i], Wt[i]) for i in range(n)])
    v_s, v_e = virtual_poses_bwd(saved, g)
    fd_s = rf.central_fd(lambda a: loss(a, xe), xs, POSE_FD_STEP)
    fd_e = rf.central_fd(lambda b: loss(xs, b), xe, POSE_FD_STEP)
    np.testing.assert_allclose(v_s, fd_s, rtol=0, atol=POSE_FD_ATOL * max(1.0, np.abs(fd_s).max()))
    np.testing.assert_allclose(v_e, fd_e, rtol=0, atol=POSE_FD_ATOL * max(1.0, np.abs(fd_e).max()))
    assert np.all(np.isfinite(v_s)) and np.all(np.isfinite(v_e))


def test_virtual_poses_input_validation():
    T = np.eye(4)
    z = np.zeros(6)
    with pytest.raises(ValueError, match="xi_start must have shape"):
        virtual_poses(T, np.zeros(5), z, 4)
    with pytest.raises(ValueError, match="n .* must be an integer >= 1"):
        virtual_poses(T, z, z, 0)
    with pytest.raises(TypeError, match="xi_end must have dtype"):
        virtual_poses(T, z, z.astype(np.float32), 4)
    with pytest.raises(ValueError, match="not rigid"):
        virtual_poses(2.0 * T, z, z, 4)



# ------------------------------------------------------------- the three-knot path
def _three_knot_cases():
    rng = np.random.default_rng(5)
    a = _axis(rng)
    half = 0.5 * (np.pi - 1e-3)
    x = 0.3 * rng.normal(size=6)
    return {
        "generic": tuple(0.3 * rng.normal(size=(3, 6))),
        "zero": (np.zeros(6),) * 3,
        "zero_length": (x, x.copy(), x.copy()),
        "tiny": (x, x + 1e-9 * rng.normal(size=6), x + 1e-9 * rng.normal(size=6)),
        # the tangents reach nearly a half turn: exp's Jacobian near its series branch and near pi
        "near_pi": (np.r_[0.2 * rng.normal(size=3), -half * a], np.r_[0.1 * rng.normal(size=3), 0.0, 0.0, 0.0],
                    np.r_[0.2 * rng.normal(size=3), half * a]),
    }


def test_knot_weights_interpolate_the_knots_and_reproduce_quadratics():
    u = np.linspace(0.0, 1.0, 11)
    W = knot_weights(u)
    np.testing.assert_allclose(knot_weights([0.0, 0.5, 1.0]), np.eye(3), atol=0)
    np.testing.assert_allclose(W.sum(axis=1), 1.0, rtol=0, atol=1e-15)  # constants
    for f in (lambda t: t, lambda t: 3 * t * t - t + 0.25):  # any quadratic through its values at the knots
        np.testing.assert_allclose(W @ f(np.array([0.0, 0.5, 1.0])), f(u), rtol=0, atol=1e-14)


def test_three_knot_path_through_its_knots_and_the_geodesic_when_straight():
    rng = np.random.default_rng(6)
    T_hat = _random_pose(rng)
    xs, xm, xe = 0.2 * rng.normal(size=(3, 6))
    poses = three_knot_poses(T_hat, xs, xm, xe, 9)
    for i, x in ((0, xs), (4, xm), (8, xe)):
        np.testing.assert_allclose(poses[i], se3_exp(x) @ T_hat, rtol=0, atol=POSE_ATOL)
    np.testing.assert_allclose(three_knot_poses(T_hat, xs, xm, xe, 1)[0], se3_exp(xm) @ T_hat, rtol=0, atol=POSE_ATOL)
    # symmetric endpoints about T̂ and the middle knot at T̂: the line through T̂, which is the geodesic
    h = 0.05 * rng.normal(size=6)
    np.testing.assert_allclose(three_knot_poses(T_hat, -h, np.zeros(6), h, 8), virtual_poses(T_hat, -h, h, 8),
                               rtol=0, atol=POSE_ATOL)
    zero = np.zeros(6)
    np.testing.assert_array_equal(three_knot_poses(T_hat, zero, zero, zero, 8), np.broadcast_to(T_hat, (8, 4, 4)))


@pytest.mark.parametrize("name", list(_three_knot_cases()))
@pytest.mark.parametrize("n", [1, 2, 5, 8])
def test_three_knot_gradient_matches_fd(name, n):
    knots = _three_knot_cases()[name]
    rng = np.random.default_rng(7)
    T_hat = _random_pose(rng)
    Wt = rng.normal(size=(n, 4, 4))
    Wt[:, 3, :] = 0.0

    def loss(*k):
        return float(np.sum(Wt * three_knot_poses(T_hat, *k, n)))

    poses, saved = three_knot_poses_fwd(T_hat, *knots, n)
    g = np.stack([matrix_grad_to_left_tangent(poses[i], Wt[i]) for i in range(n)])
    grads = three_knot_poses_bwd(saved, g)
    for j in range(3):
        def along(x, j=j):
            k = list(knots)
            k[j] = x
            return loss(*k)
        fd = rf.central_fd(along, knots[j], POSE_FD_STEP)
        np.testing.assert_allclose(grads[j], fd, rtol=0, atol=POSE_FD_ATOL * max(1.0, np.abs(fd).max()),
                                   err_msg=f"knot {j}")
        assert np.all(np.isfinite(grads[j]))
    if n == 1:  # the sharp camera is the middle knot: the endpoints get nothing
        np.testing.assert_array_equal(grads[0], 0.0)
        np.testing.assert_array_equal(grads[2], 0.0)


def test_three_knot_input_validation_and_float32():
    T = np.eye(4)
    z = np.zeros(6)
    with pytest.raises(ValueError, match="xi_mid must have shape"):
        three_knot_poses_fwd(T, z, np.zeros(5), z, 4)
    with pytest.raises(ValueError, match="xi_mid contains NaN"):
        three_knot_poses_fwd(T, z, np.full(6, np.nan), z, 4)
    with pytest.raises(TypeError, match="xi_mid must have dtype"):
        three_knot_poses_fwd(T, z, np.zeros(6, np.float32), z, 4)
    T32, x32 = np.eye(4, dtype=np.float32), np.full(6, 0.01, np.float32)
    poses, saved = three_knot_poses_fwd(T32, x32, -x32, x32, 4)
    assert poses.dtype == np.float32 and all(g.dtype == np.float32 for g in three_knot_poses_bwd(saved, np.ones((4, 6))))
