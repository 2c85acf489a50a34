"""L_depth: the rendered depth against a depth prior, up to what the prior leaves unknown
(docs/method.md §6).

A depth network's estimate is not in the scene's units (``docs/dataset_format.md §3``), and what
is unknown depends on its kind (``InitConfig.depth_prior_space``), so the term is invariant to
exactly that, per frame, and needs no alignment:

- ``"depth"`` (a video depth model: depth up to one scale): the spread of the log ratio,
  ``r = log D - log P``, about its frame mean, in L1 (robust to the prior's wrong edges) beyond
  a tolerance tau, ``L = mean max(|r - mean(r)| - tau, 0)``: invariant to any scale of either
  side, not to a shift, so the depth ratios the prior holds (near against far) are what the
  render is pulled to, and only where it departs from them by more than the prior's own
  accuracy (tau = 0.1: 10 %; 0 pulls every pixel).
- ``"metric"`` (a depth in the scene's own units, e.g. stereo over the model's renders at its
  cameras, L_stereo): the same without the frame mean, ``L = mean max(|r| - tau, 0)``: the
  depth itself is pulled, a bias of the whole frame included.
- ``"disparity"`` (a single-image network: disparity up to scale and shift): 1 - the Pearson
  correlation of 1/D with P, as the sparse-view splatting methods do (FSGS, DNGaussian):

      x = 1/D, y = P, x~ = x - mean(x), y~ = y - mean(y)
      rho = mean(x~ y~) / sqrt((mean(x~^2) + k mean(x)^2) (mean(y~^2) + k mean(y)^2)),  k = 1e-12
      L = 1 - rho  in [0, 2]

  The ``k mean^2`` floors keep rho and its gradient finite where one side is flat (a constant
  render has rho = 0, not 0/0); they move rho by ~1e-11 relative where the disparity varies by
  per cents, and are differentiated like the rest.

A pixel is valid where the prior is finite and positive ("depth", "metric"), the render's alpha is at least
``alpha_min`` (no depth is read through a transparent pixel) and the depth is above ``min_depth``;
validity is not differentiated. Fewer than two valid pixels: value 0 and no gradient. The L1's
kink (r_i at the frame mean) takes the subgradient 0 there.

``depth_prior_fwd`` / ``depth_prior_bwd`` are pure functions on plain (h, w) arrays; the gradient
is on the expected depth (the render's ``expected_depth``; with the blur model the mean over the
virtual views), computed in float64.
"""
from __future__ import annotations

import numpy as np

__all__ = ["depth_prior_fwd", "depth_prior_bwd", "SPACES", "FLAT_FLOOR"]

SPACES = ("depth", "metric", "disparity")
FLAT_FLOOR = 1e-12  # k: the variance floor of each side, relative to its squared mean


def _check(name, x, shape=None):
    if not isinstance(x, np.ndarray) or x.ndim != 2:
        raise ValueError(f"{name} must be an (h, w) array; got {getattr(x, 'shape', type(x).__name__)}")
    if shape is not None and x.shape != shape:
        raise ValueError(f"{name} must have the depth's shape {shape}; got {x.shape}")


def depth_prior_fwd(depth, prior, alpha, space="depth", alpha_min=0.5, min_depth=1e-6, mask=None, tolerance=0.0):
    """The spread of log(D / P) about its mean ("depth"), |log(D / P)| ("metric") or 1 - the
    Pearson correlation of 1/D with P ("disparity"), over the valid pixels (module docstring);
    ``tolerance``: tau of the "depth" and "metric" kinds, one number or an (h, w) map of them (a
    pixel's own, e.g. a tighter one on a mover's pixels; the frame mean is over every valid pixel
    either way). ``depth``, ``prior``,
    ``alpha``: (h, w); the prior NaN where it has no estimate; ``mask``: optional (h, w) weights, a pixel counts only where it is > 0. Returns (value, saved);
    saved is None when fewer than two pixels are valid (value 0)."""
    _check("depth", depth)
    for name, a in (("prior", prior), ("alpha", alpha)) + ((("mask", mask),) if mask is not None else ()):
        _check(name, a, depth.shape)
    if space not in SPACES:
        raise ValueError(f"space must be one of {SPACES}; got {space!r}")
    tol = np.asarray(tolerance, np.float64)
    if tol.ndim == 2:
        _check("tolerance", tol, depth.shape)
    elif tol.ndim != 0:
        raise ValueError(f"tolerance must be one number or an (h, w) map; got shape {tol.shape}")
    bad = tol[~(tol >= 0.0)]  # NaN is bad too
    if bad.size:
        got = float(tol) if tol.ndim == 0 else f"a map holding {bad[0]}"
        raise ValueError(f"tolerance must be >= 0 (a relative depth error) at every pixel; got {got}")
    d = np.asarray(depth, np.float64)
    p = np.asarray(prior, np.float64)
    valid = np.isfinite(p) & (alpha >= alpha_min) & np.isfinite(d) & (d > min_depth)
    if space != "disparity":
        valid &= p > 0
    if mask is not None:
        valid &= mask > 0
    n = int(valid.sum())
    if n < 2:
        return 0.0, None
    dv = d[valid]
    if space != "disparity":
        if tol.ndim == 2:
            tol = tol[valid]
        dev = np.log(dv) - np.log(p[valid])
        if space == "depth":
            dev -= dev.mean()
        excess = np.abs(dev) - tol
        sign = np.where(excess > 0.0, np.sign(dev), 0.0)  # pixels within tau pull nothing
        return float(np.mean(np.maximum(excess, 0.0))), (valid, dv, sign, space, depth.dtype)
    x = 1.0 / dv
    y = p[valid]
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
    if saved[-2] in ("depth", "metric"):
        valid, dv, sign, space, dtype = saved
        # d/dr_i of mean_j max(|r_j - mean(r)| - tau, 0) = (sign_i - mean(sign)) / N, sign 0
        # within tau ("metric": no mean, sign_i / N); dr_i/dD_i = 1/D_i
        out = np.zeros(valid.shape, np.float64)
        out[valid] = weight * (sign - (sign.mean() if space == "depth" else 0.0)) / (sign.size * dv)
        return out.astype(dtype, copy=False)
    valid, dv, xt, yt, xm, a, b, rho, space, dtype = saved
    n = xt.size
    # d rho / d x_i = (1/N) [y~_i / sqrt(a b) - rho (x~_i + k mean(x)) / a]
    drho_dx = (yt / np.sqrt(a * b) - rho * (xt + FLAT_FLOOR * xm) / a) / n
    g = weight * drho_dx / (dv * dv)  # dL/dx = -drho/dx, dx/dD = -1/D^2
    out = np.zeros(valid.shape, np.float64)
    out[valid] = g
    return out.astype(dtype, copy=False)
