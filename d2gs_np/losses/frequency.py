"""High-frequency loss L_freq (docs/method.md §6, Eq. 15): the render's fine detail against the target's.

Per channel c, with F = fft2(image[..., c], norm="ortho") (orthonormal: a bin's amplitude is on
the pixels' scale at any resolution), A = |F| and phi = angle(F):

    L_freq = sum_bins M (|A_r - A_t| + g(A_r) g(A_t) |wrap(phi_r - phi_t)|) / (C sum_bins M)

- M (H, W): high-pass mask over the normalised radial frequency rho = sqrt(fy^2 + fx^2) / 0.5
  (``np.fft.fftfreq`` cycles per pixel; rho = 1 at the Nyquist frequency of an axis): 0 below
  ``cutoff - FREQ_MASK_EDGE / 2``, 1 above ``cutoff + FREQ_MASK_EDGE / 2``, a raised cosine
  between. ``cutoff`` = 0.1 keeps all but the coarsest structure, which L_render already fits.
- The sum is a mean over the kept bins (weighted by M) and channels, not Eq. 15's raw sum, so
  the value does not grow with the render size as the progressive schedule changes it.
- wrap(x) = x wrapped into (-pi, pi]; the phase term is the L1 of that (at |wrap| = pi, its
  peak, the sign taken for the gradient is a choice of subgradient).
- g(A) = A^2 / (A^2 + kappa^2), kappa = FREQ_PHASE_GATE_AMPLITUDE: the phase of a near-zero
  coefficient is undefined and d phi / dF grows as 1 / A; the gate (and its derivative) vanish
  at A = 0, so the gradient stays bounded (by ~1 / (2 kappa) per bin).
- At equality the L1 terms take the subgradient 0 (as L_render's L1); at A = 0 the amplitude's
  gradient direction F / A is taken as 0, and so below FREQ_AMPLITUDE_ZERO, where a bin that is 0
  in exact arithmetic sits after the FFT's rounding (its direction would be noise).

How it is computed (the reference, ``d2gs_np.reference.frequency``, takes the full complex
spectrum of both images and is held equal to this to ~1e-13):
- Real images have Hermitian spectra, F(-k) = conj F(k), with the same amplitude, the opposite
  phase and the same mask weight, so every term of the sum is equal for k and -k. The real-input
  half spectrum (``scipy.fft.rfft2`` over the two image axes, H x (W // 2 + 1) bins) holds each
  pair once; a bin whose mirror is another stored column counts twice in the value.
- The target's spectrum does not depend on the render: ``target_spectrum`` computes it once, and
  the training term keeps it per frame while the target (and loss mask) stay the same.
- One Numba pass over the bins computes the value and each bin's cotangent
  v_F = v_re + i v_im on its real and imaginary parts; the phase difference is
  atan2(Im(F_r conj F_t), Re(F_r conj F_t)), already wrapped.
- The backward maps v_F to the image by the adjoint of the orthonormal DFT, v_x = Re(ifft2(v_F));
  the full v_F is Hermitian (the loss is even in the pair), so that is ``irfft2`` of the half.
Only the render gets a gradient. Images are computed in float64 (float32 inputs are promoted
for the FFT; the gradient is returned in the render's dtype).
"""
from __future__ import annotations

import functools
import math

import numpy as np
import scipy.fft
from numba import njit

from d2gs_np.base.checks import check_number
from d2gs_np.losses.photometric import check_float_images
from d2gs_np.constants import FREQ_AMPLITUDE_ZERO, FREQ_MASK_EDGE, FREQ_PHASE_GATE_AMPLITUDE

__all__ = ["highpass_mask", "target_spectrum", "frequency_fwd", "frequency_bwd", "warm_up"]


