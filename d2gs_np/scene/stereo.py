"""Plane-sweep stereo: a depth map of one frame from its neighbours and the given poses.

Used by the initialisation (``scene/initialize.py``, dense seeding) so that photographic detail
starts at the right depth. A few hundred sparse SIFT triangulations interpolated over a frame
put the dense seeds well in front of the true depth (docs/results.md §9), and training then never
recovers the geometry: the fit settles on semi-transparent layers near the camera that average
the texture of several views.

Method (classical plane sweep, e.g. Collins 1996; Gallup et al. 2007), all on plain arrays:

1. Depth hypotheses d_1 .. d_D uniform in inverse depth over [near, far].
2. For a reference pixel p (centre at +0.5, docs/conventions) with ray r = K^-1 (p, 1), the
   point at z-depth d is X = d r in the reference camera. In a source camera with
   cam_T_world T_s, and T_r the reference's, X_s = d (R r) + t with [R | t] = T_s T_r^-1; its
   pixel is K_s X_s / z_s. The source image is sampled there (bilinear, ``cv2.remap``; its
   integer coordinates are pixel centres, so 0.5 is subtracted).
3. Cost of a source at a hypothesis: mean absolute RGB difference, averaged over a
   ``window`` x ``window`` box (the same pixels must agree at the same depth). A source whose
   sample falls outside its image, or on its moving pixels, gives no cost there.
4. Per pixel and hypothesis the sources' costs are combined by the mean of the best half
   (at least ``min_sources``): a view that is occluded at the true depth is out-voted.
5. Winner-take-all over the hypotheses, refined by a parabola through the best cost and its
   two neighbours (in inverse depth).
6. Kept only where the result can be trusted: enough texture (the standard deviation of the
   reference's grey level over the window >= ``min_texture``), a distinct minimum (best cost
   <= ``max_cost_ratio`` x the best cost among the hypotheses that lie more than
   ``distinct_px`` source pixels, and more than two hypotheses, from the best one; the pixel
   distance per hypothesis is each reference pixel's span over the sweep in a source divided by
   D - 1, the median over the sources), at least ``min_sources`` sources, a best hypothesis
   inside the sweep (not at either end), and not on a moving pixel of the reference.
   ``info["rejected_share"]`` gives the share of pixels each check rejects on its own.

Why the distinctness can be measured in source pixels (docs/method.md §8): with a small camera
translation (the suite's cube_sign) the hypotheses two steps away lie a fraction of a source pixel
from the best, inside the minimum's own basin (a 5 x 5 window's cost rises over about a pixel,
more slowly on blurred frames), and the check rejects most pixels; one source pixel
(``StereoConfig.distinct_px = 1``) keeps many more (docs/results.md §9).

Accuracy: with D = 128 hypotheses and the parabola the depth error on textured, sharp
synthetic planes is well below 1 % (tests/scene/test_stereo.py measures it against the
true depth of a ray-cast suite scene).
"""
from __future__ import annotations

import warnings

import cv2
import numpy as np

from d2gs_np.constants import PIXEL_CENTER_OFFSET
from d2gs_np.scene.config import StereoConfig

__all__ = ["plane_sweep_depth"]


def _box(x, window):
    return cv2.blur(x, (window, window), borderType=cv2.BORDER_REFLECT)


