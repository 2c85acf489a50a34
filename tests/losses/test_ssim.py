"""SSIM: value and map against scikit-image, the filter's adjoint, backward vs central FD."""
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from skimage.metrics import structural_similarity

from d2gs_np.losses import ssim_bwd, ssim_fwd, ssim_map
from d2gs_np.losses.ssim import _blur, _blur_adjoint
from render_fixtures import central_fd

SKIMAGE_TOL = 1e-10  # the brief's bar; measured differences are ~1e-16 (same formula, other summation order)
MAP_TOL = 1e-13  # per-pixel S: ratios of O(1e-3) quantities near flat patches amplify rounding a little
ADJOINT_TOL = 1e-16  # entries of G are sums of <= 3 products of kernel weights (<= 0.27): rounding ~1e-17
# Central FD with h = 1e-6: SSIM is a smooth rational function of the pixels; measured error
# ~4e-11 against gradients of ~5e-2 per pixel on 16x16x3.
FD_H = 1e-6
FD_TOL = 1e-9
F32_TOL = 1e-5  # float32 evaluation of a mean of O(1) ratios, ~1e3 terms, float64 accumulation


def skimage_ssim(a, b, full=False):
    return structural_similarity(a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5, full=full)


def image_pair(rng, shape, noise=0.1, dtype=np.float64):
    a = rng.uniform(size=shape)
    b = np.clip(a + noise * rng.normal(size=shape), 0.0, 1.0)
    return a.astype(dtype), b.astype(dtype)


@pytest.mark.parametrize("shape", [(11, 11, 3), (16, 16, 3), (12, 29, 1), (32, 24, 2)])
def test_value_and_map_match_skimage(shape):
    rng = np.random.default_rng(0)
    a, b = image_pair(rng, shape)
    value, _ = ssim_fwd(a, b)
    ref_value, ref_map = skimage_ssim(a, b, full=True)
    assert abs(value - ref_value) <= SKIMAGE_TOL
    np.testing.assert_allclose(ssim_map(a, b), ref_map, rtol=0, atol=MAP_TOL)


def test_structured_images_match_skimage():
    # smooth gradients and flat patches (small variances: the C2-dominated regime)
    y, x = np.mgrid[0:20, 0:24] / 24.0
    a = np.stack([x, y, np.full_like(x, 0.5)], axis=-1)
    b = np.stack([x**2, 1.0 - y, np.full_like(x, 0.5)], axis=-1)
    value, _ = ssim_fwd(a, b)
    assert abs(value - skimage_ssim(a, b)) <= SKIMAGE_TOL
    assert ssim_fwd(a, a.copy())[0] == pytest.approx(1.0, abs=1e-15)


def test_filter_matches_scipy_gaussian_filter():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(2, 13, 17, 3))
    np.testing.assert_allclose(_blur(x), gaussian_filter(x, sigma=(0, 1.5, 1.5, 0), truncate=3.5, mode="reflect"),
                               rtol=0, atol=1e-15)


@pytest.mark.parametrize("hw", [(11, 11), (11, 12), (13, 17), (16, 16)])
def test_filter_is_self_adjoint(hw):
    # The backward uses G^T = G (module docstring of d2gs_np.losses.ssim). Build the dense
    # operator from the images of the unit vectors and check that it is symmetric.
    H, W = hw
    units = np.eye(H * W).reshape(H * W, H, W, 1)
    G = _blur(units).reshape(H * W, H * W)  # row k = G e_k = column k of the operator
    np.testing.assert_allclose(G, G.T, rtol=0, atol=ADJOINT_TOL)
    np.testing.assert_array_equal(_blur_adjoint(units), _blur(units))
    # a property of the 'reflect' padding: the 'nearest' one is not symmetric
    eye = np.eye(W)
    F_nearest = np.stack([gaussian_filter(e, 1.5, truncate=3.5, mode="nearest") for e in eye], axis=1)
    assert np.max(np.abs(F_nearest - F_nearest.T)) > 1e-3


@pytest.mark.parametrize("shape", [(16, 16, 3), (11, 13, 1)])
def test_backward_matches_central_fd(shape):
    rng = np.random.default_rng(2)
    a, b = image_pair(rng, shape, noise=0.2)
    _, saved = ssim_fwd(a, b)
    v_value = -0.7
    grad = ssim_bwd(saved, v_value)
    fd = central_fd(lambda x: v_value * ssim_fwd(x, b)[0], a, FD_H)
    assert np.max(np.abs(fd)) > 1e-3
    np.testing.assert_allclose(grad, fd, rtol=0, atol=FD_TOL)
    # border pixels (inside the cropped 5-pixel strip) still get gradient through the window
    assert np.max(np.abs(grad[0])) > 1e3 * FD_TOL


def test_float32_stays_float32():
    rng = np.random.default_rng(3)
    a, b = image_pair(rng, (16, 16, 3), dtype=np.float32)
    value, saved = ssim_fwd(a, b)
    assert np.asarray(value).dtype == np.float32
    assert ssim_map(a, b).dtype == np.float32
    assert ssim_bwd(saved).dtype == np.float32
    assert abs(float(value) - skimage_ssim(a.astype(np.float64), b.astype(np.float64))) <= F32_TOL
    grad64 = ssim_bwd(ssim_fwd(a.astype(np.float64), b.astype(np.float64))[1])
    np.testing.assert_allclose(ssim_bwd(saved), grad64, rtol=0, atol=F32_TOL)


def test_errors():
    rng = np.random.default_rng(4)
    a, b = image_pair(rng, (10, 16, 3))
    with pytest.raises(ValueError, match=r"at least 11x11 pixels.*got 10x16.*lambda_ssim=0"):
        ssim_fwd(a, b)
    a, b = image_pair(rng, (16, 16, 3))
    with pytest.raises(TypeError, match="ref has dtype float32"):
        ssim_fwd(a, b.astype(np.float32))
    with pytest.raises(ValueError, match=r"shape \(H, W, C\)"):
        ssim_map(a[..., 0], b[..., 0])
    with pytest.raises(ValueError, match="ref must have the shape"):
        ssim_fwd(a, b[:, :-1])
    b[3, 3, 0] = np.nan
    with pytest.raises(ValueError, match="ref contains NaN"):
        ssim_fwd(a, b)