def highpass_mask(height: int, width: int, cutoff: float = 0.1, edge: float = FREQ_MASK_EDGE):
    """(H, W) float64 weights in [0, 1] of the FFT bins (``np.fft.fft2`` layout): 0 at low, 1 at
    high normalised radial frequency, with a raised-cosine edge of width ``edge`` around
    ``cutoff`` (module docstring)."""
    fy = np.fft.fftfreq(height)[:, None]
    fx = np.fft.fftfreq(width)[None, :]
    rho = np.sqrt(fy * fy + fx * fx) / 0.5
    s = np.clip((rho - (cutoff - 0.5 * edge)) / edge, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * s)


@functools.lru_cache(maxsize=32)
def _half_weights(height: int, width: int, channels: int, cutoff: float):
    """Per-bin weights of the half spectrum, (H, W // 2 + 1) each, read-only:
    ``grad`` = M / (C sum_full M), the weight of one bin of the full spectrum, and ``value`` =
    ``grad`` x the number of full-spectrum bins the stored one stands for (2, or 1 for the
    columns that are their own mirror: frequency 0 and, for even W, the Nyquist column)."""
    M = highpass_mask(height, width, cutoff)
    grad = M[:, : width // 2 + 1] / (channels * max(float(M.sum()), np.finfo(np.float64).tiny))
    mult = np.full(width // 2 + 1, 2.0)
    mult[0] = 1.0
    if width % 2 == 0:
        mult[-1] = 1.0
    value = grad * mult[None, :]
    grad.setflags(write=False)
    value.setflags(write=False)
    return grad, value


def target_spectrum(target, mask=None):
    """Half spectrum (H, W // 2 + 1, C) complex128 of ``target`` (times ``mask``), orthonormal: what
    ``frequency_fwd`` takes as ``target_fft`` to skip the target's FFT. No checks here:
    ``frequency_fwd`` checks its shape against the render's."""
    t = target.astype(np.float64, copy=False)
    if mask is not None:
        t = t * np.asarray(mask, dtype=np.float64)[:, :, None]
    return scipy.fft.rfft2(t, axes=(0, 1), norm="ortho")


def frequency_fwd(render, target, mask=None, cutoff: float = 0.1, target_fft=None):
    """L_freq of ``render`` against ``target`` (module docstring).

    render, target: (H, W, C) float64 or float32, same shape, finite.
    mask: None, or (H, W) weights >= 0 multiplied into both images before the FFT (pixels that
        carry no loss then contribute nothing; e.g. the static pixels of the warm-up stage).
    cutoff: normalised radial frequency of the high-pass mask's midpoint, in (0, sqrt 2).
    target_fft: None, or ``target_spectrum(target, mask)`` computed before (it is not recomputed;
        the caller vouches that it belongs to this target and mask).
    Returns (value, a Python float, saved).
    """
    check_float_images(render=render, target=target)
    for name, x in (("render", render), ("target", target)):
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{name} contains NaN or inf; every pixel must be finite")
    if target.shape != render.shape:
        raise ValueError(f"target must have the render's shape {render.shape}; got {target.shape}")
    if mask is not None:
        if not isinstance(mask, np.ndarray) or mask.shape != render.shape[:2]:
            got = mask.shape if isinstance(mask, np.ndarray) else type(mask).__name__
            raise ValueError(f"mask must be an array of shape {render.shape[:2]}; got {got}")
        if not (np.all(np.isfinite(mask)) and np.all(mask >= 0.0)):
            raise ValueError("mask must hold finite weights >= 0")
    check_number(cutoff, "cutoff", 0.0, np.sqrt(2.0), lo_open=True, hi_open=True,
                 hint="a normalised radial frequency up to sqrt 2")
    if target_fft is not None:
        H, W, C = render.shape
        if not isinstance(target_fft, np.ndarray) or target_fft.shape != (H, W // 2 + 1, C) \
                or target_fft.dtype != np.complex128:
            got = (target_fft.shape, target_fft.dtype) if isinstance(target_fft, np.ndarray) else type(target_fft)
            raise ValueError(f"target_fft must be target_spectrum(target, mask): complex128 of shape "
                             f"{(H, W // 2 + 1, C)}; got {got}")
    return _frequency_fwd(render, target, mask, float(cutoff), target_fft)


def _frequency_fwd(render, target, mask, cutoff, target_fft=None):
    H, W, C = render.shape
    m = None if mask is None else np.asarray(mask, dtype=np.float64)[:, :, None]
    r = render.astype(np.float64, copy=False)
    if m is not None:
        r = r * m
    Fr = scipy.fft.rfft2(r, axes=(0, 1), norm="ortho")
    Ft = target_spectrum(target, mask) if target_fft is None else target_fft
    w_grad, w_value = _half_weights(H, W, C, cutoff)
    v_F = np.empty_like(Fr)
    value = _bins_kernel(Fr, Ft, w_grad, w_value, FREQ_PHASE_GATE_AMPLITUDE ** 2, FREQ_AMPLITUDE_ZERO, v_F)
    return float(value), dict(v_F=v_F, shape=(H, W), m=m, dtype=render.dtype)


@njit(cache=True)
def _bins_kernel(Fr, Ft, w_grad, w_value, kappa2, amp_zero, v_F):
    """Value sum over bins of w_value (|A_r - A_t| + g_r g_t |dphi|); v_F (out) the cotangent of
    each bin's (re, im) for the full-spectrum weight w_grad:
      d|A_r - A_t| = sign(A_r - A_t) F_r / A_r,
      d(g_r g_t |dphi|) = g_t |dphi| (dg/dA)/A_r F_r + g_r g_t sign(dphi) i F_r / A_r^2,
    both 0 where A_r <= amp_zero (the subgradient 0; module docstring)."""
    H, Wh, C = Fr.shape
    total = 0.0
    for y in range(H):
        for x in range(Wh):
            wg = w_grad[y, x]
            wv = w_value[y, x]
            for c in range(C):
                fr = Fr[y, x, c]
                ft = Ft[y, x, c]
                a2r = fr.real * fr.real + fr.imag * fr.imag
                a2t = ft.real * ft.real + ft.imag * ft.imag
                ar = math.sqrt(a2r)
                at = math.sqrt(a2t)
                dr = a2r + kappa2
                dt = a2t + kappa2
                gr = a2r / dr
                gt = a2t / dt
                # phase of F_r conj(F_t): the difference of the phases, wrapped to (-pi, pi]
                cre = fr.real * ft.real + fr.imag * ft.imag
                cim = fr.imag * ft.real - fr.real * ft.imag
                dphi = math.atan2(cim, cre)
                d_amp = ar - at
                total += wv * (abs(d_amp) + gr * gt * abs(dphi))
                if ar > amp_zero and wg != 0.0:
                    s_amp = 1.0 if d_amp > 0.0 else (-1.0 if d_amp < 0.0 else 0.0)
                    s_phi = 1.0 if dphi > 0.0 else (-1.0 if dphi < 0.0 else 0.0)
                    dgr = 2.0 * kappa2 / (dr * dr)
                    coef_dir = wg * (s_amp / ar + gt * abs(dphi) * dgr)
                    coef_rot = wg * gr * gt * s_phi / a2r
                    v_F[y, x, c] = complex(coef_dir * fr.real - coef_rot * fr.imag,
                                           coef_dir * fr.imag + coef_rot * fr.real)
                else:
                    v_F[y, x, c] = 0.0
    return total


def frequency_bwd(saved, v_value=1.0):
    """Gradient of ``v_value * frequency_fwd(render, target)[0]`` w.r.t. the render, (H, W, C)."""
    H, W = saved["shape"]
    v_img = scipy.fft.irfft2(v_value * saved["v_F"], s=(H, W), axes=(0, 1), norm="ortho")
    if saved["m"] is not None:
        v_img = v_img * saved["m"]
    return v_img.astype(saved["dtype"], copy=False)


def warm_up():
    """Compile (or load from the Numba cache) the bins kernel on a tiny image, so that a timed run
    does not count it (~0.7 s to compile, milliseconds from the cache)."""
    img = np.linspace(0.0, 1.0, 4 * 4 * 3).reshape(4, 4, 3)
    frequency_bwd(_frequency_fwd(img, img[::-1].copy(), None, 0.1)[1])
