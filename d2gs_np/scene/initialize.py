"""Initial point clouds for the static and dynamic Gaussian sets (docs/method.md §8, §9).

Static points
1. SIFT features per frame on static pixels (motion masks dilated, ``d2gs_np.pose.features``),
   matched between frame pairs (k, k + s) for s in ``frame_skips`` (each clamped to N - 1).
   The defaults skip frames: triangulation needs parallax more than it needs easy matches.
2. Each verified match is triangulated with the GIVEN (estimated) mid-exposure poses:
   ``cv2.triangulatePoints`` with P = K [R | t] from ``cam_T_world``, in this project's
   continuous pixel coordinates (centres at +0.5; K is in the same convention, so the pair is
   consistent). Kept if: finite, positive depth in both views, reprojection error (max of the
   two views) <= ``max_reprojection_error_px``, and triangulation angle >= ``min_parallax_deg``.
   Colour: mean of the bilinearly sampled (blurry) image colours at the two observations.
   At most ``max_static_points`` are kept (a seeded random subset).
3. Dense seeding: on ``dense_frames`` evenly spaced keyframes, a pixel grid of stride
   ``dense_stride`` over the static pixels, each lifted at its depth and coloured by its pixel.
   The depth is the keyframe's plane-sweep stereo depth (``scene/stereo.py``: the frames at
   ``frame_skips`` on either side as sources, searched over the depth range of step 4) where
   that is trusted; elsewhere (untextured pixels) the inverse depth interpolated from the
   trusted stereo pixels, or, with stereo off or too few trusted pixels, from the
   triangulated points seen in that frame (linear over their Delaunay triangulation, nearest
   outside it; isolated outlier depths dropped first). Choice: a few hundred triangulated
   points leave photographic detail to be grown by densification, which a CPU budget of a few
   thousand steps cannot afford; seeded at its pixel and depth, detail starts at its place, as
   in depth-initialised 3DGS variants. The stereo depth, not the interpolation from the
   triangulated points, because the interpolated seeds sit in front of the surfaces
   (figures: docs/results.md §9).
4. Random fill: ``random_fill_points`` points, each on the ray through a random static pixel
   (uniform in the pixel) of a random frame, at the depth interpolated (as in step 3) from the
   triangulated and dense points that frame sees (``fill_on_surface``), else at a depth
   uniform in [near, far], where
   near / far = (1 -/+ ``fill_depth_margin``) times the robust range of the triangulated points'
   depths in their first view (``robust_depth_range``: the ``fill_depth_percentiles``, clipped
   to the median x exp(+-k sigma), sigma = 1.4826 x the MAD of log depth, k =
   ``depth_range_mad``; a band of factor 1.2 around them when all depths are one). The same
   range bounds the plane sweep of step 3. Colour: the image colour at that pixel.
   Untextured regions thereby get Gaussians; wrong ones fade or are pruned during training.
   If nothing could be triangulated, near / far fall back to ``fallback_depth_range`` times
   ``scene.scene_scale`` (an error if the scene has no scale); so do they when fewer than
   ``min_range_points`` points were triangulated and their median depth lies outside that range
   (``few_points_disagree``): the points are then dropped.

Why the stereo was nearly empty on the suite's cube_sign, and the fix (docs/method.md §8; the
figures: docs/results.md §9, measured by ``python examples/init_diagnostics.py SCENE...``):
(a) the sweep's distinctness check compared the best cost with hypotheses two steps away, a
fraction of a source pixel on cube_sign, inside the minimum's own basin on blurred frames, and
rejected most pixels; with ``StereoConfig.distinct_px = 1`` it looks 1 source pixel away.
(b) With noisy poses two-view points far in front of the true depth stretch the sweep;
``depth_range_mad = 3`` clips the range to the median x exp(+-3 sigma) of the log depths
(``robust_depth_range``). Where the poses themselves are off, the seeds' depths stay wrong
whatever the checks. Both fixes are off by default (``distinct_px = 0``, ``depth_range_mad = 0``:
the earlier rules, exactly; why: docs/method.md §8).

Sparse points given with the scene (``Scene.points3d``, the optional ``ply_file_path`` of
docs/dataset_format.md §4, written by ``d2gs import-video``) replace steps 1-2's triangulation:
no features are matched, each point counts as triangulated in the first frame that sees it.
Without them nothing changes.

Returned static points are ordered: triangulated, dense, fill (``info["num_static_triangulated"]``,
``info["num_static_dense"]``, ``info["num_static_fill"]`` of each).

Dynamic points (only if some frame has a motion mask with a True pixel; otherwise None, §9)
- ``dynamic_points`` pixels drawn uniformly from all masked pixels of all frames (a uniform
  position inside each drawn pixel), colour from that frame's image.
- Depth: ``dynamic_depth_factor`` (< 1) times the median depth of the triangulated static
  points that project into that frame (the whole set's median if none does), times a
  uniform jitter in [1 - j, 1 + j] with j = ``dynamic_depth_jitter``; with ``dynamic_depth =
  "scene"`` the scene's own depth map at the seed's pixel instead (where finite), times the
  jitter (measured depth; on a synthetic scene the truth, an oracle); with ``"prior"`` the
  scene's depth priors (a depth network's estimate) aligned to the bundle adjustment's points
  when the run has them, else to the measured static points (``scene/depth_prior.py``), where a
  frame's alignment succeeds. Choice: movers are usually
  in front of the background they occlude, and a per-frame static depth is the only depth
  evidence available before training; the jitter gives the set some thickness. The
  deformation model moves these points over time, so their exact placement matters less.

``static_depth = "scene"`` lifts the dense seeds and the fill at the scene's own depth maps
(measured depth; on a synthetic scene the truth: an oracle of the static geometry) instead of
the stereo and the interpolation; the triangulated points stay as measured. ``"prior"`` lifts
them at the scene's depth priors aligned as the dynamic seeds' are (to the bundle adjustment's
points when the run has them, else to the triangulated ones), where a frame's alignment succeeds;
``"stereo_prior"`` keeps the sweep's own depth where it agrees with that prior within
``stereo_prior_tolerance`` and takes the prior elsewhere (a sweep on blurred, sparse texture fails
in places; a depth network's estimate is smooth and roughly right everywhere); with
``stereo_prior_scope = "all"`` the depths interpolated between trusted stereo pixels and the
fill's depth on the seeds' surface stand where they agree with the prior too (a plane the sweep
measured at its edges is better than a prior with a per-frame error).

``info`` (for the run log) holds counts, reprojection statistics and the depth range, plus
per-point provenance arrays (``static_source_frames``, ``dynamic_source_frames``,
``dynamic_source_pixels``).
"""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from d2gs_np.constants import MAD_TO_SIGMA, ONE_DEPTH_RANGE_FACTOR, PIXEL_CENTER_OFFSET
from d2gs_np.pose.features import detect_features, match_keypoints, static_detector_mask
from d2gs_np.geometry.camera import camera_center, check_intrinsics, project_points, unproject_points
from d2gs_np.geometry.se3 import check_rigid
from d2gs_np.scene.config import InitConfig
from d2gs_np.scene.depth_prior import align_depth_prior, align_depth_scale, fuse_depth_maps
from d2gs_np.scene.stereo import plane_sweep_depth

