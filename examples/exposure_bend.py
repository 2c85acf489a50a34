"""How far does each exposure bend, and which poses can tell? (docs/method.md §4, which path.)

``TrajectoryConfig.path = "auto"`` takes the three-knot path where the median frame's exposure bends
by more than ``bend_px`` on the start poses a run has (a kept bundle adjustment, or trusted poses),
from ``blur.endpoints.exposure_bend_px``. For each scene folder with ground truth this prints, as
the median over frames in full-resolution pixels:

- blur: the true exposure's length (start to end pose, the same pixel measure);
- true bend: the distance from the geodesic midpoint of the true exposure endpoints to the true
  mid-exposure pose, what the bend estimate stands for;
- the estimate ``exposure_bend_px`` from the true mid poses, the given poses and the kept bundle
  adjustment's poses (the scene's true median depth for the translation);
- what "auto" chooses in a run with the default config, as the run log says it.

    python examples/exposure_bend.py SCENE [SCENE ...]
"""
from __future__ import annotations

import argparse

import numpy as np

from d2gs_np.blur.endpoints import exposure_bend_px, tangent_px
from d2gs_np.data.io import load_scene
from d2gs_np.geometry.se3 import se3_interpolate, se3_inverse, se3_log
from d2gs_np.pose.given import adjusted_start
from d2gs_np.train.components import decide_components
from d2gs_np.train.config import ExperimentConfig


def bend_table(folder, config=None) -> dict:
    """The figures of the module docstring for one scene folder (medians over frames, px)."""
    cfg = config or ExperimentConfig()
    scene = load_scene(folder)
    frames = scene.frames
    if any(f.gt_exposure_start is None or f.gt_exposure_end is None or f.gt_cam_T_world is None for f in frames):
        raise ValueError(f"{folder}: every frame needs gt_cam_T_world, gt_exposure_start and gt_exposure_end "
                         "(a suite or synthetic scene made by `d2gs make-scene`)")
    focal = float(frames[0].K[0, 0])
    depth = scene.scene_scale or np.inf
    if all(f.depth is not None for f in frames):
        depth = float(np.median(np.concatenate([f.depth[np.isfinite(f.depth)] for f in frames])))
    times = np.array([f.time for f in frames])
    e = scene.exposure_fraction

    def est(P):
        return float(np.median(exposure_bend_px(P, times, e, focal, depth)))

    start, end = np.stack([f.gt_exposure_start for f in frames]), np.stack([f.gt_exposure_end for f in frames])
    mid = np.stack([f.gt_cam_T_world for f in frames])
    chord = np.stack([se3_interpolate(s, t, 0.5) for s, t in zip(start, end)])
    notes = []
    adjusted = adjusted_start(scene, cfg)
    decide_components(scene, cfg, notes.append, adjusted=adjusted.poses is not None, start_poses=adjusted.poses,
                      depth=adjusted.depth)
    return {
        "frames": len(frames), "width": frames[0].width,
        "blur": float(np.median(tangent_px(se3_log(end @ se3_inverse(start)), focal, depth))),
        "true_bend": float(np.median(tangent_px(se3_log(chord @ se3_inverse(mid)), focal, depth))),
        "from_true": est(mid), "from_given": est(np.stack([f.cam_T_world for f in frames])),
        "from_adjusted": est(adjusted.poses) if adjusted.poses is not None else None,
        "auto": next((n for n in notes if n.startswith("exposure path")), ""),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="+")
    args = ap.parse_args(argv)
    print("| scene | frames | blur px | true bend | from true poses | from given | from adjustment | auto |")
    print("|---|---|---|---|---|---|---|---|")
    for folder in args.scenes:
        r = bend_table(folder)
        adj = "declined" if r["from_adjusted"] is None else f"{r['from_adjusted']:.2f}"
        print(f"| {folder} | {r['frames']} × {r['width']} px | {r['blur']:.2f} | {r['true_bend']:.2f} | "
              f"{r['from_true']:.2f} | {r['from_given']:.2f} | {adj} | {r['auto']} |", flush=True)


if __name__ == "__main__":
    main()
