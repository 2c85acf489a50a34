"""Where do the dynamic seeds land, by the rule and by an aligned depth prior? (docs/method.md §8.)

For each suite scene folder (true depth maps needed), a modelled depth network's output is added
to every training frame (``data.suite.modelled_depth_prior``: the true depth, edges blurred,
a smooth relative error; "video": depth up to one scale for the clip, "monocular": disparity up
to a scale and shift per frame), the initial points are made with the poses a run starts from
(the bundle adjustment's, as training does, with its points as the priors' reference; or the
given or the true poses, with the measured initial points as the reference), and the table gives:

- static: the measured static points' depth error, median |z / true - 1| (triangulated, and
  dense seeds at their own pixel's stereo depth: what a prior is aligned to);
- per seeding rule, the seeds' depth over the true depth at their pixel (median, p10, p90),
  and for the prior the frames aligned and the alignment's median relative error.

    python examples/depth_prior_alignment.py SCENE [SCENE ...] [--poses adjusted|given|true]
"""
from __future__ import annotations

import argparse
import dataclasses
import warnings

import numpy as np

from d2gs_np.data.io import load_scene
from d2gs_np.data.suite import modelled_depth_prior
from d2gs_np.evaluation.metrics import seed_depth_ratio
from d2gs_np.geometry.camera import project_points
from d2gs_np.pose.given import adjusted_start
from d2gs_np.scene import initialize as init_module
from d2gs_np.scene.config import InitConfig
from d2gs_np.train.config import ExperimentConfig


def start_poses(scene, which: str):
    """(N, 4, 4) poses the initialisation is run with, and the bundle adjustment's points (the
    priors' reference in a run) when those poses are its own, else None."""
    if which == "true":
        return np.stack([f.gt_cam_T_world for f in scene.frames]), None
    if which == "adjusted":
        adjusted = adjusted_start(scene, ExperimentConfig())
        if adjusted.poses is not None:
            return adjusted.poses, adjusted.points
    return np.stack([f.cam_T_world for f in scene.frames]), None


def static_error(scene, points):
    """Median |z / true - 1| of ``points`` over the frames, off the motion masks."""
    errs = []
    for f in scene.frames:
        uv, z = project_points(points, f.cam_T_world, f.K)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < f.width) & (uv[:, 1] >= 0) & (uv[:, 1] < f.height)
        r, c = np.floor(uv[inside, 1]).astype(int), np.floor(uv[inside, 0]).astype(int)
        keep = np.ones(len(r), bool) if f.mask is None else ~f.mask[r, c]
        errs.append(np.abs(z[inside][keep] / f.depth[r, c][keep] - 1.0))
    return float(np.median(np.concatenate(errs)))


def alignment_table(folder, poses: str = "adjusted", seed: int = 0, edge_px: float = 2.0, rel_error: float = 0.1):
    scene = load_scene(folder)
    if not scene.has_depth or not scene.has_moving_pixels:
        raise ValueError(f"{folder}: needs true depth maps and moving pixels (a suite scene with movers)")
    P, anchors = start_poses(scene, poses)
    rng = np.random.default_rng(seed)
    clip_scale = np.exp(rng.uniform(-1.0, 1.0))
    frames = []
    for f, T in zip(scene.frames, P):
        frames.append(dataclasses.replace(f, cam_T_world=T))
    rows = {}
    for kind, space in (("video", "depth"), ("monocular", "disparity")):
        edge = edge_px * frames[0].width / 240.0
        with_prior = dataclasses.replace(scene, frames=[
            dataclasses.replace(f, depth_prior=modelled_depth_prior(f.depth, rng, edge, rel_error, kind, clip_scale))
            for f in frames])
        for rule in (("static_median", "prior") if kind == "video" else ("prior",)):
            cfg = InitConfig(dynamic_depth=rule, depth_prior_space=space)
            static, _, dyn, _, info = init_module.initialize_points(with_prior, cfg, np.random.default_rng(0),
                                                                    anchor_points=anchors)
            ratio = seed_depth_ratio(with_prior.frames, dyn, info["dynamic_source_frames"],
                                     info["dynamic_source_pixels"])
            name = rule if rule == "static_median" else f"prior ({kind}, {space})"
            row = {"ratio": np.percentile(ratio, [50, 10, 90])}
            if info["dynamic_depth_prior"] is not None:
                pi = info["dynamic_depth_prior"]
                row.update(aligned=f"{pi['aligned']}/{pi['frames']}", rel_error=pi["median_rel_error"],
                           reference=pi["reference"])
            rows[name] = row
            if rule == "static_median":
                rows["_static"] = static_error(with_prior, static[info["static_measured"]])
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--poses", choices=("adjusted", "given", "true"), default="adjusted")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    print(f"poses: {args.poses}")
    print("| scene | static points: median abs rel error | seeding | seed depth / true: median (p10-p90) | "
          "frames aligned | alignment rel error |")
    print("|---|---|---|---|---|---|")
    for folder in args.scenes:
        rows = alignment_table(folder, args.poses, args.seed)
        static = rows.pop("_static")
        for name, r in rows.items():
            m, lo, hi = r["ratio"]
            print(f"| {folder.rstrip('/').split('/')[-1]} | {static:.3f} | {name} | {m:.2f} ({lo:.2f}-{hi:.2f}) | "
                  f"{r.get('aligned', '-')} | {r.get('rel_error', float('nan')):.3f} |")


if __name__ == "__main__":
    main()