def plane_sweep_depth(ref_image, ref_pose, ref_K, sources, near, far, config: StereoConfig = None,
                      ref_mask=None, prior_depth=None):
    """Depth map (H, W) of a reference frame by plane sweep (module docstring); NaN where not trusted.

    ref_image: (H, W, 3) in [0, 1]; ref_pose: (4, 4) cam_T_world; ref_K: (3, 3).
    sources: list of (image (h, w, 3), cam_T_world (4, 4), K (3, 3), moving mask (h, w) bool or None).
    near, far: 0 < near < far, the z-depth range to search (widened by ``config.depth_margin``).
    ref_mask: (H, W) bool, True on moving pixels (no depth there), or None.
    prior_depth: (H, W) another depth estimate (an aligned depth prior) or None: then
    info["cost_over_prior"] (H, W) is the best cost over the cost at the hypothesis nearest the
    prior's depth (NaN where the prior is missing or outside the hypotheses), how much better
    the images say the sweep's depth is than the prior's.
    Returns (depth (H, W) float64 with NaN, info dict: kept share, hypotheses, sources).
    """
    config = StereoConfig() if config is None else config
    if not isinstance(config, StereoConfig):
        raise TypeError(f"config must be a StereoConfig; got {type(config).__name__}")
    img = np.asarray(ref_image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"ref_image must have shape (H, W, 3); got {img.shape}")
    if not (np.isfinite(near) and np.isfinite(far) and 0.0 < near < far):
        raise ValueError(f"need 0 < near < far, both finite; got near={near}, far={far}")
    H, W, _ = img.shape
    m = config.depth_margin
    inv = np.linspace(1.0 / ((1.0 - m) * near), 1.0 / ((1.0 + m) * far), config.num_depths)
    Tr = np.asarray(ref_pose, dtype=np.float64)
    Kr = np.asarray(ref_K, dtype=np.float64)
    u, v = np.meshgrid(np.arange(W) + PIXEL_CENTER_OFFSET, np.arange(H) + PIXEL_CENTER_OFFSET)
    rays = np.stack([(u - Kr[0, 2]) / Kr[0, 0], (v - Kr[1, 2]) / Kr[1, 1], np.ones_like(u)], axis=-1)

    D, S = config.num_depths, len(sources)
    cost = np.full((D, H, W, S), np.nan, dtype=np.float32)  # sources last: the combine below sorts along them
    span = np.full((S, H, W), np.nan)  # source pixels between the first and the last hypothesis
    for s, (simg, spose, sK, smask) in enumerate(sources):
        simg = np.asarray(simg, dtype=np.float32)
        sK = np.asarray(sK, dtype=np.float64)
        rel = np.asarray(spose, dtype=np.float64) @ np.linalg.inv(Tr)
        A = rays @ rel[:3, :3].T  # (H, W, 3): R r
        t = rel[:3, 3]
        # a source pixel is unusable where moving; mark it by NaN in a fourth channel
        valid_src = np.ones(simg.shape[:2], np.float32) if smask is None else (~np.asarray(smask)).astype(np.float32)
        for i, q in enumerate(inv):
            X = A / q + t
            z = X[..., 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                mx = (sK[0, 0] * X[..., 0] / z + sK[0, 2] - PIXEL_CENTER_OFFSET).astype(np.float32)
                my = (sK[1, 1] * X[..., 1] / z + sK[1, 2] - PIXEL_CENTER_OFFSET).astype(np.float32)
            bad = ~(z > 1e-9) | ~np.isfinite(mx) | ~np.isfinite(my)
            mx[bad], my[bad] = -1e6, -1e6
            if i == 0:
                first_xy = (mx.astype(np.float64), my.astype(np.float64), bad)
            elif i == D - 1:
                with np.errstate(invalid="ignore"):
                    span[s] = np.where(first_xy[2] | bad, np.nan, np.hypot(mx - first_xy[0], my - first_xy[1]))
            warped = cv2.remap(simg, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
            ok = cv2.remap(valid_src, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
            diff = np.abs(warped - img).mean(axis=2)
            okm = (ok > 0.999) & np.isfinite(diff)
            diff = np.where(okm, diff, 0.0).astype(np.float32)
            num = _box(diff, config.window)
            den = _box(okm.astype(np.float32), config.window)
            with np.errstate(invalid="ignore", divide="ignore"):
                c = np.where(den > 0.999, num / np.maximum(den, 1e-6), np.nan)  # the whole window seen
            cost[i, :, :, s] = c

    # best half of the sources, at least min_sources
    finite = np.isfinite(cost)
    n_valid = finite.sum(axis=-1)  # (D, H, W)
    srt = np.sort(np.where(finite, cost, np.inf), axis=-1)
    keep_n = np.maximum((n_valid + 1) // 2, np.minimum(config.min_sources, n_valid))
    csum = np.cumsum(np.where(np.isfinite(srt), srt, 0.0), axis=-1)
    idx = np.clip(keep_n - 1, 0, max(S - 1, 0))
    total = np.take_along_axis(csum, idx[..., None], axis=-1)[..., 0]
    combined = np.where(n_valid >= config.min_sources, total / np.maximum(keep_n, 1), np.inf)  # (D, H, W)

    best = np.argmin(combined, axis=0)  # (H, W)
    cb = np.take_along_axis(combined, best[None], axis=0)[0]
    # best cost farther than distinct_px source pixels (median over the sources, the hypotheses
    # being about evenly spaced in pixels, as in inverse depth), and than two hypotheses
    with warnings.catch_warnings():  # pixels no source sees: an all-NaN median, handled below
        warnings.simplefilter("ignore", RuntimeWarning)
        px_per_step = np.nanmedian(span, axis=0) / (D - 1) if S else np.full((H, W), np.nan)
    radius = np.where(np.isfinite(px_per_step) & (px_per_step > 0),
                      np.ceil(config.distinct_px / np.maximum(px_per_step, 1e-12)), 2.0)
    radius = np.maximum(radius, 2.0)
    levels = np.arange(D)[:, None, None]
    far_away = np.abs(levels - best[None]) > radius[None]
    c_second = np.min(np.where(far_away, combined, np.inf), axis=0)
    # parabola through the neighbours, in inverse depth
    b0 = np.clip(best, 1, D - 2)
    cm = np.take_along_axis(combined, (b0 - 1)[None], axis=0)[0]
    c0 = np.take_along_axis(combined, b0[None], axis=0)[0]
    cp = np.take_along_axis(combined, (b0 + 1)[None], axis=0)[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = cm - 2.0 * c0 + cp
        shift = np.where((denom > 0) & np.isfinite(denom), 0.5 * (cm - cp) / denom, 0.0)
    shift = np.clip(shift, -0.5, 0.5)
    step = inv[1] - inv[0]
    inv_best = np.where((best >= 1) & (best <= D - 2), inv[b0] + shift * step, inv[best])
    depth = 1.0 / inv_best

    grey = img.mean(axis=2)
    mean = _box(grey, config.window)
    std = np.sqrt(np.maximum(_box(grey * grey, config.window) - mean * mean, 0.0))
    checks = {  # each check on its own (a pixel may fail several)
        "texture": std >= config.min_texture,
        # min_sources sources see the whole window at the best hypothesis (its cost is finite)
        "sources": np.isfinite(cb) & (np.take_along_axis(n_valid, best[None], axis=0)[0] >= config.min_sources),
        "distinct": cb <= config.max_cost_ratio * c_second,
        "inside_range": (best >= 1) & (best <= D - 2),
        "static": np.ones((H, W), bool) if ref_mask is None else ~np.asarray(ref_mask, dtype=bool),
    }
    trusted = np.logical_and.reduce(list(checks.values()))
    depth = np.where(trusted, depth, np.nan)
    info = {"kept_share": float(trusted.mean()), "num_depths": D, "num_sources": S,
            "near": float(1.0 / inv[0]), "far": float(1.0 / inv[-1]),
            "rejected_share": {k: float(1.0 - v.mean()) for k, v in checks.items()}}
    if prior_depth is not None:
        info["cost_over_prior"] = _cost_over_prior(combined, cb, inv, np.asarray(prior_depth, dtype=np.float64))
    return depth, info


def _cost_over_prior(combined, cb, inv, prior):
    """(H, W) best cost over the combined cost at the hypothesis nearest ``prior`` in inverse depth;
    NaN where the prior is missing, not positive, or outside the hypotheses (plane_sweep_depth)."""
    D = len(inv)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(np.isfinite(prior) & (prior > 0), 1.0 / prior, np.nan)
        pos = (q - inv[0]) / (inv[1] - inv[0])  # fractional hypothesis index
    inside = np.isfinite(pos) & (pos >= -0.5) & (pos <= D - 0.5)
    i = np.clip(np.round(np.where(inside, pos, 0.0)).astype(np.int64), 0, D - 1)
    cp = np.take_along_axis(combined, i[None], axis=0)[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(inside & np.isfinite(cp) & np.isfinite(cb), cb / np.maximum(cp, 1e-12), np.nan)
    return r
