"""Tests for d2gs_np.geometry.se3 (tangents ordered (rho, phi), left perturbations exp(delta) T).

- exp/log round trips in every rotation regime (see test_so3.REGIMES) with random translations;
- the 6x6 left/right Jacobians and the inverse left Jacobian against central finite differences
  on the manifold, and their identities (inverses, J_r(xi) = J_l(-xi), J_l = Ad(exp xi) J_r);
- adjoint, inverse, geodesic interpolation (endpoints, midpoint, constant speed, near pi);
- the matrix-to-tangent gradient against FD of f(exp(h e_i) T); check_rigid; batching; dtypes.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from d2gs_np.constants import LOG_SYMMETRIC_BRANCH_COS, POSE_ROUNDING_TOL, RIGID_TOL, SERIES_ANGLE2
from d2gs_np.geometry import quaternion
from d2gs_np.geometry.se3 import (
    check_rigid, matrix_grad_to_left_tangent, nearest_rigid, rigid_deviation, se3_adjoint, se3_compose, se3_exp,
    se3_interpolate, se3_inverse, se3_left_jacobian, se3_left_jacobian_inv, se3_log, se3_right_jacobian,
    se3_right_jacobian_inv,
)

EPS = np.finfo(np.float64).eps

# --- Tolerances (same reasoning as test_so3.py; translations are O(1)) ----------------------------
ROUND_TRIP_TOL = 1e-12  # the requirement; measured worst ~2e-15
# Relative accuracy of the rotation part w.r.t. |phi| (absolute 1e-12 is vacuous at theta = 1e-12).
ROUND_TRIP_REL_TOL = 1e-14
FD_STEP = 1e-5
# Central FD, h = 1e-5: truncation ~h^2 |d^3 f| ~ 1e-11, rounding ~eps/h * |xi| ~ 1e-10 with
# |rho| ~ 2 (measured worst 5e-11); 1e-9 leaves a margin of 20.
FD_TOL = 1e-9
INVERSE_TOL = 1e-13  # products of 6x6 blocks with entries up to ~|rho| ~ 3: a few ulps of that
BATCH_TOL = 4 * EPS  # same arithmetic per element; allow for different BLAS paths of stacked matmuls
LOG_CUT_MARGIN = 1e-3  # inverse-Jacobian FD stays this far inside |phi| = pi, >> FD_STEP
ADJOINT_TOL = 1e-13  # T exp(d) T^-1 vs exp(Ad d): a few rounded 4x4 products with |t| ~ 3

_SIDE = 1e-12
REGIMES = {
    "zero": 0.0,
    "1e-12": 1e-12,
    "1e-8": 1e-8,
    "1e-4": 1e-4,
    "series_below": math.sqrt(SERIES_ANGLE2) * (1.0 - _SIDE),
    "series_above": math.sqrt(SERIES_ANGLE2) * (1.0 + _SIDE),
    "skew_log_branch": math.acos(LOG_SYMMETRIC_BRANCH_COS + _SIDE),
    "symmetric_log_branch": math.acos(LOG_SYMMETRIC_BRANCH_COS - _SIDE),
    "random": None,
    "pi_minus_1e-4": math.pi - 1e-4,
    "pi_minus_1e-9": math.pi - 1e-9,
    "pi": math.pi,
}
N_PER_REGIME = 32


def unit_vectors(rng, n):
    a = rng.normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def regime_angles(name, rng, n=N_PER_REGIME):
    theta = REGIMES[name]
    return rng.uniform(0.0, math.pi, size=n) if theta is None else np.full(n, theta)


def regime_xis(name, rng, n=N_PER_REGIME):
    """(n, 6) tangents: rho ~ N(0, 1), |phi| in the regime."""
    phi = unit_vectors(rng, n) * regime_angles(name, rng, n)[:, None]
    return np.concatenate([rng.normal(size=(n, 3)), phi], axis=1)


def seeded(name):
    return np.random.default_rng(list(REGIMES).index(name) + 200)


def random_poses(rng, n):
    """Rigid transforms built without se3_exp (quaternion rotation, normal translation)."""
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = quaternion.quat_to_rotmat(rng.normal(size=(n, 4)))
    T[:, :3, 3] = rng.normal(size=(n, 3))
    T[:, 3, 3] = 1.0
    return T


# --- Round trips ---------------------------------------------------------------------------------


@pytest.mark.parametrize("regime", [r for r in REGIMES if r != "pi"])
def test_log_of_exp_recovers_xi(regime):
    xi = regime_xis(regime, seeded(regime))
    back = se3_log(se3_exp(xi))
    assert np.abs(back - xi).max() <= ROUND_TRIP_TOL
    phi_err = np.linalg.norm(back[:, 3:] - xi[:, 3:], axis=1)
    assert np.all(phi_err <= ROUND_TRIP_REL_TOL * np.linalg.norm(xi[:, 3:], axis=1))


@pytest.mark.parametrize("regime", list(REGIMES))
def test_exp_of_log_recovers_pose(regime):
    rng = seeded(regime)
    axes = unit_vectors(rng, N_PER_REGIME)
    theta = regime_angles(regime, rng)
    q = np.concatenate([np.cos(0.5 * theta)[:, None], np.sin(0.5 * theta)[:, None] * axes], axis=1)
    T = np.zeros((N_PER_REGIME, 4, 4))
    T[:, :3, :3] = quaternion.quat_to_rotmat(q)
    T[:, :3, 3] = 3.0 * rng.normal(size=(N_PER_REGIME, 3))
    T[:, 3, 3] = 1.0
    xi = se3_log(T)
    assert np.abs(se3_exp(xi) - T).max() <= ROUND_TRIP_TOL
    np.testing.assert_allclose(np.linalg.norm(xi[:, 3:], axis=1), theta, rtol=0, atol=ROUND_TRIP_TOL)


def test_log_at_exactly_pi():
    """|phi| = pi: log(exp(xi)) is xi or its twin with -phi (and the matching rho); both exponentiate to T."""
    xi = regime_xis("pi", seeded("pi"))
    T = se3_exp(xi)
    back = se3_log(T)
    assert np.abs(se3_exp(back) - T).max() <= ROUND_TRIP_TOL
    np.testing.assert_allclose(np.linalg.norm(back[:, 3:], axis=1), math.pi, rtol=0, atol=ROUND_TRIP_TOL)
    same = np.linalg.norm(back[:, 3:] - xi[:, 3:], axis=1) <= ROUND_TRIP_TOL
    flipped = np.linalg.norm(back[:, 3:] + xi[:, 3:], axis=1) <= ROUND_TRIP_TOL
    assert np.all(same | flipped)
    assert np.abs(back[same] - xi[same]).max(initial=0.0) <= ROUND_TRIP_TOL


# --- Batching, dtype, inverse, compose -------------------------------------------------------------

_MIXED = ["zero", "1e-8", "series_below", "series_above", "symmetric_log_branch", "pi_minus_1e-9"]


def _mixed_xis(n, rng):
    return np.stack([regime_xis(_MIXED[i % len(_MIXED)], rng, 1)[0] for i in range(n)])


@pytest.mark.parametrize("batch", [(5,), (2, 3)])
@pytest.mark.parametrize(
    "func", [se3_exp, se3_left_jacobian, se3_left_jacobian_inv, se3_right_jacobian, se3_right_jacobian_inv],
    ids=lambda f: f.__name__,
)
def test_batched_tangent_functions_match_per_element(batch, func):
    rng = np.random.default_rng(21)
    xi = _mixed_xis(math.prod(batch), rng).reshape(batch + (6,))
    out = func(xi)
    single = np.stack([func(x) for x in xi.reshape(-1, 6)]).reshape(out.shape)
    assert out.shape[: len(batch)] == batch
    assert np.abs(out - single).max() <= BATCH_TOL


@pytest.mark.parametrize("batch", [(5,), (2, 3)])
@pytest.mark.parametrize("func", [se3_log, se3_inverse, se3_adjoint], ids=lambda f: f.__name__)
def test_batched_pose_functions_match_per_element(batch, func):
    rng = np.random.default_rng(22)
    T = se3_exp(_mixed_xis(math.prod(batch), rng)).reshape(batch + (4, 4))
    out = func(T)
    single = np.stack([func(m) for m in T.reshape(-1, 4, 4)]).reshape(out.shape)
    assert out.shape[: len(batch)] == batch
    assert np.abs(out - single).max() <= BATCH_TOL


def test_inverse_and_compose():
    rng = np.random.default_rng(23)
    A, B = random_poses(rng, 2)
    np.testing.assert_allclose(se3_inverse(A) @ A, np.eye(4), rtol=0, atol=1e-14)
    np.testing.assert_allclose(A @ se3_inverse(A), np.eye(4), rtol=0, atol=1e-14)
    np.testing.assert_array_equal(se3_compose(A, B), A @ B)


@pytest.mark.parametrize(
    "func, bad", [(se3_exp, np.zeros(3)), (se3_log, np.eye(3)), (se3_inverse, np.zeros((3, 4))),
                  (se3_left_jacobian, np.zeros((2, 5))), (se3_adjoint, np.eye(3))],
    ids=lambda x: getattr(x, "__name__", ""),
)
def test_wrong_shapes_raise(func, bad):
    with pytest.raises(ValueError, match="shape"):
        func(bad)


def test_float32_exp_stays_float32():
    xi = np.array([[0.1, -0.4, 2.0, 0.3, -0.2, 0.5], [1.0, 0.0, 0.0, 0.0, 3.0, 0.1]], dtype=np.float32)
    T = se3_exp(xi)
    assert T.dtype == np.float32
    np.testing.assert_allclose(T, se3_exp(xi.astype(np.float64)), rtol=0, atol=1e-6)


def test_float32_log_stays_float32():
    xi = np.array([[0.1, -0.4, 2.0, 0.3, -0.2, 0.5], [1.0, 0.0, 0.0, 0.0, 3.0, 0.1]])
    T32 = se3_exp(xi).astype(np.float32)
    out = se3_log(T32)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, xi, rtol=0, atol=1e-5)  # ~1e-7 relative per entry, |xi| ~ 3


# --- Jacobians -------------------------------------------------------------------------------------


def _fd(func, xi, h=FD_STEP):
    """Central differences of func(xi + h e_i), one column per tangent direction."""
    J = np.zeros((6, 6))
    for i in range(6):
        e = np.zeros(6)
        e[i] = h
        J[:, i] = (func(xi + e) - func(xi - e)) / (2 * h)
    return J


def fd_left_jacobian(xi):
    """log(exp(xi + h e_i) exp(xi)^-1): only logs of near-identity poses, valid at any |phi|."""
    T_inv = se3_inverse(se3_exp(xi))
    return _fd(lambda x: se3_log(se3_exp(x) @ T_inv), xi)


def fd_right_jacobian(xi):
    T_inv = se3_inverse(se3_exp(xi))
    return _fd(lambda x: se3_log(T_inv @ se3_exp(x)), xi)


def fd_log_left_derivative(xi):
    """d/dd log(exp(d) exp(xi)) at d = 0, which is J_l(xi)^-1 for |phi| < pi."""
    T = se3_exp(xi)
    return _fd(lambda d: se3_log(se3_exp(d) @ T), np.zeros(6))


JAC_SAMPLES = 3


@pytest.mark.parametrize("regime", list(REGIMES))
def test_left_and_right_jacobians_match_manifold_fd(regime):
    for xi in regime_xis(regime, seeded(regime), JAC_SAMPLES):
        np.testing.assert_allclose(se3_left_jacobian(xi), fd_left_jacobian(xi), rtol=0, atol=FD_TOL)
        np.testing.assert_allclose(se3_right_jacobian(xi), fd_right_jacobian(xi), rtol=0, atol=FD_TOL)


@pytest.mark.parametrize("regime", [r for r in REGIMES if r not in ("pi_minus_1e-9", "pi")] + ["inside_cut"])
def test_inverse_left_jacobian_is_the_derivative_of_log(regime):
    if regime == "inside_cut":
        rng = np.random.default_rng(24)
        phi = unit_vectors(rng, JAC_SAMPLES) * (math.pi - LOG_CUT_MARGIN)
        xis = np.concatenate([rng.normal(size=(JAC_SAMPLES, 3)), phi], axis=1)
    else:
        xis = regime_xis(regime, seeded(regime), JAC_SAMPLES)
    for xi in xis:
        np.testing.assert_allclose(se3_left_jacobian_inv(xi), fd_log_left_derivative(xi), rtol=0, atol=FD_TOL)


@pytest.mark.parametrize("regime", list(REGIMES))
def test_jacobian_identities(regime):
    for xi in regime_xis(regime, seeded(regime), 8):
        Jl, Jr = se3_left_jacobian(xi), se3_right_jacobian(xi)
        np.testing.assert_allclose(Jl @ se3_left_jacobian_inv(xi), np.eye(6), rtol=0, atol=INVERSE_TOL)
        np.testing.assert_allclose(se3_left_jacobian_inv(xi) @ Jl, np.eye(6), rtol=0, atol=INVERSE_TOL)
        np.testing.assert_allclose(Jr @ se3_right_jacobian_inv(xi), np.eye(6), rtol=0, atol=INVERSE_TOL)
        np.testing.assert_allclose(Jr, se3_left_jacobian(-xi), rtol=0, atol=INVERSE_TOL)
        # exp(xi) exp(J_r d) = exp(xi + d) = exp(J_l d) exp(xi)  =>  J_l = Ad(exp(xi)) J_r.
        np.testing.assert_allclose(Jl, se3_adjoint(se3_exp(xi)) @ Jr, rtol=0, atol=INVERSE_TOL)
        np.testing.assert_allclose(Jl @ xi, xi, rtol=0, atol=INVERSE_TOL)


# --- Adjoint ---------------------------------------------------------------------------------------


def test_adjoint_conjugates_the_exponential():
    rng = np.random.default_rng(25)
    for T in random_poses(rng, 8):
        T[:3, 3] *= 3.0
        d = 0.7 * rng.normal(size=6)
        np.testing.assert_allclose(
            T @ se3_exp(d) @ se3_inverse(T), se3_exp(se3_adjoint(T) @ d), rtol=0, atol=ADJOINT_TOL
        )


def test_adjoint_is_a_homomorphism():
    rng = np.random.default_rng(26)
    A, B = random_poses(rng, 2)
    np.testing.assert_allclose(se3_adjoint(A @ B), se3_adjoint(A) @ se3_adjoint(B), rtol=0, atol=ADJOINT_TOL)
    np.testing.assert_allclose(se3_adjoint(se3_inverse(A)) @ se3_adjoint(A), np.eye(6), rtol=0, atol=ADJOINT_TOL)


# --- Geodesic interpolation ------------------------------------------------------------------------

INTERP_TOL = 1e-12  # endpoints and equal steps: a handful of rounded exp/log/products


def _pose_pair(rng, angle):
    Ts = random_poses(rng, 1)[0]
    delta = np.concatenate([rng.normal(size=3), unit_vectors(rng, 1)[0] * angle])
    return Ts, Ts @ se3_exp(delta), delta


@pytest.mark.parametrize("angle", [0.0, 1e-8, 0.4, 2.5, math.pi - 1e-9])
def test_interpolation_endpoints_midpoint_and_speed(angle):
    rng = np.random.default_rng(27)
    Ts, Te, delta = _pose_pair(rng, angle)
    np.testing.assert_allclose(se3_interpolate(Ts, Te, 0.0), Ts, rtol=0, atol=INTERP_TOL)
    np.testing.assert_allclose(se3_interpolate(Ts, Te, 1.0), Te, rtol=0, atol=INTERP_TOL)
    assert se3_interpolate(Ts, Te, 0.3).shape == (4, 4)

    # Midpoint: equally far (geodesic distance |log|) from both ends, each half of the way.
    mid = se3_interpolate(Ts, Te, 0.5)
    to_mid = se3_log(se3_inverse(Ts) @ mid)
    from_mid = se3_log(se3_inverse(mid) @ Te)
    np.testing.assert_allclose(to_mid, from_mid, rtol=0, atol=INTERP_TOL)
    np.testing.assert_allclose(to_mid, 0.5 * delta, rtol=0, atol=INTERP_TOL)

    # Constant speed: every step of a uniform grid is the same relative motion delta / (M - 1).
    u = np.linspace(0.0, 1.0, 9)
    path = se3_interpolate(Ts, Te, u)
    assert path.shape == (9, 4, 4) and np.all(np.isfinite(path))
    steps = se3_log(se3_inverse(path[:-1]) @ path[1:])
    np.testing.assert_allclose(steps, np.broadcast_to(delta / 8, steps.shape), rtol=0, atol=INTERP_TOL)
    check_rigid(path, "path")


def test_interpolation_between_identical_poses_is_constant():
    rng = np.random.default_rng(28)
    T = random_poses(rng, 1)[0]
    path = se3_interpolate(T, T, np.linspace(0.0, 1.0, 7))
    np.testing.assert_allclose(path, np.broadcast_to(T, path.shape), rtol=0, atol=4 * EPS)


def test_interpolation_at_pi_apart_is_finite_and_hits_the_end():
    """Exactly pi apart the geodesic is not unique; either choice must be finite and end at T_e."""
    rng = np.random.default_rng(29)
    Ts, Te, _ = _pose_pair(rng, math.pi)
    path = se3_interpolate(Ts, Te, np.linspace(0.0, 1.0, 5))
    assert np.all(np.isfinite(path))
    np.testing.assert_allclose(path[-1], Te, rtol=0, atol=INTERP_TOL)
    check_rigid(path, "path")


# --- Gradient conversion -------------------------------------------------------------------------

GRAD_FD_REL_TOL = 1e-8  # central FD, h = 1e-5, of a function of size ~10 with O(1) curvature


@pytest.mark.parametrize("kind", ["linear", "quadratic"])
def test_matrix_grad_to_left_tangent_matches_fd(kind):
    """f(T) = sum(W * (T P)) (or sum(W * (T P)^2)) over homogeneous points P; compare the tangent
    gradient with central FD of f(exp(h e_i) T)."""
    rng = np.random.default_rng(30)
    P = np.concatenate([rng.normal(size=(3, 7)), np.ones((1, 7))])  # (4, K) homogeneous points
    W = rng.normal(size=(4, 7))
    if kind == "linear":
        f = lambda T: np.sum(W * (T @ P))  # noqa: E731
        grad = lambda T: W @ P.T  # noqa: E731
    else:
        f = lambda T: np.sum(W * (T @ P) ** 2)  # noqa: E731
        grad = lambda T: (2.0 * W * (T @ P)) @ P.T  # noqa: E731
    for T in se3_exp(regime_xis("random", rng, 3)):
        v = matrix_grad_to_left_tangent(T, grad(T))
        fd = np.zeros(6)
        for i in range(6):
            e = np.zeros(6)
            e[i] = FD_STEP
            fd[i] = (f(se3_exp(e) @ T) - f(se3_exp(-e) @ T)) / (2 * FD_STEP)
        scale = np.abs(fd).max()
        np.testing.assert_allclose(v, fd, rtol=0, atol=GRAD_FD_REL_TOL * scale)


def test_matrix_grad_to_left_tangent_batched():
    rng = np.random.default_rng(31)
    T = se3_exp(regime_xis("random", rng, 6)).reshape(2, 3, 4, 4)
    v_T = rng.normal(size=(2, 3, 4, 4))
    out = matrix_grad_to_left_tangent(T, v_T)
    single = np.stack([matrix_grad_to_left_tangent(a, b) for a, b in zip(T.reshape(-1, 4, 4), v_T.reshape(-1, 4, 4))])
    assert out.shape == (2, 3, 6)
    assert np.abs(out.reshape(-1, 6) - single).max() <= BATCH_TOL


# --- check_rigid -----------------------------------------------------------------------------------


def _valid_pose():
    return se3_exp(np.array([0.3, -1.0, 2.0, 0.4, -0.7, 1.1]))


def _with(T, **changes):
    T = T.copy()
    for key, value in changes.items():
        T[{"nan": (1, 2), "inf": (0, 3), "bottom": (3, 2)}[key]] = value
    return T


@pytest.mark.parametrize(
    "bad, pattern",
    [
        (_with(_valid_pose(), nan=np.nan), "NaN"),
        (_with(_valid_pose(), inf=np.inf), "inf"),
        (np.eye(4)[:3], r"shape \(\.\.\., 4, 4\)"),
        (np.eye(3), r"shape"),
        (np.diag([1.01, 1.0, 1.0, 1.0]) @ _valid_pose(), "not rigid"),  # scaled: R^T R != I
        (np.diag([1.0, 1.0, -1.0, 1.0]) @ _valid_pose(), r"not rigid.*det"),  # reflection, det -1
        (_with(_valid_pose(), bottom=1e-3), "bottom row"),
    ],
    ids=["nan", "inf", "shape_3x4", "shape_3x3", "scaled", "reflection", "bottom_row"],
)
def test_check_rigid_rejects(bad, pattern):
    with pytest.raises(ValueError, match=pattern) as info:
        check_rigid(bad, name="pose_start")
    assert "pose_start" in str(info.value)


def test_check_rigid_accepts_valid_and_slightly_drifted_poses():
    rng = np.random.default_rng(32)
    check_rigid(_valid_pose(), "T")
    check_rigid(se3_exp(regime_xis("random", rng, 6)).reshape(2, 3, 4, 4), "poses")
    drifted = _valid_pose()
    drifted[:3, :3] += 1e-9 * rng.normal(size=(3, 3))  # well inside RIGID_TOL = 1e-6
    check_rigid(drifted, "T")
    check_rigid(np.eye(4), "T")


# --- nearest_rigid: poses rigid up to the rounding of an export ----------------------------------
# Rounded to 6 decimals, each entry is off by <= 5e-7; the nearest rotation is within a few of those.
ROUNDED6_TOL = 1e-6
PROJECTED_TOL = 1e-14  # the SVD projection's result is orthonormal to a few ulps (test_so3.ORTHO_TOL)


def _rounded_poses(angles, rng, n=400):
    """Poses with rotation angles drawn from ``angles`` about random axes, random translations ~3,
    and their 6-decimal roundings."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    xi = np.concatenate([3.0 * rng.normal(size=(n, 3)), axes * rng.choice(angles, size=(n, 1))], axis=1)
    T = se3_exp(xi)
    return T, np.round(T, 6)


