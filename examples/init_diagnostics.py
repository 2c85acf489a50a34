"""Diagnostics of the static initialisation on suite scene folders (docs/method.md §8).

For each scene folder written by ``d2gs make-scene`` (it needs ``suite_config.json`` beside the
frames, from which the true depth is ray cast): the poses the trainer starts from
(``pose_init.initial_poses``, the bundle adjustment on noisy scenes), then ``initialize_points``
with the default config, and per dense keyframe the plane sweep over the same range with the
share of pixels each of its checks rejects. Depth errors are |z / (s z_true) - 1| of each seed's
depth in its source frame against the ray-cast depth through its pixel at the true pose, where s
is the scale of the poses used against the true ones (``pose_scale``; the bundle adjustment fixes
the scene's scale only up to its prior), and the true depth range is given in that scale.

    python examples/init_diagnostics.py SCENE [SCENE ...] [--out diag.json] [--no-pose-init] [--config FILE]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np


def _true_depth_maps(scene, world):
    from d2gs_np.data.suite import suite_depth_map

    return [suite_depth_map(world, f.gt_cam_T_world, f.time, f.K, f.width, f.height) for f in scene.frames]


def pose_scale(frames):
    """Scale of the poses used against the true ones: the least-squares s in c - mean(c) ~ s (g - mean(g))
    of the used and true camera centres (1 for true poses; the bundle adjustment fixes the scale only
    up to its prior; pose noise independent of the path leaves s unbiased)."""
    from d2gs_np.geometry.camera import camera_center

    c = np.stack([camera_center(f.cam_T_world) for f in frames])
    g = np.stack([camera_center(f.gt_cam_T_world) for f in frames])
    c, g = c - c.mean(0), g - g.mean(0)
    return float((c * g).sum() / (g * g).sum())


def _rel_errors(points, src, frames, true_maps, scale=1.0):
    """|z / (scale z_true) - 1| of each point in its source frame (NaN where its pixel leaves the image)."""
    from d2gs_np.geometry.camera import project_points

    err = np.full(len(points), np.nan)
    for k in np.unique(src):
        s = np.flatnonzero(src == k)
        f = frames[int(k)]
        uv, z = project_points(points[s], f.cam_T_world, f.K)
        c, r = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 0) & (c >= 0) & (c < f.width) & (r >= 0) & (r < f.height)
        zt = true_maps[int(k)][r[ok], c[ok]]
        err[s[ok]] = np.abs(z[ok] / (scale * zt) - 1.0)
    return err


def _summary(err):
    e = err[np.isfinite(err)]
    if e.size == 0:
        return {"n": 0}
    return {"n": int(e.size), "median": float(np.median(e)), "p90": float(np.percentile(e, 90)),
            "within_5pct": float(np.mean(e < 0.05))}


def diagnose(scene_dir, pose_init=True, config=None):
    from d2gs_np.data.io import load_scene
    from d2gs_np.data.suite import SuiteConfig, build_suite_world
    from d2gs_np.pose.features import static_detector_mask
    from d2gs_np.pose.given import initial_poses, triangulate_tracks
    from d2gs_np.scene.initialize import initialize_points
    from d2gs_np.scene.stereo import plane_sweep_depth
    from d2gs_np.train.config import ExperimentConfig
    from d2gs_np.pose.tracks import klt_tracks

    scene_dir = Path(scene_dir)
    scene = load_scene(scene_dir)
    world = build_suite_world(SuiteConfig(**json.loads((scene_dir / "suite_config.json").read_text())))
    config = ExperimentConfig() if config is None else config
    poses = initial_poses(scene, config) if pose_init else None
    if poses is not None:
        scene = dataclasses.replace(scene, frames=[dataclasses.replace(f, cam_T_world=P)
                                                   for f, P in zip(scene.frames, poses)])
    frames = scene.frames
    true_maps = _true_depth_maps(scene, world)
    rng = np.random.default_rng(config.train.seed)
    t0 = time.perf_counter()
    pts, _, _, _, info = initialize_points(scene, config.init, rng)
    seconds = time.perf_counter() - t0
    src = info["static_source_frames"]
    nt, nd = info["num_static_triangulated"], info["num_static_dense"]
    scale = pose_scale(frames)
    err = _rel_errors(pts, src, frames, true_maps, scale)
    true_static = np.concatenate([m[np.isfinite(m) & ~(f.mask if f.mask is not None else False)]
                                  for m, f in zip(true_maps, frames)])
    out = {
        "scene": str(scene_dir), "pose_init": poses is not None, "pose_scale": scale, "init_seconds": seconds,
        "keypoints_mean": info["num_keypoints_mean"], "matches_per_pair": info["mean_matches_per_pair"],
        "pairs_matched": f"{info['num_pairs_matched']}/{info['num_pairs']}",
        "triangulated": nt, "dense": nd, "dense_stereo": info["num_static_dense_stereo"],
        "dense_stereo_over_prior": info.get("num_static_dense_stereo_over_prior", 0),
        "stereo_kept_share": info["stereo_kept_share"], "fill": info["num_static_fill"],
        "depth_range_used": [info["fill_depth_near"], info["fill_depth_far"]],
        "depth_range_source": info["fill_depth_source"],
        "true_static_depth_p1_p99": [scale * float(np.percentile(true_static, 1)),
                                     scale * float(np.percentile(true_static, 99))],
        "err_triangulated": _summary(err[:nt]), "err_dense": _summary(err[nt:nt + nd]),
        "err_fill": _summary(err[nt + nd:]), "err_all": _summary(err),
    }
    for key in ("depth_range_tracks", "num_track_points"):
        if key in info:
            out[key] = info[key]
    # KLT tracks, triangulated with the same poses: how far they would cover the range
    fm = [f.mask for f in frames] if all(f.mask is not None for f in frames) else None
    of, ot, ouv, ntr, _ = klt_tracks([f.image for f in frames], masks=fm)
    X, ok = triangulate_tracks(np.stack([f.cam_T_world for f in frames]), np.stack([f.K for f in frames]),
                               of, ot, ouv, ntr)
    first = np.full(ntr, -1)
    first[ot[::-1]] = of[::-1]
    terr = _rel_errors(X[ok], first[ok], frames, true_maps, scale)
    out["klt_tracks"] = ntr
    out["klt_triangulated"] = int(ok.sum())
    out["err_klt"] = _summary(terr)
    # per keyframe: the sweep's rejections and kept-depth error
    N = len(frames)
    keyframes = np.unique(np.round(np.linspace(0, N - 1, min(config.init.dense_frames, N))).astype(int))
    near, far = info["fill_depth_near"], info["fill_depth_far"]
    out["keyframes"] = []
    for k in keyframes:
        f = frames[k]
        others = sorted({min(max(k + d * sgn, 0), N - 1) for d in config.init.frame_skips for sgn in (-1, 1)} - {k})
        sources = [(frames[j].image, frames[j].cam_T_world, frames[j].K, frames[j].mask) for j in others]
        static = None if f.mask is None else static_detector_mask(f.mask, config.init.features.mask_dilation_px) > 0
        dmap, sinfo = plane_sweep_depth(f.image, f.cam_T_world, f.K, sources, near, far, config.init.stereo,
                                        None if static is None else ~static)
        ok = np.isfinite(dmap)
        e = np.abs(dmap[ok] / (scale * true_maps[k][ok]) - 1.0)
        out["keyframes"].append({"frame": int(k), "kept": sinfo["kept_share"], "sweep": [sinfo["near"], sinfo["far"]],
                                 "rejected": sinfo["rejected_share"], "err": _summary(e)})
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="+")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    p.add_argument("--no-pose-init", action="store_true", help="start from the given poses (no bundle adjustment)")
    p.add_argument("--config", default=None,
                   help="a config JSON as `d2gs train --config` takes (e.g. {\"init\": {\"stereo\": {\"distinct_px\": 1}}}); "
                        "default: the present defaults")
    args = p.parse_args(argv)
    from d2gs_np.train.config import ExperimentConfig

    config = ExperimentConfig.load(args.config) if args.config else ExperimentConfig()
    results = []
    for s in args.scenes:
        r = diagnose(s, pose_init=not args.no_pose_init, config=config)
        results.append(r)
        print(json.dumps(r, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
