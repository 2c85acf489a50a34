"""The static world continued past the training frames' borders (docs/method.md §2: past the
frames' borders).

A novel view beside the camera path sees, along its edge, surfaces that no training frame saw.
Without Gaussians there it renders the background (what that costs: docs/method.md §2). Here each training frame's static render is continued outward, as
clamp-to-edge texture addressing continues an image: for every ``step_px``-th pixel of its border
whose static alpha is at least ``min_alpha``, opaque isotropic Gaussians at the render's local mean
colour there (over its background, blurred by a Gaussian of ``colour_sigma_px``) and at the pixel's
expected depth on the rays ``gap * step_px`` .. ``margin * max(W, H)`` px beyond it, every
``step_px``; the depth follows the surface's slope across the border (inverse depth affine in the
pixel, exact on a plane, measured between the border pixel and the one ``slope_px`` inside). A copy is kept only where its whole footprint (the renderer's 3.33-sigma box, one
pixel more) lies outside every training frame, so no training view changes, and only where no
static Gaussian outside every frame, nor a copy kept before it, holds its cell (a ``step_px``
voxel at the copies' median depth), so a second pass adds nothing.

Pure functions on arrays: ``border_gaussians`` from the frames' renders, ``static_renders`` to make
them from a model.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.constants import RADIUS_SIGMA
from d2gs_np.geometry.camera import project_points, unproject_points
from d2gs_np.scene.config import BorderConfig
from d2gs_np.scene.gaussians import STATIC, make_gaussians

__all__ = ["border_gaussians", "static_renders", "outside_every_frame"]

FOOTPRINT_PAD_PX = 1.0  # beyond the 3.33-sigma box: a pixel centre half a pixel inside cannot be reached


def _local_mean(image, sigma):
    """A Gaussian blur of an (H, W) or (H, W, C) image (reflecting at its edges); sigma 0: the image."""
    if sigma <= 0:
        return image
    import cv2
    return cv2.GaussianBlur(np.ascontiguousarray(image, dtype=np.float64), (0, 0), sigmaX=sigma, sigmaY=sigma,
                            borderType=cv2.BORDER_REFLECT)


def _check_frames(images, alphas, depths, poses, Ks):
    n = len(images)
    for name, seq in (("alphas", alphas), ("depths", depths), ("poses", poses), ("Ks", Ks)):
        if len(seq) != n:
            raise ValueError(f"{name} must have one entry per frame ({n}); got {len(seq)}")
    out = []
    for k in range(n):
        img = np.asarray(images[k], dtype=np.float64)
        a, d = np.asarray(alphas[k], dtype=np.float64), np.asarray(depths[k], dtype=np.float64)
        T, K = np.asarray(poses[k], dtype=np.float64), np.asarray(Ks[k], dtype=np.float64)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"images[{k}] must have shape (H, W, 3); got {img.shape}")
        if a.shape != img.shape[:2] or d.shape != img.shape[:2]:
            raise ValueError(f"alphas[{k}] and depths[{k}] must have the image's shape {img.shape[:2]}; "
                             f"got {a.shape} and {d.shape}")
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"poses[{k}] must be a finite (4, 4) cam_T_world; got shape {T.shape}")
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"Ks[{k}] must be finite (3, 3) intrinsics with positive focal lengths")
        out.append((img, a, d, T, K))
    return out


def outside_every_frame(points, sigmas, poses, Ks, sizes, eps2d=0.0):
    """(M,) bool: points whose footprint (isotropic world sigma ``sigmas`` (M,), the renderer's
    3.33-sigma box of the dilated screen covariance, one pixel more) touches no frame's image:
    each frame behind the point, or the box beyond the frame's edges. sizes: (W, H) per frame."""
    points = np.asarray(points, dtype=np.float64)
    sigmas = np.asarray(sigmas, dtype=np.float64)
    out = np.ones(len(points), dtype=bool)
    for T, K, (W, H) in zip(poses, Ks, sizes):
        uv, z = project_points(points, T, K)
        front = z > 0
        zs = np.where(front, z, 1.0)
        # an isotropic sigma's screen variance is (f sigma / z)^2 (1 + (x/z)^2) per axis (J J^T of the
        # projection); unclamped, so never smaller than the renderer's (which clamps x/z)
        tx, ty = (uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]
        pad_x = RADIUS_SIGMA * np.sqrt((sigmas * K[0, 0] / zs) ** 2 * (1.0 + tx ** 2) + eps2d) + FOOTPRINT_PAD_PX
        pad_y = RADIUS_SIGMA * np.sqrt((sigmas * K[1, 1] / zs) ** 2 * (1.0 + ty ** 2) + eps2d) + FOOTPRINT_PAD_PX
        touches = front & (uv[:, 0] + pad_x > 0) & (uv[:, 0] - pad_x < W) & (uv[:, 1] + pad_y > 0) & \
            (uv[:, 1] - pad_y < H)
        out &= ~touches
    return out


