"""Photometric loss: value against L1 + scikit-image SSIM, backward vs central FD, masks."""
import numpy as np
import pytest
from skimage.metrics import structural_similarity

from d2gs_np.losses import photometric_bwd, photometric_fwd
from render_fixtures import central_fd

VALUE_TOL = 1e-10  # L1 and SSIM are each matched to ~1e-16; 1e-10 is the SSIM bar of the brief
# Central FD, h = 1e-6. Differences are kept >= 0.05 away from 0, so no step crosses |x|'s kink;
# the rest is smooth (see test_ssim.py): error ~1e-11 against gradients ~1e-3.
FD_H = 1e-6
FD_TOL = 1e-9
F32_TOL = 1e-5


def pair_away_from_kink(rng, shape, dtype=np.float64):
    render = rng.uniform(0.2, 0.8, size=shape)
    offset = rng.uniform(0.05, 0.15, size=shape) * rng.choice([-1.0, 1.0], size=shape)
    return render.astype(dtype), (render + offset).astype(dtype)


def skimage_ssim(a, b):
    return structural_similarity(a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5)


@pytest.mark.parametrize("lam", [0.0, 0.2, 1.0])
def test_value(lam):
    rng = np.random.default_rng(0)
    render, target = pair_away_from_kink(rng, (16, 18, 3))
    loss, _ = photometric_fwd(render, target, lam)
    expected = (1 - lam) * np.mean(np.abs(render - target)) + lam * (1 - skimage_ssim(render, target))
    assert abs(loss - expected) <= VALUE_TOL


@pytest.mark.parametrize("lam", [0.0, 0.2, 1.0])
@pytest.mark.parametrize("masked", [False, True])
def test_backward_matches_central_fd(lam, masked):
    rng = np.random.default_rng(1)
    render, target = pair_away_from_kink(rng, (12, 13, 2))
    mask = rng.uniform(0.0, 1.0, size=(12, 13)) if masked else None
    _, saved = photometric_fwd(render, target, lam, mask)
    grad = photometric_bwd(saved, 1.3)
    fd = central_fd(lambda x: 1.3 * photometric_fwd(x, target, lam, mask)[0], render, FD_H)
    np.testing.assert_allclose(grad, fd, rtol=0, atol=FD_TOL)


def test_mask_semantics():
    rng = np.random.default_rng(2)
    render, target = pair_away_from_kink(rng, (16, 16, 3))
    ones = np.ones((16, 16))
    a, sa = photometric_fwd(render, target, 0.2)
    b, sb = photometric_fwd(render, target, 0.2, ones)
    assert abs(a - b) <= 1e-15
    np.testing.assert_allclose(photometric_bwd(sa), photometric_bwd(sb), rtol=0, atol=1e-18)
    # a 0/1 mask: L1 is the mean over the kept pixels only
    half = np.zeros((16, 16))
    half[:, :8] = 1.0
    l1_only, _ = photometric_fwd(render, target, 0.0, half)
    assert abs(l1_only - np.mean(np.abs(render - target)[:, :8])) <= 1e-15
    # pixels with zero weight outside every SSIM window of kept pixels get no gradient
    _, saved = photometric_fwd(render, target, 0.2, half)
    grad = photometric_bwd(saved)
    np.testing.assert_array_equal(grad[:, 14:], 0.0)  # > 5 px from every kept interior pixel
    with pytest.raises(ValueError, match="no weight inside the SSIM interior"):
        border = np.zeros((16, 16))
        border[0, 0] = 1.0
        photometric_fwd(render, target, 0.2, border)


def test_small_images_need_lambda_zero():
    rng = np.random.default_rng(3)
    render, target = pair_away_from_kink(rng, (6, 8, 3))
    loss, saved = photometric_fwd(render, target, 0.0)
    assert abs(loss - np.mean(np.abs(render - target))) <= 1e-15
    assert photometric_bwd(saved).shape == (6, 8, 3)
    with pytest.raises(ValueError, match="at least 11x11"):
        photometric_fwd(render, target, 0.2)


def test_float32_stays_float32():
    rng = np.random.default_rng(4)
    render, target = pair_away_from_kink(rng, (16, 16, 3), np.float32)
    loss, saved = photometric_fwd(render, target)
    assert np.asarray(loss).dtype == np.float32 and photometric_bwd(saved).dtype == np.float32
    loss64, saved64 = photometric_fwd(render.astype(np.float64), target.astype(np.float64))
    assert abs(float(loss) - loss64) <= F32_TOL
    np.testing.assert_allclose(photometric_bwd(saved), photometric_bwd(saved64), rtol=0, atol=F32_TOL)


def test_errors():
    rng = np.random.default_rng(5)
    render, target = pair_away_from_kink(rng, (16, 16, 3))
    with pytest.raises(ValueError, match="lambda_ssim"):
        photometric_fwd(render, target, 1.5)
    with pytest.raises(ValueError, match=r"mask must have shape \(16, 16\)"):
        photometric_fwd(render, target, 0.2, np.ones((16, 15)))
    with pytest.raises(ValueError, match="not all zero"):
        photometric_fwd(render, target, 0.2, np.zeros((16, 16)))
    with pytest.raises(TypeError, match="mask must be a float64"):
        photometric_fwd(render, target, 0.2, np.ones((16, 16), bool))
    with pytest.raises(ValueError, match="target must match"):
        photometric_fwd(render, target[:8], 0.0)
