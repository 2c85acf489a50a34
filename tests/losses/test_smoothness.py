"""L_ts: the vectorised terms and cKDTree neighbours against the loop reference, backward vs central
FD, and the stiff cases: coincident Gaussians, fewer dynamic Gaussians than K, one or none."""
import numpy as np
import pytest

from d2gs_np.constants import TS_NORM_EPS
from d2gs_np.losses.smoothness import knn, smooth_norm, spatial_bwd, spatial_fwd, time_bwd, time_fwd
from d2gs_np.reference import smoothness as ref
from d2gs_np.scene.config import DeformConfig

CFG = DeformConfig()  # P = 2, L = 2: K = 6 coefficients
REF_ARGS = (CFG.degree, CFG.order, CFG.omega)
# Vectorised against the loop reference: the same sums in another order, ~1e-15 relative.
REF_TOL = 1e-12
# Central FD: the value is a sum of ~100 norms of size ~1-10, so its rounding (~1e-14) divided
# by h dominates at small h; coefficients ~N(0, 1) keep every difference |u| >> TS_NORM_EPS, where
# the norm's third derivative is ~1 / |u|^2, so truncation is ~h^2. h = 1e-5 balances the two
# (measured max error 1.5e-10 against gradients ~1e-2..1); 1e-9 leaves margin and still catches
# any wrong factor or sign.
FD_H = 1e-5
FD_TOL = 1e-9


def _coefs(rng, n):
    return tuple(rng.standard_normal((n, CFG.num_coefs, d)) for d in (3, 4, 3))


def _fd_check(fwd, bwd, coefs, *args):
    _, saved = fwd(coefs, *args)
    grads = bwd(saved, 1.3)
    for i, c in enumerate(coefs):
        def f(x, i=i):
            cs = list(coefs)
            cs[i] = x
            return 1.3 * fwd(tuple(cs), *args)[0]
        fd = np.zeros_like(c)
        for idx in np.ndindex(*c.shape):
            xp, xm = c.copy(), c.copy()
            xp[idx] += FD_H
            xm[idx] -= FD_H
            fd[idx] = (f(xp) - f(xm)) / (2 * FD_H)
        np.testing.assert_allclose(grads[i], fd, rtol=0, atol=FD_TOL, err_msg=f"block {i}")


def test_knn_matches_brute_force():
    pts = np.random.default_rng(0).standard_normal((40, 3))
    np.testing.assert_array_equal(knn(pts, 8), ref.knn(pts, 8))


@pytest.mark.parametrize("t", [0.0, 0.37, 1.0])
def test_terms_match_the_loop_reference(t):
    rng = np.random.default_rng(1)
    coefs, pts = _coefs(rng, 25), rng.standard_normal((25, 3))
    nb = knn(pts, 8)
    assert time_fwd(coefs, t, 0.08, CFG)[0] == pytest.approx(ref.time_term(coefs, t, 0.08, *REF_ARGS), rel=REF_TOL)
    assert spatial_fwd(coefs, nb, t, CFG)[0] == pytest.approx(ref.spatial_term(coefs, nb, t, *REF_ARGS), rel=REF_TOL)


def test_time_backward_matches_central_fd():
    coefs = _coefs(np.random.default_rng(2), 5)
    _fd_check(time_fwd, time_bwd, coefs, 0.41, 0.08, CFG)


def test_spatial_backward_matches_central_fd():
    rng = np.random.default_rng(3)
    coefs, pts = _coefs(rng, 7), rng.standard_normal((7, 3))
    _fd_check(spatial_fwd, spatial_bwd, coefs, knn(pts, 3), 0.63, CFG)


def test_smooth_norm_is_smooth_at_zero():
    n, d = smooth_norm(np.zeros((2, 3)))
    assert np.all(n == 0.0) and np.all(d == 0.0)
    u = np.array([[3.0, 4.0, 0.0]])
    n, d = smooth_norm(u)
    assert n[0] == pytest.approx(5.0, abs=2 * TS_NORM_EPS)
    np.testing.assert_allclose(d, u / 5.0, rtol=1e-12)
    # derivative across zero along a line is continuous: tiny |u| gives a gradient ~ u / eps, finite
    n, d = smooth_norm(np.array([[1e-12, 0.0, 0.0]]))
    assert np.all(np.isfinite(d)) and abs(d[0, 0]) < 1e-5


