"""Classical structure from motion for a video (docs/dataset_format.md §8).

Steps (``register_video``):
1. Tracks (``SfmConfig.tracker``): "klt" (default), Lucas-Kanade tracks through the frames
   (``d2gs_np.pose.tracks``: why not SIFT on blurry frames); "sift", SIFT features per frame
   (``d2gs_np.pose.features``) matched between frame k and k + 1 .. k + ``match_window`` (ratio test,
   RANSAC on F) and joined into tracks (connected components of the match graph; a track that
   visits one frame twice is dropped). A frame with fewer than ``SfmConfig.min_keypoints`` points
   has no usable texture: a ValueError naming the frames, before any registration. Features and
   tracks avoid the motion masks when given (the importer's second pass).
3. Two-view start: among frame pairs at most ``init_max_gap`` apart, the essential matrix
   (RANSAC), ``recoverPose`` and a triangulation; the pair with the most points whose median
   triangulation angle reaches ``init_min_parallax_deg`` starts the reconstruction. A pair whose
   matches one rotation (Kabsch on the unit bearings, refitted without mismatches) maps onto each
   other within ``essential_threshold_px`` (median) counts as angle 0: pure rotation makes the essential matrix
   degenerate, and its triangulation angles spurious.
   If no pair reaches it, the video is a pure rotation (no parallax): see ``rotation_only``.
4. Every further frame (most 2D-3D correspondences first) by PnP with RANSAC, refined by
   Levenberg-Marquardt on the inliers; new tracks are triangulated from their two registered
   views farthest apart in time (kept if in front of both cameras, reprojection within
   ``max_reprojection_px`` and angle >= ``min_parallax_deg``); a bundle adjustment
   (``d2gs_np.pose.bundle``) each time the number of registered frames grows by half.
5. A final bundle adjustment over all frames and points (and the focal length, unless given),
   observations with residual above ``outlier_px`` dropped, then a second one.
6. If a frame cannot be registered, a frame keeps fewer than ``min_pnp_inliers`` consistent
   observations, or the focal length leaves [0.5, 2] x its start, steps 4-5 are retried from the
   next two-view starts (up to ``max_starts``, most points first), then from the same starts with
   the focal length held at its start; the first error is raised if all fail.

Rotation-only fallback (documented choice): all camera centres at the origin; rotations chained
from the homographies between neighbouring frames, R = K^-1 H K made orthonormal; sparse points
are the features of each frame lifted to depth 1 (so ``scene_scale`` = 1).

Poses are ``cam_T_world`` (OpenCV axes); the world is the first frame's camera, scaled so that
the median depth of the sparse points in their observing frames is 1.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from d2gs_np.base.checks import check_choice, check_int, check_number
from d2gs_np.pose.config import FeatureConfig, TrackConfig
from d2gs_np.pose.features import detect_features, match_keypoints
from d2gs_np.geometry.camera import project_points
from d2gs_np.geometry.so3 import so3_orthonormalize
from d2gs_np.scene.initialize import triangulate_matches
from d2gs_np.pose.bundle import BundleProblem, bundle_adjust, params_to_poses, poses_to_params
from d2gs_np.pose.tracks import klt_tracks

__all__ = ["SfmConfig", "SfmResult", "register_video", "build_tracks", "fix_gauge", "NoParallaxError"]


class NoParallaxError(ValueError):
    """The camera only rotates (or barely moves): depth cannot be triangulated."""


@dataclass(frozen=True)
class SfmConfig:
    """Settings of the classical camera registration. Validated on construction."""

    # SIFT at a low contrast threshold: blurry frames lose DoG contrast (as in InitConfig)
    features: FeatureConfig = field(default_factory=lambda: FeatureConfig(contrast_threshold=0.01))
    # "klt": Lucas-Kanade tracks (d2gs_np.pose.tracks: why); "sift": SIFT matches of each frame with the
    # next match_window frames joined into tracks (the comparison: docs/results.md §13)
    tracker: str = "klt"
    tracks: TrackConfig = field(default_factory=TrackConfig)
    match_window: int = 4  # match frame k with k+1 .. k+window (longer tracks: more parallax per track)
    min_keypoints: int = 20  # fewer keypoints: the frame has no usable texture (an error)
    init_max_gap: int = 10  # the two-view start is searched among pairs at most this far apart
    init_min_parallax_deg: float = 1.0  # median triangulation angle the start needs; below: no parallax
    init_min_points: int = 30  # points the two-view start needs
    min_pnp_inliers: int = 12  # a frame with fewer PnP inliers cannot be registered (an error)
    pnp_threshold_px: float = 2.0  # RANSAC inlier threshold of PnP
    min_pnp_inlier_ratio: float = 0.25  # and at least this share of its 2D-3D matches must be inliers
    essential_threshold_px: float = 1.0  # RANSAC inlier threshold of the essential matrix
    max_reprojection_px: float = 2.0  # triangulated points must reproject within this in both views
    min_parallax_deg: float = 0.2  # and be seen under at least this angle (small: PnP needs directions more than depths)
    outlier_px: float = 3.0  # observations with a larger residual after bundle adjustment are dropped
    weak_observations: int = 40  # a frame with fewer inlier observations is reported as weak
    robust_scale_px: float = 1.0  # soft_l1 scale of the bundle adjustment
    ba_max_nfev: int = 30  # function evaluations per bundle adjustment
    max_starts: int = 3  # two-view starts tried before giving up (then again with the focal length fixed)

    def __post_init__(self):
        if not isinstance(self.features, FeatureConfig):
            raise TypeError(f"SfmConfig.features must be a FeatureConfig; got {type(self.features).__name__}")
        if not isinstance(self.tracks, TrackConfig):
            raise TypeError(f"SfmConfig.tracks must be a TrackConfig; got {type(self.tracks).__name__}")
        check_choice(self.tracker, "SfmConfig.tracker", ("klt", "sift"))
        for name in ("match_window", "min_keypoints", "init_max_gap", "init_min_points", "weak_observations",
                     "ba_max_nfev", "max_starts"):
            check_int(getattr(self, name), f"SfmConfig.{name}", 1)
        check_int(self.min_pnp_inliers, "SfmConfig.min_pnp_inliers", 6, hint="PnP needs 6 points")
        for name in ("init_min_parallax_deg", "pnp_threshold_px", "min_pnp_inlier_ratio", "essential_threshold_px",
                     "max_reprojection_px", "min_parallax_deg", "outlier_px", "robust_scale_px"):
            check_number(getattr(self, name), f"SfmConfig.{name}", 0.0, lo_open=True)


@dataclass
class SfmResult:
    cam_T_world: np.ndarray  # (N, 4, 4)
    K: np.ndarray  # (3, 3) refined intrinsics
    points: np.ndarray  # (P, 3) sparse world points
    colors: np.ndarray  # (P, 3) RGB in [0, 1]
    obs_frame: np.ndarray  # (O,) frame of each inlier observation
    obs_point: np.ndarray  # (O,) point of each inlier observation
    obs_uv: np.ndarray  # (O, 2) pixel of each inlier observation
    num_keypoints: np.ndarray  # (N,) keypoints per frame
    num_observations: np.ndarray  # (N,) inlier observations per frame after bundle adjustment
    weak_frames: list  # frames with fewer than weak_observations inlier observations
    rotation_only: bool
    init_pair: tuple
    init_parallax_deg: float
    reprojection_rms_px: float
    log: list = field(default_factory=list)


def build_tracks(keypoints, matches):
    """Tracks from pairwise matches. keypoints: list of Keypoints; matches: {(a, b): Matches}.

    Returns (obs_frame (O,), obs_track (O,), obs_uv (O, 2), num_tracks): every track has >= 2
    observations in distinct frames; tracks that visit one frame twice are dropped.
    """
    N = len(keypoints)
    sizes = np.array([len(k) for k in keypoints], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    n = int(offsets[-1])
    rows = [offsets[a] + m.idx0 for (a, b), m in matches.items()]
    cols = [offsets[b] + m.idx1 for (a, b), m in matches.items()]
    empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 2)), 0)
    if n == 0 or not rows:
        return empty
    r, c = np.concatenate(rows), np.concatenate(cols)
    _, labels = connected_components(coo_matrix((np.ones(r.size), (r, c)), shape=(n, n)), directed=False)
    node_frame = np.repeat(np.arange(N), sizes)
    node_uv = np.concatenate([k.pts for k in keypoints if len(k)]) if n else np.zeros((0, 2))
    keep = np.bincount(labels)[labels] >= 2
    key = labels.astype(np.int64) * N + node_frame
    uniq, cnt = np.unique(key[keep], return_counts=True)
    keep &= ~np.isin(labels, np.unique(uniq[cnt > 1] // N))
    if not keep.any():
        return empty
    _, track = np.unique(labels[keep], return_inverse=True)
    return node_frame[keep], track.astype(np.int64), node_uv[keep], int(track.max()) + 1


def _pose(R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.ravel(t)
    return T


def _rotation_fit_error(pa, pb, K, rounds=3, inlier_px=3.0):
    """Pixel errors of the best pure rotation mapping pa -> pb: Kabsch on unit bearings, refitted on
    the matches within ``inlier_px`` (``rounds`` times) so that a few mismatches do not bias it."""
    Kinv = np.linalg.inv(K)
    ba = np.c_[pa, np.ones(len(pa))] @ Kinv.T
    bb = np.c_[pb, np.ones(len(pb))] @ Kinv.T
    ua = ba / np.linalg.norm(ba, axis=1, keepdims=True)
    ub = bb / np.linalg.norm(bb, axis=1, keepdims=True)
    use = np.ones(len(pa), dtype=bool)
    for _ in range(rounds):
        U, _, Vt = np.linalg.svd(ub[use].T @ ua[use])
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt  # ub ~ R ua
        q = ba @ R.T @ K.T
        err = np.linalg.norm(q[:, :2] / q[:, 2:3] - pb, axis=1)
        if np.sum(err < inlier_px) < 3:
            break
        use = err < inlier_px
    return err


def _two_view(pa, pb, K, cfg):
    """Essential matrix + recoverPose + triangulation -> (T_b (4, 4), inlier mask, X, median parallax, good)."""
    E, mask = cv2.findEssentialMat(pa, pb, K, cv2.RANSAC, 0.999, cfg.essential_threshold_px)
    if E is None or E.shape != (3, 3):
        return None
    _, R, t, mask = cv2.recoverPose(E, pa, pb, K, mask=mask.copy())
    inl = mask.ravel() > 0
    Tb = _pose(R, t)
    X, z0, z1, err, par, fin = triangulate_matches(pa, pb, np.eye(4), Tb, K, K)
    with np.errstate(invalid="ignore"):
        good = inl & fin & (z0 > 0) & (z1 > 0) & (err <= cfg.max_reprojection_px)
    med = float(np.median(par[good])) if good.any() else 0.0
    # Pure rotation makes E degenerate (any t fits), so the triangulation angle can be spurious: if one
    # rotation (Kabsch on the bearings, _rotation_fit_error) maps the matches onto each other within
    # the RANSAC threshold (median over all of them), the pair has no usable parallax.
    if np.median(_rotation_fit_error(pa, pb, K)) < cfg.essential_threshold_px:
        med = 0.0
    return Tb, X, med, good


def _ba(poses, points, K, obs_frame, obs_point, obs_uv, registered, fixed, cfg, refine_focal):
    idx = np.flatnonzero(registered)
    slot = np.full(len(poses), -1)
    slot[idx] = np.arange(len(idx))
    sel = registered[obs_frame] & np.isfinite(points[obs_point, 0])
    pts_used = np.unique(obs_point[sel])
    pslot = np.full(len(points), -1)
    pslot[pts_used] = np.arange(len(pts_used))
    prob = BundleProblem(poses_to_params(poses[idx]), points[pts_used], K[0, 0], K[0, 2], K[1, 2],
                         slot[obs_frame[sel]], pslot[obs_point[sel]], obs_uv[sel])
    cams, pts, f, info = bundle_adjust(prob, fixed_cams=(int(slot[fixed]),), refine_focal=refine_focal,
                                       f_scale=cfg.robust_scale_px, max_nfev=cfg.ba_max_nfev)
    poses = poses.copy()
    poses[idx] = params_to_poses(cams)
    points = points.copy()
    points[pts_used] = pts
    K = K.copy()
    K[0, 0] = K[1, 1] = f
    resid = np.full(len(obs_frame), np.inf)
    resid[sel] = info["residual_px"]
    return poses, points, K, resid, info


def _rotation_only(frame_pts, pairs, K, N, log):
    """Fallback for a camera that only rotates (module docstring). frame_pts: list of (n_k, 2) feature
    pixels per frame; pairs: {(k, k + 1): (pts in k, pts in k + 1)}."""
    Kinv = np.linalg.inv(K)
    R = [np.eye(3)]
    for k in range(N - 1):
        p0, p1 = pairs.get((k, k + 1), (np.zeros((0, 2)), np.zeros((0, 2))))
        if len(p0) < 8:
            raise ValueError(f"frames {k} and {k + 1}: too few matches ({len(p0)}) to "
                             "estimate the rotation between them; the video cannot be registered")
        H, _ = cv2.findHomography(p0, p1, cv2.RANSAC, 2.0)
        if H is None:
            raise ValueError(f"frames {k} and {k + 1}: no homography found; the video cannot be registered")
        M = Kinv @ H @ K
        M /= np.cbrt(np.linalg.det(M))
        R.append(so3_orthonormalize(M) @ R[-1])
    poses = np.stack([_pose(r, np.zeros(3)) for r in R])
    pts, fr = [], []
    for k, kp in enumerate(frame_pts):
        if len(kp) == 0:
            continue
        rays = np.c_[(kp - K[:2, 2]) / np.diag(K)[:2], np.ones(len(kp))]
        rays /= rays[:, 2:3]
        pts.append(rays @ R[k])  # depth 1 in frame k, world = R_k^T x_cam
        fr.append(np.full(len(kp), k))
    log.append("pure rotation: camera centres fixed at the origin, rotations from homographies, "
               "points at depth 1 (docs/dataset_format.md §8)")
    return poses, np.concatenate(pts), np.concatenate(fr)


def _sample_colors(images, frames, uv):
    cols = np.zeros((len(frames), 3))
    for k in np.unique(frames):
        s = frames == k
        img = images[k]
        j = np.clip(np.floor(uv[s, 0]).astype(int), 0, img.shape[1] - 1)
        i = np.clip(np.floor(uv[s, 1]).astype(int), 0, img.shape[0] - 1)
        cols[s] = img[i, j] / 255.0 if img.dtype == np.uint8 else img[i, j]
    return cols


def _check_tracks(tracks, N):
    """Validated (obs_frame, obs_track, obs_uv, num_tracks, points per frame) for N frames."""
    try:
        obs_frame, obs_track, obs_uv, T, nkp = tracks
    except (TypeError, ValueError):
        raise ValueError("tracks must be (obs_frame, obs_track, obs_uv, num_tracks, points_per_frame) as "
                         "klt_tracks returns them") from None
    obs_frame = np.asarray(obs_frame, dtype=np.int64)
    obs_track = np.asarray(obs_track, dtype=np.int64)
    obs_uv = np.asarray(obs_uv, dtype=np.float64)
    nkp = np.asarray(nkp, dtype=np.int64)
    O = len(obs_frame)
    if obs_track.shape != (O,) or obs_uv.shape != (O, 2) or nkp.shape != (N,):
        raise ValueError(f"tracks: obs_frame, obs_track (O,), obs_uv (O, 2) and points_per_frame ({N},) needed; got "
                         f"{obs_frame.shape}, {obs_track.shape}, {obs_uv.shape}, {nkp.shape}")
    if O and (obs_frame.min() < 0 or obs_frame.max() >= N or obs_track.min() < 0 or obs_track.max() >= T):
        raise ValueError(f"tracks: frames must lie in [0, {N}) and track ids in [0, {T})")
    if not np.all(np.isfinite(obs_uv)):
        raise ValueError("tracks: obs_uv has non-finite pixels")
    return obs_frame, obs_track, obs_uv, int(T), nkp


def fix_gauge(cam_T_world, points, obs_frame, obs_point):
    """The registration's gauge (module docstring): frame 0 at the identity and the median depth of
    the points in their observing frames 1. cam_T_world (N, 4, 4), points (P, 3), obs_frame and
    obs_point (O,); returns new (cam_T_world, points)."""
    T0 = cam_T_world[0].copy()
    poses = cam_T_world @ np.linalg.inv(T0)
    pts = points @ T0[:3, :3].T + T0[:3, 3]
    depths = np.einsum("oij,oj->oi", poses[obs_frame, :3, :3], pts[obs_point])[:, 2] + poses[obs_frame, 2, 3]
    s = 1.0 / float(np.median(depths))
    poses[:, :3, 3] *= s
    return poses, pts * s


def register_video(images, K, config: SfmConfig = None, refine_focal=True, masks=None, log=print,
                   tracks=None) -> SfmResult:
    """Camera poses, refined intrinsics and sparse points of a frame sequence (module docstring).

    images: list of (H, W, 3) float RGB in [0, 1] (or uint8); K: (3, 3) starting intrinsics (our
    pixel convention). masks: optional list of (H, W) bool, True = moving (no features there).
    tracks: optional KLT tracks as ``klt_tracks`` returns them (obs_frame, obs_track, obs_uv,
    num_tracks, points per frame), used instead of tracking again (the importer registers a subset
    of one set of tracks: ``d2gs_np.video.importer``); only with the "klt" tracker and no masks.
    Raises ValueError naming the frames when the video cannot be registered; NoParallaxError is
    never raised: a pure rotation falls back (``SfmResult.rotation_only``).
    """
    cfg = SfmConfig() if config is None else config
    if not isinstance(cfg, SfmConfig):
        raise TypeError(f"config must be an SfmConfig; got {type(cfg).__name__}")
    N = len(images)
    if N < 2:
        raise ValueError(f"need at least 2 frames to register a video; got {N}")
    K = np.array(K, dtype=np.float64)
    msgs = []

    def say(s):
        msgs.append(s)
        if log is not None:
            log(s)

    if masks is not None and (len(masks) != N or any(np.shape(m) != np.shape(images[0])[:2] for m in masks)):
        raise ValueError(f"masks must be one (H, W) bool array per frame ({N} frames of "
                         f"{np.shape(images[0])[:2]}); got {len(masks)}")
    if tracks is not None and (cfg.tracker != "klt" or masks is not None):
        raise ValueError("register_video: precomputed tracks need the 'klt' tracker and no masks")
    if cfg.tracker == "klt":
        obs_frame, obs_track, obs_uv, T, nkp = (_check_tracks(tracks, N) if tracks is not None else
                                                klt_tracks(images, cfg.tracks, masks, seed=cfg.features.seed))
        frame_pts = [obs_uv[obs_frame == k] for k in range(N)]
    else:
        fc = cfg.features
        kps = [detect_features(im, fc, None if masks is None else masks[k]) for k, im in enumerate(images)]
        nkp = np.array([len(k) for k in kps])
        frame_pts = [k.pts for k in kps]
    flat = np.flatnonzero(nkp < cfg.min_keypoints)
    if flat.size:
        raise ValueError(
            f"frames {flat.tolist()} have no usable texture ({nkp[flat].tolist()} keypoints, need >= "
            f"{cfg.min_keypoints}); remove them (--start/--end, or delete them from the folder), or film textured "
            "surfaces")
    say(f"{cfg.tracker}: {nkp.min()}-{nkp.max()} points per frame (median {int(np.median(nkp))})")
    if cfg.tracker != "klt":
        matches = {}
        for a in range(N):
            for b in range(a + 1, min(N, a + cfg.match_window + 1)):
                m = match_keypoints(kps[a], kps[b], fc)
                if m.num_inliers:
                    matches[(a, b)] = m
        obs_frame, obs_track, obs_uv, T = build_tracks(kps, matches)
        say(f"tracks: {T} over {len(matches)} matched pairs")
    else:
        say(f"tracks: {T}, {len(obs_frame)} observations, median length {int(np.median(np.bincount(obs_track)))}"
            if T else "tracks: none")
    lookup = np.full((N, max(T, 1)), -1, dtype=np.int64)
    lookup[obs_frame, obs_track] = np.arange(len(obs_frame))

    # ---- two-view start
    starts = []
    best_par = 0.0
    for a in range(N):
        for b in range(a + 1, min(N, a + cfg.init_max_gap + 1)):
            common = np.flatnonzero((lookup[a] >= 0) & (lookup[b] >= 0))
            if common.size < max(cfg.init_min_points, 8):
                continue
            pa, pb = obs_uv[lookup[a, common]], obs_uv[lookup[b, common]]
            res = _two_view(pa, pb, K, cfg)
            if res is None:
                continue
            Tb, X, par, good = res
            best_par = max(best_par, par)
            if par >= cfg.init_min_parallax_deg and good.sum() >= cfg.init_min_points:
                starts.append((int(good.sum()), a, b, Tb, X, common, good, par))
    if not starts:
        say(f"no frame pair has a median triangulation angle >= {cfg.init_min_parallax_deg} deg "
            f"(largest {best_par:.2f} deg): the camera only rotates, no parallax")
        pairs = {}
        for k in range(N - 1):
            both = np.flatnonzero((lookup[k] >= 0) & (lookup[k + 1] >= 0))
            pairs[(k, k + 1)] = (obs_uv[lookup[k, both]], obs_uv[lookup[k + 1, both]])
        poses, pts, pfr = _rotation_only(frame_pts, pairs, K, N, msgs)
        log and log(msgs[-1])
        uv = np.concatenate(frame_pts)
        return SfmResult(poses, K, pts, _sample_colors(images, pfr, uv), pfr, np.arange(len(pts)), uv, nkp,
                         np.bincount(pfr, minlength=N), [], True, (0, 1), best_par, float("nan"), msgs)
    K_start = K.copy()
    starts.sort(key=lambda c: -c[0])
    errors = []
    # Registration can fail from a start whose points lie on a mover or whose focal length drifts:
    # try the next starts (most points first), then the best ones with the focal length held fixed.
    plan = [(c, refine_focal) for c in starts[:cfg.max_starts]]
    if refine_focal:
        plan += [(c, False) for c in starts[:cfg.max_starts]]
    def _attempt(best, refine_focal):
        K = K_start.copy()
        _, a, b, Tb, X, common, good, par0 = best
        say(f"two-view start: frames {a} and {b}, {good.sum()} points, median angle {par0:.2f} deg")
        poses = np.tile(np.eye(4), (N, 1, 1))
        poses[b] = Tb
        registered = np.zeros(N, dtype=bool)
        registered[[a, b]] = True
        points = np.full((T, 3), np.nan)
        points[common[good]] = X[good]
        bad_obs = np.zeros(len(obs_frame), dtype=bool)
        last_ba = 2

        def triangulate_new():
            tri = np.isfinite(points[:, 0])
            reg_obs = registered[obs_frame] & ~bad_obs
            cnt = np.bincount(obs_track[reg_obs], minlength=T)
            cand = np.flatnonzero(~tri & (cnt >= 2))
            if cand.size == 0:
                return 0
            sub = lookup[:, cand]  # (N, M)
            ok = (sub >= 0) & registered[:, None]
            first = np.argmax(ok, axis=0)
            last = N - 1 - np.argmax(ok[::-1], axis=0)
            added = 0
            for fa in np.unique(first):
                for fb in np.unique(last[first == fa]):
                    s = (first == fa) & (last == fb)
                    tr = cand[s]
                    Xn, z0, z1, err, par, fin = triangulate_matches(obs_uv[lookup[fa, tr]], obs_uv[lookup[fb, tr]],
                                                                    poses[fa], poses[fb], K, K)
                    with np.errstate(invalid="ignore"):
                        g = fin & (z0 > 0) & (z1 > 0) & (err <= cfg.max_reprojection_px) & (par >= cfg.min_parallax_deg)
                    points[tr[g]] = Xn[g]
                    added += int(g.sum())
            return added

        triangulate_new()
        failed = []
        while True:
            todo = np.flatnonzero(~registered)
            todo = np.array([k for k in todo if k not in failed], dtype=np.int64)
            if todo.size == 0:
                break
            tri = np.isfinite(points[:, 0])
            counts = np.array([int(np.sum((lookup[k] >= 0) & tri)) for k in todo])
            k = int(todo[np.argmax(counts)])
            tr = np.flatnonzero((lookup[k] >= 0) & tri)
            ok = False
            if tr.size >= cfg.min_pnp_inliers:
                obj = points[tr]
                img = obs_uv[lookup[k, tr]]
                retval, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=300,
                                                             reprojectionError=cfg.pnp_threshold_px, confidence=0.999)
                if retval and inl is not None and len(inl) >= max(cfg.min_pnp_inliers, cfg.min_pnp_inlier_ratio * tr.size):
                    inl = inl.ravel()
                    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
                    poses[k] = _pose(cv2.Rodrigues(rvec)[0], tvec)
                    outl = np.setdiff1d(np.arange(tr.size), inl)
                    bad_obs[lookup[k, tr[outl]]] = True
                    ok = True
            if not ok:
                failed.append(k)
                continue
            registered[k] = True
            failed = []  # new points may now let a failed frame register
            triangulate_new()
            if registered.sum() >= 1.5 * last_ba:
                last_ba = int(registered.sum())
                use = ~bad_obs
                poses, points_ba, K, resid, info = _ba(poses, points, K, obs_frame[use], obs_track[use], obs_uv[use],
                                                       registered, a, cfg, refine_focal and registered.sum() >= 5)
                points = points_ba
                idx = np.flatnonzero(use)
                bad_obs[idx[np.isfinite(resid) & (resid > cfg.outlier_px)]] = True  # mismatches, movers
                say(f"registered {registered.sum()}/{N} frames; bundle adjustment rms {info['rms_px']:.2f} px")
        if failed:
            tri = np.isfinite(points[:, 0])
            detail = ", ".join(f"frame {k}: {nkp[k]} keypoints, {int(np.sum((lookup[k] >= 0) & tri))} seen 3D points"
                               for k in sorted(failed))
            raise ValueError(f"could not register frames {sorted(failed)} (PnP needs >= {cfg.min_pnp_inliers} inliers; "
                             f"{detail}); they are too blurry or show too little of the rest of the video: drop them "
                             "(--start/--end, --stride) or film more slowly")

        # ---- final bundle adjustment: all frames, focal length, outlier removal, again
        use = ~bad_obs & np.isfinite(points[obs_track, 0])
        for rnd in range(2):
            o_f, o_t, o_uv = obs_frame[use], obs_track[use], obs_uv[use]
            poses, points, K, resid, info = _ba(poses, points, K, o_f, o_t, o_uv, registered, a, cfg, refine_focal)
            # residual and depth checks on the used observations
            z = np.einsum("oij,oj->oi", poses[o_f, :3, :3], points[o_t])[:, 2] + poses[o_f, 2, 3]
            keep = (resid <= cfg.outlier_px) & (z > 0)
            idx = np.flatnonzero(use)
            use[idx[~keep]] = False
            say(f"bundle adjustment {rnd + 1}: rms {info['rms_px']:.2f} px (median {info['median_px']:.2f}), "
                f"focal {K[0, 0]:.1f} px, {int((~keep).sum())} observations dropped")
        # points with fewer than 2 remaining observations are dropped
        cnt = np.bincount(obs_track[use], minlength=T)
        pt_ok = (cnt >= 2) & np.isfinite(points[:, 0])
        use &= pt_ok[obs_track]
        new_id = np.full(T, -1)
        new_id[pt_ok] = np.arange(pt_ok.sum())
        o_f, o_p, o_uv = obs_frame[use], new_id[obs_track[use]], obs_uv[use]
        pts = points[pt_ok]
        # residual rms of the kept observations
        uvp = np.zeros_like(o_uv)
        for k in range(N):
            s = o_f == k
            uvp[s] = project_points(pts[o_p[s]], poses[k], K)[0]
        rms = float(np.sqrt(np.mean(np.sum((uvp - o_uv) ** 2, axis=1)))) if len(o_uv) else float("nan")
        nobs = np.bincount(o_f, minlength=N)
        lost = np.flatnonzero(nobs < cfg.min_pnp_inliers)
        if lost.size:
            raise ValueError(f"frames {lost.tolist()} keep only {nobs[lost].tolist()} consistent observations after bundle "
                             f"adjustment (need >= {cfg.min_pnp_inliers}): their poses would be guesses; drop them "
                             "(--start/--end, --stride, or delete them from the folder)")
        weak = [int(k) for k in np.flatnonzero(nobs < cfg.weak_observations)]
        # colours: mean over observations
        cols = np.zeros((len(pts), 3))
        np.add.at(cols, o_p, _sample_colors(images, o_f, o_uv))
        cols /= np.maximum(np.bincount(o_p, minlength=len(pts)), 1)[:, None]
        poses, pts = fix_gauge(poses, pts, o_f, o_p)
        if not 0.5 <= K[0, 0] / K_start[0, 0] <= 2.0:
            raise ValueError(f"the focal length drifted to {K[0, 0]:.1f} px from {K_start[0, 0]:.1f} px")
        say(f"registered all {N} frames: {len(pts)} points, reprojection rms {rms:.2f} px; "
            f"observations per frame {nobs.min()}-{nobs.max()}" + (f"; weakly constrained frames {weak}" if weak else ""))
        return SfmResult(poses, K, pts, np.clip(cols, 0, 1), o_f, o_p, o_uv, nkp, nobs, weak, False, (a, b), par0, rms,
                         msgs)

    for best, refine in plan:
        try:
            return _attempt(best, refine)
        except ValueError as e:
            errors.append(e)
            say(f"start at frames {best[1]} and {best[2]}{'' if refine else ' (focal fixed)'} failed: {str(e)[:160]}")
    raise errors[0]