__all__ = ["initialize_points", "triangulate_matches", "depth_from_trusted", "sample_image_bilinear", "pixel_scale_cap",
           "robust_depth_range", "few_points_disagree"]

# Homogeneous triangulation results with |w| below this (relative to the largest coordinate)
# are points at infinity: dividing by w would give meaningless, huge positions.
_W_MIN_REL = 1e-12


def sample_image_bilinear(image, pts):
    """Bilinear samples of image (H, W, C) at continuous pixel coords pts (M, 2) -> (M, C).

    Our convention: pixel (i, j) has its centre at (j + 0.5, i + 0.5); samples beyond the
    outermost centres take the border value (clamped).
    """
    image = np.asarray(image, dtype=np.float64)
    H, W = image.shape[:2]
    x = np.clip(pts[:, 0] - PIXEL_CENTER_OFFSET, 0.0, W - 1.0)
    y = np.clip(pts[:, 1] - PIXEL_CENTER_OFFSET, 0.0, H - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2) if W > 1 else np.zeros(len(x), dtype=np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2) if H > 1 else np.zeros(len(y), dtype=np.int64)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def triangulate_matches(pts0, pts1, cam_T_world0, cam_T_world1, K0, K1):
    """Linear (DLT) triangulation of correspondences with known poses.

    pts0, pts1 (M, 2): pixel coords in our convention. cam_T_world0/1 (4, 4), K0/K1 (3, 3).
    Returns (points (M, 3) world, depth0 (M,), depth1 (M,), reproj_err (M,) = max over the two
    views in pixels, parallax_deg (M,), finite (M,) bool). Rows with finite False (points at
    infinity) have NaN entries.
    """
    pts0 = np.asarray(pts0, dtype=np.float64)
    pts1 = np.asarray(pts1, dtype=np.float64)
    if pts0.ndim != 2 or pts0.shape[1] != 2 or pts1.shape != pts0.shape:
        raise ValueError(f"pts0 and pts1 must both have shape (M, 2); got {pts0.shape} and {pts1.shape}")
    M = pts0.shape[0]
    if M == 0:
        z = np.zeros(0)
        return np.zeros((0, 3)), z, z.copy(), z.copy(), z.copy(), np.zeros(0, dtype=bool)
    P0 = K0 @ np.asarray(cam_T_world0, dtype=np.float64)[:3, :]
    P1 = K1 @ np.asarray(cam_T_world1, dtype=np.float64)[:3, :]
    Xh = cv2.triangulatePoints(P0, P1, np.ascontiguousarray(pts0.T), np.ascontiguousarray(pts1.T)).T  # (M, 4)
    scale = np.abs(Xh).max(axis=1)
    finite = np.abs(Xh[:, 3]) > _W_MIN_REL * scale
    X = np.full((M, 3), np.nan)
    X[finite] = Xh[finite, :3] / Xh[finite, 3:4]
    uv0, z0 = project_points(np.nan_to_num(X), cam_T_world0, K0)
    uv1, z1 = project_points(np.nan_to_num(X), cam_T_world1, K1)
    err = np.maximum(np.linalg.norm(uv0 - pts0, axis=1), np.linalg.norm(uv1 - pts1, axis=1))
    r0 = X - camera_center(cam_T_world0)
    r1 = X - camera_center(cam_T_world1)
    den = np.linalg.norm(r0, axis=1) * np.linalg.norm(r1, axis=1)  # 0 only for X at a camera centre
    cosang = np.divide(np.sum(r0 * r1, axis=1), den, out=np.ones(M), where=den > 0)  # then parallax 0
    parallax = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
    for a in (z0, z1, err, parallax):
        a[~finite] = np.nan
    return X, z0, z1, err, parallax, finite


def few_points_disagree(depths, scene_scale, config) -> str:
    """Why the triangulated points (their depths (M,)) are to be dropped, or "" to keep them: fewer
    than ``min_range_points`` whose median depth lies outside ``fallback_depth_range`` x
    ``scene_scale`` (kept when there are none, enough, or no scale to check against)."""
    z = np.asarray(depths, dtype=np.float64)
    if z.size == 0 or z.size >= config.min_range_points or scene_scale is None:
        return ""
    lo, hi = (v * float(scene_scale) for v in config.fallback_depth_range)
    med = float(np.median(z))
    if lo <= med <= hi:
        return ""
    return (f"{z.size} triangulated point(s) at median depth {med:.3g}, outside the scene scale's range "
            f"[{lo:.3g}, {hi:.3g}]: dropped (InitConfig.min_range_points = {config.min_range_points})")


