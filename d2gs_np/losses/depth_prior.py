"""L_depth: the rendered depth against a depth prior, up to scale and shift (docs/method.md §6).

A depth network's estimate (a video model's depth up to one scale, or a single-image network's
disparity up to scale and shift; ``docs/dataset_format.md §3``) is not in the scene's units, so
the term scores the *Pearson correlation* of the rendered expected depth with it over the valid
pixels of one frame, as the sparse-view splatting methods do (FSGS, DNGaussian): invariant to any
positive scale and shift of either side, so it needs no alignment and cannot pull the scene
towards a misjudged scale. With ``space = "depth"`` the correlation is of the depth D with the
prior P; with ``"disparity"`` of 1/D with P.

    x   = D (depth) or 1/D (disparity), y = P, over the N valid pixels
    x~  = x - mean(x),  y~ = y - mean(y)
    rho = mean(x~ y~) / sqrt((mean(x~^2) + k mean(x)^2) (mean(y~^2) + k mean(y)^2)),  k = 1e-8
    L   = 1 - rho  in [0, 2]

The ``k mean^2`` floors keep rho and its gradient finite where one side is flat (a constant
render has rho = 0, not 0/0); they move rho by ~1e-8 relative where the depth varies by per
cents, and are differentiated like the rest. A pixel is valid where the prior is finite, the
render's alpha is at least ``alpha_min`` (no depth is read through a transparent pixel) and the
depth is above ``min_depth``; validity is not differentiated. Fewer than two valid pixels: value 0
and no gradient.

``depth_prior_fwd`` / ``depth_prior_bwd`` are pure functions on plain (h, w) arrays; the gradient
is on the expected depth (the render's ``expected_depth``; with the blur model the mean over the
virtual views), computed in float64.
"""
from __future__ import annotations

import numpy as np

__all__ = ["depth_prior_fwd", "depth_prior_bwd", "SPACES", "FLAT_FLOOR"]

SPACES = ("depth", "disparity")
FLAT_FLOOR = 1e-8  # k: the variance floor of each side, relative to its squared mean


def _check(name, x, shape=None):
    if not isinstance(x, np.ndarray) or x.ndim != 2:
        raise ValueError(f"{name} must be an (h, w) array; got {getattr(x, 'shape', type(x).__name__)}")
    if shape is not None and x.shape != shape:
        raise ValueError(f"{name} must have the depth's shape {shape}; got {x.shape}")


def depth_prior_fwd(depth, prior, alpha, space="depth", alpha_min=0.5, min_depth=1e-6, mask=None):
    """1 - Pearson correlation of the rendered depth (or its inverse) with the prior (module
    docstring). ``depth``, ``prior``, ``alpha``: (h, w); the prior NaN where it has no estimate;
    ``mask``: optional (h, w) weights, a pixel counts only where it is > 0. Returns (value, saved);
    saved is None when fewer than two pixels are valid (value 0)."""
    _check("depth", depth)
    for name, a in (("prior", prior), ("alpha", alpha)) + ((("mask", mask),) if mask is not None else ()):
        _check(name, a, depth.shape)
    if space not in SPACES:
        raise ValueError(f"space must be one of {SPACES}; got {space!r}")
    d = np.asarray(depth, np.float64)
    valid = np.isfinite(prior) & (alpha >= alpha_min) & np.isfinite(d) & (d > min_depth)
    if mask is not None:
        valid &= mask > 0
    n = int(valid.sum())
    if n < 2:
        return 0.0, None
    dv = d[valid]
    x = dv if space == "depth" else 1.0 / dv
    y = np.asarray(prior, np.float64)[valid]
    xm, ym = x.mean(), y.mean()
    xt, yt = x - xm, y - ym
    c = np.mean(xt * yt)
    a = np.mean(xt * xt) + FLAT_FLOOR * xm * xm
    b = np.mean(yt * yt) + FLAT_FLOOR * ym * ym
    if b <= 0.0:  # a prior of zeros everywhere valid: nothing to correlate with
        return 0.0, None
    rho = c / np.sqrt(a * b)
    return float(1.0 - rho), (valid, dv, xt, yt, xm, a, b, rho, space, depth.dtype)


def depth_prior_bwd(saved, weight=1.0):
    """Cotangent (h, w) on the rendered depth of ``weight`` x the value of ``depth_prior_fwd``;
    zero at invalid pixels. ``saved`` None (no valid pixels): None."""
    if saved is None:
        return None
    valid, dv, xt, yt, xm, a, b, rho, space, dtype = saved
    n = xt.size
    # d rho / d x_i = (1/N) [y~_i / sqrt(a b) - rho (x~_i + k mean(x)) / a]
    drho_dx = (yt / np.sqrt(a * b) - rho * (xt + FLAT_FLOOR * xm) / a) / n
    g = -weight * drho_dx
    if space == "disparity":
        g = g * (-1.0 / (dv * dv))
    out = np.zeros(valid.shape, np.float64)
    out[valid] = g
    return out.astype(dtype, copy=False)
