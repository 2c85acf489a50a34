"""Point tracks through a video by pyramidal Lucas-Kanade (KLT) (docs/dataset_format.md §8).

Why not SIFT matching alone: on the suite's blurry 240x135 frames a SIFT keypoint's descriptor
changes with the blur direction (the hand shake turns it from frame to frame) and repetitive
texture (brick, gravel) fails the ratio test, so few keypoints match the next frame
(docs/results.md §12) and tracks rarely reach 3 frames: too little parallax per track and
frames that share too few 3D points with the rest break the registration. Lucas-Kanade follows a
corner by its local intensity pattern over a small displacement, which blur of a few pixels does
not destroy, and keeps following it while it stays visible.

``klt_tracks``, frame by frame:
1. the active points of frame k - 1 are tracked into frame k (``cv2.calcOpticalFlowPyrLK``) and
   back again; a point is kept if both succeed, it lands inside the frame, and the backward track
   returns within ``fb_px`` of where it started (forward-backward check: occlusions, drift on
   edges and blurred texture fail it); a point that fails is tracked again with a larger window
   (``retry_window_px``): a streak that turns from one frame to the next fits inside it;
2. the kept pairs are checked against one fundamental matrix (RANSAC, ``ransac_px``): points on
   objects that move against the camera's motion, and the remaining drifts, leave the track there;
3. new Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) are detected at least ``min_distance_px``
   from the active points until frame k has ``max_corners`` points; none inside a motion mask
   (dilated by ``mask_dilation_px``), and active points that enter a mask end there.
Coordinates leave this module in our pixel convention (OpenCV's + 0.5, docs/conventions.md §2).
"""
from __future__ import annotations


import cv2
import numpy as np

from d2gs_np.constants import PIXEL_CENTER_OFFSET
from d2gs_np.pose.config import TrackConfig
from d2gs_np.pose.features import static_detector_mask, to_gray_u8

__all__ = ["klt_tracks"]


def _lk_window(a, b, pts, window, cfg):
    win = (window, window)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, None, winSize=win, maxLevel=cfg.levels, criteria=crit)
    p0, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, winSize=win, maxLevel=cfg.levels, criteria=crit)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & np.all(np.isfinite(p1), axis=1)
    ok &= np.linalg.norm(p0 - pts, axis=1) < cfg.fb_px
    return p1, ok


def _lk(a, b, pts, cfg):
    p1, ok = _lk_window(a, b, pts, cfg.window_px, cfg)
    if cfg.retry_window_px and not ok.all():
        bad = np.flatnonzero(~ok)
        p1b, okb = _lk_window(a, b, pts[bad], cfg.retry_window_px, cfg)
        p1[bad[okb]] = p1b[okb]
        ok[bad[okb]] = True
    return p1, ok


def klt_tracks(images, config: TrackConfig = None, masks=None, seed=0):
    """Tracks through ``images`` (module docstring).

    images: list of (H, W, 3) or (H, W) frames (uint8, or float in [0, 1]); masks: optional list of
    (H, W) bool, True = moving (no points there). Returns (obs_frame (O,), obs_track (O,), obs_uv
    (O, 2) in our pixel convention, num_tracks, corners (N,) points per frame); every track has at
    least 2 observations, in consecutive frames.
    """
    cfg = TrackConfig() if config is None else config
    if not isinstance(cfg, TrackConfig):
        raise TypeError(f"config must be a TrackConfig; got {type(cfg).__name__}")
    N = len(images)
    gray = [to_gray_u8(im) for im in images]
    H, W = gray[0].shape
    if any(g.shape != (H, W) for g in gray):
        raise ValueError("all frames must have the same size to be tracked")
    if masks is not None and len(masks) != N:
        raise ValueError(f"got {len(masks)} masks for {N} frames")
    usable = [None if masks is None else static_detector_mask(masks[k], cfg.mask_dilation_px) > 0 for k in range(N)]
    pts = np.zeros((0, 2), np.float32)
    ids = np.zeros(0, np.int64)
    nt = 0
    obs_f, obs_t, obs_uv = [], [], []
    corners = np.zeros(N, dtype=np.int64)
    cv2.setRNGSeed(seed)
    for k in range(N):
        if k > 0 and len(pts):
            p1, ok = _lk(gray[k - 1], gray[k], pts, cfg)
            ok &= (p1[:, 0] >= 0) & (p1[:, 0] <= W - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= H - 1)
            if usable[k] is not None:
                ij = np.clip(np.round(p1).astype(np.int64), 0, [W - 1, H - 1])
                ok[ok] &= usable[k][ij[ok, 1], ij[ok, 0]]
            if ok.sum() >= 8:
                _, inl = cv2.findFundamentalMat(pts[ok], p1[ok], cv2.FM_RANSAC, cfg.ransac_px, 0.999, 2000)
                if inl is not None:
                    ok[np.flatnonzero(ok)[inl.ravel() == 0]] = False
            pts, ids = p1[ok], ids[ok]
        free = np.full((H, W), 255, np.uint8)
        if usable[k] is not None:
            free[~usable[k]] = 0
        for x, y in np.round(pts).astype(np.int64):
            cv2.circle(free, (int(x), int(y)), cfg.min_distance_px, 0, -1)
        need = cfg.max_corners - len(pts)
        if need > 0:
            c = cv2.goodFeaturesToTrack(gray[k], need, cfg.quality, cfg.min_distance_px, mask=free)
            if c is not None:
                c = c.reshape(-1, 2).astype(np.float32)
                pts = np.vstack([pts, c])
                ids = np.r_[ids, nt + np.arange(len(c))]
                nt += len(c)
        corners[k] = len(pts)
        obs_f.append(np.full(len(pts), k, dtype=np.int64))
        obs_t.append(ids.copy())
        obs_uv.append(pts.astype(np.float64) + PIXEL_CENTER_OFFSET)
    f, t, uv = np.concatenate(obs_f), np.concatenate(obs_t), np.concatenate(obs_uv)
    keep = np.bincount(t, minlength=nt)[t] >= 2  # single observations are no tracks
    _, track = np.unique(t[keep], return_inverse=True)
    return f[keep], track.astype(np.int64), uv[keep], int(track.max()) + 1 if keep.any() else 0, corners
