"""L_iso (losses/isometry.py): zero on rigid motions, the relative change of a pair's distance
otherwise, its gradient against central differences in float64, units-free, finite on
coincident pairs and tiny or huge scenes, and descent on it makes a torn motion rigid."""
import numpy as np
import pytest

from d2gs_np.losses.isometry import isometry_bwd, isometry_fwd, pair_floor, second_time
from d2gs_np.losses.smoothness import knn
from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.deformation import deform_basis

CFG = DeformConfig()  # degree 2, order 2, omega 2 pi: K = 6, [t, t^2, sin wt, sin 2wt, cos wt, cos 2wt]
K = CFG.num_coefs


def _rigid(x, spin=0.7, drift=(0.3, -0.2, 0.1), bend=(0.05, 0.1, 0.0)):
    """Base positions and coefficients of mu(t) = Rz(w t) x + drift t + bend t^2 (spin 1; the turn
    at the basis frequency w through its sin / cos terms) or x + drift t + bend t^2 (spin 0),
    which the basis holds exactly: rigid motions of the whole set."""
    n = x.shape[0]
    A0 = x.copy()
    C = np.zeros((n, K, 3))
    C[:, 0] = drift
    C[:, 1] = bend
    # Rz(wt) x = (x cos - y sin, x sin + y cos, z): A0 keeps z; the cos term carries (x, y), the sin term (-y, x)
    A0[:, :2] = (1.0 - spin) * x[:, :2]
    C[:, 4, 0], C[:, 4, 1] = spin * x[:, 0], spin * x[:, 1]
    C[:, 2, 0], C[:, 2, 1] = -spin * x[:, 1], spin * x[:, 0]
    return A0, C


def _positions(A0, C, t):
    return A0 + np.einsum("k,nkd->nd", deform_basis(t, CFG)[0], C)


def test_second_time_stays_in_the_clip():
    assert second_time(0.2, 0.25) == 0.45 and second_time(0.75, 0.25) == 1.0
    assert second_time(0.9, 0.25) == pytest.approx(0.65)


@pytest.mark.parametrize("t", [0.0, 0.3, 0.9])
def test_zero_on_a_rigid_motion(t):
    # a full turn about z at the basis frequency plus a curved drift (spin 1), and the drift alone
    # (spin 0): every pair keeps its distance; rounding leaves ~1e-16 relative changes
    x = np.random.default_rng(0).normal(size=(30, 3))
    for spin in (1.0, 0.0):
        A0, C = _rigid(x, spin=spin)
        d = [np.linalg.norm(_positions(A0, C, s)[:, None] - _positions(A0, C, s)[None], axis=-1) for s in (0.1, 0.6)]
        np.testing.assert_allclose(d[0], d[1], atol=1e-12)  # the fixture is rigid
        nb = knn(_positions(A0, C, 0.5), 6)
        v, saved = isometry_fwd(A0, C, nb, t, 0.25, 1e-9, CFG)
        assert v < 1e-24
        gA, gC = isometry_bwd(saved, 1.0)
        assert np.abs(gA).max() < 1e-11 and np.abs(gC).max() < 1e-11


def test_a_uniform_stretch_gives_its_relative_change():
    # mu(t) = (1 + t) x: every pair's distance grows by the same factor, r = 2 (s1 - s2) / (s1 + s2)
    x = np.random.default_rng(1).normal(size=(25, 3))
    C = np.zeros((25, K, 3))
    C[:, 0] = x
    nb = knn(x, 5)
    t, eps = 0.2, 0.3
    v, _ = isometry_fwd(x, C, nb, t, eps, 1e-12, CFG)
    s1, s2 = 1 + t, 1 + t + eps
    assert v == pytest.approx((2 * (s1 - s2) / (s1 + s2)) ** 2, rel=1e-12)


@pytest.mark.parametrize("t", [0.1, 0.95])  # 0.95: the second time is t - eps
def test_gradient_matches_central_differences(t):
    rng = np.random.default_rng(2)
    A0, C = rng.normal(size=(15, 3)), 0.3 * rng.normal(size=(15, K, 3))
    nb = knn(A0, 4)
    v, saved = isometry_fwd(A0, C, nb, t, 0.25, 1e-3, CFG)
    gA, gC = isometry_bwd(saved, 2.5)
    h = 1e-6  # values ~0.5, rounding ~1e-16 / h = 1e-10 relative: 1e-7 catches any wrong factor

    def f(a, c):
        return isometry_fwd(a, c, nb, t, 0.25, 1e-3, CFG)[0]

    for x, g, other in ((A0, gA, "A0"), (C, gC, "C")):
        num = np.zeros_like(x)
        for idx in np.ndindex(x.shape):
            d = np.zeros_like(x)
            d[idx] = h
            num[idx] = (f(A0 + d, C) - f(A0 - d, C)) / (2 * h) if other == "A0" else \
                (f(A0, C + d) - f(A0, C - d)) / (2 * h)
        np.testing.assert_allclose(g, 2.5 * num, rtol=1e-6, atol=1e-9 * np.abs(num).max())


