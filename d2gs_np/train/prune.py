"""Which Gaussians to remove: pure rules on parameter arrays, applied by the trainer's pruning step.

Three rules, each a boolean "remove" mask per set:
- ``transparent``: opacity below a floor (3DGS: 0.005). They cost render time and carry nothing.
- ``oversized``: the largest scale axis above ``max_scale_fraction`` x the scene extent (3DGS's
  "big points" rule, 0.1 x extent). A Gaussian that large is a smear that the photometric loss
  keeps alive to explain average colour over a wide area, at the cost of every pixel it covers.
- ``escaped`` (dynamic set only): the centre of a dynamic Gaussian, deformed to each training
  frame's time and projected with that frame's pose, falls on a static pixel (outside the
  frame's motion mask, dilated by ``mask_dilation_px``) in more than ``max_outside_share`` of
  the frames where it is in view. Motion masks say where moving things are; a dynamic
  Gaussian that lives on static pixels smears the moving object over the background and
  competes with the static set for its pixels.
"""
from __future__ import annotations

import cv2
import numpy as np

from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.deformation import deform_basis
from d2gs_np.train.config import PruneConfig


def transparent(opacity_logits, min_opacity):
    """Remove mask (N,): sigmoid(logit) <= min_opacity, compared in logit space (no overflow)."""
    if not 0.0 < min_opacity < 1.0:
        return np.zeros(len(opacity_logits), dtype=bool)
    return opacity_logits <= np.log(min_opacity) - np.log1p(-min_opacity)


def oversized(log_scales, extent, max_scale_fraction):
    """Remove mask (N,): max scale axis > max_scale_fraction x extent (off when the fraction is 0)."""
    if max_scale_fraction <= 0:
        return np.zeros(len(log_scales), dtype=bool)
    return np.max(log_scales, axis=1) > np.log(max_scale_fraction * extent)


def dynamic_centres(base_means, coef_means, times, deform_config: DeformConfig):
    """Deformed centres of dynamic Gaussians at each time: (T, N, 3)."""
    B = np.stack([deform_basis(float(t), deform_config)[0] for t in times])  # (T, K)
    return base_means[None] + np.einsum("tk,nkd->tnd", B, coef_means)


def outside_share(centres, poses, Ks, masks, mask_dilation_px):
    """Share of in-view frames where each centre lands on a static pixel.

    centres (T, N, 3) world points per frame; poses (T, 4, 4) cam_T_world; Ks (T, 3, 3); masks list
    of T (H, W) bool (True = moving). Returns (share (N,), frames in view (N,)); share is 0 for a
    Gaussian never in view (no evidence against it).
    """
    T, N, _ = centres.shape
    outside = np.zeros(N)
    seen = np.zeros(N)
    kernel = None
    if mask_dilation_px > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * mask_dilation_px + 1,) * 2)
    for k in range(T):
        m = masks[k]
        if m is None:
            continue
        if kernel is not None:
            m = cv2.dilate(m.astype(np.uint8), kernel) > 0
        H, W = m.shape
        p = centres[k] @ poses[k][:3, :3].T + poses[k][:3, 3]
        z = p[:, 2]
        front = z > 1e-9  # at or behind the camera centre: not in view
        uv = np.full((N, 2), -1.0)
        uv[front] = (p[front, :2] / z[front, None]) @ Ks[k][:2, :2].T + Ks[k][:2, 2]
        j, i = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        vis = front & (j >= 0) & (j < W) & (i >= 0) & (i < H)
        seen += vis
        outside[vis] += ~m[i[vis], j[vis]]
    share = np.divide(outside, seen, out=np.zeros(N), where=seen > 0)
    return share, seen


def escaped(base_means, coef_means, times, poses, Ks, masks, deform_config, config: PruneConfig):
    """Remove mask (N,) of dynamic Gaussians living on static pixels (see the module docstring)."""
    if config.max_outside_share <= 0 or len(base_means) == 0:
        return np.zeros(len(base_means), dtype=bool)
    return escaped_at(dynamic_centres(base_means, coef_means, times, deform_config), poses, Ks, masks, config)


def escaped_at(centres, poses, Ks, masks, config: PruneConfig):
    """``escaped`` of the dynamic centres (T, N, 3) at the frames' times (a scene with rigid
    clusters: ``scene.rigid.dynamic_positions``)."""
    if config.max_outside_share <= 0 or centres.shape[1] == 0:
        return np.zeros(centres.shape[1], dtype=bool)
    share, seen = outside_share(centres, poses, Ks, masks, config.mask_dilation_px)
    return (seen > 0) & (share > config.max_outside_share)
