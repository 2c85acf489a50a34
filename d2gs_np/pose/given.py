"""Bundle adjustment of the given poses before training (docs/method.md §5: the initial poses).

The pose solver of ``train/pose_solver.py`` refines the poses against depths rendered from the
scene being trained, which is fitted to the same poses it tests: it fixes the error between
neighbouring frames (the i.i.d. part of the pose noise) but not the slow drift, which the scene
absorbs; adding pairs of distant frames to the solver made it worse, because the rendered depths
agree with the poses they were fitted to. A classical bundle adjustment has no such loop: its 3D
points are unknowns of the same problem, and the video importer's (``video/``) recovers the
suite's trajectories from the blurry frames alone better than the given poses are
(docs/results.md §12). So before training, when the poses are not trusted:

1. tracks through the blurry frames (KLT, ``pose/tracks.py``), none inside the motion masks;
2. each track with ``min_views`` observations or more triangulated with the *given* poses (linear,
   all its views), kept if in front of every camera and seen under at least ``min_parallax_deg``;
   fewer than ``min_points`` such tracks (a short or streaked clip): triangulated again at the
   looser ``fallback_min_views`` / ``fallback_parallax_deg``, which must give ``fallback_min_points``;
3. a robust bundle adjustment (``pose/bundle.py``: Levenberg-Marquardt with the points eliminated,
   or SciPy's trust region, ``solver``; soft-L1 loss) over every
   camera and every point, started at the given poses, with a prior that holds each camera near
   its given pose (``prior_rot_deg``, ``prior_trans_rel``: it fixes the world frame and scale of
   the given poses, and the slow drift that short tracks leave free); observations beyond
   ``outlier_px`` dropped, and again. A frame with fewer than ``min_frame_observations``
   observations (counted before each round) is held at its given pose: a handful of tracks in a streaked
   frame could turn it by degrees against the prior;
3b. with the frames' depth priors (one scale for the clip) and ``depth_prior_weight`` > 0, a third
   round with a depth row per observation (``pose.bundle.depth_prior_rows``): the clip scale is the
   median of log z - log prior over the second round's observations, held; the result is scaled
   about the mean camera centre back to the second round's path length (the prior holds the
   structure's shape against the path, not the scene's scale);
4. checks: the adjustment is kept only if its residual is below ``max_rms_px`` and its cameras
   stay within ``max_change_deg`` / ``max_change_rel`` (of the scene depth) of the given ones;
   else the given poses are kept and the log says why.

Training then starts from these poses (initial points, the endpoint model's reference poses) and
the pose solver's prior holds them instead of the given ones; evaluation still reports the given
poses as the initial trajectory.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from d2gs_np.geometry.camera import camera_center
from d2gs_np.geometry.sampling import bilinear_fwd
from d2gs_np.geometry.so3 import so3_exp, so3_log
from d2gs_np.pose.bundle import (BundleProblem, bundle_adjust, camera_covariance, params_to_poses, poses_to_params,
                                 relative_rotation_std)
from d2gs_np.pose.config import PoseInitConfig
from d2gs_np.pose.tracks import klt_tracks

__all__ = ["triangulate_tracks", "adjust_given_poses", "initial_poses", "AdjustedStart", "adjusted_start",
           "track_reprojection_rms"]

def triangulate_tracks(cam_T_world, K, obs_frame, obs_track, obs_uv, num_tracks, min_views=3,
                       min_parallax_deg=1.0):
    """Linear (DLT) triangulation of every track from all its views with known poses.

    cam_T_world (N, 4, 4), K (3, 3) shared or (N, 3, 3) per frame, observations in our pixel
    convention.
    Returns (points (num_tracks, 3), ok (num_tracks,) bool): a track is ok if it has at least
    ``min_views`` views, its point lies in front of every camera that sees it, and its rays
    open to ``min_parallax_deg`` (the largest angle of a ray to the track's first ray).
    """
    T = np.asarray(cam_T_world, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    obs_frame = np.asarray(obs_frame, dtype=np.int64)
    obs_track = np.asarray(obs_track, dtype=np.int64)
    uv = np.asarray(obs_uv, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or K.shape not in ((3, 3), (T.shape[0], 3, 3)):
        raise ValueError(f"cam_T_world must be (N, 4, 4) and K (3, 3) or (N, 3, 3); got {T.shape}, {K.shape}")
    if obs_track.shape != obs_frame.shape or uv.shape != (obs_frame.shape[0], 2):
        raise ValueError("obs_frame (O,), obs_track (O,) and obs_uv (O, 2) must agree")
    if obs_frame.size == 0:
        return np.full((num_tracks, 3), np.nan), np.zeros(num_tracks, dtype=bool)
    P = K @ T[:, :3, :]  # (N, 3, 4) projection matrices (pixel centres at +0.5 are in K's cx, cy)
    rows_u = uv[:, :1] * P[obs_frame, 2] - P[obs_frame, 0]  # (O, 4)
    rows_v = uv[:, 1:] * P[obs_frame, 2] - P[obs_frame, 1]
    A = np.zeros((num_tracks, 4, 4))  # normal matrices sum_o a a^T per track
    for rows in (rows_u, rows_v):
        rows = rows / np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-300)
        np.add.at(A, obs_track, rows[:, :, None] * rows[:, None, :])
    _, vecs = np.linalg.eigh(A)
    Xh = vecs[:, :, 0]
    w = Xh[:, 3]
    ok = np.abs(w) > 1e-12
    X = np.where(ok[:, None], Xh[:, :3] / np.where(ok, w, 1.0)[:, None], np.nan)
    views = np.bincount(obs_track, minlength=num_tracks)
    ok &= views >= min_views
    # in front of every camera that sees it
    z = np.einsum("oj,oj->o", T[obs_frame, 2, :3], X[obs_track]) + T[obs_frame, 2, 3]
    front = np.ones(num_tracks, dtype=bool)
    np.logical_and.at(front, obs_track, np.nan_to_num(z, nan=-1.0) > 0)
    ok &= front
    # parallax: the largest angle of a view's ray to the track's first ray (at least half the
    # largest angle between any two of its rays)
    C = camera_center(T)
    ray = X[obs_track] - C[obs_frame]
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-300)
    first = np.zeros(num_tracks, dtype=np.int64)
    seen, first_obs = np.unique(obs_track, return_index=True)
    first[seen] = first_obs
    cosang = np.einsum("oj,oj->o", ray, ray[first[obs_track]])
    mincos = np.ones(num_tracks)
    np.minimum.at(mincos, obs_track, np.nan_to_num(cosang, nan=1.0))
    ok &= mincos <= np.cos(np.deg2rad(min_parallax_deg))
    ok &= np.all(np.isfinite(X), axis=1)
    return X, ok


def _depths(T, X):
    """(N, P) depths of points X (P, 3) in cameras T (N, 4, 4)."""
    return np.einsum("nj,pj->np", T[:, 2, :3], X) + T[:, 2, 3][:, None]


def _rotation_deg(A, B):
    return np.degrees(np.linalg.norm(so3_log(A[:, :3, :3] @ np.transpose(B[:, :3, :3], (0, 2, 1))), axis=-1))


def _log_prior_at(depth_priors, obs_cam, uv):
    """Each observation's log depth prior, read bilinearly at its pixel (NaN: no prior there)."""
    out = np.full(len(obs_cam), np.nan)
    for k, d in enumerate(depth_priors):
        sel = np.flatnonzero(obs_cam == k)
        if d is None or not sel.size:
            continue
        d = np.asarray(d, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            logd = np.where(np.isfinite(d) & (d > 0), np.log(np.where(d > 0, d, 1.0)), np.nan)
        out[sel] = bilinear_fwd(logd, uv[sel])[0]
    return out


def _round_entry(binfo, observations, solver):
    """A round of ``info["rounds"]``: what ``bundle_adjust`` said of it."""
    keys = ("rms_px_start", "rms_px", "median_px", "nfev", "cost", "iterations", "status", "cost_history",
            "seconds_history")
    return {**{k: binfo[k] for k in keys}, "observations": int(observations), "solver": solver}


def _spread(cams):
    """The camera centres of cams (C, 6), their mean, and their RMS distance from it."""
    c = camera_center(params_to_poses(cams))
    m = c.mean(axis=0)
    return c, m, float(np.sqrt(np.mean(np.sum((c - m) ** 2, axis=1))))


def _rescaled(cams, pts, spread):
    """Cameras (C, 6) and points scaled about the mean camera centre so that the centres' RMS
    distance from it is ``spread`` (rotations unchanged); the factor applied."""
    c, m, now = _spread(cams)
    k = spread / now if now > 0 and spread > 0 else 1.0
    out = cams.copy()
    out[:, 3:] = -np.einsum("cij,cj->ci", so3_exp(cams[:, :3]), m + k * (c - m))
    return out, m + k * (pts - m), k


def adjust_given_poses(images, masks, cam_T_world, K, config: PoseInitConfig = None, seed=0, tracks=None,
                       depth_priors=None):
    """Bundle adjustment of the given poses (module docstring).

    images: N (H, W, 3) frames in [0, 1]; masks: N (H, W) bool (True = moving) or None;
    cam_T_world (N, 4, 4) given poses; K (3, 3) intrinsics shared by every frame (fx may differ
    from fy). Returns (poses (N, 4, 4), info dict): ``info["kept"]`` says whether the adjusted
    poses were kept (else ``poses`` are the given ones and ``info["reason"]`` says why), with the
    counts, residuals and change against the given poses. depth_priors: optional N (H, W) depth
    maps (NaN or None: no estimate) of one scale for the clip, used with ``depth_prior_weight`` > 0
    (step 3b of the module docstring; ``info["depth_prior"]`` says what it did). tracks: optional (obs_frame, obs_track,
    obs_uv, num_tracks) from ``klt_tracks(images, config.tracks, masks=masks, seed=seed)``, computed
    here when None (a benchmark passes them to compare solvers on the same tracks).
    """
    cfg = PoseInitConfig() if config is None else config
    t0 = time.perf_counter()
    T0 = np.asarray(cam_T_world, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    N = T0.shape[0]
    info = {"kept": False, "frames": N}
    if N < 3:
        info["reason"] = f"{N} frames: a bundle adjustment needs at least 3"
        return T0.copy(), info
    # the adjustment has one focal length: scale v so that fy becomes fx
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if tracks is None:
        tracks = klt_tracks(images, cfg.tracks, masks=masks, seed=seed)
    of, ot, ouv, nt = tracks[0], tracks[1], tracks[2], tracks[3]
    ouv = np.array(ouv, dtype=np.float64)
    ouv_image = ouv.copy()  # the observed pixels as the images have them (the depth priors' grid)
    ouv[:, 1] = cy + (ouv[:, 1] - cy) * (fx / fy)
    Kx = np.array([[fx, 0.0, cx], [0.0, fx, cy], [0.0, 0.0, 1.0]])
    X, ok = triangulate_tracks(T0, Kx, of, ot, ouv, nt, cfg.min_views, cfg.min_parallax_deg)
    info.update(tracks=int(nt), points=int(ok.sum()))
    need = cfg.min_points
    if ok.sum() < cfg.min_points and cfg.fallback_min_points:
        # too few for the first gates: the looser ones (PoseInitConfig.fallback_*)
        X, ok = triangulate_tracks(T0, Kx, of, ot, ouv, nt, cfg.fallback_min_views, cfg.fallback_parallax_deg)
        need = cfg.fallback_min_points
        info.update(fallback=(f"{info['points']} tracks triangulated at {cfg.min_views} views / "
                              f"{cfg.min_parallax_deg:g} deg, fewer than min_points {cfg.min_points}: "
                              f"{int(ok.sum())} at {cfg.fallback_min_views} views / {cfg.fallback_parallax_deg:g} deg"),
                    points=int(ok.sum()))
    sel = ok[ot]
    if ok.sum() < need:
        info["reason"] = (f"too few triangulated tracks ({int(ok.sum())} of {nt}; min_points {cfg.min_points}"
                          + (f", fallback_min_points {need} at the looser gates)" if "fallback" in info else ")"))
        return T0.copy(), info
    given = poses_to_params(T0)
    cams = given.copy()
    keep_pts = np.flatnonzero(ok)
    slot = np.full(nt, -1)
    slot[keep_pts] = np.arange(len(keep_pts))
    o_cam, o_pt, o_uv, o_img = of[sel], slot[ot[sel]], ouv[sel], ouv_image[sel]
    pts = X[keep_pts]
    depth = float(np.median(_depths(T0, pts)))
    prior = (given, cfg.prior_trans_rel * depth, np.deg2rad(cfg.prior_rot_deg))
    smooth = cfg.smooth_trans_rel * depth if cfg.smooth_trans_rel > 0 else None
    rounds = []
    held = np.zeros(N, dtype=bool)
    for r in range(2):
        # weakly observed frames: back to the given pose and held there
        held |= np.bincount(o_cam, minlength=N) < cfg.min_frame_observations
        cams[held] = given[held]
        if held.all():
            info["reason"] = (f"no frame has {cfg.min_frame_observations} observations of triangulated tracks "
                              f"(min_frame_observations)")
            return T0.copy(), info
        prob = BundleProblem(cams, pts, fx, cx, cy, o_cam, o_pt, o_uv)
        cams_new, pts_new, _, binfo = bundle_adjust(prob, fixed_cams=tuple(np.flatnonzero(held).tolist()),
                                                    loss="soft_l1", f_scale=cfg.robust_px,
                                                    max_nfev=cfg.max_nfev, prior=prior, solver=cfg.solver,
                                                    smooth=smooth)
        rounds.append(_round_entry(binfo, len(o_cam), cfg.solver))
        cams, pts = cams_new, pts_new
        if r == 0:
            inl = binfo["residual_px"] <= cfg.outlier_px
            o_cam, o_pt, o_uv, o_img = o_cam[inl], o_pt[inl], o_uv[inl], o_img[inl]
    if depth_priors is not None and cfg.depth_prior_weight > 0:
        cams, pts, info["depth_prior"] = _depth_round(cams, pts, fx, cx, cy, o_cam, o_pt, o_uv, o_img, depth_priors,
                                                      held, prior, smooth, cfg, rounds)
    per_frame = np.bincount(o_cam, minlength=N)
    # how well the tracks determine each frame's rotation against the others (the last round's
    # problem at its solution); a held frame has the prior's uncertainty
    Sigma, free = camera_covariance(BundleProblem(cams, pts, fx, cx, cy, o_cam, o_pt, o_uv), cams, pts,
                                    tuple(np.flatnonzero(held).tolist()), "soft_l1", cfg.robust_px, prior,
                                    smooth)
    rot_std = np.degrees(relative_rotation_std(Sigma, free, N))
    rot_std[held] = cfg.prior_rot_deg
    info.update(rounds=rounds, observations_per_frame=per_frame.tolist(), held_frames=np.flatnonzero(held).tolist(),
                rot_std_rel_deg=rot_std.tolist(), seconds=time.perf_counter() - t0)
    T1 = params_to_poses(cams)
    turn = _rotation_deg(T1, T0)
    move = np.linalg.norm(camera_center(T1) - camera_center(T0), axis=1) / max(depth, 1e-300)
    info.update(change_deg_mean=float(turn.mean()), change_deg_max=float(turn.max()),
                change_rel_mean=float(move.mean()), change_rel_max=float(move.max()), depth=depth)
    rms = rounds[-1]["rms_px"]
    if not np.all(np.isfinite(T1)):
        info["reason"] = "the adjustment returned non-finite poses"
    elif rms > cfg.max_rms_px:
        info["reason"] = f"residual {rms:.2f} px > max_rms_px {cfg.max_rms_px}"
    elif turn.max() > cfg.max_change_deg or move.max() > cfg.max_change_rel:
        info["reason"] = (f"it moved a camera by {turn.max():.2f} deg / {move.max():.3f} x depth, beyond "
                          f"max_change_deg {cfg.max_change_deg} / max_change_rel {cfg.max_change_rel}")
    else:
        info["kept"] = True
        # its points seen by at least two inlier observations, in the adjusted poses' world
        info["points_xyz"] = pts[np.bincount(o_pt, minlength=len(pts)) >= 2]
        return T1, info
    return T0.copy(), info


def _depth_round(cams, pts, fx, cx, cy, o_cam, o_pt, o_uv, o_img, depth_priors, held, prior, smooth, cfg, rounds):
    """Step 3b of the module docstring: (cams, points, info)."""
    if len(depth_priors) != len(cams):
        raise ValueError(f"depth_priors must have one map (or None) per frame ({len(cams)}); got {len(depth_priors)}")
    logd = _log_prior_at(depth_priors, o_cam, o_img)
    T = params_to_poses(cams)
    z = _depths(T, pts)[o_cam, o_pt]
    has = np.isfinite(logd) & (z > 0)
    info = {"observations": int(has.sum())}
    if has.sum() < cfg.min_points:
        info["reason"] = f"{int(has.sum())} observations have a depth prior, fewer than min_points {cfg.min_points}"
        return cams, pts, info
    log_a = float(np.median(np.log(z[has]) - logd[has]))
    spread = _spread(cams)[2]
    prob = BundleProblem(cams, pts, fx, cx, cy, o_cam, o_pt, o_uv)
    new_cams, new_pts, _, binfo = bundle_adjust(prob, fixed_cams=tuple(np.flatnonzero(held).tolist()), loss="soft_l1",
                                                f_scale=cfg.robust_px, max_nfev=cfg.max_nfev, prior=prior,
                                                solver=cfg.solver, smooth=smooth,
                                                depth=(logd, log_a, cfg.depth_prior_weight))
    if not np.any(held):  # held frames pin the scale themselves; else back to the second round's path length
        new_cams, new_pts, k = _rescaled(new_cams, new_pts, spread)
    else:
        k = 1.0
    z_new = _depths(params_to_poses(new_cams), new_pts)[o_cam, o_pt]
    has &= z_new > 0
    rounds.append(dict(_round_entry(binfo, len(o_cam), cfg.solver), depth_prior=True))
    info.update(scale=float(np.exp(log_a)), rescaled=float(k),
                depth_change=float(np.exp(np.median(np.log(z_new[has] / z[has])))),
                rel_error_before=float(np.median(np.abs(np.expm1(np.log(z[has]) - log_a - logd[has])))),
                rel_error_after=float(np.median(np.abs(np.expm1(np.log(z_new[has]) - np.log(k) - log_a - logd[has])))))
    return new_cams, new_pts, info


def initial_poses(scene, config, note=None):
    """The poses a fresh run starts from (``Trainer``): the bundle adjustment of the scene's given
    poses when ``config.pose_init`` runs (mode "on"; "auto": unless the scene flags its poses as
    exact or the config turns pose refinement off, ``pose_solver.mode = "off"``) and it is kept,
    else None (the given poses). Says in the log what it did and why."""
    return adjusted_start(scene, config, note).poses


@dataclass(frozen=True)
class AdjustedStart:
    """What the bundle adjustment before training hands to the run (``adjusted_start``)."""

    poses: Optional[np.ndarray]  # (N, 4, 4) the kept adjustment's poses; None: the given poses
    held_frames: tuple = ()  # frames it held at their given poses (sorted)
    # per frame, its rotation's uncertainty relative to the others (``relative_rotation_std``)
    # over the prior's (``prior_rot_deg``); 1 for a held frame; () when nothing was kept
    rotation_uncertainty: tuple = ()
    depth: Optional[float] = None  # the median depth of its triangulated points in the given cameras
    points: Optional[np.ndarray] = None  # (P, 3) its points seen by two inlier observations or more


def adjusted_start(scene, config, note=None) -> AdjustedStart:
    """``initial_poses``, with the frames a kept adjustment held at their given poses and how well
    it determined each frame's rotation (``AdjustedStart``)."""
    say = note if note is not None else (lambda m: None)
    pc = config.pose_init
    if pc.mode == "off":
        say("pose initialisation (bundle adjustment of the given poses): off (config pose_init.mode = off)")
        return AdjustedStart(None)
    if pc.mode == "auto":
        if getattr(scene, "poses_trusted", None):
            say("pose initialisation (bundle adjustment): left out (the scene flags its poses as exact)")
            return AdjustedStart(None)
        if config.pose_solver.mode == "off":
            say("pose initialisation (bundle adjustment): left out (pose refinement is off: pose_solver.mode = off)")
            return AdjustedStart(None)
    frames = scene.frames
    K = np.asarray(frames[0].K, dtype=np.float64)
    if any(not np.allclose(f.K, K, rtol=1e-9, atol=0.0) or f.width != frames[0].width for f in frames):
        say("pose initialisation (bundle adjustment): left out (the frames do not share one camera)")
        return AdjustedStart(None)
    masks = [f.mask for f in frames] if all(f.mask is not None for f in frames) else None
    given = np.stack([f.cam_T_world for f in frames]).astype(np.float64)
    depth_priors, depth_note = None, ""
    if pc.depth_prior_weight > 0:
        if not getattr(scene, "has_depth_prior", False):
            depth_note = "; depth prior rows left out (the scene has no depth priors)"
        elif config.init.depth_prior_space != "depth":
            depth_note = (f"; depth prior rows left out (init.depth_prior_space = {config.init.depth_prior_space}: "
                          f"a scale and shift per frame leave the structure's shape free)")
        else:
            depth_priors = [f.depth_prior for f in frames]
    poses, info = adjust_given_poses([f.image for f in frames], masks, given, K, pc, seed=config.train.seed,
                                     depth_priors=depth_priors)
    dp = info.get("depth_prior")
    if dp is not None:
        depth_note = (f"; depth prior rows: {dp['reason']}" if "reason" in dp else
                      f"; depth prior rows on {dp['observations']} observations (weight {pc.depth_prior_weight:g}): "
                      f"the points' depths x{dp['depth_change']:.3f} (median), their prior's relative error "
                      f"{dp['rel_error_before']:.3f} -> {dp['rel_error_after']:.3f}, path rescaled x{dp['rescaled']:.3f}")
    counts = (f"{info.get('points', 0)} points from {info.get('tracks', 0)} tracks")
    if "fallback" in info:
        counts += f" ({info['fallback']})"
    if "rounds" in info:
        r = info["rounds"]
        counts += (f", reprojection rms {r[0]['rms_px_start']:.2f} -> {r[-1]['rms_px']:.2f} px over "
                   f"{r[-1]['observations']} observations, {info['seconds']:.1f}s")
    counts += depth_note
    if not info["kept"]:
        say(f"pose initialisation (bundle adjustment): given poses kept: {info['reason']} ({counts})")
        return AdjustedStart(None)
    held = info["held_frames"]
    if held:
        counts += (f"; {len(held)} frame(s) held at the given pose (fewer than {pc.min_frame_observations} "
                   f"observations): {held}")
    rel = np.asarray(info["rot_std_rel_deg"])
    say(f"pose initialisation (bundle adjustment): poses moved {info['change_deg_mean']:.3f} deg / "
        f"{info['change_rel_mean']:.4f} x depth on average (max {info['change_deg_max']:.3f} deg / "
        f"{info['change_rel_max']:.4f}); {counts}; rotation uncertainty against the other frames "
        f"{np.median(rel):.3f} deg median (min {rel.min():.3f}, max {rel.max():.3f}; prior {pc.prior_rot_deg:g})")
    return AdjustedStart(poses, tuple(int(k) for k in held), tuple(float(x) for x in rel / pc.prior_rot_deg),
                         float(info["depth"]), info["points_xyz"])


def track_reprojection_rms(cam_T_world, K, tracks, min_views=3, min_parallax_deg=1.0, clip_px=3.0):
    """How well poses explain point tracks on their own: every track triangulated with the poses
    and intrinsics (K (3, 3) or (N, 3, 3))
    (``triangulate_tracks``) and reprojected; the RMS of the pixel errors, each clipped at
    ``clip_px`` (a mismatch counts as a bad observation, not as an unbounded one).

    tracks: (obs_frame, obs_track, obs_uv, num_tracks) as ``pose.tracks.klt_tracks`` returns.
    Depends on no rendered depth: the pose solver's independent check (``PoseSolverConfig.
    track_check``). Returns (rms_px, observations used); (nan, 0) when no track qualifies.
    """
    T = np.asarray(cam_T_world, dtype=np.float64)
    of, ot, uv, nt = tracks[0], tracks[1], np.asarray(tracks[2], dtype=np.float64), int(tracks[3])
    X, ok = triangulate_tracks(T, K, of, ot, uv, nt, min_views, min_parallax_deg)
    sel = ok[ot]
    if not sel.any():
        return float("nan"), 0
    x = np.einsum("oij,oj->oi", T[of[sel], :3, :3], X[ot[sel]]) + T[of[sel], :3, 3]
    Ko = np.broadcast_to(np.asarray(K, dtype=np.float64), (T.shape[0], 3, 3))[of[sel]]
    proj = np.einsum("oij,oj->oi", Ko[:, :2, :2], x[:, :2] / x[:, 2:]) + Ko[:, :2, 2]
    err = np.minimum(np.linalg.norm(proj - uv[sel], axis=1), clip_px)
    return float(np.sqrt(np.mean(err ** 2))), int(sel.sum())
