"""High-frequency loss L_freq: the fast half-spectrum path against the full-spectrum NumPy reference,
backward vs central FD (even and odd sizes, masks), analytic values, a cached target spectrum, and
the stiff cases: identical images, constant images, a single-pixel impulse, amplitude-zero bins;
gradients stay finite and within the bound the phase gate guarantees."""
import numpy as np
import pytest

from d2gs_np.constants import FREQ_PHASE_GATE_AMPLITUDE
from d2gs_np.losses.frequency import frequency_bwd, frequency_fwd, highpass_mask, target_spectrum
from d2gs_np.reference import frequency as reference
from render_fixtures import central_fd

# Central FD with h = 1e-6 on images in [0.2, 0.8]: their bins have amplitudes ~1e-2..1, far above
# the gate's kappa = 1e-3 and away from equal amplitudes / phases, so the function is smooth
# with curvature ~1 / A^2 <~ 1e4 per bin; the FD error ~h^2 * 1e8 / (bins) plus rounding
# 1e-16 / h stays below 1e-9 (measured ~3e-10) against gradients ~1e-2.
FD_H = 1e-6
FD_TOL = 1e-8


def _pair(rng, shape):
    return rng.uniform(0.2, 0.8, size=shape), rng.uniform(0.2, 0.8, size=shape)


def _grad_bound(shape, cutoff=0.1):
    """Bound on ||v_image||_2 (the FFT is unitary): per bin the amplitude part is <= w, the
    gate-derivative part <= w pi max|dg/dA| = w pi 0.65 / kappa, the phase part <= w / (2 kappa)."""
    H, W, C = shape
    M = highpass_mask(H, W, cutoff)
    w = np.broadcast_to(M[:, :, None] / (C * M.sum()), shape)
    return float(np.sqrt(np.sum(w ** 2))) * (1.0 + 3.0 / FREQ_PHASE_GATE_AMPLITUDE)


# The fast path sums the half spectrum (each mirrored pair once, doubled) in one Numba pass and
# the reference the full spectrum with NumPy: the same terms in another order and FFT, so they
# agree to rounding. Measured at 135 x 240 x 3: value 6e-15 relative, gradient 3e-14 of its
# largest entry; 1e-12 leaves room for other sizes and FFT builds and is far below any
# error in the pairing (a missed or double-counted column changes the value by > 1e-3).
REF_TOL = 1e-12


@pytest.mark.parametrize("shape", [(10, 12, 3), (7, 9, 2), (9, 10, 1), (8, 7, 3), (135, 240, 3)])
@pytest.mark.parametrize("masked", [False, True])
def test_fast_path_matches_the_full_spectrum_reference(shape, masked):
    rng = np.random.default_rng(sum(shape))
    render, target = _pair(rng, shape)
    mask = (rng.uniform(size=shape[:2]) > 0.3).astype(np.float64) if masked else None
    value, saved = frequency_fwd(render, target, mask)
    ref_value, ref_saved = reference.frequency_fwd(render, target, mask)
    assert value == pytest.approx(ref_value, rel=REF_TOL)
    grad, ref_grad = frequency_bwd(saved, 0.7), reference.frequency_bwd(ref_saved, 0.7)
    np.testing.assert_allclose(grad, ref_grad, rtol=0, atol=REF_TOL * np.abs(ref_grad).max())


def test_a_given_target_spectrum_gives_the_same_result_and_a_wrong_one_is_refused():
    rng = np.random.default_rng(11)
    render, target = _pair(rng, (9, 12, 3))
    mask = (rng.uniform(size=(9, 12)) > 0.5).astype(np.float64)
    value, saved = frequency_fwd(render, target, mask)
    value2, saved2 = frequency_fwd(render, target, mask, target_fft=target_spectrum(target, mask))
    assert value2 == value
    np.testing.assert_array_equal(frequency_bwd(saved2), frequency_bwd(saved))
    with pytest.raises(ValueError, match="target_fft must be target_spectrum"):
        frequency_fwd(render, target, target_fft=target_spectrum(target[:, :10]))
    with pytest.raises(ValueError, match="target_fft must be target_spectrum"):
        frequency_fwd(render, target, target_fft=target_spectrum(target).astype(np.complex64))


@pytest.mark.parametrize("shape", [(10, 12, 3), (7, 9, 2)])  # even and odd sizes
def test_backward_matches_central_fd(shape):
    render, target = _pair(np.random.default_rng(0), shape)
    _, saved = frequency_fwd(render, target)
    grad = frequency_bwd(saved, 1.7)
    fd = central_fd(lambda x: 1.7 * frequency_fwd(x, target)[0], render, FD_H)
    np.testing.assert_allclose(grad, fd, rtol=0, atol=FD_TOL)


def test_backward_with_a_mask_matches_central_fd():
    rng = np.random.default_rng(1)
    render, target = _pair(rng, (9, 10, 3))
    mask = (rng.uniform(size=(9, 10)) > 0.3).astype(np.float64)
    _, saved = frequency_fwd(render, target, mask)
    grad = frequency_bwd(saved)
    fd = central_fd(lambda x: frequency_fwd(x, target, mask)[0], render, FD_H)
    np.testing.assert_allclose(grad, fd, rtol=0, atol=FD_TOL)
    assert np.all(grad[mask == 0] == 0.0)  # pixels outside the mask get no gradient


