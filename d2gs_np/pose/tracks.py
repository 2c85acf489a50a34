"""Point tracks through a video by pyramidal Lucas-Kanade (KLT) (docs/dataset_format.md §8).

Why not SIFT matching alone: on the suite's blurry 240x135 frames a SIFT keypoint's descriptor
changes with the blur direction (the hand shake turns it from frame to frame) and repetitive
texture (brick, gravel) fails the ratio test, so only 20-40 of ~300 keypoints per frame match the
next frame (crossing, seed 0) and tracks rarely reach 3 frames: too little parallax per track and
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

import numbers
from dataclasses import dataclass

import cv2
import numpy as np

from d2gs_np.constants import PIXEL_CENTER_OFFSET
from d2gs_np.pose.features import static_detector_mask, to_gray_u8

__all__ = ["TrackConfig", "klt_tracks"]


@dataclass(frozen=True)
class TrackConfig:
    """Settings of the KLT tracker. Validated on construction."""

    # points per frame: 240x135 suite frames have 500-600 Shi-Tomasi corners at quality 0.005
    max_corners: int = 600
    quality: float = 0.005  # Shi-Tomasi quality (share of the best corner's score): low, blur lowers corner scores
    min_distance_px: int = 5  # corners (new and active) at least this far apart
    window_px: int = 15  # Lucas-Kanade window; 15 px: a few px of blur fits inside
    # points that fail (step 1) with window_px are tracked again with this window (0: no retry). The
    # fast shake of the suite's crossing, seed 1, streaks its star field along a turning direction:
    # with 15 px alone only 11-14 static tracks span frames 10-12, the static world cannot be
    # registered across them, and the registration bridged them on the crossing card (relative
    # rotation errors of 4.7 deg per frame in frames 12-16). Retrying at 21 px keeps 50-60 there.
    # Import accuracy (examples/import_accuracy.py, seeds 0 / 1), ATE/depth and mask IoU, 0 -> 21:
    # crossing 0.99 / 1.91 % -> 0.91 / 1.57 %, IoU 0.47 / 0.27 -> 0.58 / 0.60; cube_sign ATE 0.40 /
    # 0.18 % -> 1.49 / 0.19 %; the rest within 0.14 % ATE and 0.02 IoU; the static photo_room marks
    # 0.5 / 1.1 -> 0.5 / 2.2 % of its pixels. A 21 px window for every point instead: big_mover seed 1
    # fails (ATE 3.9 %), photo_room marks 2.4 / 4.0 %
    retry_window_px: int = 21
    levels: int = 3  # pyramid levels (3: displacements of ~30 px between neighbouring frames)
    fb_px: float = 0.5  # forward-backward error above which a track ends
    ransac_px: float = 1.0  # distance to the epipolar line (F between neighbouring frames) for an inlier
    mask_dilation_px: int = 4  # as FeatureConfig.mask_dilation_px: keep off the border of a mover

    def __post_init__(self):
        for name in ("max_corners", "min_distance_px", "window_px", "levels", "mask_dilation_px", "retry_window_px"):
            v = getattr(self, name)
            lo = 0 if name in ("levels", "mask_dilation_px", "retry_window_px") else 1
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < lo:
                raise ValueError(f"TrackConfig.{name} must be an int >= {lo}; got {v!r}")
        if self.window_px < 3:
            raise ValueError(f"TrackConfig.window_px must be >= 3; got {self.window_px}")
        if 0 < self.retry_window_px < 3:
            raise ValueError(f"TrackConfig.retry_window_px must be 0 (no retry) or >= 3; got {self.retry_window_px}")
        for name in ("quality", "fb_px", "ransac_px"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not np.isfinite(v) or v <= 0:
                raise ValueError(f"TrackConfig.{name} must be a finite number > 0; got {v!r}")
        if self.quality >= 1:
            raise ValueError(f"TrackConfig.quality must be in (0, 1); got {self.quality}")


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