def _rays(width, height, step, gap, reach, inset):
    """Border pixels and, for each, the pixels outward (k * step past the border, k = gap..reach):
    (border rows, border cols, inset rows, inset cols, outward u, outward v, distance past the
    border pixel's centre), one entry per (border pixel, k); the inset pixel lies ``inset`` px
    inside the border pixel, on its row or column."""
    rows, cols, irows, icols, us, vs, dist = [], [], [], [], [], [], []
    ks = np.arange(gap, reach + 1, dtype=np.float64) * step
    for side in ("left", "right", "top", "bottom"):
        if side in ("left", "right"):
            along = np.arange(0.5 * step, height, step)
            r = np.minimum(along.astype(np.int64), height - 1)
            c = np.zeros_like(r) if side == "left" else np.full_like(r, width - 1)
            ir, ic = r, (c + inset if side == "left" else c - inset)
            u = np.broadcast_to((-ks if side == "left" else width + ks)[None, :], (len(r), len(ks)))
            v = np.repeat((r + 0.5)[:, None], len(ks), axis=1)
        else:
            along = np.arange(0.5 * step, width, step)
            c = np.minimum(along.astype(np.int64), width - 1)
            r = np.zeros_like(c) if side == "top" else np.full_like(c, height - 1)
            ir, ic = (r + inset if side == "top" else r - inset), c
            v = np.broadcast_to((-ks if side == "top" else height + ks)[None, :], (len(c), len(ks)))
            u = np.repeat((c + 0.5)[:, None], len(ks), axis=1)
        rows.append(np.repeat(r, len(ks)))
        cols.append(np.repeat(c, len(ks)))
        irows.append(np.repeat(ir, len(ks)))
        icols.append(np.repeat(ic, len(ks)))
        us.append(u.ravel())
        vs.append(v.ravel())
        dist.append(np.tile(ks + 0.5, len(along)))
    return tuple(np.concatenate(x) for x in (rows, cols, irows, icols, us, vs, dist))


