"""Evaluation of a finished run (docs/method.md §10, docs/dataset_format.md §6) -> RUN/metrics.json.

- dvs: render each training frame at its optimised mid-exposure pose and time,
  compare with its sharp ground truth (PSNR, SSIM over the whole image).
- nvs: align the optimised mid-exposure trajectory to the true one with a
  similarity (Umeyama on camera centres), map each test view into the
  reconstruction frame with its inverse, render at the test time, compare.
- nvs_pose_opt (with ``test_pose_steps`` > 0, ``d2gs eval --test-pose-opt N``): the same test
  views after each aligned pose was refined against its image on the frozen scene for N steps
  (``pose_fit.fit_pose``; the protocol of BARF and BAD-Gaussians), with the mean rotation and
  translation of the refinement and the moving / static split of ``nvs``. Reported beside
  ``nvs``, never instead of it.
- nvs_rig: the same test views placed relative to the training frame of their time, as a
  stereo rig's second camera follows the first (DyBluRF's evaluation protocol): each view's
  pose in its frame's camera, carried onto our optimised mid pose of that frame. No global
  alignment enters, so a trajectory that is right locally but bent as a whole scores as its
  scene does. Reported beside ``nvs``, never instead of it.
- input_blur: the blurry inputs against the sharp frames (what doing nothing scores).
- trajectory: ATE, RPE_t, RPE_r of the optimised mid poses against the true
  ones, and the same three for the given (initial) poses under ``initial``.
Absent ground truth means absent keys, never zeros.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from d2gs_np.evaluation import metrics
from d2gs_np.data.io import load_scene
from d2gs_np.geometry.camera import camera_center
from d2gs_np.geometry.trajectory import frame_relative_poses
from d2gs_np.pose.config import PoseFitConfig
from d2gs_np.pose.fit import fit_pose
from d2gs_np.scene.render_inputs import render_inputs_fwd
from d2gs_np.train.checkpoint import atomic_write_text, check_output_path, load_checkpoint
from d2gs_np.train.model import SCENE_PREFIXES, Model, frame_render_fwd
from d2gs_np.train.run_folder import CHECKPOINT_NAME, FINAL_NAME, METRICS_NAME, check_scene_of_run


@dataclass
class LoadedRun:
    """A finished (or interrupted) run: its model (``train.model.Model``: ``render``,
    ``mid_pose``, ``mid_poses``, ``params``, ``poses_est``, ``times``) and the checkpoint's
    record (``meta``: steps, seconds of training, ``left_out``, the scene folder)."""

    run_dir: Path
    model: Model
    meta: dict


def load_run(run_dir) -> LoadedRun:
    """The finished model of a run (final.npz, else the latest checkpoint)."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise ValueError(f"run folder {run_dir} is a file; pass the folder given to d2gs train --out")
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder {run_dir} does not exist; train first (d2gs train SCENE --out {run_dir})")
    path = run_dir / FINAL_NAME
    if not path.exists():
        path = run_dir / CHECKPOINT_NAME
    arrays, meta = load_checkpoint(path)
    return LoadedRun(run_dir, Model.from_checkpoint(arrays, meta), meta)


def _image_metrics(pairs):
    """Mean PSNR, SSIM and FLIP (``metrics.flip``, lower is better) over image pairs. PSNR of
    identical images is infinite; strict JSON has no infinity, so it is written as null (with
    ``identical: true``)."""
    ps = [metrics.psnr(a, b) for a, b in pairs]
    ss = [metrics.ssim(a, b) for a, b in pairs]
    fl = [metrics.flip(a, b) for a, b in pairs]
    mean_psnr = float(np.mean(ps))
    out = {"psnr": mean_psnr if np.isfinite(mean_psnr) else None, "ssim": float(np.mean(ss)),
           "flip": float(np.mean(fl)), "num_images": len(pairs)}
    if not np.isfinite(mean_psnr):
        out["identical"] = True
    return out