@pytest.mark.parametrize("regime, angles", [
    ("near_zero", [0.0, 1e-12, 1e-8, 1e-4]),
    ("near_pi", [math.pi, math.pi - 1e-12, math.pi - 1e-8, math.pi - 1e-4]),
    ("random", np.linspace(0.1, 3.0, 30)),
])
def test_nearest_rigid_gives_back_a_rotation_from_6_decimals(regime, angles):
    T, rounded = _rounded_poses(angles, np.random.default_rng(41))
    out, dev = nearest_rigid(rounded, "poses")
    fixed = dev > RIGID_TOL
    if regime == "near_zero":
        # R_ji = -R_ij off the diagonal and round(-x) = -round(x): the rounding error is skew, so
        # R^T R - I = E + E^T vanishes to first order and nothing leaves RIGID_TOL
        assert not fixed.any()
    else:
        assert 0 < fixed.sum() < len(T)  # some roundings leave RIGID_TOL, the ones within it are kept
    np.testing.assert_array_equal(out[~fixed], rounded[~fixed])
    assert rigid_deviation(out[fixed]).max(initial=0.0) <= PROJECTED_TOL
    assert np.linalg.det(out[fixed, :3, :3]).min(initial=1.0) > 0
    np.testing.assert_array_equal(out[:, :3, 3], rounded[:, :3, 3])  # translations kept
    assert np.abs(out[:, :3, :3] - T[:, :3, :3]).max() <= ROUNDED6_TOL
    check_rigid(out[fixed], "projected")
    # near pi the rotation angle stays near pi (no jump to the other side of the cut)
    cos = np.clip((np.trace(out[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)
    cos_true = np.clip((np.trace(T[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)
    assert np.abs(np.arccos(cos) - np.arccos(cos_true)).max() <= 2e-3  # arccos is steep at the ends


@pytest.mark.parametrize("angle", [0.0, 1e-10, 1e-6, math.pi - 1e-10, math.pi])
def test_nearest_rigid_projects_drifted_rotations_near_0_and_pi(angle):
    """Entry noise of 1e-5 (not skew): projected to a rotation, which keeps the skew part of the noise
    only, so it stays within the noise of the truth, and its angle near 0 or near pi."""
    rng = np.random.default_rng(44)
    axes = rng.normal(size=(50, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    T = se3_exp(np.concatenate([rng.normal(size=(50, 3)), angle * axes], axis=1))
    noise = 1e-5 * rng.normal(size=(50, 3, 3))
    drifted = T.copy()
    drifted[:, :3, :3] += noise
    out, dev = nearest_rigid(drifted, "T")
    assert dev.min() > RIGID_TOL and rigid_deviation(out).max() <= PROJECTED_TOL
    assert np.abs(out[:, :3, :3] - T[:, :3, :3]).max() <= np.abs(noise).max()
    phi = np.linalg.norm(se3_log(out)[:, 3:], axis=1)
    # the kept skew part, |entries| <= max |noise| ~ 4e-5, turns the rotation by at most ~sqrt(2) of that
    assert np.abs(phi - angle).max() <= 1e-4


def test_nearest_rigid_keeps_rigid_poses_bitwise_and_reports_deviation():
    rng = np.random.default_rng(42)
    T = se3_exp(regime_xis("random", rng, 6))
    out, dev = nearest_rigid(T, "T")
    np.testing.assert_array_equal(out, T)
    assert dev.shape == (6,) and dev.max() <= 1e-14
    drifted = _valid_pose()
    drifted[:3, :3] += 2e-4 * rng.normal(size=(3, 3))
    out, dev = nearest_rigid(drifted, "T")
    assert RIGID_TOL < dev <= POSE_ROUNDING_TOL and rigid_deviation(out) <= PROJECTED_TOL


@pytest.mark.parametrize(
    "bad, pattern",
    [
        (np.diag([1.0, 1.0, -1.0, 1.0]) @ _valid_pose(), r"not rigid: det\(R\) = -1 <= 0, a reflection"),
        (np.diag([1.002, 1.0, 1.0, 1.0]) @ _valid_pose(), r"not rigid: the singular values of R are in \[1, 1.002\]"),
        (_with(_valid_pose(), bottom=2e-3), r"not rigid: bottom row"),
        (np.zeros((4, 4)), r"det\(R\) = 0 <= 0"),
        (_with(_valid_pose(), nan=np.nan), "NaN"),
        (np.eye(3), "shape"),
    ],
    ids=["reflection", "scale", "bottom_row", "singular", "nan", "shape"],
)
def test_nearest_rigid_refuses_what_is_not_a_rotation(bad, pattern):
    with pytest.raises(ValueError, match=pattern) as info:
        nearest_rigid(bad, "c2w")
    assert str(info.value).startswith("c2w ")


def test_nearest_rigid_tolerance_is_both_orthogonality_products():
    """R R^T - I and R^T R - I differ off orthogonal: the loader inverts its poses, so both count."""
    rng = np.random.default_rng(43)
    for _ in range(200):
        M = _valid_pose()
        M[:3, :3] += 1e-6 * rng.normal(size=(3, 3))
        R = M[:3, :3]
        a, b = np.abs(R.T @ R - np.eye(3)).max(), np.abs(R @ R.T - np.eye(3)).max()
        assert rigid_deviation(M) >= max(a, b)
        out, _ = nearest_rigid(M, "T")
        check_rigid(out, "T")
        check_rigid(se3_inverse(out), "inverse")