def robust_depth_range(depths, config):
    """(lo, hi, source note) of the depths (M,) (non-finite and non-positive ones ignored; at least
    one must remain): the ``fill_depth_percentiles``, clipped to median x exp(+-k sigma) with
    sigma = 1.4826 MAD of log depth and k = ``depth_range_mad``, so that outlying triangulations
    cannot stretch the range; all at one depth d: [d / f, f d], f = ONE_DEPTH_RANGE_FACTOR."""
    z = np.asarray(depths, dtype=np.float64)
    z = z[np.isfinite(z) & (z > 0)]
    if z.size == 0:
        raise ValueError("robust_depth_range: depths must hold at least one finite positive depth; got none")
    med = float(np.median(z))
    lo, hi = (float(v) for v in np.percentile(z, config.fill_depth_percentiles))
    note = "triangulated (percentiles)"
    if config.depth_range_mad > 0:
        sigma = MAD_TO_SIGMA * float(np.median(np.abs(np.log(z) - np.log(med))))
        band_lo, band_hi = med * np.exp(-config.depth_range_mad * sigma), med * np.exp(config.depth_range_mad * sigma)
        if lo < band_lo or hi > band_hi:
            note = "triangulated (percentiles clipped to the median +- k MAD band)"
        lo, hi = max(lo, band_lo), min(hi, band_hi)
    if not lo < hi:  # one depth (one point, or MAD 0): a band around it
        lo, hi = med / ONE_DEPTH_RANGE_FACTOR, med * ONE_DEPTH_RANGE_FACTOR
        note = f"triangulated (one depth: median / {ONE_DEPTH_RANGE_FACTOR:g} .. median x {ONE_DEPTH_RANGE_FACTOR:g})"
    return lo, hi, note


def _check_scene(scene):
    frames = getattr(scene, "frames", None)
    if not isinstance(frames, list) or len(frames) == 0:
        raise ValueError("scene must have a non-empty list of frames")
    for k, f in enumerate(frames):
        if f.image is None:
            raise ValueError(f"scene.frames[{k}].image is None; load the scene with images")
        if f.image.shape != (f.height, f.width, 3):
            raise ValueError(f"scene.frames[{k}].image must have shape ({f.height}, {f.width}, 3); got {f.image.shape}")
        check_rigid(f.cam_T_world, f"scene.frames[{k}].cam_T_world")
        check_intrinsics(f.K, f"scene.frames[{k}].K")
        if f.mask is not None and f.mask.shape != (f.height, f.width):
            raise ValueError(f"scene.frames[{k}].mask must have shape ({f.height}, {f.width}); got {f.mask.shape}")


def interpolate_inverse_depth(uv, z, query, outlier_rel=0.15, neighbours=8):
    """Depth at pixels ``query`` (Q, 2) interpolated from sparse depths z (M,) at pixels uv (M, 2).

    Inverse depth is interpolated linearly over a Delaunay triangulation of uv (exact on a plane
    seen in perspective, where 1/z is affine in the pixel coordinates) and by the nearest sparse
    point outside their convex hull. Before that, a sparse depth that differs by more than
    ``outlier_rel`` (relative) from the median of its ``neighbours`` nearest points is dropped
    (a mismatched triangulation). Returns (depth (Q,), kept (M,) bool); all NaN with fewer than
    three usable points or points on one line.
    """
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
    from scipy.spatial import QhullError, cKDTree

    uv = np.asarray(uv, dtype=np.float64)
    inv = 1.0 / np.asarray(z, dtype=np.float64)
    kept = np.isfinite(inv) & (inv > 0)
    if kept.sum() > neighbours:
        idx = np.flatnonzero(kept)
        _, nn = cKDTree(uv[idx]).query(uv[idx], k=neighbours + 1)
        med = np.median(inv[idx][nn[:, 1:]], axis=1)
        kept[idx] = np.abs(inv[idx] / med - 1.0) <= outlier_rel
    out = np.full(len(query), np.nan)
    if kept.sum() < 3:
        return out, kept
    try:
        lin = LinearNDInterpolator(uv[kept], inv[kept])(query)
    except QhullError:  # collinear or coincident points: no triangulation
        return out, kept
    near = NearestNDInterpolator(uv[kept], inv[kept])(query)
    inv_q = np.where(np.isfinite(lin), lin, near)
    with np.errstate(divide="ignore"):
        out = np.where(inv_q > 0, 1.0 / inv_q, np.nan)
    return out, kept