def test_zero_deformation_and_common_motion_cost_nothing():
    rng = np.random.default_rng(4)
    zero = tuple(np.zeros((6, CFG.num_coefs, d)) for d in (3, 4, 3))
    assert time_fwd(zero, 0.5, 0.08, CFG)[0] == 0.0
    # every Gaussian moves the same way: no spatial cost, and no spatial gradient
    same = tuple(np.repeat(rng.standard_normal((1, CFG.num_coefs, d)), 6, axis=0) for d in (3, 4, 3))
    nb = knn(rng.standard_normal((6, 3)), 3)
    value, saved = spatial_fwd(same, nb, 0.5, CFG)
    assert value == 0.0 and all(np.all(g == 0.0) for g in spatial_bwd(saved))


def test_coincident_gaussians():
    rng = np.random.default_rng(5)
    pts = np.repeat(rng.standard_normal((1, 3)), 5, axis=0)  # five Gaussians at one place
    nb = knn(pts, 8)
    assert nb.shape == (5, 4)
    for g in range(5):
        assert sorted(nb[g]) == [j for j in range(5) if j != g]  # every other one, never itself
    # two coincident pairs among other points: each is the other's nearest
    pts2 = np.concatenate([rng.standard_normal((6, 3)), pts[:2], pts[:1] + 5.0, pts[:1] + 5.0])
    nb2 = knn(pts2, 2)
    assert nb2[6, 0] == 7 and nb2[7, 0] == 6 and nb2[8, 0] == 9 and nb2[9, 0] == 8
    assert np.all(nb2 != np.arange(10)[:, None])
    # zero neighbour difference: value 0, gradient 0 and finite
    same = tuple(np.repeat(rng.standard_normal((1, CFG.num_coefs, d)), 5, axis=0) for d in (3, 4, 3))
    value, saved = spatial_fwd(same, nb, 0.2, CFG)
    grads = spatial_bwd(saved)
    assert value == 0.0 and all(np.all(np.isfinite(g)) and np.all(g == 0.0) for g in grads)


def test_fewer_gaussians_than_k_one_and_none():
    rng = np.random.default_rng(6)
    for n, k_expected in ((4, 3), (1, 0), (0, 0)):
        pts, coefs = rng.standard_normal((n, 3)), _coefs(rng, n)
        nb = knn(pts, 8)
        assert nb.shape == (n, k_expected)
        value, saved = spatial_fwd(coefs, nb, 0.5, CFG)
        grads = spatial_bwd(saved)
        assert all(g.shape == c.shape and np.all(np.isfinite(g)) for g, c in zip(grads, coefs))
        tv, ts = time_fwd(coefs, 0.5, 0.08, CFG)
        assert all(g.shape == c.shape for g, c in zip(time_bwd(ts), coefs))
        if k_expected == 0:
            assert value == 0.0 and all(np.all(g == 0.0) for g in grads)
        else:
            assert value == pytest.approx(ref.spatial_term(coefs, nb, 0.5, *REF_ARGS), rel=REF_TOL)
        if n == 0:
            assert tv == 0.0


def test_float32_blocks_keep_their_dtype():
    rng = np.random.default_rng(7)
    coefs = tuple(c.astype(np.float32) for c in _coefs(rng, 6))
    nb = knn(rng.standard_normal((6, 3)), 3)
    assert all(g.dtype == np.float32 for g in spatial_bwd(spatial_fwd(coefs, nb, 0.3, CFG)[1]))
    assert all(g.dtype == np.float32 for g in time_bwd(time_fwd(coefs, 0.3, 0.08, CFG)[1]))


def test_bad_input_names_the_argument():
    rng = np.random.default_rng(8)
    coefs = _coefs(rng, 5)
    with pytest.raises(ValueError, match=r"neighbours must be an \(5, k\) index array.*rebuild it with knn"):
        spatial_fwd(coefs, np.zeros((4, 2), dtype=int), 0.1, CFG)
    with pytest.raises(ValueError, match=r"integer indices in \[0, 5\)"):
        spatial_fwd(coefs, np.full((5, 2), 7), 0.1, CFG)
    with pytest.raises(ValueError, match=r"coefs\[1\] must have shape \(N, 6, D\)"):
        time_fwd((coefs[0], coefs[1][:, :3]), 0.1, 0.08, CFG)
    with pytest.raises(ValueError, match="eps must be a finite non-zero time offset"):
        time_fwd(coefs, 0.1, 0.0, CFG)
    with pytest.raises(ValueError, match=r"points must be an \(N, 3\) array"):
        knn(np.zeros((4, 2)), 3)
    with pytest.raises(ValueError, match="k must be an integer >= 1"):
        knn(np.zeros((4, 3)), 0)
