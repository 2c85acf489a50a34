"""Depth priors aligned to the static reconstruction (docs/method.md §8, the dynamic seeds).

A prior is a per-pixel estimate that a depth network gives, known up to what the network
cannot know. Two kinds:
- "depth": a depth up to one scale for the whole clip, as video depth models that align their
  frames give it (Align3R, which the paper uses, and metric-depth networks). The scale is the
  median of z / prior over the static points of every frame (``align_depth_scale``).
- "disparity": inverse depth up to a scale and a shift per frame, as single-image networks
  give it. With x the prior at the pixels of the static points seen in the frame and y their
  inverse depth, y ~ a x + b by least squares, refitted on the points within ``k`` robust
  sigmas (1.4826 MAD) of the line (``align_depth_prior``), as MonoSDF and DN-Splatter align a
  monocular depth to COLMAP's sparse points per image. The shift is told only where the static
  points span depths: against a flat back wall it is not, and the frame falls back.
Static points are taken off the dilated motion mask. The aligned maps give the movers a depth
that the photometric loss cannot (docs/method.md §8: a mover's depth is not observable from one
moving camera).

``fuse_depth_maps``: a network's error is partly new in every frame; a static surface point seen
in K frames has K estimates of its depth, and their geometric mean keeps only the share of the
error the frames have in common (docs/method.md §8, the priors fused over the frames).
"""
from __future__ import annotations

import numpy as np

from d2gs_np.constants import MAD_TO_SIGMA, PIXEL_CENTER_OFFSET
from d2gs_np.geometry.camera import project_points, unproject_points

__all__ = ["fit_scale_shift", "align_depth_prior", "align_depth_scale", "fuse_depth_maps"]


def _prior_at_points(prior, uv, z):
    """(x, z): the prior at the pixels holding the points ``uv`` (M, 2; centres at +0.5) and
    their depths, for the points in front of the camera, inside the image and at a pixel with
    an estimate (finite)."""
    H, W = prior.shape
    uv, z = np.asarray(uv, dtype=np.float64).reshape(-1, 2), np.asarray(z, dtype=np.float64).ravel()
    ok = np.isfinite(z) & (z > 0) & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    x = prior[np.floor(uv[ok, 1]).astype(np.int64), np.floor(uv[ok, 0]).astype(np.int64)]
    have = np.isfinite(x)
    return x[have], z[ok][have]


