"""Reference L_freq (docs/method.md §6, Eq. 15): the full complex spectrum of every image, in NumPy
float64, written from the definition in ``d2gs_np.losses.frequency`` (same mask, gate, wrap and
zero-amplitude rule). The fast path there uses the real-input half spectrum, a cached target
spectrum and one Numba pass over the bins; tests hold it to this one. It does not import the fast
path (only the mask, which is the definition of M).
"""
from __future__ import annotations

import numpy as np

from d2gs_np.constants import FREQ_AMPLITUDE_ZERO, FREQ_PHASE_GATE_AMPLITUDE
from d2gs_np.losses.frequency import highpass_mask

__all__ = ["frequency_fwd", "frequency_bwd"]


def _gate(a2, kappa2):
    """g = A^2 / (A^2 + kappa^2) and dg/dA / A = 2 kappa^2 / (A^2 + kappa^2)^2."""
    d = a2 + kappa2
    return a2 / d, 2.0 * kappa2 / (d * d)


def frequency_fwd(render, target, mask=None, cutoff: float = 0.1):
    """L_freq of render (H, W, C) against target, both multiplied by mask (H, W) when given.
    Returns (value, saved). No input checks: the fast path's ``frequency_fwd`` makes them."""
    H, W, C = render.shape
    m = None if mask is None else np.asarray(mask, dtype=np.float64)[:, :, None]
    r = render.astype(np.float64)
    t = target.astype(np.float64)
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
    saved = dict(Fr=Fr, a2r=a2r, Ar=Ar, gr=gr, dgr=dgr, gt=gt, d_amp=d_amp, wrapped=wrapped, weight=weight, m=m)
    return value, saved


def frequency_bwd(saved, v_value=1.0):
    """Gradient of ``v_value * frequency_fwd(...)[0]`` w.r.t. the render, (H, W, C) float64:
    the cotangent on each bin's real and imaginary parts, v_F = v_re + i v_im, mapped back by the
    adjoint of the orthonormal DFT, v_x = Re(ifft2(v_F))."""
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
    return v_img
