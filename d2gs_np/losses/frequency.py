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
- wrap(x) = x wrapped into [-pi, pi); the phase term is the L1 of that.
- g(A) = A^2 / (A^2 + kappa^2), kappa = FREQ_PHASE_GATE_AMPLITUDE: the phase of a near-zero
  coefficient is undefined and d phi / dF grows as 1 / A; the gate (and its derivative) vanish
  at A = 0, so the gradient stays bounded (by ~1 / (2 kappa) per bin).
- At equality the L1 terms take the subgradient 0 (as L_render's L1); at A = 0 the amplitude's
  gradient direction F / A is taken as 0, and so below FREQ_AMPLITUDE_ZERO, where a bin that is 0
  in exact arithmetic sits after the FFT's rounding (its direction would be noise).

The backward maps the cotangent on each bin's real and imaginary parts (v_F = v_re + i v_im)
to the image by the adjoint of the real-to-complex orthonormal DFT: v_x = Re(ifft2(v_F, ortho)).
Only the render gets a gradient. Images are computed in float64 (float32 inputs are promoted
for the FFT; the gradient is returned in the render's dtype).
"""
from __future__ import annotations

import numbers

import numpy as np

from d2gs_np.constants import FREQ_AMPLITUDE_ZERO, FREQ_MASK_EDGE, FREQ_PHASE_GATE_AMPLITUDE

__all__ = ["highpass_mask", "frequency_fwd", "frequency_bwd"]


def highpass_mask(height: int, width: int, cutoff: float = 0.1, edge: float = FREQ_MASK_EDGE):
    """(H, W) float64 weights in [0, 1] of the FFT bins (``np.fft.fft2`` layout): 0 at low, 1 at
    high normalised radial frequency, with a raised-cosine edge of width ``edge`` around
    ``cutoff`` (module docstring)."""
    fy = np.fft.fftfreq(height)[:, None]
    fx = np.fft.fftfreq(width)[None, :]
    rho = np.sqrt(fy * fy + fx * fx) / 0.5
    s = np.clip((rho - (cutoff - 0.5 * edge)) / edge, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * s)


def _gate(a2, kappa2):
    """g = A^2 / (A^2 + kappa^2) and dg/dA / A = 2 kappa^2 / (A^2 + kappa^2)^2 (both finite at A = 0)."""
    d = a2 + kappa2
    return a2 / d, 2.0 * kappa2 / (d * d)


def frequency_fwd(render, target, mask=None, cutoff: float = 0.1):
    """L_freq of ``render`` against ``target`` (module docstring).

    render, target: (H, W, C) float64 or float32, same shape, finite.
    mask: None, or (H, W) weights >= 0 multiplied into both images before the FFT (pixels that
        carry no loss then contribute nothing; e.g. the static pixels of the warm-up stage).
    cutoff: normalised radial frequency of the high-pass mask's midpoint, in (0, sqrt 2).
    Returns (value, a Python float, saved).
    """
    for name, x in (("render", render), ("target", target)):
        if not isinstance(x, np.ndarray) or x.dtype not in (np.float64, np.float32):
            got = x.dtype if isinstance(x, np.ndarray) else type(x).__name__
            raise TypeError(f"{name} must be a float64 or float32 array; got {got}")
        if x.ndim != 3:
            raise ValueError(f"{name} must have shape (H, W, C); got {x.shape}")
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
    if isinstance(cutoff, bool) or not isinstance(cutoff, numbers.Real) or not 0.0 < cutoff < np.sqrt(2.0):
        raise ValueError(f"cutoff must be a normalised radial frequency in (0, sqrt 2); got {cutoff!r}")
    return _frequency_fwd(render, target, mask, float(cutoff))


def _frequency_fwd(render, target, mask, cutoff):
    H, W, C = render.shape
    m = None if mask is None else np.asarray(mask, dtype=np.float64)[:, :, None]
    r = render.astype(np.float64, copy=False)
    t = target.astype(np.float64, copy=False)
    if m is not None:
        r, t = r * m, t * m
    Fr = np.fft.fft2(r, axes=(0, 1), norm="ortho")
    Ft = np.fft.fft2(t, axes=(0, 1), norm="ortho")
    M = highpass_mask(H, W, cutoff)[:, :, None]
    weight = M / (C * max(float(M.sum()), np.finfo(np.float64).tiny))  # weighted mean over bins and channels
    a2r, a2t = Fr.real ** 2 + Fr.imag ** 2, Ft.real ** 2 + Ft.imag ** 2
    Ar, At = np.sqrt(a2r), np.sqrt(a2t)
    kappa2 = FREQ_PHASE_GATE_AMPLITUDE ** 2
    gr, dgr = _gate(a2r, kappa2)
    gt, _ = _gate(a2t, kappa2)
    dphi = np.angle(Fr) - np.angle(Ft)
    wrapped = np.mod(dphi + np.pi, 2.0 * np.pi) - np.pi
    d_amp = Ar - At
    value = float(np.sum(weight * (np.abs(d_amp) + gr * gt * np.abs(wrapped))))
    saved = dict(Fr=Fr, a2r=a2r, Ar=Ar, gr=gr, dgr=dgr, gt=gt, d_amp=d_amp, wrapped=wrapped, weight=weight, m=m,
                 dtype=render.dtype)
    return value, saved


def frequency_bwd(saved, v_value=1.0):
    """Gradient of ``v_value * frequency_fwd(render, target)[0]`` w.r.t. the render, (H, W, C)."""
    Fr, a2r, Ar, w = saved["Fr"], saved["a2r"], saved["Ar"], v_value * saved["weight"]
    nonzero = Ar > FREQ_AMPLITUDE_ZERO
    safe_a = np.where(nonzero, Ar, 1.0)
    safe_a2 = np.where(nonzero, a2r, 1.0)
    # d A / d(re, im) = (re, im) / A;  d phi / d(re, im) = (-im, re) / A^2  (0 where A = 0)
    abs_phase = np.abs(saved["wrapped"])
    # amplitude: |A_r - A_t| + gate-derivative part of the phase term g_t |wrap| dg_r/dA
    coef_dir = w * (np.sign(saved["d_amp"]) / safe_a + saved["gt"] * abs_phase * saved["dgr"])
    # phase: g_r g_t sign(wrap) d phi_r
    coef_rot = w * saved["gr"] * saved["gt"] * np.sign(saved["wrapped"]) / safe_a2
    coef_dir = np.where(nonzero, coef_dir, 0.0)
    coef_rot = np.where(nonzero, coef_rot, 0.0)
    v_re = coef_dir * Fr.real - coef_rot * Fr.imag
    v_im = coef_dir * Fr.imag + coef_rot * Fr.real
    v_img = np.fft.ifft2(v_re + 1j * v_im, axes=(0, 1), norm="ortho").real
    if saved["m"] is not None:
        v_img = v_img * saved["m"]
    return v_img.astype(saved["dtype"], copy=False)