def _split_psnr(pairs, masks) -> dict:
    """PSNR over the moving and over the static pixels of image pairs, pooled over the pairs (the
    squared error summed over every masked pixel and channel), and the moving share; {} when no
    pair has a mask. A pair without a mask counts as all static; a side with no pixel is None."""
    if all(m is None for m in masks):
        return {}
    sums, counts = np.zeros(2), np.zeros(2)
    for (a, b), m in zip(pairs, masks):
        moving = np.zeros(a.shape[:2], bool) if m is None else np.asarray(m, bool)
        e = ((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2).sum(-1)
        sums += [e[moving].sum(), e[~moving].sum()]
        counts += [a.shape[2] * moving.sum(), a.shape[2] * (~moving).sum()]

    def db(k):
        if counts[k] == 0:
            return None
        return float(10.0 * np.log10(counts[k] / sums[k])) if sums[k] > 0 else None
    return {"moving_psnr": db(0), "static_psnr": db(1), "moving_share": float(counts[0] / counts.sum())}


def evaluate(run: LoadedRun, scene, test_pose_steps: int = 0) -> dict:
    """Metrics dictionary of docs/method.md §10 for a loaded run and its scene (images loaded).
    ``test_pose_steps`` > 0 adds ``nvs_pose_opt`` (module docstring)."""
    out = {}
    frames, model = scene.frames, run.model
    if len(frames) != model.num_frames or not np.allclose([f.time for f in frames], model.times):
        raise ValueError(f"the scene's {len(frames)} frames do not match the {model.num_frames} frames (times) the "
                         "run was trained on; evaluate with the scene it was trained on")
    mids = model.mid_poses()
    outs = [model.render_outputs(mids[k], f.time, f.K, f.width, f.height) for k, f in enumerate(frames)]
    renders = [o["image"] for o in outs]
    if scene.has_sharp:
        masks = [f.mask for f in frames]
        pairs = [(r, f.sharp) for r, f in zip(renders, frames)]
        out["dvs"] = {**_image_metrics(pairs), **_split_psnr(pairs, masks)}
        pairs = [(f.image, f.sharp) for f in frames]
        out["input_blur"] = {**_image_metrics(pairs), **_split_psnr(pairs, masks)}
    if scene.has_depth:
        s = _depth_scale(mids, scene)
        out.setdefault("dvs", {})["depth"] = _depth_metrics([s * o["expected_depth"] for o in outs],
                                                            [f.depth for f in frames], [f.mask for f in frames], s)
    # What can be measured without ground truth: how well the model, blurred as in training,
    # explains the inputs, and how much finer detail its sharp renders carry than the inputs.
    refit = [frame_render_fwd(model, k, model.Ks[k], model.widths[k], model.heights[k])[0]["image"]
             for k in range(len(frames))]
    out["input_fit"] = _image_metrics([(r, f.image) for r, f in zip(refit, frames)])
    g_renders = float(np.mean([metrics.gradient_energy(r) for r in renders]))
    g_inputs = float(np.mean([metrics.gradient_energy(f.image) for f in frames]))
    out["sharpness"] = {"renders": g_renders, "inputs": g_inputs,
                        "ratio": g_renders / g_inputs if g_inputs > 0 else None}
    if scene.has_gt_poses and len(frames) >= 3:
        try:
            out.update(_trajectory_and_nvs(run, scene, mids, test_pose_steps))
        except ValueError as e:  # e.g. a camera that never moves: no Sim(3) alignment exists
            out["trajectory"] = {"skipped": str(e)}
    elif scene.test_frames and len(frames) >= 3:
        # no true poses: test views in the given poses' frame (e.g. a stereo benchmark's other camera)
        try:
            out.update(_novel_views(run, scene, mids, run.model.poses_est, test_pose_steps))
            out["nvs"]["aligned_to"] = "given poses"
        except ValueError as e:
            out["nvs"] = {"skipped": str(e)}
    out["train_seconds"] = float(run.meta["seconds"])
    out["steps"] = int(run.meta["step"])
    out["num_gaussians"] = int(model.num_gaussians())
    out["left_out"] = list(run.meta["left_out"])
    return out


def align_with_orientations(est_cam_T_world, gt_cam_T_world, depth=None):
    """Sim(3) (s, R, t) with gt ~= s R est + t, fitted (Umeyama) on each camera's centre and on the
    three points one length d along its axes, so orientations pin the rotation even when the
    centres are (nearly) collinear.

    d: ``depth`` (the scene's depth in the ground truth's units, e.g. ``Scene.scene_scale``), else
    the spread of the true centres (RMS distance from their mean); the estimate's d is scaled by
    the ratio of the two spreads. With d at the scene's depth a rotation error and a centre error
    weigh as they move the image (f d_theta against f |d_c| / depth): fitted at the spread (a
    hand-held path is short), the centres' small errors outweighed the orientations and turned
    the alignment far more than the cameras were off (docs/results.md §14)."""
    ce, cg = camera_center(est_cam_T_world), camera_center(gt_cam_T_world)
    spread_e = float(np.sqrt(np.mean(np.sum((ce - ce.mean(0)) ** 2, axis=1))))
    spread_g = float(np.sqrt(np.mean(np.sum((cg - cg.mean(0)) ** 2, axis=1))))
    d_g = float(depth) if depth is not None and np.isfinite(depth) and depth > 0 else (spread_g or 1.0)
    d_e = d_g * spread_e / spread_g if spread_g > 0 and spread_e > 0 else d_g

    def points(T, c, d):
        axes = np.swapaxes(np.asarray(T)[:, :3, :3], 1, 2)  # columns: camera axes in world coordinates
        return np.concatenate([c] + [c + d * axes[:, :, j] for j in range(3)])
    return metrics.umeyama(points(est_cam_T_world, ce, d_e), points(gt_cam_T_world, cg, d_g), with_scale=True)


def baseline_errors(est_cam_T_world, gt_cam_T_world, depth=None, gaps=(1, 4, 8)):
    """{gap: (median |b_est| / |b_true|, median angle between them in degrees)} of the baselines
    between frames k and k + gap in camera k's axes, the estimate's scaled by the alignment of
    ``align_with_orientations`` (at ``depth``). Gaps the clip is too short for are left out. Why the
    short baselines matter to novel views: docs/results.md §4, session 43."""
    est, gt = np.asarray(est_cam_T_world, np.float64), np.asarray(gt_cam_T_world, np.float64)
    s = align_with_orientations(est, gt, depth)[0]
    ce, cg = camera_center(est), camera_center(gt)
    out = {}
    for d in gaps:
        if d >= len(gt):
            continue
        bt = np.einsum("nij,nj->ni", gt[:-d, :3, :3], cg[d:] - cg[:-d])
        be = s * np.einsum("nij,nj->ni", est[:-d, :3, :3], ce[d:] - ce[:-d])
        nt, ne = np.linalg.norm(bt, axis=1), np.linalg.norm(be, axis=1)
        cos = np.clip(np.sum(bt * be, axis=1) / (nt * ne), -1.0, 1.0)
        out[d] = (float(np.median(ne / nt)), float(np.degrees(np.median(np.arccos(cos)))))
    return out


def _trajectory_and_nvs(run: LoadedRun, scene, mids, test_pose_steps=0) -> dict:
    out = {}
    frames = scene.frames
    gt = np.stack([f.gt_cam_T_world for f in frames])
    ate = metrics.ate(mids, gt)
    rpe_t, rpe_r = metrics.rpe(mids, gt)
    ate0 = metrics.ate(run.model.poses_est, gt)
    rpe_t0, rpe_r0 = metrics.rpe(run.model.poses_est, gt)
    # The alignment's own scale: ATE is taken after a free Sim(3), so a trajectory that shrank or
    # grew as a whole keeps a small ATE; "scale" (gt ~= scale R est + t) says when it did.
    scale, scale0 = metrics.align_trajectory(mids, gt)[0], metrics.align_trajectory(run.model.poses_est, gt)[0]
    out["trajectory"] = {"ate": float(ate), "rpe_t": float(rpe_t), "rpe_r": float(rpe_r), "scale": float(scale),
                         "initial": {"ate": float(ate0), "rpe_t": float(rpe_t0), "rpe_r": float(rpe_r0),
                                     "scale": float(scale0)}}
    P0 = run.model.poses_init
    if P0 is not None and not np.array_equal(P0, run.model.poses_est):
        # training started from the bundle adjustment of the given poses (pose_init.py)
        rpe_tb, rpe_rb = metrics.rpe(P0, gt)
        out["trajectory"]["bundle_adjusted"] = {"ate": float(metrics.ate(P0, gt)), "rpe_t": float(rpe_tb),
                                                "rpe_r": float(rpe_rb),
                                                "scale": float(metrics.align_trajectory(P0, gt)[0])}
    if scene.test_frames:
        out.update(_novel_views(run, scene, mids, gt, test_pose_steps))
    return out


def _novel_views(run: LoadedRun, scene, mids, reference, test_pose_steps=0) -> dict:
    """``nvs``, ``nvs_rig`` (and ``nvs_pose_opt``) of the scene's test views, given in the frame of
    the ``reference`` poses (N, 4, 4) of the training frames: the true ones, or the given ones for
    a scene without ground-truth poses whose test views share the given poses' frame (a stereo
    benchmark's second camera, docs/dataset_format.md §11)."""
    out = {}
    # The similarity aligning our trajectory to the reference, inverted, carries the test views
    # into the reconstruction's frame. It is fitted on camera centres AND orientations: a
    # hand-held path is close to a line or an arc, about which centres alone leave the rotation
    # undetermined (ATE keeps the centres-only protocol).
    s, R, t = metrics.sim3_inverse(*align_with_orientations(mids, reference, scene.scene_scale))
    views = scene.test_frames
    seen = [seen_by_training(f.cam_T_world, f, scene.frames) for f in views] if _has_seen_split(scene) else None
    model = run.model
    poses = [metrics.sim3_apply_to_poses(s, R, t, f.cam_T_world) for f in views]
    out["nvs"] = _score_views(model, poses, scene, s, seen)
    frame_of = frame_of_views(scene)
    if frame_of is None:
        out["nvs_rig"] = {"skipped": "a test view's time is no training frame's time: no frame to place it beside"}
    else:
        # reference units per ours is 1 / s (s maps the reference into our frame)
        rig = frame_relative_poses(np.stack([f.cam_T_world for f in views]), reference[frame_of], mids[frame_of],
                                   scale=1.0 / s)
        out["nvs_rig"] = {**_score_views(model, list(rig), scene, s, seen), "frames": [int(k) for k in frame_of]}
    if test_pose_steps > 0:
        fitted, moves = [], []
        scene_params = {n: v for n, v in model.params.items() if n.startswith(SCENE_PREFIXES)}
        for pose, f in zip(poses, views):
            ri, _ = render_inputs_fwd(scene_params, float(f.time), model.config.deform)
            pose_fit, info = fit_pose(ri, pose, f.K, f.width, f.height, f.image, model.background,
                                      PoseFitConfig(steps=int(test_pose_steps)), model.config.render)
            fitted.append((model.render(pose_fit, f.time, f.K, f.width, f.height), f.image))
            moves.append((float(np.linalg.norm(info["xi"][3:])), float(np.linalg.norm(info["xi"][:3]))))
        out["nvs_pose_opt"] = {**_image_metrics(fitted), **_split_psnr(fitted, [f.mask for f in views]),
                               "steps": int(test_pose_steps),
                               "mean_rotation_deg": float(np.degrees(np.mean([m[0] for m in moves]))),
                               "mean_translation": float(np.mean([m[1] for m in moves]))}
    return out


def _score_views(model, poses, scene, s, seen=None) -> dict:
    """The test views rendered at ``poses`` (our frame) and scored against their images: image
    metrics, the moving / static split, with true depth the depth errors (our depths divided by
    ``s``, the similarity that maps the reference's units into ours), and with ``seen`` (the
    views' ``seen_by_training`` masks) the seen / unseen split; ``views``: each view's figures."""
    views = scene.test_frames
    outs = [model.render_outputs(p, f.time, f.K, f.width, f.height) for p, f in zip(poses, views)]
    pairs = [(o["image"], f.image) for o, f in zip(outs, views)]
    res = {**_image_metrics(pairs), **_split_psnr(pairs, [f.mask for f in views])}
    split = None
    if all(f.depth is not None for f in views):
        res["depth"] = _depth_metrics([o["expected_depth"] / s for o in outs], [f.depth for f in views],
                                      [f.mask for f in views], 1.0 / s)
        if seen is not None:
            split = _seen_split(pairs, seen)
            res.update(_seen_psnr(split))
    res["views"] = _view_metrics(pairs, scene, split)
    return res


FRAME_TIME_TOL = 1e-6  # normalised time within which a test view belongs to a training frame


def frame_of_views(scene):
    """Index of the training frame at each test view's time, or None when some view has none."""
    times = np.array([f.time for f in scene.frames])
    out = []
    for f in scene.test_frames:
        k = int(np.argmin(np.abs(times - f.time)))
        if abs(times[k] - f.time) > FRAME_TIME_TOL:
            return None
        out.append(k)
    return np.array(out, dtype=np.int64)


SEEN_DEPTH_TOL = 0.01  # relative depth agreement that counts a training frame as seeing a point


def seen_by_training(view_pose, view, frames):
    """(H, W) bool: the pixels of a view (pose ``view_pose``, intrinsics and true depth ``view.depth``)
    whose surface point some training frame sees: inside its image, in front of it, and at its
    true depth there within SEEN_DEPTH_TOL (``frames``' true poses and depth maps). False where
    the view has no surface."""
    from d2gs_np.geometry.camera import project_points

    t = view.depth
    ok = np.isfinite(t) & (t > 0)
    i, j = np.nonzero(ok)
    rays = (np.linalg.inv(view.K) @ np.stack([j + 0.5, i + 0.5, np.ones(len(i))])) * t[i, j]
    T = np.linalg.inv(view_pose)
    pts = (T[:3, :3] @ rays + T[:3, 3:4]).T
    seen = np.zeros(len(pts), bool)
    for f in frames:
        uv, z = project_points(pts, f.gt_cam_T_world, f.K)
        c, r = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (z > 0) & (c >= 0) & (c < f.width) & (r >= 0) & (r < f.height)
        d = np.full(len(pts), np.nan)
        d[inside] = f.depth[r[inside], c[inside]]
        seen |= inside & (np.abs(z - d) <= SEEN_DEPTH_TOL * d)
    out = np.zeros(t.shape, bool)
    out[i[seen], j[seen]] = True
    return out


def _has_seen_split(scene) -> bool:
    """Whether the test views can be split into seen and unseen pixels: true depth for every view
    and true poses for every frame."""
    return scene.has_depth and scene.has_gt_poses and all(f.depth is not None for f in scene.test_frames)


def _seen_split(pairs, seen) -> list:
    """Per test view: the squared error summed over its seen and its unseen pixels (``seen``: the
    views' ``seen_by_training`` masks), and their value counts, as ((2,), (2,)) arrays."""
    out = []
    for (a, b), m in zip(pairs, seen):
        e = ((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2).sum(-1)
        out.append((np.array([e[m].sum(), e[~m].sum()]), np.array([3 * m.sum(), 3 * (~m).sum()])))
    return out


def _db(sums, counts, k):
    return float(10.0 * np.log10(counts[k] / sums[k])) if counts[k] and sums[k] > 0 else None


def _seen_psnr(split) -> dict:
    """Novel-view PSNR on the pixels some training frame saw (``seen_by_training``) and on the
    rest, pooled over the test views (``split``: their ``_seen_split``), and the unseen share: what
    a test camera beside the path sees that no training view did cannot be reconstructed, only
    extrapolated."""
    sums, counts = sum(s for s, _ in split), sum(c for _, c in split)
    return {"seen_psnr": _db(sums, counts, 0), "unseen_psnr": _db(sums, counts, 1),
            "unseen_share": float(counts[1] / counts.sum())}


def _view_metrics(pairs, scene, split=None) -> list:
    """Each test view's time and PSNR; with true depth maps and poses also its seen and unseen
    PSNR and unseen share (``split``: the views' ``_seen_split``). A test view beside the path's
    end sees a strip no training frame saw, so its PSNR is capped whatever the model does
    elsewhere: at ``unseen_psnr - 10 log10(unseen_share)`` with its unseen pixels as rendered
    (docs/method.md §10)."""
    views = []
    for k, ((a, b), f) in enumerate(zip(pairs, scene.test_frames)):
        p = float(metrics.psnr(a, b))
        v = {"time": float(f.time), "psnr": p if np.isfinite(p) else None}
        if split is not None:
            s, c = split[k]
            v.update(seen_psnr=_db(s, c, 0), unseen_psnr=_db(s, c, 1), unseen_share=float(c[1] / c.sum()))
        views.append(v)
    return views


def _depth_scale(mids, scene) -> float:
    """The factor that carries the reconstruction's depths into the true depths' units: the scale
    of the similarity aligning our mid poses to the true ones (as the novel views use it); 1
    without true poses (the given poses' units are then the truth's) or when no alignment exists."""
    if not scene.has_gt_poses or len(scene.frames) < 3:
        return 1.0
    gt = np.stack([f.gt_cam_T_world for f in scene.frames])
    try:
        return float(align_with_orientations(mids, gt, scene.scene_scale)[0])
    except ValueError:
        return 1.0


def _depth_metrics(preds, trues, masks, scale) -> dict:
    """AbsRel and delta1 (``metrics.depth_errors``) pooled over views (every scored pixel weighs
    alike), on all, static and moving pixels (``masks``; a view without one is all static), and
    the ``scale`` the rendered depths were multiplied by."""
    terms = {"": [], "_static": [], "_moving": []}
    for p, t, m in zip(preds, trues, masks):
        moving = np.zeros(np.shape(t), bool) if m is None else np.asarray(m, bool)
        terms[""].append(metrics.depth_error_terms(p, t))
        terms["_static"].append(metrics.depth_error_terms(p, t, ~moving))
        terms["_moving"].append(metrics.depth_error_terms(p, t, moving))
    out = {}
    for part, ts in terms.items():
        rel = np.concatenate([r for r, _ in ts])
        ratio = np.concatenate([q for _, q in ts])
        out[f"absrel{part}"] = float(rel.mean()) if rel.size else None
        out[f"delta1{part}"] = float(np.mean(ratio < 1.25)) if rel.size else None
    out["scale"] = float(scale)
    return out


def verdict(result: dict, baseline: dict = None) -> list:
    """What a run's metrics say about deblurring, in plain lines (``d2gs eval``, ``d2gs demo``, the
    report). With sharp ground truth: the deblurred renders against the blurry inputs, and against
    ``baseline`` (the metrics of a no-blur run of the same scene and budget) when given; a loss is
    said first, in so many words. Without: the blurred model's fit to the inputs and the renders'
    sharpness against the inputs'."""
    lines = []
    d, i = _psnr_of(result, "dvs"), _psnr_of(result, "input_blur")
    if d is not None and i is not None:
        gain = d - i
        if gain < 0:
            lines.append(f"the method LOST to its input: deblurred renders {d:.2f} dB against the sharp frames, "
                         f"{-gain:.2f} dB below the blurry inputs ({i:.2f} dB)")
        else:
            lines.append(f"deblurred renders {d:.2f} dB against the sharp frames, {gain:+.2f} dB over the blurry "
                         f"inputs ({i:.2f} dB)")
        dm, im = (result.get(k, {}).get("moving_psnr") for k in ("dvs", "input_blur"))
        if dm is not None and im is not None:
            lines.append(f"{'on the moving pixels the method LOST to its input' if dm < im else 'on the moving pixels'}"
                         f": {dm:.2f} dB against the blurry inputs' {im:.2f} dB ({dm - im:+.2f} dB; "
                         f"{100 * result['dvs']['moving_share']:.0f} % of the pixels move)")
        b = _psnr_of(baseline or {}, "dvs")
        if b is not None:
            lines.append(f"{'the blur model LOST to the no-blur baseline' if d < b else 'the blur model beat the no-blur baseline'}"
                         f": {d - b:+.2f} dB against its {b:.2f} dB (n = 1, same scene and budget)")
    else:
        fit, ratio = _psnr_of(result, "input_fit"), (result.get("sharpness") or {}).get("ratio")
        if fit is not None:
            line = f"no sharp frames to score against: the model, blurred as in training, fits the inputs at {fit:.2f} dB"
            if ratio is not None:
                line += (f"; its sharp renders carry {ratio:.2f}x the inputs' gradient energy "
                         f"({'sharper than' if ratio > 1 else 'no sharper than'} the inputs)")
            lines.append(line)
    return lines


def _psnr_of(result, key):
    part = result.get(key) if isinstance(result, dict) else None
    return part.get("psnr") if isinstance(part, dict) else None


def evaluate_run(run_dir, scene_dir=None, test_pose_steps: int = 0, note=None) -> dict:
    """Load a run and its scene, evaluate, write RUN/metrics.json atomically, return the metrics.
    ``test_pose_steps`` > 0 adds novel views after test-pose refinement (``nvs_pose_opt``).
    A scene other than the one the run was trained on (frames, sizes, times or image content,
    ``data.fingerprint``) is refused before any work; ``note(line)`` hears of a copy of it in
    another folder."""
    run = load_run(run_dir)
    check_output_path(Path(run_dir) / "metrics.json", "metrics file", is_file=True)  # before the evaluation
    given = scene_dir is not None
    scene_dir = scene_dir or run.meta.get("scene_root")
    if scene_dir is None:
        raise ValueError("the run does not record its scene folder; pass it explicitly (d2gs eval RUN --scene SCENE)")
    scene = load_scene(scene_dir)
    fix = ("evaluate with the run's own scene (leave out --scene) or a copy of it" if given else
           "the folder has changed since training; evaluate with the scene as it was (--scene COPY)")
    for line in check_scene_of_run(run.meta, scene, run_dir, "--scene" if given else "the run's own scene", fix):
        if note is not None:
            note(line)
    result = evaluate(run, scene, test_pose_steps)
    atomic_write_text(Path(run_dir) / METRICS_NAME, json.dumps(result, indent=2, allow_nan=False))
    return result
