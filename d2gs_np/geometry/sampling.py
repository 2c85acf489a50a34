"""Bilinear reads of an image or depth map at sub-pixel points, and their backward (pixel centres at
+0.5, docs/conventions.md §2). Used by the pose solver's depth reads and by L_reproj."""
from __future__ import annotations

import numpy as np

from d2gs_np.constants import PIXEL_CENTER_OFFSET

__all__ = ["bilinear_fwd", "bilinear_bwd"]


def bilinear_fwd(image, pts):
    """Bilinear read of an (H, W) map at (M, 2) pixels (centres at +0.5); NaN outside the
    centres' hull or where a tap is NaN. Returns (values (M,), saved)."""
    image = np.asarray(image)
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    H, W = image.shape
    x, y = pts[:, 0] - PIXEL_CENTER_OFFSET, pts[:, 1] - PIXEL_CENTER_OFFSET
    inside = (x >= 0) & (y >= 0) & (x <= W - 1) & (y <= H - 1)
    x0 = np.clip(np.floor(np.where(inside, x, 0)).astype(np.int64), 0, max(W - 2, 0))
    y0 = np.clip(np.floor(np.where(inside, y, 0)).astype(np.int64), 0, max(H - 2, 0))
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = np.where(inside, x - x0, 0.0), np.where(inside, y - y0, 0.0)
    idx = np.stack([y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1], axis=1)  # (M, 4) flat taps
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    taps = image.reshape(-1)[idx]
    vals = w[:, 0] * taps[:, 0] + w[:, 1] * taps[:, 1] + w[:, 2] * taps[:, 2] + w[:, 3] * taps[:, 3]
    vals = np.where(inside, vals, np.nan)
    return vals, {"idx": idx, "w": w, "inside": inside, "shape": (H, W), "dtype": image.dtype}


def bilinear_bwd(saved, v_vals):
    """(H, W) gradient of <v_vals, bilinear_fwd(image, pts)> on the image (zero where a value
    is NaN or the gradient is 0)."""
    v = np.where(saved["inside"] & np.isfinite(v_vals), v_vals, 0.0)
    H, W = saved["shape"]
    out = np.bincount(saved["idx"].ravel(), weights=(saved["w"] * v[:, None]).ravel(), minlength=H * W)
    return out.reshape(H, W).astype(saved["dtype"], copy=False)
