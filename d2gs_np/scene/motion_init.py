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
3. each track's image motion from frame to frame (a tumbling, rolling or
   swinging object turns, not only travels): SIFT features inside the
   component in both frames, ratio-test matches and a RANSAC similarity
   (``cv2.estimateAffinePartial2D``, 2 px; a pair with fewer than
   ``min_rotation_inliers`` inliers moves by the difference of the centroids
   alone). With ``warp="flow"`` (the default) the similarity is refined by
   dense optical flow (OpenCV's DIS) between the first image and the second
   pulled back by the similarity, each reduced to the object (outside its
   dilated region: the region's mean colour), so the flow finds only what one
   similarity misses: a tumbling object's faces, perspective, parallax;
4. a seed at pixel p of frame k in track j is carried by these maps, pair by
   pair, forwards to the later frames of its track and backwards to the
   earlier ones: its target pixel in each frame m. ``warp="similarity"`` or
   ``"homography"`` chain RANSAC similarities or homographies alone (W_j(m)
   W_j(k)^-1 p); ``warp="centroid"``, the earlier rule, keeps the seed's
   offset o = p - c_j(k) to the component's centroid, turned and scaled with
   the similarity's angle a_j and scale s_j: c_j(m) + (s_j(m) / s_j(k))
   R(a_j(m) - a_j(k)) o. The target is lifted to 3D at the seed's own camera
   depth with the given pose of frame m (the depth of a moving object is not
   observable from one moving camera without a prior; the fitted motion is
   the one that reprojects right at that depth);
5. base position and polynomial + Fourier coefficients are fitted to those
   targets by ridge-regularised least squares (ridge on the coefficients only,
   ``ridge`` x the track's frames; 1e-4: enough to pose a track shorter than
   the 1 + K coefficients, small enough not to shrink a mover's sweep,
   docs/results.md §9).

The maps follow the object's texture, not its mask: where the object is cut
by the image border, blurred into the background or partly occluded, the
centroid of what is visible moves differently from the object. Against the
true motion of the suite's movers the flow rule is the closest on every scene
(``examples/motion_init_accuracy.py``; docs/results.md §9).

With ``rigid`` (``MotionInitConfig.rigid``) each track of three or more seeds is one rigid
object instead: its pose at each frame is the rotation and translation (no scale) that takes its
seeds at the track's middle frame to their targets there, the pose path is fitted by the same
basis, and its seeds keep zero coefficients in its frame (``scene/rigid.py``). The targets sit at
each seed's own depth, so that pose holds the turn in the image plane only; with ``rigid_fit =
"pairs"`` and the per-frame depth maps the seeds were lifted at, the pose is chained instead from
each consecutive pair of the track's frames: the pair's flow correspondences inside the object
(step 3's maps), lifted at both frames' depths, and the rigid motion between them (a RANSAC
similarity, its scale dropped), which holds a turn out of the image plane too. With ``rigid_fit =
"bundle"`` those chained poses are refined together with the object's shape by a bundle adjustment
over short flow tracks inside it, the depth maps a weak term (``scene/object_bundle.py``): where the
depth maps' error tilts each frame's lifted object differently, the pairs find no rigid motion, and
the turn shows only as foreshortening over several frames.

Seeds whose pixel lies in no tracked component keep zero coefficients. Only
the means are initialised; rotations and colours start with zero residuals.
"""
from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from d2gs_np.constants import PIXEL_CENTER_OFFSET
from d2gs_np.geometry.camera import unproject_points
from d2gs_np.scene.config import WARPS, DeformConfig, MotionInitConfig
from d2gs_np.scene.deformation import deform_basis

WARP_W_MIN = 1e-6  # a homogeneous pixel with w below this is at or behind infinity
RIGID_MIN_SEEDS = 3  # a rotation needs three points off one line
RIGID_SHAPE_SEEDS = 20  # seeds of the reference frame enough to stand for the object's shape (PnP)
PAIR_MIN_POINTS = 12  # correspondences a pair's rigid motion needs ("pairs"); fewer: no turn measured
PAIR_MAX_POINTS = 800  # correspondences a pair keeps, on a regular grid over the object
PAIR_ERODE_PX = 2  # the object's region eroded by this much: off its blurred rim and depth edges
PAIR_INLIER_FRACTION = 0.1  # RANSAC inlier distance, a fraction of the object's median radius
PAIR_MIN_INLIER_SHARE = 0.5  # a pair with fewer inliers than this share measures no turn
PAIR_RANSAC_ITERS = 200
# a correspondence's depth within this factor of its region's median depth in both frames: a blurred
# mover's mask also covers the streak it leaves, where the depth is the background's
PAIR_DEPTH_GATE = 1.25


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


def relative_warp(image0, region0, image1, region1, kind="similarity", min_inliers=6):
    """3 x 3 map of pixels from region0 of image0 to region1 of image1, in our pixel convention
    (the centre of pixel j at j + 0.5), fitted by RANSAC (2 px) to SIFT matches inside the
    (slightly dilated) regions: a similarity (rotation, scale, translation; ``kind="similarity"``)
    or a homography (``"homography"``, exact for a plane).

    image0/1 (H, W, 3) in [0, 1]; region0/1 (H, W) bool. Returns (H (3, 3) or None, inliers): None
    when fewer than ``min_inliers`` matches support one warp.
    """
    from d2gs_np.pose.features import to_gray_u8

    if kind not in WARPS[1:]:
        raise ValueError(f"relative_warp: kind must be one of {WARPS[1:]}; got {kind!r}")
    sift = cv2.SIFT_create(contrastThreshold=0.02)
    kernel = np.ones((5, 5), np.uint8)
    kp0, d0 = sift.detectAndCompute(to_gray_u8(image0), cv2.dilate(region0.astype(np.uint8), kernel) * 255)
    kp1, d1 = sift.detectAndCompute(to_gray_u8(image1), cv2.dilate(region1.astype(np.uint8), kernel) * 255)
    if d0 is None or d1 is None or len(kp0) < 2 or len(kp1) < 2:
        return None, 0
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
    good = [m for m, n in (p for p in pairs if len(p) == 2) if m.distance < 0.75 * n.distance]
    if len(good) < max(min_inliers, 4):  # a homography needs 4 matches
        return None, len(good)
    p0 = np.float32([kp0[m.queryIdx].pt for m in good]) + PIXEL_CENTER_OFFSET  # OpenCV's pixel centres are at j
    p1 = np.float32([kp1[m.trainIdx].pt for m in good]) + PIXEL_CENTER_OFFSET
    cv2.setRNGSeed(0)
    if kind == "homography":
        H, inl = cv2.findHomography(p0, p1, cv2.RANSAC, 2.0)
    else:
        A, inl = cv2.estimateAffinePartial2D(p0, p1, method=cv2.RANSAC, ransacReprojThreshold=2.0)
        H = None if A is None else np.vstack([A, [0.0, 0.0, 1.0]])
    n = int(inl.sum()) if inl is not None else 0
    if H is None or n < min_inliers or not np.all(np.isfinite(H)):
        return None, n
    return np.asarray(H, dtype=np.float64), n


def relative_similarity(image0, region0, image1, region1, min_inliers=6):
    """In-image rotation (radians, counter-clockwise in pixel axes) and scale taking region0 of image0
    to region1 of image1: the rotation and scale of ``relative_warp(..., "similarity")``.
    Returns (angle, scale, inliers); (0, 1, n) when no similarity is supported.
    """
    H, n = relative_warp(image0, region0, image1, region1, "similarity", min_inliers)
    if H is None:
        return 0.0, 1.0, n
    return float(np.arctan2(H[1, 0], H[0, 0])), float(np.hypot(H[0, 0], H[1, 0])), n


def _pair_warp(frames, labels, a, b, kind, min_inliers):
    """3 x 3 map of pixels from track member a = (frame, centroid, component) to member b: the
    ``relative_warp`` of their regions, or the centroids' difference when it has too few inliers."""
    (k0, c0p, c0), (k1, c1p, c1) = a, b
    H, _ = relative_warp(frames[k0].image, labels[k0] == c0, frames[k1].image, labels[k1] == c1, kind, min_inliers)
    if H is None:
        H = np.eye(3)
        H[:2, 2] = np.asarray(c1p) - np.asarray(c0p)
    return H


def _track_warps(frames, labels, mem, kind, min_inliers):
    """(M, 3, 3) maps of a track's first-frame pixels to each of its frames, chained from the
    ``_pair_warp`` of consecutive frames."""
    W = [np.eye(3)]
    for a, b in zip(mem[:-1], mem[1:]):
        W.append(_pair_warp(frames, labels, a, b, kind, min_inliers) @ W[-1])
    return np.stack(W)


def _pair_map(frames, labels, a, b, min_inliers):
    """The map of pixels of track member a = (k0, centroid, component) to member b's frame k1,
    as a function of (P, 2) pixels: the pair's similarity (``_pair_warp``) refined by dense optical
    flow (OpenCV's DIS, medium
    preset) between image k0 and image k1 pulled back by that similarity, so that the flow only
    has to find what the similarity misses (a tumbling object's faces, perspective, parallax)."""
    from d2gs_np.pose.features import to_gray_u8
    from d2gs_np.scene.initialize import sample_image_bilinear

    (k0, _, c0), (k1, _, c1) = a, b
    img0, img1 = frames[k0].image, frames[k1].image
    H = _pair_warp(frames, labels, a, b, "similarity", min_inliers)
    S = np.eye(3)
    S[:2, 2] = -PIXEL_CENTER_OFFSET  # ours -> OpenCV's pixel centres
    Hcv = S @ H @ np.linalg.inv(S)
    h, w = img0.shape[:2]
    # The flow sees the object only: outside its (dilated) region each image is its region's mean
    # colour, so the background's motion cannot drag the object's flow along.
    kernel = np.ones((5, 5), np.uint8)
    only = []
    for img, k, c in ((img0, k0, c0), (img1, k1, c1)):
        region = cv2.dilate((labels[k] == c).astype(np.uint8), kernel).astype(bool)
        only.append(np.where(region[..., None], img, img[region].mean(axis=0)).astype(np.float32))
    pulled = cv2.warpPerspective(only[1], Hcv, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_REPLICATE)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(to_gray_u8(only[0]), to_gray_u8(pulled), None).astype(np.float64)

    def apply(p):
        q = p + sample_image_bilinear(flow, p)
        q = np.c_[q, np.ones(len(q))] @ H.T
        return q[:, :2] / q[:, 2:3]
    return apply


def _track_flow_pixels(frames, labels, mem, here, px, min_inliers):
    """Pixels (S, M, 2) of seeds px (S, 2), each seen at track position here (S,), carried through
    the track's members mem (M,) by the chained maps of ``_pair_map`` (forward after its frame,
    backward before)."""
    S, M = len(px), len(mem)
    pos = np.full((S, M, 2), np.nan)
    pos[np.arange(S), here] = px
    for q in range(M - 1):  # forward: seeds seen at or before q
        on = np.flatnonzero(here <= q)
        if len(on):
            pos[on, q + 1] = _pair_map(frames, labels, mem[q], mem[q + 1], min_inliers)(pos[on, q])
    for q in range(M - 1, 0, -1):  # backward: seeds seen at or after q
        on = np.flatnonzero(here >= q)
        if len(on):
            pos[on, q - 1] = _pair_map(frames, labels, mem[q], mem[q - 1], min_inliers)(pos[on, q])
    return pos


def warp_pixel(W, px):
    """Pixel px (2,) carried by the maps W (M, 3, 3): (pixels (M, 2), ok (M,) bool). A map that sends
    it to or behind infinity (a chained homography can) is not ok; its pixel is NaN."""
    q = np.asarray(W, dtype=np.float64) @ np.array([px[0], px[1], 1.0])
    ok = np.isfinite(q).all(axis=1) & (q[:, 2] > WARP_W_MIN)
    pix = np.full((len(q), 2), np.nan)
    pix[ok] = q[ok, :2] / q[ok, 2:3]
    return pix, ok


def _track_turns(frames, labels, mem, min_inliers):
    """Accumulated (angle, scale) of a track's object at each of its frames, relative to its first."""
    angle, scale = [0.0], [1.0]
    for (k0, _, c0), (k1, _, c1) in zip(mem[:-1], mem[1:]):
        a, s, _ = relative_similarity(frames[k0].image, labels[k0] == c0, frames[k1].image, labels[k1] == c1,
                                      min_inliers)
        angle.append(angle[-1] + a)
        scale.append(scale[-1] * s)
    return np.array(angle), np.array(scale)


def _object_region(labels, k, c):
    """Member (k, c)'s component, eroded by ``PAIR_ERODE_PX`` (the whole component if that empties it)."""
    region = labels[k] == c
    size = 2 * PAIR_ERODE_PX + 1
    inner = cv2.erode(region.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
    return inner if inner.any() else region


def pair_motion(frames, labels, a, b, depth_maps, min_inliers=6):
    """The rigid motion (R (3, 3), t (3,)) taking the world points of track member a = (k0, centroid,
    component) to those of member b (x_b = R x_a + t), from the pair's map (``_pair_map``) on a grid
    of the object's pixels in k0, both ends lifted at ``depth_maps`` (per frame (H, W), NaN or
    non-positive where unknown), those within ``PAIR_DEPTH_GATE`` of their region's median depth in
    both frames: a RANSAC similarity (3-point samples, inliers within ``PAIR_INLIER_FRACTION`` of the
    object's median radius), refitted on its inliers; the scale is dropped
    (each frame's depth may carry its own), the translation is the one that keeps the inliers'
    centroid. Returns (R, t, number of inliers), or None where too few correspondences or inliers."""
    from d2gs_np.geometry.trajectory import umeyama
    from d2gs_np.scene.initialize import sample_image_bilinear

    (k0, _, c0), (k1, _, c1) = a, b
    if depth_maps[k0] is None or depth_maps[k1] is None:
        return None
    region0, region1 = _object_region(labels, k0, c0), _object_region(labels, k1, c1)
    ys, xs = np.nonzero(region0)
    stride = max(1, int(np.ceil(np.sqrt(len(xs) / PAIR_MAX_POINTS))))
    on_grid = (ys % stride == 0) & (xs % stride == 0)
    p = np.c_[xs[on_grid], ys[on_grid]] + PIXEL_CENTER_OFFSET
    if len(p) < PAIR_MIN_POINTS:
        return None
    q = _pair_map(frames, labels, a, b, min_inliers)(p)
    h, w = region1.shape
    ok = np.isfinite(q).all(axis=1)
    qi = np.clip(np.floor(np.nan_to_num(q)).astype(np.int64), 0, [w - 1, h - 1])
    ok &= region1[qi[:, 1], qi[:, 0]]
    d0, d1 = (sample_image_bilinear(np.nan_to_num(np.asarray(depth_maps[k], np.float64), nan=0.0, posinf=0.0,
                                                  neginf=0.0)[..., None], x)[:, 0]
              for k, x in ((k0, p), (k1, np.nan_to_num(q))))
    ok &= (d0 > 0) & (d1 > 0)
    if ok.sum() < PAIR_MIN_POINTS:
        return None
    for d in (d0, d1):
        med = float(np.median(d[ok]))
        ok &= (d < PAIR_DEPTH_GATE * med) & (d > med / PAIR_DEPTH_GATE)
    if ok.sum() < PAIR_MIN_POINTS:
        return None
    P = unproject_points(p[ok], d0[ok], frames[k0].cam_T_world, frames[k0].K)
    Q = unproject_points(q[ok], d1[ok], frames[k1].cam_T_world, frames[k1].K)
    size = float(np.sqrt(np.median(((P - np.median(P, axis=0)) ** 2).sum(axis=1))))
    if not size > 0:
        return None
    rng = np.random.default_rng(len(P))  # deterministic: the same pair gives the same motion
    best = None
    for _ in range(PAIR_RANSAC_ITERS):
        pick = rng.choice(len(P), 3, replace=False)
        try:
            s, R, t = umeyama(P[pick], Q[pick])
        except ValueError:  # three points at one place
            continue
        inl = np.linalg.norm(Q - (s * P @ R.T + t), axis=1) < PAIR_INLIER_FRACTION * size
        if best is None or inl.sum() > best.sum():
            best = inl
    if best is None or best.sum() < max(PAIR_MIN_POINTS, PAIR_MIN_INLIER_SHARE * len(P)):
        return None
    _, R, _ = umeyama(P[best], Q[best])
    t = Q[best].mean(axis=0) - R @ P[best].mean(axis=0)
    return R, t, int(best.sum())


def _chained_poses(frames, labels, mem, depth_maps, ref, centre, min_inliers):
    """Object -> world poses {frame: (R, t)} of track members mem, chained from the pair motions
    (``pair_motion``) outwards from the member at frame ``ref``, which has (I, centre). A pair
    without a motion carries the pose by the pair's centroid shift alone (no turn). Returns
    (poses, number of pairs without a motion)."""
    ks = [m for m, _, _ in mem]
    r = ks.index(ref)
    poses = {ref: (np.eye(3), np.asarray(centre, np.float64))}
    missed = 0
    for n in range(r, len(mem) - 1):  # forward: pose(n + 1) = motion(n -> n + 1) o pose(n)
        Rn, tn = poses[ks[n]]
        mo = pair_motion(frames, labels, mem[n], mem[n + 1], depth_maps, min_inliers)
        missed += mo is None
        if mo is None:
            poses[ks[n + 1]] = (Rn, tn + _centroid_shift(frames, mem[n], mem[n + 1], tn))
        else:
            poses[ks[n + 1]] = (mo[0] @ Rn, mo[0] @ tn + mo[1])
    for n in range(r, 0, -1):  # backward: pose(n - 1) = motion(n - 1 -> n)^-1 o pose(n)
        Rn, tn = poses[ks[n]]
        mo = pair_motion(frames, labels, mem[n - 1], mem[n], depth_maps, min_inliers)
        missed += mo is None
        if mo is None:
            poses[ks[n - 1]] = (Rn, tn - _centroid_shift(frames, mem[n - 1], mem[n], tn))
        else:
            poses[ks[n - 1]] = (mo[0].T @ Rn, mo[0].T @ (tn - mo[1]))
    return poses, missed


def bundle_track(frames, labels, mem, depth_maps, ref, poses, window, depth_sigma, accel_deg, min_inliers=6):
    """Poses {frame: (R, t)} of track members mem refined by the object bundle (``rigid_fit =
    "bundle"``, ``scene/object_bundle.py``) from ``poses`` ({frame: (R, t)}, e.g. ``_chained_poses``');
    the member at frame ``ref`` keeps its pose. The points are tracked by the pair maps of step 3
    inside the object's regions (``_object_region``), their depths gated by ``PAIR_DEPTH_GATE``.
    Returns (poses, the bundle's info)."""
    from d2gs_np.scene.object_bundle import bundle_poses, track_observations

    ks = [k for k, _, _ in mem]
    M = len(mem)
    fwd = [_pair_map(frames, labels, mem[n], mem[n + 1], min_inliers) for n in range(M - 1)]
    bwd = [_pair_map(frames, labels, mem[n + 1], mem[n], min_inliers) for n in range(M - 1)]
    regions = [_object_region(labels, k, c) for k, _, c in mem]
    obs = track_observations(fwd, bwd, regions, [depth_maps[k] for k in ks], window, PAIR_DEPTH_GATE)
    out, info = bundle_poses([(frames[k].cam_T_world, frames[k].K) for k in ks], obs, ks.index(ref),
                             [poses[k] for k in ks], depth_sigma, accel_deg)
    return dict(zip(ks, out)), info


def _centroid_shift(frames, a, b, at):
    """World shift of an object between members a and b from its components' centroids, each lifted
    at the depth of the point ``at`` in that member's camera (a pair without a measured motion)."""
    out = []
    for k, cent, _ in (a, b):
        T = frames[k].cam_T_world
        z = float((T[:3, :3] @ at + T[:3, 3])[2])
        out.append(unproject_points(np.asarray(cent, np.float64)[None], np.array([max(z, 1e-9)]), T, frames[k].K)[0])
    return out[1] - out[0]


def initialize_deformation(scene, seed_points, seed_frames, seed_pixels, deform_config: DeformConfig,
                           config: MotionInitConfig = MotionInitConfig(), depth_maps=None):
    """Base means (Nd, 3) and position coefficients (Nd, K, 3) for dynamic seeds.

    scene: the training Scene (masks and poses used). seed_points (Nd, 3): seeds lifted at frame
    seed_frames (Nd,) from continuous pixels seed_pixels (Nd, 2). depth_maps: per frame (H, W) or
    None, the depths the seeds were lifted at (``initialize_points``' ``dynamic_depth_maps``); needed
    by ``rigid_fit = "pairs"``. Returns (means, coef_means, info).
    """
    frames = scene.frames
    if config.rigid and config.rigid_fit in ("pairs", "bundle"):
        if depth_maps is None:
            raise ValueError(f"MotionInitConfig.rigid_fit = {config.rigid_fit!r} lifts the pairs' correspondences at "
                             "the depth the dynamic seeds were lifted at, and these seeds have none: set "
                             "init.dynamic_depth "
                             "to 'prior' (a scene with depth priors) or 'scene' (true depth), or rigid_fit to "
                             "'kabsch'")
        if len(depth_maps) != len(frames):
            raise ValueError(f"initialize_deformation: depth_maps has {len(depth_maps)} entries for {len(frames)} "
                             "frames")
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
    if config.warp == "centroid":
        turns = {j: _track_turns(frames, labels, mem, config.min_rotation_inliers) if config.rotation and len(mem) > 1
                 else (np.zeros(len(mem)), np.ones(len(mem))) for j, mem in members.items()}
    elif config.warp in ("similarity", "homography"):
        warps = {j: _track_warps(frames, labels, mem, config.warp, config.min_rotation_inliers)
                 for j, mem in members.items() if len(mem) > 1}
    # Each seed's track (-1: in no component, or in a track of one frame) and its place in the track.
    seed_track = np.full(Nd, -1)
    seed_here = np.zeros(Nd, dtype=np.int64)
    for i in range(Nd):
        k, px = int(seed_frames[i]), seed_pixels[i]
        comp = labels[k][min(max(int(px[1]), 0), frames[k].height - 1), min(max(int(px[0]), 0), frames[k].width - 1)]
        if comp >= 0 and len(members[int(track_ids[k][comp])]) > 1:
            seed_track[i] = int(track_ids[k][comp])
            seed_here[i] = [m for m, _, _ in members[seed_track[i]]].index(k)
    if config.warp == "flow":  # every seed of a track carried at once
        flow_pix = {}
        for j in np.unique(seed_track[seed_track >= 0]):
            sel = np.flatnonzero(seed_track == j)
            pos = _track_flow_pixels(frames, labels, members[int(j)], seed_here[sel], seed_pixels[sel],
                                     config.min_rotation_inliers)
            for n, i in enumerate(sel):
                flow_pix[int(i)] = pos[n]

    times = np.array([f.time for f in frames])
    basis = np.stack([np.concatenate([[1.0], deform_basis(t, deform_config)[0]]) for t in times])  # (N, 1 + K)
    tracked = 0
    paths = {}  # seed -> (its track's frames, its 3D targets there)
    for i in np.flatnonzero(seed_track >= 0):
        k, px, j, here = int(seed_frames[i]), seed_pixels[i], int(seed_track[i]), int(seed_here[i])
        mem = members[j]
        fidx = np.array([m for m, _, _ in mem])
        if config.warp == "centroid":
            ang, sc = turns[j]
            da, ds = ang - ang[here], sc / sc[here]
            offset = px - mem[here][1]
            pix = np.stack([cent for _, cent, _ in mem]) + ds[:, None] * np.stack(
                [np.cos(da) * offset[0] - np.sin(da) * offset[1], np.sin(da) * offset[0] + np.cos(da) * offset[1]],
                axis=1)
        elif config.warp == "flow":
            pix = flow_pix[i]
        else:
            pix, ok = warp_pixel(warps[j] @ np.linalg.inv(warps[j][here]), px)  # seed frame -> the track's
            if ok.sum() < 2:
                continue
            fidx, pix = fidx[ok], pix[ok]
        pc = (frames[k].cam_T_world[:3, :3] @ seed_points[i]) + frames[k].cam_T_world[:3, 3]
        depth = np.array([float(pc[2])])
        targets = np.stack([unproject_points(pix[n][None], depth, frames[m].cam_T_world, frames[m].K)[0]
                            for n, m in enumerate(fidx)])  # (M, 3)
        paths[int(i)] = (fidx, targets, pix)
        tracked += 1
    info = {"num_tracks": num_tracks, "num_tracked_seeds": tracked}
    clustered = {}
    if config.rigid:
        chain = None
        if config.rigid_fit in ("pairs", "bundle"):
            chain = dict(frames=frames, labels=labels, members=members, depth_maps=depth_maps,
                         min_inliers=config.min_rotation_inliers,
                         bundle=config if config.rigid_fit == "bundle" else None)
        clustered = _rigid_clusters(paths, seed_track, seed_frames, seed_points, basis, config.ridge,
                                    frames if config.rigid_fit == "pnp" else None, chain)
        if chain is not None:
            info["rigid_pairs_missed"] = int(sum(cl["missed"] for cl in clustered.values()))
            info["rigid_pairs"] = int(sum(cl["pairs"] for cl in clustered.values()))
            if config.rigid_fit == "bundle":
                info["rigid_bundles"] = [cl["bundle"] for _, cl in sorted(clustered.items())]
        info["rigid"] = _rigid_blocks(clustered, Nd, K)
        info["num_clusters"] = len(clustered)
    for i, (fidx, targets, _) in paths.items():
        if int(seed_track[i]) in clustered:
            means[i] = info["rigid"]["local"][i]
            continue
        sol = _ridge_fit(basis[fidx], targets, config.ridge)  # (1 + K, 3)
        means[i] = sol[0]
        coefs[i] = sol[1:]
    return means, coefs, info


def _ridge_fit(A, targets, ridge):
    """Base value and coefficients (1 + K, D) of the deformation through ``targets`` (M, D) at the
    basis rows A (M, 1 + K): ridge-regularised least squares, the base value not shrunk (step 5)."""
    reg = ridge * len(A) * np.eye(A.shape[1])
    reg[0, 0] = 0.0
    return np.linalg.solve(A.T @ A + reg, A.T @ targets)


def _rigid_clusters(paths, seed_track, seed_frames, seed_points, basis, ridge, frames=None, chain=None):
    """One rigid path per track with at least ``RIGID_MIN_SEEDS`` seeds (``MotionInitConfig.rigid``).

    The track's seeds at its middle frame are the object's shape (centred on their centroid);
    its pose at each frame is the rotation and translation (Kabsch, no scale) taking that shape to
    the seeds' targets there. With ``frames`` (``rigid_fit = "pnp"``) that pose is then refined so the
    shape projects onto the seeds' tracked pixels (``_pnp_pose``): the targets are lifted at each
    seed's own depth, which no rigid shape meets while the object turns or changes depth, and the
    pixels are what was seen. The poses are fitted by the deformation's basis (position; the raw
    quaternion, signs made continuous). Each seed's local position is its own lifted point pulled
    back by the fitted pose at its own frame, so the seed starts where it was seen. With ``chain``
    (``rigid_fit = "pairs"``: the frames, component labels, track members, depth maps and the
    similarity's inlier count; ``bundle``: the MotionInitConfig of ``rigid_fit = "bundle"`` or None)
    the poses are ``_chained_poses`` over the track's members instead, from the shape's centroid at
    the middle frame, and with ``bundle`` refined by ``bundle_track``.
    Returns {track: dict(seeds, p (1 + K, 3), q (1 + K, 4), local (S, 3)[, missed, pairs[, bundle]])}.
    """
    from d2gs_np.geometry.quaternion import quat_to_rotmat, rotmat_to_quat
    from d2gs_np.geometry.trajectory import umeyama

    out = {}
    for j in np.unique(seed_track[seed_track >= 0]):
        seeds = [i for i in np.flatnonzero(seed_track == j) if int(i) in paths]
        if len(seeds) < RIGID_MIN_SEEDS:
            continue
        frames_j = sorted({int(m) for i in seeds for m in paths[int(i)][0]})
        at = {int(i): dict(zip((int(m) for m in paths[int(i)][0]), paths[int(i)][1])) for i in seeds}
        px = {int(i): dict(zip((int(m) for m in paths[int(i)][0]), paths[int(i)][2])) for i in seeds}
        ref = frames_j[len(frames_j) // 2]
        shape_seeds = [i for i in seeds if ref in at[int(i)]]
        own = [i for i in shape_seeds if int(seed_frames[i]) == ref]
        if frames is not None and len(own) >= RIGID_SHAPE_SEEDS:
            shape_seeds = own  # lifted at the reference frame's own depths: one consistent shape
        if len(shape_seeds) < RIGID_MIN_SEEDS:
            continue
        X = np.stack([at[int(i)][ref] for i in shape_seeds])
        centre = X.mean(axis=0)
        X = X - centre
        fit_frames, pos, quat = [], [], []
        extra = {}
        if chain is not None:
            own = [i for i in seeds if int(seed_frames[i]) == ref]  # lifted at the reference frame's own depth
            if own:
                centre = np.mean([seed_points[i] for i in own], axis=0)
            mem = chain["members"][int(j)]
            chained, missed = _chained_poses(chain["frames"], chain["labels"], mem, chain["depth_maps"], ref,
                                             centre, chain["min_inliers"])
            extra = dict(missed=missed, pairs=len(mem) - 1)
            if chain.get("bundle") is not None:
                b = chain["bundle"]
                chained, extra["bundle"] = bundle_track(chain["frames"], chain["labels"], mem, chain["depth_maps"],
                                                        ref, chained, b.bundle_window, b.bundle_depth_sigma,
                                                        b.bundle_accel_deg, chain["min_inliers"])
            for m in sorted(chained):
                q = rotmat_to_quat(chained[m][0])
                if quat and float(q @ quat[-1]) < 0.0:
                    q = -q
                fit_frames.append(m)
                pos.append(chained[m][1])
                quat.append(q)
        for m in (frames_j if chain is None else ()):
            have = [n for n, i in enumerate(shape_seeds) if m in at[int(i)]]
            if len(have) < RIGID_MIN_SEEDS:
                continue
            Y = np.stack([at[int(shape_seeds[n])][m] for n in have])
            try:
                _, R, t = umeyama(X[have], Y, with_scale=False)
            except ValueError:  # the seeds there all at one place
                continue
            if frames is not None:
                uv = np.stack([px[int(shape_seeds[n])][m] for n in have])
                R, t = _pnp_pose(X[have], uv, frames[m], R, t)
            q = rotmat_to_quat(R)
            if quat and float(q @ quat[-1]) < 0.0:
                q = -q  # continuous signs, so the raw quaternion's fit follows the turn
            fit_frames.append(m)
            pos.append(t)
            quat.append(q)
        if len(fit_frames) < 2:
            continue
        A = basis[fit_frames]
        p, q = _ridge_fit(A, np.stack(pos), ridge), _ridge_fit(A, np.stack(quat), ridge)
        local = []
        for i in seeds:
            k = int(seed_frames[i])
            pk, rk = basis[k] @ p, basis[k] @ q
            R = quat_to_rotmat(rk)
            local.append(R.T @ (np.asarray(seed_points[i], np.float64) - pk))
        out[int(j)] = dict(seeds=np.asarray(seeds), p=p, q=q, local=np.stack(local), **extra)
    return out


def _pnp_pose(X, uv, frame, R, t):
    """The object pose (R, t), object -> world, that projects the shape X (S, 3) onto the pixels uv
    (S, 2) in ``frame`` best: OpenCV's iterative PnP from the given pose, on the RANSAC inliers
    (2 px) when at least RIGID_MIN_SEEDS support it; the given pose where PnP fails."""
    T = np.asarray(frame.cam_T_world, np.float64)
    Rc, tc = T[:3, :3] @ R, T[:3, :3] @ t + T[:3, 3]  # object -> camera
    if len(X) < 6 or not np.all(np.isfinite(uv)):
        return R, t
    rvec, _ = cv2.Rodrigues(Rc)
    obj, img = X.astype(np.float64), uv.astype(np.float64)  # the pixel convention cancels: same K both ways
    Kc = np.asarray(frame.K, np.float64)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, Kc, None, rvec.copy(), tc.reshape(3, 1).copy(),
                                             useExtrinsicGuess=True, reprojectionError=2.0, iterationsCount=100,
                                             flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or inl is None or len(inl) < max(RIGID_MIN_SEEDS, 6):
        return R, t
    ok, rvec, tvec = cv2.solvePnP(obj[inl[:, 0]], img[inl[:, 0]], Kc, None, rvec, tvec, useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or not np.all(np.isfinite(tvec)) or float(tvec.ravel()[2]) <= 0.0:
        return R, t
    Rc = cv2.Rodrigues(rvec)[0]
    return T[:3, :3].T @ Rc, T[:3, :3].T @ (tvec.ravel() - T[:3, 3])


def _rigid_blocks(clustered, Nd, K):
    """The ``rigid.*`` blocks, the cluster ids (Nd,) and the clustered seeds' local positions."""
    C = len(clustered)
    blocks = {"rigid.means": np.zeros((C, 3)), "rigid.quats": np.tile([1.0, 0.0, 0.0, 0.0], (C, 1)),
              "rigid.deform_means": np.zeros((C, K, 3)), "rigid.deform_quats": np.zeros((C, K, 4))}
    ids = np.full(Nd, -1.0)
    local = {}
    for c, (j, cl) in enumerate(sorted(clustered.items())):
        blocks["rigid.means"][c], blocks["rigid.deform_means"][c] = cl["p"][0], cl["p"][1:]
        blocks["rigid.quats"][c], blocks["rigid.deform_quats"][c] = cl["q"][0], cl["q"][1:]
        ids[cl["seeds"]] = c
        local.update({int(i): x for i, x in zip(cl["seeds"], cl["local"])})
    return dict(blocks=blocks, cluster=ids, local=local)
