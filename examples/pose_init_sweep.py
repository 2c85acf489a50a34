"""The bundle adjustment before training (``pose/given.py``) under settings of ``PoseInitConfig``, on
suite scenes with the given noisy poses, without training (docs/method.md §5, the path's
smoothness; issue #40): per scene, seed and setting, the ATE of the adjusted poses and the
baselines between frames k and k + gap (gaps 1 / 4 / 8) against the true ones (median length
ratio, median direction error; ``evaluation.runs.baseline_errors``), the adjustment's structure
against its own path (``structure_ratio``: median and 10th-90th percentiles of s z / z_true over
its points in every frame, s the orientation-aligned Sim(3) scale of the adjusted poses; 1 = the
true shape at the path's scale) and the seconds the adjustment took (the tracks included). Each
setting is NAME=VALUE of a numeric ``PoseInitConfig`` field; "given" rows are the given poses.
--depth-prior gives the scenes the suite's modelled video depth prior (for depth_prior_weight).

    python examples/pose_init_sweep.py --scenes cube_sign crossing --seeds 0 1 \
        --set smooth_trans_rel=0 smooth_trans_rel=0.001
    python examples/pose_init_sweep.py --depth-prior --set depth_prior_weight=0 depth_prior_weight=1
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

GAPS = (1, 4, 8)


def parse_setting(text: str):
    """'name=value' -> (name, float value), the name a numeric PoseInitConfig field."""
    from d2gs_np.pose.config import PoseInitConfig

    name, sep, value = text.partition("=")
    fields = {f.name: f for f in dataclasses.fields(PoseInitConfig)}
    if not sep or name not in fields or not isinstance(fields[name].default, (int, float)) \
            or isinstance(fields[name].default, bool):
        numeric = sorted(n for n, f in fields.items() if isinstance(f.default, (int, float))
                         and not isinstance(f.default, bool))
        raise SystemExit(f"--set {text!r}: write NAME=VALUE with NAME one of {numeric}")
    try:
        return name, type(fields[name].default)(float(value))
    except ValueError:
        raise SystemExit(f"--set {text!r}: {value!r} is not a number") from None


def structure_ratio(points, poses, frames, scene_scale):
    """(median, p10, p90) of s z / z_true over the points (P, 3) seen in each frame (z their depth in
    ``poses``, z_true the frame's true depth at their pixel), s the scale that aligns the poses to
    the frames' true ones with their orientations (``evaluation.runs.align_with_orientations``)."""
    from d2gs_np.evaluation.runs import align_with_orientations
    from d2gs_np.geometry.camera import project_points

    gt = np.stack([f.gt_cam_T_world for f in frames])
    s = align_with_orientations(poses, gt, scene_scale)[0]
    ratios = []
    for f, T in zip(frames, poses):
        uv, z = project_points(points, T, f.K)
        ins = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < f.width) & (uv[:, 1] >= 0) & (uv[:, 1] < f.height)
        zt = f.depth[uv[ins, 1].astype(int), uv[ins, 0].astype(int)]
        ok = np.isfinite(zt) & (zt > 0)
        ratios.append(s * z[ins][ok] / zt[ok])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    if not r.size:
        raise ValueError("structure_ratio: no point lands on a pixel with a true depth")
    return float(np.median(r)), float(np.quantile(r, 0.1)), float(np.quantile(r, 0.9))


def row(label, poses, gt, depth, seconds=None, structure=None):
    from d2gs_np.evaluation.metrics import ate
    from d2gs_np.evaluation.runs import baseline_errors

    e = baseline_errors(poses, gt, depth, GAPS)
    cells = " | ".join(f"x{e[d][0]:.2f}, {e[d][1]:.0f}°" if d in e else "–" for d in GAPS)
    st = "–" if structure is None else f"{structure[0]:.3f} ({structure[1]:.2f}-{structure[2]:.2f})"
    return f"| {label} | {ate(poses, gt):.4f} | {cells} | {st} | {'' if seconds is None else f'{seconds:.1f}'} |"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["photo_room", "wall_disk", "cube_sign", "crossing", "big_mover"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--set", nargs="+", default=["smooth_trans_rel=0"], dest="settings",
                    help="NAME=VALUE settings of PoseInitConfig, one adjustment each")
    ap.add_argument("--depth-prior", action="store_true",
                    help="give the scenes the suite's modelled video depth prior (SuiteConfig.depth_prior)")
    args = ap.parse_args(argv)
    settings = [parse_setting(s) for s in args.settings]

    from d2gs_np.data.suite import make_suite_scene
    from d2gs_np.pose.given import adjusted_start
    from d2gs_np.train.config import ExperimentConfig

    print("| scene, seed, poses | ATE | " + " | ".join(f"gap {d}: length ratio, direction" for d in GAPS)
          + " | structure / path (p10-p90) | seconds |")
    print("|---" * (len(GAPS) + 4) + "|")
    for scene_name in args.scenes:
        for seed in args.seeds:
            scene = make_suite_scene(scene_name, seed, **({"depth_prior": "video"} if args.depth_prior else {}))
            gt = np.stack([f.gt_cam_T_world for f in scene.frames])
            given = np.stack([f.cam_T_world for f in scene.frames])
            print(row(f"{scene_name} {seed} given", given, gt, scene.scene_scale), flush=True)
            for name, value in settings:
                base = ExperimentConfig()
                cfg = dataclasses.replace(base, pose_init=dataclasses.replace(base.pose_init, **{name: value}))
                t0 = time.perf_counter()
                start = adjusted_start(scene, cfg)
                seconds = time.perf_counter() - t0
                poses = given if start.poses is None else start.poses
                label = f"{scene_name} {seed} {name}={value:g}" + ("" if start.poses is not None else " (not kept)")
                st = (None if start.poses is None or start.points is None or not len(start.points) else
                      structure_ratio(start.points, start.poses, scene.frames, scene.scene_scale))
                print(row(label, poses, gt, scene.scene_scale, seconds, st), flush=True)


if __name__ == "__main__":
    main()