@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_units_free_at_tiny_and_huge_scenes(scale):
    rng = np.random.default_rng(3)
    A0, C = rng.normal(size=(20, 3)), 0.3 * rng.normal(size=(20, K, 3))
    nb = knn(A0, 5)
    v, saved = isometry_fwd(A0, C, nb, 0.4, 0.25, 1e-3, CFG)
    gA, gC = isometry_bwd(saved)
    vs, saved_s = isometry_fwd(A0 * scale, C * scale, nb, 0.4, 0.25, 1e-3 * scale, CFG)
    gAs, gCs = isometry_bwd(saved_s)
    assert vs == pytest.approx(v, rel=1e-9)
    np.testing.assert_allclose(gAs * scale, gA, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(gCs * scale, gC, rtol=1e-7, atol=1e-12)
    assert np.all(np.isfinite(gAs)) and np.all(np.isfinite(gCs))


def test_coincident_pairs_are_finite_and_pull_nothing():
    A0 = np.zeros((6, 3))
    C = np.zeros((6, K, 3))
    C[:, 0] = (1.0, 2.0, 3.0)  # all move together, on one point
    nb = knn(A0, 3)
    v, saved = isometry_fwd(A0, C, nb, 0.5, 0.25, 1e-9, CFG)
    gA, gC = isometry_bwd(saved)
    assert v == 0.0 and np.all(gA == 0.0) and np.all(gC == 0.0)
    # two of them come apart in time only: finite, and the gradient pulls them back together
    C[1, 0] += 1e-7
    v, saved = isometry_fwd(A0, C, nb, 0.5, 0.25, 1e-9, CFG)
    gA, gC = isometry_bwd(saved)
    assert np.isfinite(v) and v > 0 and np.all(np.isfinite(gC)) and gC[1, 0] @ (C[1, 0] - C[0, 0]) > 0


@pytest.mark.parametrize("n", [0, 1])
def test_no_pairs_give_zero(n):
    A0, C = np.ones((n, 3)), np.zeros((n, K, 3))
    nb = knn(A0, 8) if n else np.zeros((0, 0), dtype=np.int64)
    v, saved = isometry_fwd(A0, C, nb, 0.5, 0.25, 1e-3, CFG)
    gA, gC = isometry_bwd(saved)
    assert v == 0.0 and gA.shape == (n, 3) and gC.shape == (n, K, 3) and not gA.any() and not gC.any()


def test_float32_keeps_its_dtype_and_value():
    rng = np.random.default_rng(4)
    A0, C = rng.normal(size=(20, 3)), 0.3 * rng.normal(size=(20, K, 3))
    nb = knn(A0, 5)
    v64, s64 = isometry_fwd(A0, C, nb, 0.3, 0.25, 1e-3, CFG)
    v32, s32 = isometry_fwd(A0.astype(np.float32), C.astype(np.float32), nb, 0.3, 0.25, 1e-3, CFG)
    g32 = isometry_bwd(s32)
    assert all(g.dtype == np.float32 for g in g32)
    assert v32 == pytest.approx(v64, rel=1e-5)  # float32 inputs ~6e-8 relative, amplified by r's ratio
    np.testing.assert_allclose(g32[1], isometry_bwd(s64)[1], rtol=1e-3, atol=1e-6)


def test_descent_makes_a_torn_motion_rigid():
    # a rigid turn with every Gaussian's coefficients jittered: descent on C alone (the base
    # positions held) brings the term down by 100x
    rng = np.random.default_rng(5)
    x = rng.normal(size=(40, 3))
    A0, C = _rigid(x, spin=1.0)
    C = C + 0.05 * rng.normal(size=C.shape)
    nb = knn(_positions(A0, C, 0.5), 6)
    start = None
    for i in range(3000):
        for t in (0.0, 0.25, 0.5, 0.75):
            v, saved = isometry_fwd(A0, C, nb, t, 0.25, 1e-6, CFG)
            C = C - 0.5 * isometry_bwd(saved)[1]
        start = v if start is None else start
    end = np.mean([isometry_fwd(A0, C, nb, t, 0.25, 1e-6, CFG)[0] for t in (0.0, 0.25, 0.5, 0.75)])
    assert end < start / 100


def test_pair_floor_follows_the_scene_units():
    x = np.random.default_rng(6).normal(size=(30, 3))
    nb = knn(x, 4)
    d = np.median(np.linalg.norm(x[:, None] - x[nb], axis=-1))
    assert pair_floor(x, nb) == pytest.approx(0.01 * d) and pair_floor(1e3 * x, nb) == pytest.approx(10 * d)
    assert pair_floor(np.zeros((3, 3)), knn(np.zeros((3, 3)), 2)) == 1e-12
    assert pair_floor(np.zeros((1, 3)), np.zeros((1, 0), dtype=np.int64)) == 1e-12


def test_bad_input_is_refused_with_what_to_do():
    A0, C = np.zeros((4, 3)), np.zeros((4, K, 3))
    nb = knn(np.random.default_rng(0).normal(size=(4, 3)), 2)
    with pytest.raises(ValueError, match="NaN"):
        isometry_fwd(np.full((4, 3), np.nan), C, nb, 0.5, 0.25, 1e-3, CFG)
    with pytest.raises(ValueError, match=r"coef_means \(N, 6, 3\)"):
        isometry_fwd(A0, np.zeros((4, 5, 3)), nb, 0.5, 0.25, 1e-3, CFG)
    with pytest.raises(ValueError, match="rebuild it"):
        isometry_fwd(A0, C, nb[:3], 0.5, 0.25, 1e-3, CFG)
    with pytest.raises(ValueError, match="rebuild it"):
        isometry_fwd(A0, C, nb + 4, 0.5, 0.25, 1e-3, CFG)
    with pytest.raises(ValueError, match="eps"):
        isometry_fwd(A0, C, nb, 0.5, 0.0, 1e-3, CFG)
    with pytest.raises(ValueError, match="floor"):
        isometry_fwd(A0, C, nb, 0.5, 0.25, 0.0, CFG)
    with pytest.raises(TypeError, match="DeformConfig"):
        isometry_fwd(A0, C, nb, 0.5, 0.25, 1e-3, None)