def test_value_matches_the_formula_written_out():
    rng = np.random.default_rng(2)
    render, target = _pair(rng, (8, 11, 1))
    Fr, Ft = np.fft.fft2(render[:, :, 0], norm="ortho"), np.fft.fft2(target[:, :, 0], norm="ortho")
    M = highpass_mask(8, 11)
    k2 = FREQ_PHASE_GATE_AMPLITUDE ** 2
    g = lambda a: a * a / (a * a + k2)  # noqa: E731
    dphi = np.angle(Fr) - np.angle(Ft)
    dphi = (dphi + np.pi) % (2 * np.pi) - np.pi
    expected = np.sum(M * (np.abs(np.abs(Fr) - np.abs(Ft)) + g(np.abs(Fr)) * g(np.abs(Ft)) * np.abs(dphi))) / M.sum()
    assert frequency_fwd(render, target)[0] == pytest.approx(expected, rel=1e-12)


def test_identical_images_give_zero_and_zero_gradient():
    img = np.random.default_rng(3).uniform(size=(12, 13, 3))
    value, saved = frequency_fwd(img, img.copy())
    grad = frequency_bwd(saved)
    assert value == 0.0
    assert np.all(grad == 0.0)


def test_constant_images_are_finite_and_only_low_frequency_differs():
    a, b = np.full((16, 16, 3), 0.3), np.full((16, 16, 3), 0.7)  # they differ only in the DC bin
    value, saved = frequency_fwd(a, b)
    grad = frequency_bwd(saved)
    assert value < 1e-15  # the DC bin is masked out; every other bin is ~0 in both
    # those bins are 0 up to rounding (< FREQ_AMPLITUDE_ZERO): the subgradient 0, not a unit
    # vector in the direction of the rounding noise
    assert np.all(grad == 0.0)
    # a textured target against a constant render: finite, bounded
    tex = np.random.default_rng(9).uniform(0.2, 0.8, size=a.shape)
    grad = frequency_bwd(frequency_fwd(a, tex)[1])
    assert np.all(np.isfinite(grad)) and np.linalg.norm(grad) <= _grad_bound(a.shape)


def test_a_single_pixel_impulse_has_the_analytic_value():
    H, W = 9, 14
    impulse = np.zeros((H, W, 1))
    impulse[4, 6, 0] = 1.0
    # |F| = 1 / sqrt(H W) in every bin; the target's bins are all 0, so its phase is gated out
    value, saved = frequency_fwd(impulse, np.zeros((H, W, 1)))
    assert value == pytest.approx(1.0 / np.sqrt(H * W), rel=1e-12)
    grad = frequency_bwd(saved)
    assert np.all(np.isfinite(grad))
    # a shifted impulse: same amplitudes, only phases differ, and the value stays finite
    shifted = np.roll(impulse, 3, axis=1)
    v2, s2 = frequency_fwd(impulse, shifted)
    assert 0.0 < v2 < np.pi and np.all(np.isfinite(frequency_bwd(s2)))


def test_amplitude_zero_bins_in_the_target_gate_the_phase_off():
    rng = np.random.default_rng(4)
    render = rng.uniform(0.2, 0.8, size=(10, 10, 2))
    target = np.full((10, 10, 2), 0.5)  # every non-DC bin has amplitude ~0 (rounding)
    value, saved = frequency_fwd(render, target)
    M = highpass_mask(10, 10)[:, :, None]
    A = np.abs(np.fft.fft2(render, axes=(0, 1), norm="ortho"))
    assert value == pytest.approx(float(np.sum(M * A) / (2 * M.sum())), rel=1e-10)  # amplitudes only
    grad = frequency_bwd(saved)
    fd = central_fd(lambda x: frequency_fwd(x, target)[0], render, FD_H)
    np.testing.assert_allclose(grad, fd, rtol=0, atol=FD_TOL)


def test_gradient_stays_bounded_at_amplitudes_near_the_gate():
    # a render whose high-frequency bins are ~kappa in size: the phase's 1 / A is tamed by the gate
    rng = np.random.default_rng(5)
    target = rng.uniform(0.2, 0.8, size=(12, 12, 3))
    render = 0.5 + 1e-3 * rng.standard_normal((12, 12, 3))
    grad = frequency_bwd(frequency_fwd(render, target)[1])
    assert np.all(np.isfinite(grad)) and np.linalg.norm(grad) <= _grad_bound(render.shape)


def test_mask_is_a_high_pass_with_a_smooth_edge():
    # 64 px: bin j of an axis has rho = j / 32; the ramp spans rho in [0.075, 0.125] = j in [2.4, 4]
    M = highpass_mask(64, 64)
    assert M[0, 0] == 0.0 and M[0, 2] == 0.0 and M[32, 32] == 1.0
    assert M[0, 3] == pytest.approx(0.5 - 0.5 * np.cos(np.pi * (3 / 32 - 0.075) / 0.05), rel=1e-12)
    assert M[0, 4] == pytest.approx(1.0, abs=1e-15) and M[0, 5] == 1.0
    assert M[0, 3] == M[0, 61] == M[3, 0]  # radial: symmetric in +-f and in the axes
    assert np.all((M >= 0) & (M <= 1))


def test_float32_render_gets_a_float32_gradient():
    render, target = _pair(np.random.default_rng(6), (8, 8, 3))
    grad = frequency_bwd(frequency_fwd(render.astype(np.float32), target.astype(np.float32))[1])
    assert grad.dtype == np.float32


def test_bad_input_names_the_argument():
    img = np.zeros((8, 8, 3))
    with pytest.raises(TypeError, match="render must be a float64 or float32 array"):
        frequency_fwd(img.astype(int), img)
    with pytest.raises(ValueError, match="target must have the render's shape"):
        frequency_fwd(img, np.zeros((8, 9, 3)))
    with pytest.raises(ValueError, match="NaN"):
        frequency_fwd(np.full((8, 8, 3), np.nan), img)
    with pytest.raises(ValueError, match="mask must be an array of shape"):
        frequency_fwd(img, img, mask=np.ones((3, 3)))
    with pytest.raises(ValueError, match="cutoff"):
        frequency_fwd(img, img, cutoff=2.0)
