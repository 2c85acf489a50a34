"""How far a run's exposure endpoints are from the true ones (docs/method.md §4), beside the
velocity start's, on a synthetic scene with ``gt_exposure_start`` / ``gt_exposure_end``.

For each RUN SCENE pair, medians over the frames, each as a rotation in degrees (``_deg``) and a
translation in scene units (``_t``):

- spread: ``T_e T_s^-1`` (the exposure's own motion, invariant to the world frame) against the
  truth's; learned, and the velocity start's from the run's start poses (the given poses or their
  bundle adjustment) for each ``--windows`` h (``TrajectoryConfig.velocity_window``); beside the
  true exposures' own motion (``spread_true_deg``, ``spread_true_t``) for scale;
- mid: the learned geodesic mid-exposure pose against the true mid pose (after no alignment:
  meaningful for runs on true poses or after a small ATE);
- blur (``_px``, suite scenes only: it needs the true world of ``suite_config.json``): what the
  blur looks like in the image. Every 4th pixel of each frame is lifted at its true depth into the
  camera at the exposure's geodesic midpoint; its blur vector is its projection at the exposure's
  end minus at its start. The error is |b - b*| against the true exposure's b*, median over pixels
  and frames, in pixels; ``blur_true_px`` is the median length of b* for scale. Unlike the angles,
  it weighs rotation and translation as the image sees them (translation by inverse depth).
  ``blur_ratio_learned`` is the learned blur's length against the true one (the median over
  frames of median |b| / median |b*|): below 1 the learned exposure is shorter than the truth.
  Read it beside the comb of virtual views: n views at u_i = i / (n - 1) (Eq. 9) blur like a
  box n / (n - 1) times the endpoints' spread, and the suite's blurry frames, 16 sub-frames
  placed the same way, like a box 16 / 15 times the true one; so learned endpoints that blur
  exactly as the frames do have a ratio of about (16 / 15) (n - 1) / n (0.8 for the 4 views
  of a 3 px blur; docs/method.md §4).

    python examples/exposure_error.py runs/photo_room scenes/photo_room_s0_blurry_true \\
        runs/wall_disk scenes/wall_disk_s0_blurry_true --windows 1 3
"""
from __future__ import annotations

import argparse

import numpy as np

from d2gs_np.data.io import load_scene
from d2gs_np.evaluation.runs import load_run
from d2gs_np.geometry import se3_exp, se3_interpolate, se3_inverse
from d2gs_np.geometry.camera import project_points, unproject_points
from d2gs_np.geometry.so3 import so3_log
from d2gs_np.blur.endpoints import XI_END, XI_START, velocity_endpoints


def rotation_deg(T):
    """(...,) rotation angle of (..., 4, 4) rigid transforms in degrees (of their rotation block)."""
    return np.degrees(np.linalg.norm(so3_log(np.asarray(T)[..., :3, :3]), axis=-1))


def translation(T):
    """(...,) length of the translation of (..., 4, 4) rigid transforms, in scene units."""
    return np.linalg.norm(np.asarray(T)[..., :3, 3], axis=-1)


def spread_error(starts, ends, true_starts, true_ends):
    """(N,) the difference D = (T_e T_s^-1)(T*_e T*_s^-1)^-1 of the exposures' own motions:
    (rotation of D in degrees, translation of D in scene units)."""
    D = np.einsum("nij,njk->nik", own_motion(starts, ends), se3_inverse(own_motion(true_starts, true_ends)))
    return rotation_deg(D), translation(D)


def own_motion(starts, ends):
    """(N, 4, 4) T_e T_s^-1: an exposure's own motion, invariant to the world frame."""
    return np.einsum("nij,njk->nik", ends, se3_inverse(starts))


def mid_camera_points(scene_dir, true_starts, true_ends, step=4, scene=None):
    """Per frame (M, 3) points in the camera of the true exposure's geodesic midpoint: every
    ``step``-th pixel lifted at the true depth of the scene's world (suite scenes: rebuilt from
    ``suite_config.json``); None for a scene without one. ``scene``: the folder already loaded."""
    import json
    from pathlib import Path

    from d2gs_np.data.suite import SuiteConfig, build_suite_world, suite_depth_map

    cfg_path = Path(scene_dir) / "suite_config.json"
    if not cfg_path.exists():
        return None
    world = build_suite_world(SuiteConfig(**json.loads(cfg_path.read_text())))
    scene = load_scene(scene_dir, load_images=False) if scene is None else scene
    mids = se3_interpolate(true_starts, true_ends, 0.5)
    out = []
    for k, f in enumerate(scene.frames):
        jj, ii = np.meshgrid(np.arange(0, f.width, step), np.arange(0, f.height, step))
        depth = suite_depth_map(world, f.gt_cam_T_world, f.time, f.K, f.width, f.height)[ii, jj]
        ok = np.isfinite(depth)
        X = unproject_points(np.stack([jj[ok], ii[ok]], axis=1) + 0.5, depth[ok], f.gt_cam_T_world, f.K)
        out.append(X @ mids[k][:3, :3].T + mids[k][:3, 3])  # world -> the exposure's mid camera
    return out


