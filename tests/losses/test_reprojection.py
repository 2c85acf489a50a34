"""L_reproj on rendered depth (losses/reprojection.py): the cycle residual and its gradient on
both depths against central differences in float64, the bilinear read and its scatter, exact
geometry giving zero, and the stiff cases (no depth, zero or negative depth, a point behind the
partner camera, a match outside the image)."""
import numpy as np
import pytest

from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.geometry.sampling import bilinear_bwd, bilinear_fwd
from d2gs_np.losses.reprojection import cauchy, cycle_bwd, cycle_fwd

K = np.array([[120.0, 0.0, 80.0], [0.0, 118.0, 45.0], [0.0, 0.0, 1.0]])


def _poses(rng):
    M_a = se3_exp(np.r_[rng.normal(0, 0.05, 3), rng.normal(0, 0.1, 3)])
    M_b = se3_exp(np.r_[rng.normal(0, 0.05, 3), rng.normal(0, 0.1, 3)]) @ M_a
    return M_a, M_b


def _exact_matches(rng, M_a, M_b, m=40):
    """Pixels in a, their true depths, and the true pixels and depths in b."""
    pts_a = rng.uniform([10, 10], [150, 80], size=(m, 2))
    d_a = rng.uniform(2.0, 5.0, m)
    X_a = d_a[:, None] * np.linalg.solve(K, np.c_[pts_a, np.ones(m)].T).T
    T = M_b @ np.linalg.inv(M_a)
    X_b = X_a @ T[:3, :3].T + T[:3, 3]
    pts_b = (X_b @ K.T)[:, :2] / X_b[:, 2:3]
    return pts_a, d_a, pts_b, X_b[:, 2]


def test_exact_geometry_costs_nothing():
    rng = np.random.default_rng(0)
    M_a, M_b = _poses(rng)
    pts_a, d_a, pts_b, d_b = _exact_matches(rng, M_a, M_b)
    cost, saved = cycle_fwd(d_a, pts_a, K, M_a, d_b, pts_b, K, M_b, 10.0, 1.0)
    assert saved["valid"].all()
    assert np.abs(saved["residuals"]).max() < 1e-9
    assert cost < 1e-18
    v_a, v_b = cycle_bwd(saved)
    assert np.abs(v_a).max() < 1e-9 and np.abs(v_b).max() < 1e-9


@pytest.mark.parametrize("beta", [0.0, 10.0, 100.0])
def test_cycle_gradient_matches_central_differences(beta):
    # Depths 10 % off, so every residual row is nonzero and the Cauchy weights vary; central
    # differences at eps 1e-6 on depths of O(1) have truncation error O(eps^2 * 3rd derivative)
    # ~1e-11 and rounding error ~1e-16 / 1e-6 = 1e-10 on a cost of O(1-100): 1e-6 relative holds.
    rng = np.random.default_rng(1)
    M_a, M_b = _poses(rng)
    pts_a, d_a, pts_b, d_b = _exact_matches(rng, M_a, M_b, m=12)
    d_a = d_a * rng.uniform(0.9, 1.1, d_a.shape)
    d_b = d_b * rng.uniform(0.9, 1.1, d_b.shape)
    _, saved = cycle_fwd(d_a, pts_a, K, M_a, d_b, pts_b, K, M_b, beta, 1.0)
    v_a, v_b = cycle_bwd(saved, 0.7)
    eps = 1e-6
    for which, v in (("a", v_a), ("b", v_b)):
        num = np.zeros_like(v)
        for i in range(len(v)):
            up, dn = (d_a.copy(), d_b.copy()), (d_a.copy(), d_b.copy())
            idx = 0 if which == "a" else 1
            up[idx][i] += eps
            dn[idx][i] -= eps
            cu = cycle_fwd(up[0], pts_a, K, M_a, up[1], pts_b, K, M_b, beta, 1.0)[0]
            cd = cycle_fwd(dn[0], pts_a, K, M_a, dn[1], pts_b, K, M_b, beta, 1.0)[0]
            num[i] = 0.7 * (cu - cd) / (2 * eps)
        np.testing.assert_allclose(v, num, rtol=1e-6, atol=1e-9)
    if beta == 0.0:
        assert np.all(v_b == 0.0)  # without the depth row the compared depth has no pull


