"""Tests for d2gs_np.geometry.quaternion (wxyz, docs/conventions.md §1)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from d2gs_np.geometry.quaternion import quat_multiply, quat_normalize, quat_to_rotmat, rotmat_to_quat
from d2gs_np.geometry.so3 import so3_exp

EPS = np.finfo(np.float64).eps
# Quaternion <-> matrix conversions are a few products and one square root per entry; Shepperd's
# pivot keeps the division well conditioned, so a few ulps per component (measured <= 2.2e-16).
QUAT_TOL = 8 * EPS
# Small components (near-identity rotations) are recovered relative to their own size:
# they come from differences R_ij - R_ji of entries computed to ~1 ulp of themselves.
QUAT_SMALL_REL_TOL = 1e-14


def unit_quats(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, :1] < 0, -q, q)  # w >= 0, the canonical sign of rotmat_to_quat


def unit_vectors(rng, n):
    a = rng.normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def axis_angle_quats(theta, axes):
    return np.concatenate([np.cos(0.5 * theta)[:, None], np.sin(0.5 * theta)[:, None] * axes], axis=1)


def test_matrix_is_the_gsplat_formula_and_a_rotation():
    rng = np.random.default_rng(40)
    for q in unit_quats(rng, 8):
        w, x, y, z = q
        expected = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ])
        R = quat_to_rotmat(q)
        np.testing.assert_allclose(R, expected, rtol=0, atol=QUAT_TOL)
        np.testing.assert_allclose(R.T @ R, np.eye(3), rtol=0, atol=QUAT_TOL)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=QUAT_TOL)


def test_round_trip_random():
    rng = np.random.default_rng(41)
    q = unit_quats(rng, 64)
    back = rotmat_to_quat(quat_to_rotmat(q))
    np.testing.assert_allclose(back, q, rtol=0, atol=QUAT_TOL)
    assert np.all(back[:, 0] >= 0.0)


def test_round_trip_negative_w_returns_the_canonical_sign():
    rng = np.random.default_rng(42)
    q = -unit_quats(rng, 16)  # w <= 0: same rotation as -q
    np.testing.assert_allclose(rotmat_to_quat(quat_to_rotmat(q)), -q, rtol=0, atol=QUAT_TOL)


def test_round_trip_180_degrees():
    """w = 0: q and -q both have w = 0 and both are canonical; the rotation must round-trip."""
    rng = np.random.default_rng(43)
    axes = unit_vectors(rng, 32)
    q = np.concatenate([np.zeros((32, 1)), axes], axis=1)
    back = rotmat_to_quat(quat_to_rotmat(q))
    assert np.all(back[:, 0] >= 0.0)
    err = np.minimum(np.abs(back - q).max(axis=1), np.abs(back + q).max(axis=1))
    assert err.max() <= QUAT_TOL
    np.testing.assert_allclose(quat_to_rotmat(back), quat_to_rotmat(q), rtol=0, atol=QUAT_TOL)
    # Axis-aligned half turns (pivots tie between candidates).
    for k in range(1, 4):
        e = np.zeros(4)
        e[k] = 1.0
        back = rotmat_to_quat(quat_to_rotmat(e))
        assert min(np.abs(back - e).max(), np.abs(back + e).max()) <= QUAT_TOL


@pytest.mark.parametrize("theta", [0.0, 1e-12, 1e-8, 1e-4, math.pi - 1e-9])
def test_round_trip_small_and_near_half_turn(theta):
    rng = np.random.default_rng(44)
    q = axis_angle_quats(np.full(16, theta), unit_vectors(rng, 16))
    back = rotmat_to_quat(quat_to_rotmat(q))
    np.testing.assert_allclose(back, q, rtol=0, atol=QUAT_TOL)
    if theta < 1.0:  # the vector part is small: keep its relative accuracy
        err = np.linalg.norm(back[:, 1:] - q[:, 1:], axis=1)
        assert np.all(err <= QUAT_SMALL_REL_TOL * np.linalg.norm(q[:, 1:], axis=1))


@pytest.mark.parametrize("theta", [0.0, 1e-8, 0.5, 2.0, math.pi - 1e-9, math.pi])
def test_matrix_matches_so3_exp_of_axis_angle(theta):
    rng = np.random.default_rng(45)
    axes = unit_vectors(rng, 16)
    q = axis_angle_quats(np.full(16, theta), axes)
    np.testing.assert_allclose(quat_to_rotmat(q), so3_exp(theta * axes), rtol=0, atol=QUAT_TOL)


def test_multiply_matches_matrix_product():
    rng = np.random.default_rng(46)
    a, b = unit_quats(rng, 16), unit_quats(rng, 16)
    ab = quat_multiply(a, b)
    np.testing.assert_allclose(quat_to_rotmat(ab), quat_to_rotmat(a) @ quat_to_rotmat(b), rtol=0, atol=QUAT_TOL)
    np.testing.assert_allclose(np.linalg.norm(ab, axis=1), 1.0, rtol=0, atol=QUAT_TOL)
    # Identity and inverse (conjugate).
    one = np.array([1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(quat_multiply(one, a), a, rtol=0, atol=0)
    conj = a * np.array([1.0, -1.0, -1.0, -1.0])
    np.testing.assert_allclose(quat_multiply(a, conj), np.broadcast_to(one, a.shape), rtol=0, atol=QUAT_TOL)
    # Non-commutative: i j = k, j i = -k.
    i, j, k = np.eye(4)[1], np.eye(4)[2], np.eye(4)[3]
    np.testing.assert_array_equal(quat_multiply(i, j), k)
    np.testing.assert_array_equal(quat_multiply(j, i), -k)


def test_unnormalised_input_gives_the_normalised_matrix():
    """gsplat normalises inside _quat_to_rotmat, so any positive (or negative) scale is irrelevant."""
    rng = np.random.default_rng(47)
    q = unit_quats(rng, 16)
    for s in (1e-6, 0.3, 7.0, -2.0, 1e6):
        np.testing.assert_allclose(quat_to_rotmat(s * q), quat_to_rotmat(q), rtol=0, atol=QUAT_TOL)
    np.testing.assert_allclose(np.linalg.norm(quat_normalize(3.0 * q), axis=1), 1.0, rtol=0, atol=QUAT_TOL)


def test_zero_quaternion_raises():
    with pytest.raises(ValueError, match="norm"):
        quat_to_rotmat(np.zeros(4))
    with pytest.raises(ValueError, match="norm"):
        quat_normalize(np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]))


@pytest.mark.parametrize("func, bad", [(quat_to_rotmat, np.ones(3)), (quat_multiply, np.ones(3)),
                                       (rotmat_to_quat, np.eye(4)), (quat_normalize, np.ones((2, 5)))],
                         ids=lambda x: getattr(x, "__name__", ""))
def test_wrong_shapes_raise(func, bad):
    with pytest.raises(ValueError, match="shape"):
        func(bad, bad) if func is quat_multiply else func(bad)


def test_batched_leading_axes():
    rng = np.random.default_rng(48)
    q = unit_quats(rng, 6).reshape(2, 3, 4)
    R = quat_to_rotmat(q)
    assert R.shape == (2, 3, 3, 3)
    np.testing.assert_array_equal(R.reshape(6, 3, 3), np.stack([quat_to_rotmat(x) for x in q.reshape(6, 4)]))
    np.testing.assert_allclose(rotmat_to_quat(R), q, rtol=0, atol=QUAT_TOL)
    np.testing.assert_array_equal(quat_multiply(q, q[:, ::-1]).reshape(6, 4),
                                  np.stack([quat_multiply(a, b) for a, b in zip(q.reshape(6, 4), q[:, ::-1].reshape(6, 4))]))


def test_float32_stays_float32():
    rng = np.random.default_rng(49)
    q = unit_quats(rng, 4).astype(np.float32)
    R = quat_to_rotmat(q)
    assert R.dtype == np.float32
    assert rotmat_to_quat(R).dtype == np.float32
    assert quat_multiply(q, q).dtype == np.float32
    np.testing.assert_allclose(rotmat_to_quat(R), q, rtol=0, atol=1e-6)  # float32: ~6e-8 per entry
