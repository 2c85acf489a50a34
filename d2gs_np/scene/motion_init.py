"""Initial deformation of the dynamic set from tracked motion masks.

docs/method.md §8 seeds dynamic Gaussians inside the masked regions but leaves their
initial deformation open. With zero coefficients a Gaussian seeded from frame
k sits where the object was at t_k *at every time*, occluding the background
in all other frames, and the photometric gradient mostly lowers its opacity
rather than moving it. We use the masks once more:

1. each frame's mask is split into connected components (8-connectivity,
   components smaller than ``min_area_fraction`` of the image are ignored);
2. components are tracked across consecutive frames by optimal assignment of
   their centroids (Hungarian, gated at ``max_jump_fraction`` of the image
   diagonal);
3. the image rotation and scale of each track from frame to frame (a
   tumbling, rolling or swinging object turns, not only travels): SIFT
   features inside the component in both frames, ratio-test matches and a
   RANSAC similarity (``cv2.estimateAffinePartial2D``); a pair with fewer than
   ``min_rotation_inliers`` inliers counts as no rotation. Accumulated along
   the track: angle a_j(m) and scale s_j(m) relative to its first frame;
4. a seed at pixel p of frame k in track j keeps its offset o = p - c_j(k) to
   the track's centroid, turned with the object: at every frame m of the track
   its target pixel is c_j(m) + (s_j(m) / s_j(k)) R(a_j(m) - a_j(k)) o, lifted
   to 3D at the seed's own camera depth with the given pose of frame m (the
   object is assumed to stay at a similar distance; the in-image rotation is
   the part of a 3D rotation the masks and features can show);
5. base position and polynomial + Fourier coefficients are fitted to those
   targets by ridge-regularised least squares (ridge on the coefficients only).

Seeds whose pixel lies in no tracked component keep zero coefficients. Only
the means are initialised; rotations and colours start with zero residuals.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from d2gs_np.geometry.camera import unproject_points
from d2gs_np.scene.deformation import DeformConfig, deform_basis


@dataclass(frozen=True)
class MotionInitConfig:
    enabled: bool = True
    min_area_fraction: float = 5e-4  # components below this share of the image are noise
    max_jump_fraction: float = 0.25  # centroid jump gate between consecutive frames, x image diagonal
    ridge: float = 1e-2  # Tikhonov weight on the coefficients relative to the number of frames
    rotation: bool = True  # follow each track's in-image rotation (step 3); False: translation only
    min_rotation_inliers: int = 6  # fewer RANSAC inliers between two frames: no rotation measured

    def __post_init__(self):
        if not 0.0 <= self.min_area_fraction < 1.0:
            raise ValueError(f"MotionInitConfig.min_area_fraction must be in [0, 1); got {self.min_area_fraction}")
        if self.max_jump_fraction <= 0.0:
            raise ValueError(f"MotionInitConfig.max_jump_fraction must be > 0; got {self.max_jump_fraction}")
        if not self.ridge > 0.0:  # tracks shorter than 1 + K frames need it to be well posed
            raise ValueError(f"MotionInitConfig.ridge must be > 0; got {self.ridge}")
        if self.min_rotation_inliers < 3:  # a similarity has 4 degrees of freedom: 2 points + 1 check
            raise ValueError(f"MotionInitConfig.min_rotation_inliers must be >= 3; got {self.min_rotation_inliers}")


def mask_components(mask, min_area):
    """Connected components of a bool (H, W) mask: (labels (H, W) int32, centroids (C, 2) in our pixel
    convention (centre of pixel j at j + 0.5), areas (C,)) keeping components of >= min_area pixels;
    labels of dropped components are -1, kept ones are 0..C-1."""
    n, labels, stats, cents = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = [c for c in range(1, n) if stats[c, cv2.CC_STAT_AREA] >= min_area]
    remap = np.full(n, -1, dtype=np.int32)
    remap[keep] = np.arange(len(keep), dtype=np.int32)
    return remap[labels], cents[keep] + 0.5, stats[keep, cv2.CC_STAT_AREA].astype(np.float64)


def track_components(centroids, gate):
    """Link per-frame components into tracks: list over frames of (C_k,) track ids.

    Consecutive frames are matched by the Hungarian algorithm on centroid distance; pairs farther
    apart than ``gate`` pixels are not linked and start a new track.
    """
    ids, next_id = [], 0
    for k, c in enumerate(centroids):
        cur = np.full(len(c), -1, dtype=np.int64)
        if k > 0 and len(c) and len(centroids[k - 1]):
            prev = centroids[k - 1]
            cost = np.linalg.norm(c[:, None, :] - prev[None, :, :], axis=2)
            rows, cols = linear_sum_assignment(cost)
            for r, q in zip(rows, cols):
                if cost[r, q] <= gate:
                    cur[r] = ids[k - 1][q]
        for r in np.flatnonzero(cur < 0):
            cur[r] = next_id
            next_id += 1
        ids.append(cur)
    return ids


def relative_similarity(image0, region0, image1, region1, min_inliers=6):
    """In-image rotation (radians, counter-clockwise in pixel axes) and scale taking region0 of image0
    to region1 of image1, from SIFT matches inside the regions and a RANSAC similarity.

    image0/1 (H, W, 3) in [0, 1]; region0/1 (H, W) bool. Returns (angle, scale, inliers); (0, 1, n)
    when fewer than ``min_inliers`` matches support one similarity (no rotation measured).
    """
    from d2gs_np.features import to_gray_u8

    sift = cv2.SIFT_create(contrastThreshold=0.02)
    kernel = np.ones((5, 5), np.uint8)
    kp0, d0 = sift.detectAndCompute(to_gray_u8(image0), cv2.dilate(region0.astype(np.uint8), kernel) * 255)
    kp1, d1 = sift.detectAndCompute(to_gray_u8(image1), cv2.dilate(region1.astype(np.uint8), kernel) * 255)
    if d0 is None or d1 is None or len(kp0) < 2 or len(kp1) < 2:
        return 0.0, 1.0, 0
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
    good = [m for m, n in (p for p in pairs if len(p) == 2) if m.distance < 0.75 * n.distance]
    if len(good) < min_inliers:
        return 0.0, 1.0, len(good)
    p0 = np.float32([kp0[m.queryIdx].pt for m in good])
    p1 = np.float32([kp1[m.trainIdx].pt for m in good])
    cv2.setRNGSeed(0)
    A, inl = cv2.estimateAffinePartial2D(p0, p1, method=cv2.RANSAC, ransacReprojThreshold=2.0)
    n = int(inl.sum()) if inl is not None else 0
    if A is None or n < min_inliers:
        return 0.0, 1.0, n
    scale = float(np.hypot(A[0, 0], A[1, 0]))
    return float(np.arctan2(A[1, 0], A[0, 0])), scale, n


def _track_turns(frames, labels, mem, min_inliers):
    """Accumulated (angle, scale) of a track's object at each of its frames, relative to its first."""
    angle, scale = [0.0], [1.0]
    for (k0, _, c0), (k1, _, c1) in zip(mem[:-1], mem[1:]):
        a, s, _ = relative_similarity(frames[k0].image, labels[k0] == c0, frames[k1].image, labels[k1] == c1,
                                      min_inliers)
        angle.append(angle[-1] + a)
        scale.append(scale[-1] * s)
    return np.array(angle), np.array(scale)