def test_cauchy_matches_its_closed_form():
    r = np.array([-3.0, -0.5, 0.0, 0.25, 2.0, 1e8])
    rho, drho = cauchy(r, 2.0)
    np.testing.assert_allclose(rho, 2.0 * np.log(1 + r ** 2 / 4.0))
    np.testing.assert_allclose(drho, r / (1 + r ** 2 / 4.0))
    assert np.isfinite(rho).all() and np.isfinite(drho).all()


def test_invalid_depths_and_points_behind_are_dropped_with_zero_gradient():
    rng = np.random.default_rng(2)
    M_a, M_b = _poses(rng)
    pts_a, d_a, pts_b, d_b = _exact_matches(rng, M_a, M_b, m=6)
    d_a = d_a.copy()
    d_b = d_b * 1.05
    d_a[0], d_a[1], d_b[2], d_b[3] = np.nan, 0.0, -1.0, np.inf
    # match 4 lifted far behind camb: a depth of -50 puts it behind camera a and b
    d_a[4] = -50.0
    cost, saved = cycle_fwd(d_a, pts_a, K, M_a, d_b, pts_b, K, M_b, 10.0, 1.0)
    assert saved["valid"].tolist() == [False, False, False, False, False, True]
    assert np.isfinite(cost) and cost > 0
    assert np.isnan(saved["residuals"][:5]).all()
    v_a, v_b = cycle_bwd(saved)
    assert np.all(v_a[:5] == 0) and np.all(v_b[:5] == 0) and v_a[5] != 0


def test_point_behind_partner_camera_is_dropped():
    # b looks the other way: every lifted point lies behind it
    M_a = np.eye(4)
    M_b = np.diag([-1.0, 1.0, -1.0, 1.0])  # turned by pi about y
    pts = np.array([[80.0, 45.0], [20.0, 30.0]])
    cost, saved = cycle_fwd(np.array([2.0, 3.0]), pts, K, M_a, np.array([2.0, 3.0]), pts, K, M_b, 10.0, 1.0)
    assert cost == 0.0 and not saved["valid"].any()
    assert all(np.all(v == 0) for v in cycle_bwd(saved))


def test_no_matches():
    e = np.zeros((0, 2))
    cost, saved = cycle_fwd(np.zeros(0), e, K, np.eye(4), np.zeros(0), e, K, np.eye(4), 10.0, 1.0)
    assert cost == 0.0
    assert [v.shape for v in cycle_bwd(saved)] == [(0,), (0,)]


def test_shape_errors_name_the_arguments():
    with pytest.raises(ValueError, match="d_a, d_b"):
        cycle_fwd(np.ones(3), np.zeros((2, 2)), K, np.eye(4), np.ones(2), np.zeros((2, 2)), K, np.eye(4), 10, 1)


def test_bilinear_read_and_scatter_are_adjoint():
    rng = np.random.default_rng(3)
    img = rng.normal(size=(9, 13))
    pts = np.c_[rng.uniform(0.5, 12.5, 20), rng.uniform(0.5, 8.5, 20)]
    pts = np.r_[pts, [[0.1, 3.0], [13.2, 4.0], [6.5, 4.5]]]  # two outside the centres' hull, one on a centre
    vals, saved = bilinear_fwd(img, pts)
    assert np.isnan(vals[-3]) and np.isnan(vals[-2])
    assert vals[-1] == pytest.approx(img[4, 6])
    v = rng.normal(size=len(pts))
    g = bilinear_bwd(saved, v)
    ok = np.isfinite(vals)
    # <v, A img> == <A^T v, img> (the read is linear in the image)
    assert np.sum(v[ok] * vals[ok]) == pytest.approx(np.sum(g * img), rel=1e-12)
    # a linear ramp is read exactly
    yy, xx = np.mgrid[0:9, 0:13]
    ramp = 2.0 * (xx + 0.5) - 3.0 * (yy + 0.5)
    r, _ = bilinear_fwd(ramp, pts[ok])
    np.testing.assert_allclose(r, 2.0 * pts[ok, 0] - 3.0 * pts[ok, 1], atol=1e-12)


def test_bilinear_nan_taps_give_nan_and_no_gradient():
    img = np.ones((4, 4))
    img[1, 1] = np.nan
    vals, saved = bilinear_fwd(img, np.array([[1.8, 1.7], [3.5, 3.5]]))
    assert np.isnan(vals[0]) and vals[1] == pytest.approx(1.0)
    g = bilinear_bwd(saved, np.where(np.isfinite(vals), 1.0, np.nan))
    assert np.isfinite(g).all() and g.sum() == pytest.approx(1.0)
