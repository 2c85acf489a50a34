"""L_dgrad: the rendered depth's shape against a depth prior's, neighbour by neighbour
(docs/method.md §6).

L_depth (``losses/depth_prior.py``) pulls a pixel's depth ratio only where it departs from the
frame's by more than the prior's accuracy, so inside that band a mover's Gaussians drift along
their rays patch by patch and the object tears in a novel view (docs/method.md §8). A depth
network's errors are smooth: its depth *differences* between neighbouring pixels are far better
than its depths. The term matches those differences, in log depth, as the monocular dynamic
methods match depth gradients (shape-of-motion's gradient loss; MiDaS's gradient matching):

    r = log D - log P,   L = (sum over pairs |r_i - r_j|) / (number of pairs)

over the horizontal and vertical neighbour pairs (i, j) whose two pixels are both valid. A scale
of either side, per frame, cancels in r_i - r_j: no alignment is needed and the frame's depth
scale stays free, which is what a mover seen from one camera at a time leaves unknown. The L1 is
robust to the prior's wrong edges; at r_i = r_j the subgradient 0 is taken.

A pixel is valid where the prior is finite and positive, the render's alpha is at least
``alpha_min``, the depth is above ``min_depth`` and ``mask`` (optional weights: the frame's moving
pixels, the warm-up's static ones) is > 0; validity is not differentiated. No valid pair: value 0
and no gradient. Only priors up to a scale or metric ones fit this form: a disparity up to a shift
does not (its log differences move with the shift), and the term builder leaves it out there.

``depth_gradient_fwd`` / ``depth_gradient_bwd`` are pure functions on plain (h, w) arrays; the
gradient is on the expected depth, computed in float64.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.losses.depth_prior import _check

__all__ = ["depth_gradient_fwd", "depth_gradient_bwd"]


def depth_gradient_fwd(depth, prior, alpha, alpha_min=0.5, min_depth=1e-6, mask=None):
    """Mean |r_i - r_j| over the valid neighbour pairs, r = log(depth / prior) (module docstring).
    ``depth``, ``prior``, ``alpha``, ``mask``: (h, w); the prior NaN where it has no estimate.
    Returns (value, saved); saved is None when no pair is valid (value 0)."""
    _check("depth", depth)
    for name, a in (("prior", prior), ("alpha", alpha)) + ((("mask", mask),) if mask is not None else ()):
        _check(name, a, depth.shape)
    d = np.asarray(depth, np.float64)
    p = np.asarray(prior, np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(p) & (p > 0) & (np.asarray(alpha) >= alpha_min) & np.isfinite(d) & (d > min_depth)
    if mask is not None:
        valid &= np.asarray(mask) > 0
    pair_x = valid[:, 1:] & valid[:, :-1]
    pair_y = valid[1:, :] & valid[:-1, :]
    n = int(pair_x.sum() + pair_y.sum())
    if n == 0:
        return 0.0, None
    r = np.zeros_like(d)
    r[valid] = np.log(d[valid]) - np.log(p[valid])
    dx = np.where(pair_x, r[:, 1:] - r[:, :-1], 0.0)
    dy = np.where(pair_y, r[1:, :] - r[:-1, :], 0.0)
    value = (np.abs(dx).sum() + np.abs(dy).sum()) / n
    return float(value), (np.sign(dx), np.sign(dy), valid, d, n, depth.dtype)


def depth_gradient_bwd(saved, weight=1.0):
    """Cotangent (h, w) on the rendered depth of ``weight`` x the value of ``depth_gradient_fwd``;
    zero at invalid pixels. ``saved`` None (no valid pair): None."""
    if saved is None:
        return None
    sx, sy, valid, d, n, dtype = saved
    # d/dr of sum |r_j - r_i| over a pair: +sign at j (the later pixel), -sign at i
    v_r = np.zeros(d.shape, np.float64)
    v_r[:, 1:] += sx
    v_r[:, :-1] -= sx
    v_r[1:, :] += sy
    v_r[:-1, :] -= sy
    out = np.zeros(d.shape, np.float64)
    out[valid] = weight * v_r[valid] / (n * d[valid])  # dr/dD = 1/D
    return out.astype(dtype, copy=False)