def depth_from_trusted(dmap, query, outlier_rel, max_anchors=4000):
    """Depth (Q,) at pixels ``query`` (Q, 2) interpolated (``interpolate_inverse_depth``) from the
    finite pixels of ``dmap`` (H, W), at most ``max_anchors`` of them evenly spread (the anchors of
    the untextured pixels); None with fewer than 16 finite pixels."""
    trusted = np.argwhere(np.isfinite(dmap))
    if len(trusted) < 16:
        return None
    anc = trusted[::max(1, len(trusted) // max_anchors)]
    anc_uv = np.stack([anc[:, 1] + PIXEL_CENTER_OFFSET, anc[:, 0] + PIXEL_CENTER_OFFSET], axis=1)
    return interpolate_inverse_depth(anc_uv, dmap[anc[:, 0], anc[:, 1]], query, outlier_rel)[0]


def depth_from_points(points, frame, query, outlier_rel, max_points=None):
    """Depth (Q,) at pixels ``query`` (Q, 2) of ``frame``, interpolated (``interpolate_inverse_depth``)
    from the ``points`` (M, 3) it sees in front of it and inside the image; at most ``max_points``
    of them, evenly spread over the list (None: all). NaN where there are fewer than three."""
    if points.shape[0] < 3:
        return np.full(len(query), np.nan)
    uv, z = project_points(points, frame.cam_T_world, frame.K)
    vis = np.flatnonzero((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < frame.width) & (uv[:, 1] >= 0)
                         & (uv[:, 1] < frame.height))
    if max_points is not None:
        vis = vis[::max(1, len(vis) // max_points)]
    return interpolate_inverse_depth(uv[vis], z[vis], query, outlier_rel)[0]


def _agrees(depth, prior, tolerance):
    """Where ``depth`` is within ``tolerance`` (relative) of ``prior``; False where either is missing."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.abs(depth / prior - 1.0) <= tolerance


def dense_seed(frames, keyframes, ref_points, stride, outlier_rel, dilation_px, stereo=None, depth_range=None,
               skips=(2, 4, 8), depth_maps=None, prior_maps=None, prior_tolerance=None, prior_scope="measured",
               prior_cost_ratio=0.0):
    """Pixel-grid points of each keyframe's static pixels at their stereo depth, else at depths
    interpolated from trusted stereo pixels or from ref_points (module docstring, step 3).

    Keyframe number i uses grid offset (i mod stride) in both axes, so keyframes sample
    different pixels. ``stereo``: a StereoConfig (None or disabled: interpolation from
    ref_points only); ``depth_range``: (near, far) of the sweep; ``skips``: source frames k +- s;
    ``depth_maps``: per-frame (H, W) depths (``InitConfig.static_depth = "scene"``) that replace the
    stereo where finite and > 0; ``prior_maps``: per-frame (H, W) aligned depth priors (or None per
    frame) that replace every depth but the stereo's own within ``prior_tolerance`` (relative) of
    them (``static_depth = "stereo_prior"``; None: everywhere, ``"prior"``); ``prior_scope``
    "all": the interpolated depths within the tolerance stand too (``InitConfig.stereo_prior_scope``);
    ``prior_cost_ratio`` > 0: the sweep's own depth stands also where its cost is at most that
    fraction of the cost at the prior's depth (``InitConfig.stereo_prior_cost_ratio``).
    Returns (points (P, 3), colours (P, 3), source frames (P,), info dict); info["measured"] (P,)
    is True for the points at a stereo depth of their own pixel (not interpolated).
    """
    pts, cols, src, measured = [], [], [], []
    info = {"stereo_kept_share": [], "stereo_seeds": 0, "stereo_kept_over_prior": 0}
    use_stereo = (stereo is not None and stereo.enabled and depth_range is not None and len(frames) > 1
                  and depth_maps is None and not (prior_maps is not None and prior_tolerance is None))
    for i, k in enumerate(keyframes):
        f = frames[k]
        off = i % stride
        rows, cols_ = np.meshgrid(np.arange(off, f.height, stride), np.arange(off, f.width, stride), indexing="ij")
        rows, cols_ = rows.ravel(), cols_.ravel()
        static = None
        if f.mask is not None:
            static = static_detector_mask(f.mask, dilation_px) > 0
            keep = static[rows, cols_]
            rows, cols_ = rows[keep], cols_[keep]
        pix = np.stack([cols_ + PIXEL_CENTER_OFFSET, rows + PIXEL_CENTER_OFFSET], axis=1).astype(np.float64)
        depth = np.full(len(pix), np.nan)
        own = np.zeros(len(pix), dtype=bool)
        sinfo = {}
        if use_stereo:
            N = len(frames)
            others = sorted({min(max(k + d * sgn, 0), N - 1) for d in skips for sgn in (-1, 1)} - {k})
            sources = [(frames[j].image, frames[j].cam_T_world, frames[j].K, frames[j].mask) for j in others]
            weigh = (prior_tolerance is not None and prior_cost_ratio > 0 and prior_maps is not None
                     and prior_maps[k] is not None)
            dmap, sinfo = plane_sweep_depth(f.image, f.cam_T_world, f.K, sources, depth_range[0], depth_range[1],
                                            stereo, None if static is None else ~static,
                                            prior_maps[k] if weigh else None)
            info["stereo_kept_share"].append(sinfo["kept_share"])
            depth = dmap[rows, cols_]
            own = np.isfinite(depth)
            info["stereo_seeds"] += int(own.sum())
            miss = ~np.isfinite(depth)
            if miss.any():
                filled = depth_from_trusted(dmap, pix[miss], outlier_rel)
                if filled is not None:
                    depth[miss] = filled
        if depth_maps is not None and depth_maps[k] is not None:
            given = depth_maps[k][rows, cols_]
            use = np.isfinite(given) & (given > 0)
            depth[use], own[use] = given[use], True
        if prior_maps is not None and prior_maps[k] is not None:
            prior = prior_maps[k][rows, cols_]
            use = np.isfinite(prior) & (prior > 0)
            if prior_tolerance is not None:  # the sweep's own (or any stereo) depth stands where it agrees
                agree = _agrees(depth, prior, prior_tolerance)
                use &= ~(agree & (own if prior_scope == "measured" else np.isfinite(depth)))
                if "cost_over_prior" in sinfo:  # ... or where the images prefer the sweep's depth
                    with np.errstate(invalid="ignore"):
                        better = own & ~agree & (sinfo["cost_over_prior"][rows, cols_] <= prior_cost_ratio)
                    info["stereo_kept_over_prior"] += int((better & use).sum())
                    use &= ~better
            depth[use], own[use] = prior[use], False
        if not np.all(np.isfinite(depth)):
            miss = ~np.isfinite(depth)
            depth[miss] = depth_from_points(ref_points, f, pix[miss], outlier_rel)
        ok = np.isfinite(depth) & (depth > 0)
        if not np.any(ok):
            continue
        pts.append(unproject_points(pix[ok], depth[ok], f.cam_T_world, f.K))
        cols.append(f.image[rows[ok], cols_[ok]])
        src.append(np.full(int(ok.sum()), k, dtype=np.int64))
        measured.append(own[ok])
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64), {**info, "measured": np.zeros(0, bool)}
    return np.concatenate(pts), np.concatenate(cols), np.concatenate(src), {**info, "measured": np.concatenate(measured)}


def _random_pixels(rng, frames, pools, n):
    """n draws of (frame index, continuous pixel) uniformly over the pixels listed in ``pools``.

    pools[k]: flat pixel indices (row-major) available in frame k.
    """
    sizes = np.array([len(p) for p in pools], dtype=np.int64)
    all_flat = np.concatenate([np.asarray(p, dtype=np.int64) for p in pools])
    all_frame = np.repeat(np.arange(len(pools)), sizes)
    draw = rng.integers(0, all_flat.size, n)
    frame_idx, flat = all_frame[draw], all_flat[draw]
    widths = np.array([f.width for f in frames], dtype=np.int64)[frame_idx]
    rows, cols = np.divmod(flat, widths)
    pix = np.stack([cols + rng.random(n), rows + rng.random(n)], axis=1)  # uniform inside the pixel
    return frame_idx, pix


def _scene_points(scene):
    """The scene's sparse points (``Scene.points3d``, docs/dataset_format.md §4) in the layout of the
    triangulated ones: (points, colours, source frame, depth there, reprojection error (NaN: unknown)).
    A point's source frame is the first frame that sees it in front of the camera and inside the
    image; points no frame sees are dropped."""
    pts = np.asarray(scene.points3d, dtype=np.float64)
    cols = np.full_like(pts, 0.5) if scene.points3d_colors is None else np.asarray(scene.points3d_colors, np.float64)
    src = np.full(len(pts), -1, dtype=np.int64)
    depth = np.full(len(pts), np.nan)
    for k, f in enumerate(scene.frames):
        uv, z = project_points(pts, f.cam_T_world, f.K)
        vis = (src < 0) & (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < f.width) & (uv[:, 1] >= 0) & (uv[:, 1] < f.height)
        src[vis], depth[vis] = k, z[vis]
    keep = src >= 0
    return pts[keep], cols[keep], src[keep], depth[keep], np.full(int(keep.sum()), np.nan)


def _at_pixels(maps, src, pix):
    """Values of per-frame maps (a list of (H, W) arrays or None) at each seed's pixel (the pixel
    that holds it); NaN where its frame's map is None."""
    out = np.full(len(src), np.nan)
    for i, (k, p) in enumerate(zip(src, pix)):
        m = maps[k]
        if m is not None:
            out[i] = m[min(max(int(p[1]), 0), m.shape[0] - 1), min(max(int(p[0]), 0), m.shape[1] - 1)]
    return out


def _aligned_priors(frames, static_pts, which, config: InitConfig, dilation_px):
    """Depth maps from the frames' priors (scene/depth_prior.py), for the frames in ``which``
    (None elsewhere and where a frame cannot be aligned), aligned to ``static_pts`` seen off
    each frame's dilated motion mask; and a summary for the run log."""
    uvs, zs = [], []
    for k in which:
        f = frames[int(k)]
        uv, z = project_points(static_pts, f.cam_T_world, f.K) if len(static_pts) else (np.zeros((0, 2)), np.zeros(0))
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < f.width) & (uv[:, 1] >= 0) & (uv[:, 1] < f.height)
        if f.mask is not None and inside.any():
            allowed = static_detector_mask(f.mask, dilation_px) > 0
            r = np.clip(np.floor(uv[inside, 1]).astype(np.int64), 0, f.height - 1)
            c = np.clip(np.floor(uv[inside, 0]).astype(np.int64), 0, f.width - 1)
            inside[np.flatnonzero(inside)] = allowed[r, c]
        uvs.append(uv[inside])
        zs.append(z[inside])
    maps = [None] * len(frames)
    reasons, errs, scale = {}, [], None
    if config.depth_prior_space == "depth":  # one scale for the clip
        scale, info = align_depth_scale([frames[int(k)].depth_prior for k in which], uvs, zs,
                                        config.depth_prior_min_points)
        if scale is None:
            reasons = {int(k): info["reason"] for k in which}
        else:
            errs.append(info["rel_error"])
            for k in which:
                maps[int(k)] = scale * frames[int(k)].depth_prior
    else:  # a scale and shift per frame
        for k, uv, z in zip(which, uvs, zs):
            maps[int(k)], info = align_depth_prior(frames[int(k)].depth_prior, uv, z, config.depth_prior_space,
                                                   config.depth_prior_min_points)
            if maps[int(k)] is None:
                reasons[int(k)] = info["reason"]
            else:
                errs.append(info["rel_error"])
    summary = {"frames": len(which), "aligned": len(which) - len(reasons), "failed": reasons,
               "median_rel_error": float(np.median(errs)) if errs else float("nan"),
               "scale": None if scale is None else float(scale)}  # the clip's scale ("depth" space)
    return maps, summary


def resolve_depth_sources(config: InitConfig, scene) -> InitConfig:
    """``config`` with "auto" depth sources decided by the scene: the depth priors for the static
    ("stereo_prior") and the dynamic ("prior") seeds when every training frame has one, else the
    sweep ("stereo") and the static-median rule."""
    has = bool(scene.has_depth_prior)
    changes = {}
    if config.static_depth == "auto":
        changes["static_depth"] = "stereo_prior" if has else "stereo"
    if config.dynamic_depth == "auto":
        changes["dynamic_depth"] = "prior" if has else "static_median"
    return dataclasses.replace(config, **changes) if changes else config


def initialize_points(scene, config: InitConfig = None, rng=None, anchor_points=None):
    """Initial static and dynamic points of ``scene`` (see the module docstring).

    scene: d2gs_np.data.scene.Scene with images (and optional masks, True = dynamic).
    config: InitConfig. rng: np.random.Generator (subsampling, fill, dynamic seeding).
    anchor_points: optional (P, 3) static points known better than these (the bundle
    adjustment's, in the frames' poses): with ``depth_prior_min_points`` of them or more, the
    depth priors are aligned to them instead of the measured initial points.
    Returns (static_points (Ns, 3), static_colors (Ns, 3), dynamic_points (Nd, 3) or None,
    dynamic_colors (Nd, 3) or None, info dict). Colours are RGB in [0, 1], float64.
    """
    config = InitConfig() if config is None else config
    if not isinstance(config, InitConfig):
        raise TypeError(f"config must be an InitConfig; got {type(config).__name__}")
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a np.random.Generator (np.random.default_rng(seed)); got {type(rng).__name__}")
    _check_scene(scene)
    config = resolve_depth_sources(config, scene)
    if config.dynamic_depth == "scene" and not scene.has_depth:
        raise ValueError("InitConfig.dynamic_depth = 'scene' needs a depth map for every training frame "
                         "(depth_file_path, docs/dataset_format.md §3); this scene has none: use 'static_median'")
    if config.static_depth == "scene" and not scene.has_depth:
        raise ValueError("InitConfig.static_depth = 'scene' needs a depth map for every training frame "
                         "(depth_file_path, docs/dataset_format.md §3); this scene has none: use 'stereo'")
    if config.static_depth in ("prior", "stereo_prior") and not scene.has_depth_prior:
        raise ValueError(f"InitConfig.static_depth = {config.static_depth!r} needs a depth prior for every training "
                         "frame (depth_prior_file_path, docs/dataset_format.md §3); this scene lacks one: add them "
                         "or use 'stereo'")
    if config.dynamic_depth == "prior" and scene.has_moving_pixels and not scene.has_depth_prior:
        raise ValueError("InitConfig.dynamic_depth = 'prior' needs a depth prior for every training frame "
                         "(depth_prior_file_path, docs/dataset_format.md §3); this scene lacks one: add them "
                         "or use 'static_median'")
    frames = scene.frames
    N = len(frames)
    fc = config.features

    # ---- 1. features and matches on static pixels (or the scene's own sparse points, below)
    given = getattr(scene, "points3d", None) is not None and len(scene.points3d) > 0
    keypoints = [] if given else [detect_features(f.image, fc, f.mask) for f in frames]
    skips = sorted({min(s, N - 1) for s in config.frame_skips}) if N > 1 else []
    pairs = [] if given else [(k, k + s) for s in skips for k in range(N - s)]
    tri_pts, tri_cols, tri_src, tri_depth, tri_err = [], [], [], [], []
    num_matches = []
    for a, b in pairs:
        m = match_keypoints(keypoints[a], keypoints[b], fc)
        num_matches.append(m.num_inliers)
        if m.num_inliers == 0:
            continue
        fa, fb = frames[a], frames[b]
        X, z0, z1, err, parallax, finite = triangulate_matches(
            m.pts0, m.pts1, fa.cam_T_world, fb.cam_T_world, fa.K, fb.K)
        with np.errstate(invalid="ignore"):
            keep = (finite & (z0 > 0) & (z1 > 0) & (err <= config.max_reprojection_error_px)
                    & (parallax >= config.min_parallax_deg))
        if not np.any(keep):
            continue
        cols = 0.5 * (sample_image_bilinear(fa.image, m.pts0[keep]) + sample_image_bilinear(fb.image, m.pts1[keep]))
        tri_pts.append(X[keep])
        tri_cols.append(cols)
        tri_src.append(np.full(int(keep.sum()), a, dtype=np.int64))
        tri_depth.append(z0[keep])
        tri_err.append(err[keep])
    if tri_pts:
        tri_pts, tri_cols = np.concatenate(tri_pts), np.concatenate(tri_cols)
        tri_src, tri_depth, tri_err = np.concatenate(tri_src), np.concatenate(tri_depth), np.concatenate(tri_err)
    else:
        tri_pts, tri_cols = np.zeros((0, 3)), np.zeros((0, 3))
        tri_src, tri_depth, tri_err = np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
    if given:  # sparse points of the scene folder (e.g. from d2gs import-video) replace the triangulation
        tri_pts, tri_cols, tri_src, tri_depth, tri_err = _scene_points(scene)
    num_triangulated = tri_pts.shape[0]
    if num_triangulated > config.max_static_points:
        sel = np.sort(rng.choice(num_triangulated, config.max_static_points, replace=False))
        tri_pts, tri_cols, tri_src, tri_depth, tri_err = (
            a[sel] for a in (tri_pts, tri_cols, tri_src, tri_depth, tri_err))

    # ---- 2. depth range for the random fill
    dropped_note = few_points_disagree(tri_depth, scene.scene_scale, config)
    if dropped_note:
        tri_pts, tri_cols, tri_src, tri_depth, tri_err = (a[:0] for a in (tri_pts, tri_cols, tri_src, tri_depth, tri_err))
    if tri_depth.size > 0:
        p_lo, p_hi, depth_source = robust_depth_range(tri_depth, config)
        near, far = (1.0 - config.fill_depth_margin) * p_lo, (1.0 + config.fill_depth_margin) * p_hi
    elif scene.scene_scale is not None:
        near, far = (v * float(scene.scene_scale) for v in config.fallback_depth_range)
        depth_source = f"fallback ({dropped_note or 'nothing triangulated'})"
    else:
        raise ValueError(
            "no static point could be triangulated and the scene has no scene_scale to guess depths from; "
            "check the poses and images, lower InitConfig.features.contrast_threshold, or set scene.scene_scale"
        )

    # ---- 2b. the depth priors for the static seeds (static_depth = "prior" / "stereo_prior")
    # each frame's static pixels off the dilated motion mask (None: no mask, all static)
    static_allowed = [None if f.mask is None else static_detector_mask(f.mask, fc.mask_dilation_px) > 0
                      for f in frames]
    static_prior, static_prior_info = None, None
    if config.static_depth in ("prior", "stereo_prior"):
        if anchor_points is not None and len(anchor_points) >= config.depth_prior_min_points:
            reference, what = np.asarray(anchor_points, dtype=np.float64), "the bundle adjustment's points"
        else:
            reference, what = tri_pts, "the triangulated points"
        static_prior, static_prior_info = _aligned_priors(frames, reference, np.arange(N), config,
                                                          fc.mask_dilation_px)
        static_prior_info["reference"] = f"{what} ({len(reference)})"
        if config.depth_prior_fusion:  # each static pixel's depth from every frame that sees its point
            static_prior, static_prior_info["fusion"] = fuse_depth_maps(
                static_prior, [f.cam_T_world for f in frames], [f.K for f in frames], static_allowed,
                config.depth_prior_fusion_gate)

    # ---- 3. dense pixel-grid seeding at interpolated depths
    dense_pts, dense_cols = np.zeros((0, 3)), np.zeros((0, 3))
    dense_src = np.zeros(0, dtype=np.int64)
    dense_info = {"stereo_kept_share": [], "stereo_seeds": 0, "measured": np.zeros(0, dtype=bool)}
    if config.dense_frames > 0 and (tri_pts.shape[0] >= 3 or (config.stereo.enabled and N > 1)):
        keyframes = np.unique(np.round(np.linspace(0, N - 1, min(config.dense_frames, N))).astype(int))
        dense_pts, dense_cols, dense_src, dense_info = dense_seed(
            frames, keyframes, tri_pts, config.dense_stride, config.dense_outlier_rel, fc.mask_dilation_px,
            config.stereo, (near, far), config.frame_skips,
            [f.depth for f in frames] if config.static_depth == "scene" else None, static_prior,
            config.stereo_prior_tolerance if config.static_depth == "stereo_prior" else None,
            config.stereo_prior_scope, config.stereo_prior_cost_ratio)

    # ---- 4. random fill on static pixels
    static_pools = [np.arange(f.height * f.width) if a is None else np.flatnonzero(a.ravel())
                    for f, a in zip(frames, static_allowed)]
    n_fill = config.random_fill_points if sum(len(p) for p in static_pools) > 0 else 0
    fill_pts, fill_cols = np.zeros((0, 3)), np.zeros((0, 3))
    fill_src = np.zeros(0, dtype=np.int64)
    if n_fill > 0:
        fill_src, pix = _random_pixels(rng, frames, static_pools, n_fill)
        depth = rng.uniform(near, far, n_fill)
        fill_pts = np.empty((n_fill, 3))
        fill_cols = np.empty((n_fill, 3))
        anchors = np.concatenate([tri_pts, dense_pts]) if config.fill_on_surface else np.zeros((0, 3))
        for k in np.unique(fill_src):
            s = fill_src == k
            # on the surface the seeds describe, where they describe one
            d = depth_from_points(anchors, frames[k], pix[s], config.dense_outlier_rel, max_points=4000)
            maps = ([frames[k].depth] if config.static_depth == "scene" else
                    [static_prior[k]] if static_prior is not None else None)
            if maps is not None:  # the scene's depth (or the aligned prior) at the pixel, where it has one
                z = _at_pixels(maps, np.zeros(int(s.sum()), dtype=np.int64), pix[s])
                take = np.isfinite(z) & (z > 0)
                if config.static_depth == "stereo_prior" and config.stereo_prior_scope == "all":
                    take &= ~_agrees(d, z, config.stereo_prior_tolerance)  # the surface stands where it agrees
                d = np.where(take, z, d)
            depth[s] = np.where(np.isfinite(d) & (d > 0), d, depth[s])
            fill_pts[s] = unproject_points(pix[s], depth[s], frames[k].cam_T_world, frames[k].K)
            fill_cols[s] = sample_image_bilinear(frames[k].image, pix[s])

    static_points = np.concatenate([tri_pts, dense_pts, fill_pts])
    static_colors = np.clip(np.concatenate([tri_cols, dense_cols, fill_cols]), 0.0, 1.0)

    # ---- 5. dynamic points inside the masks
    dyn_pools = [np.flatnonzero(f.mask.ravel()) if f.mask is not None else np.zeros(0, dtype=np.int64) for f in frames]
    has_moving = sum(len(p) for p in dyn_pools) > 0
    dynamic_points = dynamic_colors = None
    dyn_src = np.zeros(0, dtype=np.int64)
    dyn_pix = np.zeros((0, 2))
    frame_depth = np.full(N, np.nan)
    prior_info = None
    dyn_maps = None  # per-frame depth maps the dynamic seeds were lifted at ("scene", "prior"), else None
    if has_moving and config.dynamic_points > 0:
        ref = tri_pts if tri_pts.shape[0] > 0 else fill_pts
        fallback = float(np.median(tri_depth)) if tri_depth.size else 0.5 * (near + far)
        for k, f in enumerate(frames):
            uv, z = project_points(ref, f.cam_T_world, f.K) if ref.shape[0] else (np.zeros((0, 2)), np.zeros(0))
            vis = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < f.width) & (uv[:, 1] >= 0) & (uv[:, 1] < f.height)
            frame_depth[k] = float(np.median(z[vis])) if np.any(vis) else fallback
        dyn_src, dyn_pix = _random_pixels(rng, frames, dyn_pools, config.dynamic_points)
        jitter = rng.uniform(1.0 - config.dynamic_depth_jitter, 1.0 + config.dynamic_depth_jitter, len(dyn_src))
        depth = config.dynamic_depth_factor * frame_depth[dyn_src] * jitter
        if config.dynamic_depth == "scene":  # the scene's depth maps at the seeds' pixels (checked above)
            dyn_maps = [f.depth for f in frames]
            measured = _at_pixels(dyn_maps, dyn_src, dyn_pix) * jitter
            ok = np.isfinite(measured) & (measured > 0)
            depth = np.where(ok, measured, depth)
        elif config.dynamic_depth == "prior":  # each frame's prior aligned to the static points seen there
            # the bundle adjustment's points, else the measured static points: triangulated, and
            # dense seeds at their own pixel's stereo depth
            if anchor_points is not None and len(anchor_points) >= config.depth_prior_min_points:
                reference, what = np.asarray(anchor_points, dtype=np.float64), "the bundle adjustment's points"
            else:
                reference = np.concatenate([tri_pts, dense_pts[dense_info["measured"]]])
                what = "the measured static points"
            aligned, prior_info = _aligned_priors(frames, reference, np.unique(dyn_src), config,
                                                  fc.mask_dilation_px)
            prior_info["reference"] = f"{what} ({len(reference)})"
            dyn_maps = aligned
            measured = _at_pixels(aligned, dyn_src, dyn_pix) * jitter
            ok = np.isfinite(measured) & (measured > 0)
            depth = np.where(ok, measured, depth)
            prior_info["seeds_from_prior"] = int(ok.sum())
        dynamic_points = np.empty((len(dyn_src), 3))
        dynamic_colors = np.empty((len(dyn_src), 3))
        for k in np.unique(dyn_src):
            s = dyn_src == k
            dynamic_points[s] = unproject_points(dyn_pix[s], depth[s], frames[k].cam_T_world, frames[k].K)
            dynamic_colors[s] = sample_image_bilinear(frames[k].image, dyn_pix[s])
        dynamic_colors = np.clip(dynamic_colors, 0.0, 1.0)

    if not has_moving:
        dynamic_note = "no masks" if all(f.mask is None for f in frames) else "masks have no moving pixels"
    elif config.dynamic_points == 0:
        dynamic_note = "dynamic_points = 0"
    else:
        dynamic_note = "seeded in masks"
    info = {
        "num_static_triangulated": int(tri_pts.shape[0]),
        "num_static_dense": int(dense_pts.shape[0]),
        "num_static_dense_stereo": int(dense_info["stereo_seeds"]),
        "num_static_dense_stereo_over_prior": int(dense_info.get("stereo_kept_over_prior", 0)),
        "stereo_kept_share": float(np.mean(dense_info["stereo_kept_share"])) if dense_info["stereo_kept_share"]
        else float("nan"),
        "num_static_fill": int(fill_pts.shape[0]),
        "num_dynamic": 0 if dynamic_points is None else int(dynamic_points.shape[0]),
        "reproj_error_mean_px": float(tri_err.mean()) if tri_err.size else float("nan"),
        "num_pairs_matched": int(sum(n > 0 for n in num_matches)),
        "mean_matches_per_pair": float(np.mean(num_matches)) if num_matches else 0.0,
        "reproj_error_median_px": float(np.median(tri_err)) if tri_err.size else float("nan"),
        "num_triangulated_before_cap": int(num_triangulated),
        "num_pairs": len(pairs),
        "num_keypoints_mean": float(np.mean([len(kp) for kp in keypoints])) if keypoints else 0.0,
        "fill_depth_near": float(near),
        "fill_depth_far": float(far),
        "fill_depth_source": depth_source,
        "dynamic": dynamic_note,
        "dynamic_frame_depths": frame_depth,
        "dynamic_depth_prior": prior_info,
        "static_depth_prior": static_prior_info,
        "static_depth": config.static_depth, "dynamic_depth": config.dynamic_depth,  # as decided ("auto")
        "static_source_frames": np.concatenate([tri_src, dense_src, fill_src]),
        # the static points at a measured depth: triangulated, or dense at their own pixel's stereo depth
        "static_measured": np.concatenate([np.ones(len(tri_src), bool), dense_info["measured"],
                                           np.zeros(len(fill_src), bool)]),
        "dynamic_source_frames": dyn_src,
        "dynamic_source_pixels": dyn_pix,
        "dynamic_depth_maps": dyn_maps,
    }
    return static_points, static_colors, dynamic_points, dynamic_colors, info


def pixel_scale_cap(points, source_frames, frames, max_px):
    """Log of the largest initial scale of each point (N,): ``max_px`` pixels at its depth in its
    source frame (max_px * z / fx); +inf where max_px is 0 or the point is not in front of it."""
    points = np.asarray(points, dtype=np.float64)
    cap = np.full(len(points), np.inf)
    if max_px <= 0 or len(points) == 0:
        return cap
    src = np.asarray(source_frames, dtype=np.int64)
    for k in np.unique(src):
        s = src == k
        f = frames[int(k)]
        z = points[s] @ f.cam_T_world[2, :3] + f.cam_T_world[2, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            cap[s] = np.where(z > 0, np.log(max_px * np.maximum(z, 1e-300) / f.K[0, 0]), np.inf)
    return cap
