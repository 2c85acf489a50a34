"""L_var (losses/depth_variance.py): the squared coefficient of variation of the depths along a ray.
Its gradient against central differences, its value on one layer and on two (against the direct
weighted variance), its scale invariance, the pixels it ignores, extreme inputs, bad input; the
z-features' gradient."""
import numpy as np
import pytest

from render_fixtures import central_fd as _central

from d2gs_np.losses.depth_variance import depth_variance_bwd, depth_variance_fwd, z_features_bwd, z_features_fwd

H, W = 7, 9


def _sums(seed=0, layers=3):
    """D, D2, alpha of pixels that each blend ``layers`` Gaussians at depths 1-8 with weights summing below 1."""
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.05, 0.9, (H, W, layers))
    w *= rng.uniform(0.55, 0.99, (H, W, 1)) / w.sum(axis=2, keepdims=True)
    z = rng.uniform(1.0, 8.0, (H, W, layers))
    return (w * z).sum(2), (w * z * z).sum(2), w.sum(2), w, z


def test_value_is_the_weighted_variance_over_the_squared_mean():
    D, D2, a, w, z = _sums()
    value, _ = depth_variance_fwd(D, D2, a, alpha_min=0.5)
    wn = w / w.sum(2, keepdims=True)
    mean = (wn * z).sum(2)
    var = (wn * (z - mean[..., None]) ** 2).sum(2)
    keep = a >= 0.5
    assert value == pytest.approx(float(np.mean(var[keep] / mean[keep] ** 2)), rel=1e-12)


def test_one_layer_is_zero_and_scale_does_not_matter():
    D, D2, a, w, z = _sums(layers=1)
    assert abs(depth_variance_fwd(D, D2, a)[0]) < 1e-14
    D, D2, a, _, _ = _sums(seed=3)
    v1 = depth_variance_fwd(D, D2, a)[0]
    for s in (1e-6, 1e6):  # the scene in other units: the same value
        assert depth_variance_fwd(s * D, s * s * D2, a, min_depth=0.0)[0] == pytest.approx(v1, rel=1e-10)
    assert v1 > 0.01


def test_gradient_matches_central_differences():
    # h = 1e-6 on D ~ 3, D2 ~ 15: truncation O(h^2 q''') ~ 1e-12, rounding ~ 1e-16 x 1 / 1e-6 = 1e-10;
    # 1e-7 relative to the largest entry
    D, D2, a, _, _ = _sums(seed=1)
    mask = np.ones((H, W), bool)
    mask[0, :4] = False  # pixels outside the loss mask get nothing
    value, saved = depth_variance_fwd(D, D2, a, alpha_min=0.6, mask=mask)
    vD, vD2, va = depth_variance_bwd(saved, weight=2.5)
    f = lambda d, d2, al: 2.5 * depth_variance_fwd(d, d2, al, alpha_min=0.6, mask=mask)[0]
    for got, num in ((vD, _central(lambda x: f(x, D2, a), D, 1e-6)), (vD2, _central(lambda x: f(D, x, a), D2, 1e-6)),
                     (va, _central(lambda x: f(D, D2, x), a, 1e-6))):
        assert np.max(np.abs(got - num)) < 1e-7 * np.max(np.abs(num))
    assert np.all(vD[0, :4] == 0) and np.all(va[a < 0.6] == 0)


def test_no_valid_pixel_is_zero_without_gradient():
    D, D2, a, _, _ = _sums()
    value, saved = depth_variance_fwd(D, D2, np.zeros_like(a))
    assert value == 0.0 and saved is None and depth_variance_bwd(saved) is None
    # alpha exactly 1 (opaque) and 0 both finite; depth at the floor left out
    a1 = np.ones_like(a)
    a1[0, 0] = 0.0
    D0 = D.copy()
    D0[1, 1] = 0.0
    value, saved = depth_variance_fwd(D0, D2, a1)
    assert np.isfinite(value) and all(np.all(np.isfinite(g)) for g in depth_variance_bwd(saved))


def test_bad_input_is_named():
    D, D2, a, _, _ = _sums()
    with pytest.raises(ValueError, match="depth2 must have shape"):
        depth_variance_fwd(D, D2[:-1], a)
    bad = a.copy()
    bad[2, 2] = np.nan
    with pytest.raises(ValueError, match="alpha contains NaN"):
        depth_variance_fwd(D, D2, bad)
    with pytest.raises(ValueError, match=r"\(h, w\) map"):
        depth_variance_fwd(D[0], D2[0], a[0])


def test_z_features_and_their_gradient():
    rng = np.random.default_rng(4)
    from d2gs_np.geometry.se3 import se3_exp
    T = se3_exp(np.r_[0.3, -0.2, 0.5, 0.4, 0.1, -0.3])
    means = rng.standard_normal((6, 3)) + np.r_[0, 0, 4.0]
    feats, z = z_features_fwd(means, T)
    np.testing.assert_allclose(z, (means @ T[:3, :3].T + T[:3, 3])[:, 2], rtol=1e-14)
    np.testing.assert_allclose(feats[:, 1], z ** 2, rtol=1e-14)
    assert np.all(feats[:, 2] == 0)
    v = rng.standard_normal((6, 3))
    got = z_features_bwd(v, z, T)
    num = _central(lambda m: float(np.sum(v * z_features_fwd(m, T)[0])), means, 1e-6)
    assert np.max(np.abs(got - num)) < 1e-7 * np.max(np.abs(num))