def initialize_deformation(scene, seed_points, seed_frames, seed_pixels, deform_config: DeformConfig,
                           config: MotionInitConfig = MotionInitConfig()):
    """Base means (Nd, 3) and position coefficients (Nd, K, 3) for dynamic seeds.

    scene: the training Scene (masks and poses used). seed_points (Nd, 3): seeds lifted at frame
    seed_frames (Nd,) from continuous pixels seed_pixels (Nd, 2). Returns (means, coef_means, info).
    """
    frames = scene.frames
    Nd = seed_points.shape[0]
    K = deform_config.num_coefs
    means = np.array(seed_points, dtype=np.float64, copy=True)
    coefs = np.zeros((Nd, K, 3))
    info = {"num_tracks": 0, "num_tracked_seeds": 0}
    if not config.enabled or Nd == 0 or not scene.has_masks:
        return means, coefs, info

    labels, cents = [], []
    for f in frames:
        lab, c, _ = mask_components(f.mask, config.min_area_fraction * f.width * f.height)
        labels.append(lab)
        cents.append(c)
    diag = float(np.hypot(frames[0].width, frames[0].height))
    track_ids = track_components(cents, config.max_jump_fraction * diag)
    num_tracks = int(max((t.max() + 1 for t in track_ids if len(t)), default=0))
    # Per track: frame indices and centroids.
    members = {j: [] for j in range(num_tracks)}
    for k, ids in enumerate(track_ids):
        for c, j in enumerate(ids):
            members[int(j)].append((k, cents[k][c], c))
    turns = {j: _track_turns(frames, labels, mem, config.min_rotation_inliers) if config.rotation and len(mem) > 1
             else (np.zeros(len(mem)), np.ones(len(mem))) for j, mem in members.items()}

    times = np.array([f.time for f in frames])
    basis = np.stack([np.concatenate([[1.0], deform_basis(t, deform_config)[0]]) for t in times])  # (N, 1 + K)
    tracked = 0
    for i in range(Nd):
        k = int(seed_frames[i])
        px = seed_pixels[i]
        r = min(max(int(px[1]), 0), frames[k].height - 1)
        c = min(max(int(px[0]), 0), frames[k].width - 1)
        comp = labels[k][r, c]
        if comp < 0:
            continue
        j = int(track_ids[k][comp])
        mem = members[j]
        if len(mem) < 2:
            continue
        offset = px - cents[k][comp]
        pc = (frames[k].cam_T_world[:3, :3] @ seed_points[i]) + frames[k].cam_T_world[:3, 3]
        depth = float(pc[2])
        fidx = np.array([m for m, _, _ in mem])
        ang, sc = turns[j]
        here = int(np.flatnonzero(fidx == k)[0])
        da, ds = ang - ang[here], sc / sc[here]
        rot_off = ds[:, None] * np.stack([np.cos(da) * offset[0] - np.sin(da) * offset[1],
                                          np.sin(da) * offset[0] + np.cos(da) * offset[1]], axis=1)
        cent_m = np.stack([cent for _, cent, _ in mem])
        targets = np.stack([unproject_points((cent_m[q] + rot_off[q])[None], np.array([depth]),
                                             frames[m].cam_T_world, frames[m].K)[0]
                            for q, m in enumerate(fidx)])  # (M, 3)
        A = basis[fidx]  # (M, 1 + K)
        reg = config.ridge * len(fidx) * np.eye(1 + K)
        reg[0, 0] = 0.0  # the base position is not shrunk
        sol = np.linalg.solve(A.T @ A + reg, A.T @ targets)  # (1 + K, 3)
        means[i] = sol[0]
        coefs[i] = sol[1:]
        tracked += 1
    info = {"num_tracks": num_tracks, "num_tracked_seeds": tracked}
    return means, coefs, info