def blur_vectors(points, K, starts, ends):
    """Per frame (M, 2) blur vectors in pixels: the projection of each mid-camera point at the
    exposure's end minus at its start (mid = the geodesic midpoint of starts, ends)."""
    mids = se3_interpolate(starts, ends, 0.5)
    return [project_points(x, ends[k] @ se3_inverse(mids[k]), K)[0]
            - project_points(x, starts[k] @ se3_inverse(mids[k]), K)[0] for k, x in enumerate(points)]


def _median_distance(b, bt):
    return float(np.median(np.concatenate([np.linalg.norm(u - v, axis=1) for u, v in zip(b, bt)])))


def blur_error_px(points, K, starts, ends, true_starts, true_ends):
    """Median |b - b*| over all points and frames (``blur_vectors``), in pixels."""
    return _median_distance(blur_vectors(points, K, starts, ends), blur_vectors(points, K, true_starts, true_ends))


def blur_length_ratio(b, bt):
    """Median over frames of median |b| / median |b*| (``blur_vectors`` of a run against the
    truth); frames whose true blur is shorter than 1e-9 px are skipped (nan if all are)."""
    r = []
    for u, v in zip(b, bt):
        true = float(np.median(np.linalg.norm(v, axis=1)))
        if true > 1e-9:
            r.append(float(np.median(np.linalg.norm(u, axis=1))) / true)
    return float(np.median(r)) if r else float("nan")


def exposure_errors(run_dir, scene_dir, windows=(1, 3)):
    """Medians over the frames: ``spread_true_deg`` / ``_t`` (the true exposures' own motion, for scale),
    ``spread_learned_deg`` / ``_t``, ``mid_learned_deg`` / ``_t`` and ``spread_start_h{h}_deg`` /
    ``_t`` (module docstring); ``_deg`` in degrees, ``_t`` in scene units; on suite scenes also
    ``blur_true_px``, ``blur_learned_px``, ``blur_ratio_learned`` and ``blur_start_h{h}_px``."""
    scene = load_scene(scene_dir)
    if any(f.gt_exposure_start is None or f.gt_exposure_end is None for f in scene.frames):
        raise SystemExit(f"{scene_dir}: no gt_exposure_start / gt_exposure_end; use a synthetic scene")
    model = load_run(run_dir).model
    if XI_START not in model.params:
        raise SystemExit(f"{run_dir}: the run has no direct endpoint blocks (blur model off, or PoseNet)")
    ts, te = (np.stack([getattr(f, a) for f in scene.frames]) for a in ("gt_exposure_start", "gt_exposure_end"))
    true_own = own_motion(ts, te)
    out = {"spread_true_deg": float(np.median(rotation_deg(true_own))), "spread_true_t": float(np.median(translation(true_own)))}

    def put(name, rot, trans):
        out[f"{name}_deg"] = float(np.median(rot))
        out[f"{name}_t"] = float(np.median(trans))

    points = mid_camera_points(scene_dir, ts, te, scene=scene)
    K = scene.frames[0].K
    if points is not None:
        true_blur = blur_vectors(points, K, ts, te)  # once: every error below is against it
        out["blur_true_px"] = float(np.median(np.concatenate([np.linalg.norm(b, axis=1) for b in true_blur])))
    Ts = np.einsum("nij,njk->nik", se3_exp(model.params[XI_START]), model.poses_ref)
    Te = np.einsum("nij,njk->nik", se3_exp(model.params[XI_END]), model.poses_ref)
    put("spread_learned", *spread_error(Ts, Te, ts, te))
    if points is not None:
        learned_blur = blur_vectors(points, K, Ts, Te)
        out["blur_learned_px"] = _median_distance(learned_blur, true_blur)
        out["blur_ratio_learned"] = blur_length_ratio(learned_blur, true_blur)
    mids = model.mid_poses()  # the geodesic midpoints of (Ts, Te)
    true_mids = np.stack([f.gt_cam_T_world for f in scene.frames])
    D = np.einsum("nij,njk->nik", mids, se3_inverse(true_mids))
    put("mid_learned", rotation_deg(D), translation(D))
    times = np.array([f.time for f in scene.frames])
    fraction = scene.exposure_fraction if scene.exposure_fraction is not None else 0.5
    for h in windows:
        xs, xe = velocity_endpoints(model.start_poses, times, fraction, window=h)
        Vs = np.einsum("nij,njk->nik", se3_exp(xs), model.start_poses)
        Ve = np.einsum("nij,njk->nik", se3_exp(xe), model.start_poses)
        put(f"spread_start_h{h}", *spread_error(Vs, Ve, ts, te))
        if points is not None:
            out[f"blur_start_h{h}_px"] = _median_distance(blur_vectors(points, K, Vs, Ve), true_blur)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pairs", nargs="+", help="RUN SCENE [RUN SCENE ...]")
    ap.add_argument("--windows", type=int, nargs="+", default=[1, 3])
    args = ap.parse_args()
    if len(args.pairs) % 2:
        raise SystemExit("give RUN SCENE pairs")
    rows = [(r, exposure_errors(r, s, args.windows)) for r, s in zip(args.pairs[::2], args.pairs[1::2])]
    keys = list(rows[0][1])
    print("| run | " + " | ".join(keys) + " |")
    print("|---|" + "---|" * len(keys))
    for r, e in rows:
        print(f"| {r} | " + " | ".join(f"{e[k]:.3f}" for k in keys) + " |")


if __name__ == "__main__":
    main()