def fit_scale_shift(x, y, rounds: int = 3, k: float = 3.0):
    """Robust y ~ a x + b on 1-D arrays of equal length (>= 3): least squares on all, then up to
    ``rounds`` refits on the points whose residual is within k robust sigmas of the last fit.
    Returns (a, b, inliers (bool mask)), or None when x does not vary over the inliers (no
    scale can be told: a constant prior, or a single distinct pixel)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    keep = np.ones(x.shape[0], dtype=bool)
    a = b = None
    for _ in range(rounds + 1):
        xs, ys = x[keep], y[keep]
        if xs.size < 3 or np.ptp(xs) <= 1e-12 * max(np.max(np.abs(xs)), 1e-300):
            return None
        xm, ym = xs.mean(), ys.mean()
        # centred normal equations: well conditioned whatever the prior's offset
        a = float(np.dot(xs - xm, ys - ym) / np.dot(xs - xm, xs - xm))
        b = float(ym - a * xm)
        r = y - (a * x + b)
        sigma = MAD_TO_SIGMA * np.median(np.abs(r[keep] - np.median(r[keep])))
        new = np.abs(r) <= k * sigma + 1e-12 * max(np.max(np.abs(y)), 1e-300)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    return a, b, keep


def align_depth_prior(prior, uv, z, space: str = "disparity", min_points: int = 20):
    """Depth map (H, W) from ``prior`` (H, W; NaN = no estimate) aligned to the static points at
    pixels ``uv`` (M, 2; pixel centres at +0.5) with camera depths ``z`` (M,) in this frame.

    ``space``: "disparity" (the prior is a x / z + b) or "depth" (a x z + b). Returns (depth,
    info): depth NaN where the prior has no estimate or the fitted line is not positive; depth
    None when the frame cannot be aligned (fewer than ``min_points`` usable points, a prior
    constant over them, or a scale that is not positive: the prior falls where the points
    rise, as a depth given for a disparity does), with the reason in ``info["reason"]``. info
    also has "points", "scale", "shift" and "rel_error" (median |fit - z| / z on the inliers)."""
    if space not in ("disparity", "depth"):
        raise ValueError(f"align_depth_prior: space must be 'disparity' or 'depth'; got {space!r}")
    prior = np.asarray(prior, dtype=np.float64)
    x, zz = _prior_at_points(prior, uv, z)
    info = {"points": int(x.size), "scale": float("nan"), "shift": float("nan"), "rel_error": float("nan")}
    if x.size < min_points:
        return None, {**info, "reason": f"{x.size} static points with a prior value (fewer than {min_points})"}
    y = 1.0 / zz if space == "disparity" else zz
    fit = fit_scale_shift(x, y)
    if fit is None:
        return None, {**info, "reason": "the prior does not vary over the static points"}
    a, b, inl = fit
    info.update(scale=a, shift=b)
    if not a > 0:
        other = "depth" if space == "disparity" else "disparity"
        return None, {**info, "reason": f"the fitted scale {a:.3g} is not positive: is the prior a {other}? "
                                        f"(InitConfig.depth_prior_space = '{other}')"}
    v = a * prior + b
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = np.where(v > 0, (1.0 / v) if space == "disparity" else v, np.nan)
        fit_z = a * x[inl] + b
        fit_z = 1.0 / fit_z if space == "disparity" else fit_z
        info["rel_error"] = float(np.median(np.abs(fit_z - zz[inl]) / zz[inl]))
    depth[~np.isfinite(depth)] = np.nan
    return depth, info


def align_depth_scale(priors, uvs, zs, min_points: int = 20):
    """One scale for a clip's depth priors: ``priors`` a list of (H, W) maps (NaN = no estimate),
    ``uvs`` / ``zs`` per frame the static points' pixels (M_k, 2) and depths (M_k,). The scale is
    exp(median of log(z / prior)) over every usable point of every frame, robust to a share of
    wrong points below one half. Returns (scale or None, info) with "points" and "rel_error"
    (median |scale prior - z| / z), or None and info["reason"] when fewer than ``min_points``
    points have a prior value."""
    logs = []
    for prior, uv, z in zip(priors, uvs, zs):
        x, zz = _prior_at_points(np.asarray(prior, dtype=np.float64), uv, z)
        logs.append(np.log(zz[x > 0]) - np.log(x[x > 0]))
    logs = np.concatenate(logs) if logs else np.zeros(0)
    info = {"points": int(logs.size), "scale": float("nan"), "rel_error": float("nan")}
    if logs.size < min_points:
        return None, {**info, "reason": f"{logs.size} static points with a prior value (fewer than {min_points})"}
    m = float(np.median(logs))
    info.update(scale=float(np.exp(m)), rel_error=float(np.median(np.abs(np.expm1(m - logs)))))
    return info["scale"], info


def _bilinear(logd, good, uv, z):
    """(indices, values): the map ``logd`` (H, W; a log depth) interpolated bilinearly at the
    points ``uv`` (M, 2; pixel centres at +0.5) in front of the camera (``z`` > 0) whose four
    neighbouring pixels are all ``good``; the rest are left out."""
    H, W = logd.shape
    x, y = uv[:, 0] - PIXEL_CENTER_OFFSET, uv[:, 1] - PIXEL_CENTER_OFFSET
    inside = (z > 0) & (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    idx = np.flatnonzero(inside)
    x, y = x[idx], y[idx]
    c0 = np.minimum(np.floor(x).astype(np.int64), max(W - 2, 0))
    r0 = np.minimum(np.floor(y).astype(np.int64), max(H - 2, 0))
    c1, r1 = np.minimum(c0 + 1, W - 1), np.minimum(r0 + 1, H - 1)
    have = good[r0, c0] & good[r0, c1] & good[r1, c0] & good[r1, c1]
    idx, x, y, c0, r0, c1, r1 = idx[have], x[have], y[have], c0[have], r0[have], c1[have], r1[have]
    fx, fy = x - c0, y - r0
    value = ((1 - fy) * ((1 - fx) * logd[r0, c0] + fx * logd[r0, c1])
             + fy * ((1 - fx) * logd[r1, c0] + fx * logd[r1, c1]))
    return idx, value


def fuse_depth_maps(maps, cam_T_worlds, Ks, usable=None, gate: float = 0.3):
    """Per-frame depth maps fused over the frames: each usable pixel of frame k lifted at its depth
    d_k, projected into every other frame j, and d_k times exp(mean of log(map_j(p') / z_j)) over
    the frames that see it (frame k itself counting 0), where p' and z_j are the point's pixel and
    depth in frame j (the map read bilinearly in log depth, where its four pixels are usable).
    For a static surface with per-frame log errors e_j this gives the mean of the e_j over the
    frames that see the point: the independent share of the error falls as 1 / sqrt(K).

    ``maps``: list of (H, W) depth maps in one unit (NaN = no estimate) or None (a frame without
    one: neither fused nor used); ``cam_T_worlds`` / ``Ks``: the frames' poses (4, 4) and
    intrinsics (3, 3); ``usable``: per frame a bool (H, W) mask of the pixels that may be fused and
    read (the static pixels; None: all); ``gate``: a frame's reading counts only within |log ratio|
    <= gate (occlusions, other surfaces, a mover's pixel the mask missed). Unusable pixels keep
    their value. Returns (fused maps, info): info "views" (median count of frames per fused
    pixel, itself included) and "fused_share" (share of fused pixels seen by another frame)."""
    if not gate > 0:
        raise ValueError(f"fuse_depth_maps: gate must be > 0 (a |log ratio|, e.g. 0.3); got {gate!r}")
    n = len(maps)
    if len(cam_T_worlds) != n or len(Ks) != n or (usable is not None and len(usable) != n):
        raise ValueError(f"fuse_depth_maps: {n} maps need as many poses, intrinsics and masks; got "
                         f"{len(cam_T_worlds)}, {len(Ks)}, {None if usable is None else len(usable)}")
    maps = [None if m is None else np.asarray(m, dtype=np.float64) for m in maps]
    ok = []
    for k, m in enumerate(maps):
        if m is None:
            ok.append(None)
            continue
        if m.ndim != 2:
            raise ValueError(f"fuse_depth_maps: map {k} must be (H, W); got shape {m.shape}")
        good = np.isfinite(m) & (m > 0)
        if usable is not None and usable[k] is not None:
            u = np.asarray(usable[k], dtype=bool)
            if u.shape != m.shape:
                raise ValueError(f"fuse_depth_maps: mask {k} has shape {u.shape}, its map {m.shape}")
            good &= u
        ok.append(good)
    logs = [None if m is None else np.log(np.where(g, m, 1.0)) for m, g in zip(maps, ok)]  # once per frame
    fused, views, seen = [], [], 0
    for k, m in enumerate(maps):
        if m is None:
            fused.append(None)
            continue
        rows, cols = np.nonzero(ok[k])
        out = m.copy()
        if rows.size == 0:
            fused.append(out)
            continue
        d = m[rows, cols]
        pix = np.stack([cols + PIXEL_CENTER_OFFSET, rows + PIXEL_CENTER_OFFSET], axis=1).astype(np.float64)
        X = unproject_points(pix, d, cam_T_worlds[k], Ks[k])
        total, count = np.zeros(rows.size), np.ones(rows.size)
        for j, lj in enumerate(logs):
            if j == k or lj is None:
                continue
            uv, z = project_points(X, cam_T_worlds[j], Ks[j])
            idx, value = _bilinear(lj, ok[j], uv, z)
            log_ratio = value - np.log(z[idx])
            near = np.abs(log_ratio) <= gate
            total[idx[near]] += log_ratio[near]
            count[idx[near]] += 1.0
        out[rows, cols] = d * np.exp(total / count)
        fused.append(out)
        views.append(count)
        seen += int((count > 1).sum())
    allv = np.concatenate(views) if views else np.zeros(0)
    info = {"views": float(np.median(allv)) if allv.size else 0.0,
            "fused_share": float(seen / allv.size) if allv.size else 0.0}
    return fused, info
