"""Which point tracks move together, and which group is the static world (docs/dataset_format.md §8).

Why: a registration follows whatever rigid motion best explains the tracks. A scene of two layers
at different depths (a large panel swaying in front of a wall) is a trap: for any two image
motions of the layers there is a camera rotation plus translation that explains both, so the
panel's tracks are triangulated as static points and the camera path absorbs the panel's sway,
with every reprojection residual under a pixel (the suite's big_mover: docs/results.md §13).
Epipolar geometry cannot tell the layers apart; the image motion of each layer can: between two
frames one homography maps most of a layer's tracks.

``track_groups``: for each frame pair (k, k + gap), a homography by RANSAC takes its inliers as one
group and a second homography on the rest as the other; two tracks' affinity is the share of the
pairs where both were grouped that put them in the same group; the tracks are split in two by the
sign of the second eigenvector of the normalised affinity (spectral clustering, Shi and Malik's
normalised cut). A static scene with depth splits too (its planes); that is harmless, because the
importer keeps its first registration unless the static group's own registration disagrees with
it (``d2gs_np.video.importer.static_motion``).

``border_share``: which group is the static world. A mover sits inside the frame and the world
surrounds it, however many corners the mover has: the group whose points own more of the frame
border (each border pixel belongs to the group with the nearer point) is taken for the static one.
"""
from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

__all__ = ["track_groups", "border_share"]


def track_groups(obs_frame, obs_track, obs_uv, num_tracks, gap=2, threshold_px=1.5, max_tracks=1500,
                 min_pair_tracks=20, min_pairs=2):
    """Two groups of tracks that move together (module docstring).

    obs_frame, obs_track (O,), obs_uv (O, 2): observations of ``num_tracks`` tracks. Only tracks of
    3 observations or more take part, the ``max_tracks`` longest (memory is max_tracks^2); a track
    grouped in fewer than ``min_pairs`` frame pairs is left out. Returns labels (num_tracks,) in
    {-1 (left out), 0, 1}; all -1 when fewer than 2 tracks could be grouped.
    """
    obs_frame = np.asarray(obs_frame, dtype=np.int64)
    obs_track = np.asarray(obs_track, dtype=np.int64)
    obs_uv = np.asarray(obs_uv, dtype=np.float64)
    labels = np.full(num_tracks, -1, dtype=np.int64)
    if num_tracks == 0 or len(obs_frame) == 0:
        return labels
    length = np.bincount(obs_track, minlength=num_tracks)
    cand = np.flatnonzero(length >= 3)
    cand = cand[np.argsort(-length[cand], kind="stable")][:max_tracks]
    if cand.size < 2:
        return labels
    slot = np.full(num_tracks, -1, dtype=np.int64)
    slot[cand] = np.arange(cand.size)
    sel = slot[obs_track] >= 0
    N = int(obs_frame.max()) + 1
    look = np.full((N, cand.size), -1, dtype=np.int64)
    look[obs_frame[sel], slot[obs_track[sel]]] = np.flatnonzero(sel)
    same = np.zeros((cand.size, cand.size), dtype=np.float32)
    both = np.zeros((cand.size, cand.size), dtype=np.float32)
    cv2.setRNGSeed(0)
    for a in range(N - gap):
        com = np.flatnonzero((look[a] >= 0) & (look[a + gap] >= 0))
        if com.size < min_pair_tracks:
            continue
        pa = obs_uv[look[a, com]].astype(np.float32)
        pb = obs_uv[look[a + gap, com]].astype(np.float32)
        lab = np.zeros(com.size, dtype=np.int64)
        _, inl = cv2.findHomography(pa, pb, cv2.RANSAC, threshold_px)
        if inl is None:
            continue
        lab[inl.ravel() > 0] = 1
        rest = np.flatnonzero(lab == 0)
        if rest.size >= 8:
            _, inl2 = cv2.findHomography(pa[rest], pb[rest], cv2.RANSAC, threshold_px)
            if inl2 is not None:
                lab[rest[inl2.ravel() > 0]] = 2
        g = lab > 0
        idx, lg = com[g], lab[g]
        both[np.ix_(idx, idx)] += 1.0
        same[np.ix_(idx, idx)] += (lg[:, None] == lg[None, :])
    use = np.flatnonzero(np.diag(both) >= min_pairs)
    if use.size < 2:
        return labels
    B = both[np.ix_(use, use)].astype(np.float64)
    A = np.where(B > 0, same[np.ix_(use, use)] / np.maximum(B, 1.0), 0.0)
    d = A.sum(axis=1)
    dm = 1.0 / np.sqrt(np.maximum(d, 1e-12))
    _, vec = np.linalg.eigh(dm[:, None] * A * dm[None, :])
    x = vec[:, -2] * dm  # the normalised cut's relaxed indicator
    labels[cand[use]] = (x > 0).astype(np.int64)
    return labels


def border_share(uv_a, frame_a, uv_b, frame_b, num_frames, W, H):
    """Share of the frame border owned by point set a against point set b, pooled over the frames.

    uv_* (n, 2) pixels (our convention) in frames frame_* (n,). Each frame's border pixels (one
    pixel apart along the edges) belong to the set with the nearer point in that frame; frames
    where either set has no point are left out. Returns a number in [0, 1]; NaN when no frame has
    points of both sets.
    """
    xs, ys = np.arange(W) + 0.5, np.arange(H) + 0.5
    border = np.concatenate([np.c_[xs, np.zeros(W)], np.c_[xs, np.full(W, float(H))],
                             np.c_[np.zeros(H), ys], np.c_[np.full(H, float(W)), ys]])
    own_a = total = 0
    for k in range(num_frames):
        a, b = uv_a[frame_a == k], uv_b[frame_b == k]
        if len(a) == 0 or len(b) == 0:
            continue
        da, _ = cKDTree(a).query(border)
        db, _ = cKDTree(b).query(border)
        own_a += int(np.sum(da < db))
        total += len(border)
    return own_a / total if total else float("nan")