def border_gaussians(images, alphas, depths, poses, Ks, config: BorderConfig, existing=None, eps2d=0.0):
    """New static rows past the frames' borders (module docstring), and a summary.

    images, alphas, depths: per frame the static set's render (H, W, 3) over the training background,
    its alpha and expected depth (H, W); poses: (4, 4) cam_T_world and Ks (3, 3) of those renders.
    existing: (N, 3) static centres (those outside every frame hold their cells), or None.
    eps2d: the renderer's screen dilation (``RenderConfig.eps2d``), for the footprints.
    Returns (blocks of ``make_gaussians("static", ...)`` or None when there are none, info dict).
    """
    frames = _check_frames(images, alphas, depths, poses, Ks)
    info = {"added": 0, "candidates": 0}
    if config.margin <= 0 or not frames:
        info["reason"] = "off (BorderConfig.margin = 0)" if config.margin <= 0 else "no frames"
        return None, info
    sizes = [(img.shape[1], img.shape[0]) for img, *_ in frames]
    pts, cols, sig = [], [], []
    for (img, a, d, T, K), (W, H) in zip(frames, sizes):
        reach = int(np.ceil(config.margin * max(W, H) / config.step_px))
        if reach < config.gap:
            continue
        inset = min(config.slope_px, W - 1, H - 1)
        r, c, ir, ic, u, v, dist = _rays(W, H, config.step_px, config.gap, reach, inset)
        z, al, z_in, al_in = d[r, c], a[r, c], d[ir, ic], a[ir, ic]
        ok = np.isfinite(z) & (z > 0) & np.isfinite(al) & (al >= config.min_alpha)
        if not ok.any():
            continue
        r, c, u, v, z, al, dist = r[ok], c[ok], u[ok], v[ok], z[ok], al[ok], dist[ok]
        z_in, al_in = z_in[ok], al_in[ok]
        # a plane's inverse depth is affine in the pixel: continued outward at the slope between the
        # inset pixel and the border one (none where the inset pixel has no surface), within a factor
        # max_depth_ratio of the border's depth
        inv = 1.0 / z
        has = (inset > 0) & np.isfinite(z_in) & (z_in > 0) & np.isfinite(al_in) & (al_in >= config.min_alpha)
        slope = np.where(has, (inv - 1.0 / np.where(has, z_in, 1.0)) / max(inset, 1), 0.0)
        q = config.max_depth_ratio
        inv_out = np.clip(inv + slope * dist, inv / q, inv * q)
        # the border's local mean colour as the frame renders it, over its background: one bright pixel
        # (a star of a dark sky drawn as opaque stars over transparent black) replicated would be a streak
        colour = _local_mean(img, config.colour_sigma_px)[r, c]
        z = 1.0 / inv_out
        pts.append(unproject_points(np.stack([u, v], axis=1), z, T, K))
        cols.append(np.clip(colour, 0.0, 1.0))
        sig.append(config.sigma * config.step_px * z / K[0, 0])
    if not pts:
        info["reason"] = f"no border pixel has static alpha >= {config.min_alpha:g} and a finite depth"
        return None, info
    X, C, S = np.concatenate(pts), np.concatenate(cols), np.concatenate(sig)
    info["candidates"] = int(len(X))
    out = outside_every_frame(X, S, [f[3] for f in frames], [f[4] for f in frames], sizes, eps2d)
    X, C, S = X[out], C[out], S[out]
    if len(X) == 0:
        info["reason"] = "every copy would touch a training frame"
        return None, info
    cell = float(np.median(S)) / config.sigma  # the copies' spacing at their median depth
    keys = np.floor(X / cell).astype(np.int64)
    held = set()
    if existing is not None and len(existing):
        E = np.asarray(existing, dtype=np.float64)
        e_out = outside_every_frame(E, np.zeros(len(E)), [f[3] for f in frames], [f[4] for f in frames], sizes)
        held = set(map(tuple, np.floor(E[e_out] / cell).astype(np.int64)))
    keep = np.zeros(len(X), dtype=bool)
    for i, key in enumerate(map(tuple, keys)):
        if key not in held:
            held.add(key)
            keep[i] = True
    X, C, S = X[keep], C[keep], S[keep]
    info.update(added=int(len(X)), cell=cell)
    if len(X) == 0:
        info["reason"] = "every cell past the borders is held already"
        return None, info
    n = len(X)
    opacity = np.clip(config.opacity, 1e-6, 1.0 - 1e-6)
    blocks = make_gaussians(STATIC, means=X, log_scales=np.repeat(np.log(S)[:, None], 3, axis=1),
                            quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
                            opacity_logits=np.full(n, np.log(opacity / (1.0 - opacity))), colors=C)
    return blocks, info


def static_renders(model, poses=None):
    """Per training frame the static set's (image, alpha, expected depth) at its mid-exposure pose
    (``poses``: (N, 4, 4) to use instead), sharp, at the frame's size: the inputs of
    ``border_gaussians``."""
    params = {k: v for k, v in model.params.items() if k.startswith(f"{STATIC}.") or k.startswith("camera.")}
    static = model.replace(params=params)
    poses = model.mid_poses() if poses is None else poses
    outs = [static.render_outputs(poses[k], float(model.times[k]), model.Ks[k], model.widths[k], model.heights[k])
            for k in range(model.num_frames)]
    return [o["image"] for o in outs], [o["alpha"] for o in outs], [o["expected_depth"] for o in outs]
