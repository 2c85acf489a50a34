"""Where a run's novel views land, and the camera baselines behind it (docs/results.md §4, "Novel
views beside their frame's camera", session 43).

For each test view, the image shift between the model's render and the true view on the static
pixels (OpenCV's DIS optical flow, render -> truth; 10 px borders left out): its median vector and
the median distance of the pixels' shifts from it, with the test pose through the global alignment
(`nvs`) and beside its frame's camera (`nvs_rig`), and the same for the training frame of its time
against its sharp frame. A near-uniform shift is the view's pose or the parallax of its offset;
a wide spread, geometry. Then the camera baselines between frames k and k + gap (gaps 1, 4, 8), in
the first camera's axes, of the given, the bundle-adjusted and the trained poses against the true
ones: median length ratio (after the alignment's scale) and median direction error in degrees;
with --sharp-tracks also those of the same bundle adjustment run on the sharp frames instead of
the blurry ones (what better tracks would give; needs the scene's sharp frames).

    python examples/nvs_registration.py RUN [RUN ...] [--sharp-tracks]
"""
from __future__ import annotations

import argparse

import numpy as np

from d2gs_np.evaluation.runs import baseline_errors  # the tests reach it here too

GAPS = (1, 4, 8)
BORDER_PX = 10  # flow at the image border is extrapolated: left out


def view_shift(render, truth, mask=None, border=BORDER_PX):
    """(median shift (2,) in px, x then y, render -> truth; median distance of the pixels' shifts
    from it) over the pixels off ``mask`` (moving pixels) and off the border."""
    import cv2

    grey = [cv2.cvtColor((np.clip(a, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY) for a in (render, truth)]
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(grey[0], grey[1], None)
    keep = np.ones(grey[0].shape, bool) if mask is None else ~np.asarray(mask, bool)
    keep[:border], keep[-border:], keep[:, :border], keep[:, -border:] = False, False, False, False
    v = flow[keep]
    if len(v) == 0:
        raise ValueError(f"no pixel left to measure: the image is {grey[0].shape} and the border {border} px")
    mu = np.median(v, axis=0)
    return mu, float(np.median(np.linalg.norm(v - mu, axis=1)))


def _fmt_shift(shift):
    mu, spread = shift
    return f"({mu[0]:+.2f}, {mu[1]:+.2f}) ± {spread:.2f}"


def report(run_dir, sharp_tracks=False) -> str:
    from d2gs_np.data.io import load_scene
    from d2gs_np.evaluation import metrics
    from d2gs_np.evaluation.runs import frame_of_views, align_with_orientations, load_run
    from d2gs_np.geometry.trajectory import frame_relative_poses

    run = load_run(run_dir)
    scene = load_scene(run.meta["scene_root"])
    if not scene.has_gt_poses or not scene.test_frames:
        raise SystemExit(f"{run_dir}: its scene has no true poses or no test views to measure against")
    model, frames = run.model, scene.frames
    mids = model.mid_poses()
    gt = np.stack([f.gt_cam_T_world for f in frames])
    fwd = align_with_orientations(mids, gt, scene.scene_scale)
    s, R, t = metrics.sim3_inverse(*fwd)
    k = frame_of_views(scene)
    rig = None if k is None else frame_relative_poses(np.stack([f.cam_T_world for f in scene.test_frames]), gt[k],
                                                      mids[k], scale=fwd[0])
    lines = [f"{run_dir}", "| test view t | shift, aligned px | shift, beside its frame px | its frame's render px |",
             "|---|---|---|---|"]
    for j, f in enumerate(scene.test_frames):
        aligned = view_shift(model.render(metrics.sim3_apply_to_poses(s, R, t, f.cam_T_world), f.time, f.K, f.width,
                                          f.height), f.image, f.mask)
        beside = "–" if rig is None else _fmt_shift(view_shift(model.render(rig[j], f.time, f.K, f.width, f.height),
                                                               f.image, f.mask))
        own = "–"
        if k is not None and frames[k[j]].sharp is not None:
            fr = frames[k[j]]
            own = _fmt_shift(view_shift(model.render(mids[k[j]], fr.time, fr.K, fr.width, fr.height), fr.sharp, fr.mask))
        lines.append(f"| {f.time:.2f} | {_fmt_shift(aligned)} | {beside} | {own} |")
    lines += ["", "| poses | " + " | ".join(f"gap {d}: length ratio, direction error" for d in GAPS) + " |",
              "|---" * (len(GAPS) + 1) + "|"]
    adjusted = model.poses_init if model.poses_init is not None else None
    rows = [("given", model.poses_est), ("bundle-adjusted", adjusted), ("trained", mids)]
    if sharp_tracks:
        rows.append(("bundle-adjusted on the sharp frames", _adjusted_on_sharp(scene)))
    for name, P in rows:
        if P is None:
            continue
        e = baseline_errors(P, gt, scene.scene_scale)
        lines.append(f"| {name} | " + " | ".join(f"x{e[d][0]:.2f}, {e[d][1]:.0f}°" if d in e else "–" for d in GAPS)
                     + " |")
    return "\n".join(lines)


def _adjusted_on_sharp(scene):
    """The default bundle adjustment of the scene's given poses on tracks through its sharp frames."""
    import copy

    from d2gs_np.pose.given import initial_poses
    from d2gs_np.train.config import ExperimentConfig

    if any(f.sharp is None for f in scene.frames):
        raise SystemExit("--sharp-tracks needs the scene's sharp frames")
    sharp = copy.copy(scene)
    sharp.frames = [copy.copy(f) for f in scene.frames]
    for f in sharp.frames:
        f.image = f.sharp
    return initial_poses(sharp, ExperimentConfig())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run folders of scenes with true poses and test views (the suite's)")
    ap.add_argument("--sharp-tracks", action="store_true",
                    help="also the bundle adjustment on the sharp frames' tracks (a few seconds a scene)")
    args = ap.parse_args(argv)
    print("\n\n".join(report(r, args.sharp_tracks) for r in args.runs))


if __name__ == "__main__":
    main()
