"""Motion masks from dense optical flow against the flow the camera motion explains (docs/dataset_format.md §8).

For frame k and each neighbour j = k -/+ ``gap`` that exists:
1. observed flow k -> j: OpenCV Farneback dense flow on grey frames (``observed_flow``: why not DIS);
2. expected flow of a static world: each pixel lifted at the depth interpolated from the sparse
   points seen in frame k (inverse depth, linear over their Delaunay triangulation, nearest
   outside it: ``d2gs_np.scene.initialize.interpolate_inverse_depth``), moved by the relative
   pose and projected into j;
3. the photometric test: the observed flow explains the pixel's colour better than the static
   hypothesis (neighbour j sampled along each flow, both low-passed: mean absolute differences
   r_static - r_observed > ``photo_threshold``).
A pixel is moving when it passes the test for any neighbour (``combine``; "all": for every one).
Optionally (``geometric``, off by default: MaskConfig says why) a pixel must first also disagree
with the static flow: e_j = |observed - expected| > ``threshold_px + relative * |t_j|``, t_j the
depth-dependent part of the expected flow; farther than ``support_fraction`` x max(W, H) pixels
from a sparse point seen in frame k, the distance of the observed flow from the epipolar line
instead. The raw mask is opened (radius ``open_px``: speckle), closed (``close_px``: holes), components
smaller than ``min_area_fraction`` of the frame are dropped, and the holes the rest enclose are
filled (``fill_holes``). No moving object gives
empty masks.

``static_motion_masks``: sparse points on movers get depths that make the static warp nearly
explain the mover around them; points with more than ``prune_share`` of their observations inside
the masks are left out of the depth and the masks made again (``prune_rounds`` times).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from d2gs_np.base.checks import check_bool, check_choice, check_int, check_number
from d2gs_np.constants import PIXEL_CENTER_OFFSET
from d2gs_np.pose.features import to_gray_u8
from d2gs_np.geometry.camera import project_points
from d2gs_np.scene.initialize import interpolate_inverse_depth

__all__ = ["MaskConfig", "motion_masks", "expected_flow", "observed_flow", "points_off_masks", "static_motion_masks",
           "fill_holes"]


@dataclass(frozen=True)
class MaskConfig:
    """Settings of the motion masks. Validated on construction."""

    gap: int = 1  # neighbours k -/+ gap
    threshold_px: float = 1.5  # disagreement (px) above which a pixel may be moving
    relative: float = 0.3  # plus this fraction of the depth-dependent expected flow
    open_px: int = 2  # morphological opening radius (removes speckle)
    close_px: int = 3  # closing radius (fills holes)
    grow_px: int = 0  # final dilation radius
    min_area_fraction: float = 0.002  # smaller connected components are dropped
    # depth is trusted within this distance (fraction of max(W, H)) of a sparse point seen in the
    # frame; farther away only the epipolar (depth-free) part of the disagreement is used
    support_fraction: float = 0.08
    # "any": moving if one neighbour disagrees (a higher IoU than "all": docs/results.md §13; the
    # photometric gate already rejects disocclusions, which "all" was meant to)
    combine: str = "any"
    flow: str = "farneback"  # or "dis" (observed_flow)
    # photometric gate: a pixel is moving only if the observed flow explains its colour better than
    # the static hypothesis does, by photo_threshold (mean absolute RGB difference in [0, 1] between
    # frame k and the neighbour sampled along each flow, both low-passed by a Gaussian of photo_sigma_px)
    photo_threshold: float = 0.01
    photo_sigma_px: float = 1.5
    # geometric gate (steps 3 and the epipolar test) before the photometric one. Off: on the blurry
    # suite Farneback's flow is wrong on most static brick and gravel, while on a slow mover it
    # follows the background; the masks are better without it (docs/results.md §13)
    geometric: bool = False
    # static_motion_masks: sparse points with more than prune_share of their observations inside the
    # masks are taken for points on movers and left out of the depth, then the masks are made again
    # (prune_rounds times). A triangulated point on a slow mover gets a depth that lets the static
    # warp nearly explain the mover around it. One round at share 0.3 raises the IoU on the movers;
    # more rounds or share 0 mark static pixels (docs/results.md §13)
    prune_rounds: int = 1
    prune_share: float = 0.3
    # fill holes (background pixels enclosed by a mask component): a blurred mover's flat interior
    # has no flow to observe (the crossing card's centre); the IoU rises on most suite scenes
    # (docs/results.md §13)
    fill_holes: bool = True

    def __post_init__(self):
        check_int(self.gap, "MaskConfig.gap", 1)
        for name in ("open_px", "close_px", "grow_px"):
            check_int(getattr(self, name), f"MaskConfig.{name}", 0)
        for name in ("geometric", "fill_holes"):
            check_bool(getattr(self, name), f"MaskConfig.{name}")
        check_number(self.prune_share, "MaskConfig.prune_share", 0.0, 1.0)
        check_choice(self.flow, "MaskConfig.flow", ("farneback", "dis"))
        check_choice(self.combine, "MaskConfig.combine", ("all", "any"))
        for name in ("threshold_px", "relative", "min_area_fraction", "support_fraction", "photo_threshold",
                     "photo_sigma_px"):
            check_number(getattr(self, name), f"MaskConfig.{name}", 0.0)


def observed_flow(img0, img1, method="farneback"):
    """Dense flow (H, W, 2) from img0 to img1 (pixel displacement, x then y).

    "farneback": Farneback's polynomial expansion (pyramid 0.5 x 4 levels, window 15, 5 iterations,
    poly_n 7, sigma 1.5); "dis": DIS, medium preset, which fails on blurred repetitive brick
    (docs/results.md §13)."""
    a, b = to_gray_u8(img0), to_gray_u8(img1)
    if method == "dis":
        return cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(a, b, None).astype(np.float64)
    return cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 15, 5, 7, 1.5, 0).astype(np.float64)


def _pixel_grid(W, H):
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    return np.stack([jj.ravel() + PIXEL_CENTER_OFFSET, ii.ravel() + PIXEL_CENTER_OFFSET], axis=1)


def depth_map(points, cam_T_world, K, W, H):
    """Depth (H, W) of frame (cam_T_world, K) interpolated from the sparse points it sees (NaN: none),
    and the distance (H, W) in pixels from each pixel to the nearest of those points."""
    uv, z = project_points(points, cam_T_world, K)
    vis = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    d, _ = interpolate_inverse_depth(uv[vis], z[vis], _pixel_grid(W, H))
    seeds = np.full((H, W), 255, dtype=np.uint8)
    ij = np.floor(uv[vis]).astype(np.int64)
    seeds[ij[:, 1], ij[:, 0]] = 0
    dist = cv2.distanceTransform(seeds, cv2.DIST_L2, 5) if vis.any() else np.full((H, W), np.inf)
    return d.reshape(H, W), dist


def epipolar_distance(flow, T_k, T_j, K):
    """Distance (H, W) in pixels of each flow target from the epipolar line of its source pixel: the
    part of a disagreement no depth can explain (0 for a static world, whatever its depth)."""
    H, W = flow.shape[:2]
    pix = _pixel_grid(W, H)
    rel = T_j @ np.linalg.inv(T_k)
    tx = np.array([[0, -rel[2, 3], rel[1, 3]], [rel[2, 3], 0, -rel[0, 3]], [-rel[1, 3], rel[0, 3], 0]])
    Kinv = np.linalg.inv(K)
    F = Kinv.T @ tx @ rel[:3, :3] @ Kinv
    x0 = np.c_[pix, np.ones(len(pix))]
    x1 = np.c_[pix + flow.reshape(-1, 2), np.ones(len(pix))]
    line = x0 @ F.T  # lines in image j
    num = np.abs(np.sum(line * x1, axis=1))
    den = np.hypot(line[:, 0], line[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, num / den, 0.0).reshape(H, W)


def expected_flow(depth, T_k, T_j, K):
    """Flow (H, W, 2) of a static world from frame k to frame j, and its depth-dependent part (H, W, 2).

    depth (H, W) of frame k; T_k, T_j: cam_T_world; K shared intrinsics.
    """
    H, W = depth.shape
    pix = _pixel_grid(W, H)
    Kinv = np.linalg.inv(K)
    rays = np.c_[pix, np.ones(len(pix))] @ Kinv.T  # z = 1
    rel = T_j @ np.linalg.inv(T_k)
    R, t = rel[:3, :3], rel[:3, 3]
    d = depth.ravel()
    xr = rays @ R.T  # rotation only
    x = d[:, None] * xr + t
    with np.errstate(divide="ignore", invalid="ignore"):
        p = x[:, :2] / x[:, 2:3] * np.diag(K)[:2] + K[:2, 2]
        pr = xr[:, :2] / xr[:, 2:3] * np.diag(K)[:2] + K[:2, 2]
    flow = (p - pix).reshape(H, W, 2)
    return flow, (p - pr).reshape(H, W, 2)


def _lowpass(img, sigma):
    img = np.asarray(img)
    img = img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img.astype(np.float32)
    return cv2.GaussianBlur(img, (0, 0), sigma) if sigma > 0 else img


def photometric_residual(img_k, img_j, flow, sigma):
    """Mean absolute RGB difference (H, W) between frame k and frame j sampled at p + flow(p), both
    low-passed (Gaussian sigma px); samples outside frame j count as explained (0)."""
    a, b = _lowpass(img_k, sigma), _lowpass(img_j, sigma)
    H, W = flow.shape[:2]
    jj, ii = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    mx = (jj + np.nan_to_num(flow[..., 0])).astype(np.float32)
    my = (ii + np.nan_to_num(flow[..., 1])).astype(np.float32)
    warped = cv2.remap(b, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    r = np.abs(a - warped).mean(axis=2)
    inside = (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)
    return np.where(inside, r, 0.0)


def fill_holes(mask):
    """(H, W) bool mask with every background region that does not reach the frame edge set."""
    m = np.asarray(mask, dtype=bool)
    H, W = m.shape
    pad = np.zeros((H + 2, W + 2), np.uint8)
    pad[1:-1, 1:-1] = m
    cv2.floodFill(pad, np.zeros((H + 4, W + 4), np.uint8), (0, 0), 2)  # the background reached from outside
    return pad[1:-1, 1:-1] != 2


def _clean(mask, cfg):
    m = mask.astype(np.uint8)
    if cfg.open_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, cv2.getStructuringElement(
            cv2.MORPH_ELLIPSE, (2 * cfg.open_px + 1, 2 * cfg.open_px + 1)))
    if cfg.close_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, cv2.getStructuringElement(
            cv2.MORPH_ELLIPSE, (2 * cfg.close_px + 1, 2 * cfg.close_px + 1)))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    min_area = cfg.min_area_fraction * m.size
    keep = np.zeros(n, dtype=bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area
    out = keep[lab]
    if cfg.fill_holes and out.any():
        out = fill_holes(out)
    if cfg.grow_px > 0 and out.any():
        out = cv2.dilate(out.astype(np.uint8), cv2.getStructuringElement(
            cv2.MORPH_ELLIPSE, (2 * cfg.grow_px + 1, 2 * cfg.grow_px + 1))) > 0
    return out


def motion_masks(images, cam_T_world, K, points, config: MaskConfig = None, log=None):
    """Motion masks (list of (H, W) bool, True = moving) for registered frames (module docstring).

    images: list of (H, W, 3) frames (uint8 or float in [0, 1]); cam_T_world (N, 4, 4); K (3, 3);
    points (P, 3) sparse static points. Returns (masks, info with per-frame moving fractions).
    """
    cfg = MaskConfig() if config is None else config
    if not isinstance(cfg, MaskConfig):
        raise TypeError(f"config must be a MaskConfig; got {type(cfg).__name__}")
    N = len(images)
    H, W = images[0].shape[:2]
    masks = []
    support = cfg.support_fraction * max(W, H)
    for k in range(N):
        depth, dist = depth_map(points, cam_T_world[k], K, W, H)
        if not np.any(np.isfinite(depth)):
            masks.append(np.zeros((H, W), dtype=bool))
            continue
        votes = []
        for j in (k - cfg.gap, k + cfg.gap):
            if not 0 <= j < N:
                continue
            obs = observed_flow(images[k], images[j], cfg.flow)
            exp, trans = expected_flow(depth, cam_T_world[k], cam_T_world[j], K)
            if cfg.geometric:
                e = np.nan_to_num(np.linalg.norm(obs - exp, axis=2), nan=0.0)
                thr = cfg.threshold_px + cfg.relative * np.nan_to_num(np.linalg.norm(trans, axis=2))
                full = e > thr
                if np.linalg.norm(trans) > 0:  # a moving camera centre: epipolar test where depth is unsupported
                    epi = epipolar_distance(obs, cam_T_world[k], cam_T_world[j], K) > cfg.threshold_px
                    full = np.where(dist <= support, full, epi)
            else:
                full = np.ones((H, W), dtype=bool)
            if cfg.photo_threshold > 0:
                r_static = photometric_residual(images[k], images[j], exp, cfg.photo_sigma_px)
                r_obs = photometric_residual(images[k], images[j], obs, cfg.photo_sigma_px)
                full &= r_static - r_obs > cfg.photo_threshold
            votes.append(full)
        moving = np.logical_and.reduce(votes) if cfg.combine == "all" else np.logical_or.reduce(votes)
        masks.append(_clean(moving, cfg))
        if log is not None and (k + 1) % 10 == 0:
            log(f"motion masks: {k + 1}/{N} frames")
    frac = [float(m.mean()) for m in masks]
    return masks, {"moving_fraction": frac}


def points_off_masks(obs_frame, obs_point, obs_uv, masks, num_points, max_share):
    """(P,) bool: sparse points with at most ``max_share`` of their observations inside the masks.

    obs_frame, obs_point (O,) ints, obs_uv (O, 2) pixels (our convention); masks (N, H, W) bool."""
    M = np.asarray(masks, dtype=bool)
    if M.ndim != 3:
        raise ValueError(f"masks must be (N, H, W) bool; got shape {M.shape}")
    N, H, W = M.shape
    obs_frame = np.asarray(obs_frame, dtype=np.int64)
    obs_point = np.asarray(obs_point, dtype=np.int64)
    if obs_frame.size and (obs_frame.min() < 0 or obs_frame.max() >= N):
        raise ValueError(f"obs_frame must index the {N} masks; got frames {obs_frame.min()}..{obs_frame.max()}")
    ij = np.floor(np.asarray(obs_uv, dtype=np.float64)).astype(np.int64)
    on = M[obs_frame, np.clip(ij[:, 1], 0, H - 1), np.clip(ij[:, 0], 0, W - 1)]
    cnt = np.bincount(obs_point, minlength=num_points)
    inside = np.bincount(obs_point, weights=on.astype(np.float64), minlength=num_points)
    return inside <= max_share * cnt


def static_motion_masks(images, cam_T_world, K, points, obs_frame, obs_point, obs_uv, config: MaskConfig = None,
                        log=None):
    """``motion_masks`` from the sparse points that are not on movers (MaskConfig.prune_rounds).

    obs_frame, obs_point, obs_uv: the registration's inlier observations of ``points``. Returns
    (masks, info) with info["static_points"] (P,) bool: the points the final masks were made from.
    """
    cfg = MaskConfig() if config is None else config
    if not isinstance(cfg, MaskConfig):
        raise TypeError(f"config must be a MaskConfig; got {type(cfg).__name__}")
    points = np.asarray(points, dtype=np.float64)
    keep = np.ones(len(points), dtype=bool)
    masks, info = motion_masks(images, cam_T_world, K, points, cfg, log=log)
    for _ in range(cfg.prune_rounds):
        new = points_off_masks(obs_frame, obs_point, obs_uv, masks, len(points), cfg.prune_share)
        if np.array_equal(new, keep):
            break
        keep = new
        masks, info = motion_masks(images, cam_T_world, K, points[keep], cfg, log=log)
    info["static_points"] = keep
    return masks, info
