"""Photometric loss L_render = (1 - lambda) L1 + lambda (1 - SSIM) (docs/method.md §6, Eq. 17).

L1 is the mean absolute difference over pixels and channels; SSIM is
``d2gs_np.losses.ssim`` (scikit-image's definition: 11-tap Gaussian window, 5-pixel border
cropped). The default lambda = 0.2 gives 0.8 L1 + 0.2 (1 - SSIM).

Optional mask (H, W), weights >= 0 (e.g. 1 on static pixels): L1 becomes the weighted mean
sum(m |d|) / (C sum(m)), and SSIM the weighted mean of the SSIM map over the interior,
sum_interior(m S) / (C sum_interior(m)). With mask=None both are the plain means.

At |render - target| = 0 the L1 term uses the subgradient 0 (sign(0) = 0).
With lambda = 0 the SSIM term is not evaluated (so images smaller than 11x11 are allowed).
"""
from __future__ import annotations

import numpy as np

from d2gs_np.base.checks import check_number
from d2gs_np.losses.ssim import _check_images, _ssim_fwd_weighted, ssim_bwd

__all__ = ["photometric_fwd", "photometric_bwd", "check_float_images"]


def check_float_images(**images):
    """Each keyword's value is a float64 or float32 array of shape (H, W, C); else TypeError or
    ValueError naming it."""
    for name, x in images.items():
        if not isinstance(x, np.ndarray) or x.dtype not in (np.float64, np.float32):
            got = x.dtype if isinstance(x, np.ndarray) else type(x).__name__
            raise TypeError(f"{name} must be a float64 or float32 array; got {got}")
        if x.ndim != 3:
            raise ValueError(f"{name} must have shape (H, W, C); got {x.shape}")


def photometric_fwd(render, target, lambda_ssim=0.2, mask=None):
    """(1 - lambda_ssim) * L1 + lambda_ssim * (1 - SSIM) of ``render`` against ``target``.

    render, target: (H, W, C), same float dtype (float32 kept).
    lambda_ssim: weight in [0, 1].
    mask: None or (H, W) non-negative weights of that dtype, not all zero.
    Returns (loss scalar of the images' dtype, saved).
    """
    check_number(lambda_ssim, "lambda_ssim", 0.0, 1.0)
    lam = float(lambda_ssim)
    if lam > 0.0:
        _check_images(render, target)  # also enforces H, W >= 11
    else:
        check_float_images(render=render, target=target)
        if target.dtype != render.dtype or target.shape != render.shape:
            raise ValueError(f"target must match render {render.shape} {render.dtype}; got {target.shape} {target.dtype}")
        if not (np.all(np.isfinite(render)) and np.all(np.isfinite(target))):
            raise ValueError("render and target must be finite")
    dtype = render.dtype
    H, W, C = render.shape
    if mask is not None:
        if not isinstance(mask, np.ndarray) or mask.dtype != dtype:
            got = mask.dtype if isinstance(mask, np.ndarray) else type(mask).__name__
            raise TypeError(f"mask must be a {dtype} array like render; got {got}")
        if mask.shape != (H, W):
            raise ValueError(f"mask must have shape ({H}, {W}); got {mask.shape}")
        if not (np.all(np.isfinite(mask)) and np.all(mask >= 0.0)) or not mask.sum() > 0.0:
            raise ValueError("mask must hold finite weights >= 0, not all zero")

    diff = render - target
    if mask is None:
        l1_weights = np.full((H, W, 1), 1.0 / (H * W * C), dtype=dtype)
    else:
        l1_weights = (mask / (C * np.sum(mask, dtype=np.float64))).astype(dtype)[:, :, None]
    l1 = np.sum(l1_weights * np.abs(diff), dtype=np.float64)
    loss = (1.0 - lam) * l1
    ssim_saved = None
    if lam > 0.0:
        ssim_value, ssim_saved = _ssim_fwd_weighted(render, target, mask)
        loss += lam * (1.0 - float(ssim_value))
    saved = dict(diff=diff, l1_weights=l1_weights, lam=lam, ssim=ssim_saved)
    return dtype.type(loss), saved


def photometric_bwd(saved, v_loss=1.0):
    """Gradient of ``v_loss * photometric_fwd(...)[0]`` w.r.t. render, (H, W, C)."""
    diff, lam = saved["diff"], saved["lam"]
    dtype = diff.dtype
    v_render = (dtype.type(v_loss * (1.0 - lam)) * saved["l1_weights"]) * np.sign(diff)
    if saved["ssim"] is not None:
        v_render = v_render + ssim_bwd(saved["ssim"], -lam * v_loss)
    return v_render
