"""The bundle adjustment before training (``pose/given.py``) under settings of ``PoseInitConfig``, on
suite scenes with the given noisy poses, without training (docs/method.md §5, the path's
smoothness; issue #40): per scene, seed and setting, the ATE of the adjusted poses and the
baselines between frames k and k + gap (gaps 1 / 4 / 8) against the true ones (median length
ratio, median direction error; ``evaluation.runs.baseline_errors``), and the
seconds the adjustment took (the tracks included). Each setting is NAME=VALUE of a numeric
``PoseInitConfig`` field; "given" rows are the given poses.

    python examples/pose_init_sweep.py --scenes cube_sign crossing --seeds 0 1 \
        --set smooth_trans_rel=0 smooth_trans_rel=0.001
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


def row(label, poses, gt, depth, seconds=None):
    from d2gs_np.evaluation.metrics import ate
    from d2gs_np.evaluation.runs import baseline_errors

    e = baseline_errors(poses, gt, depth, GAPS)
    cells = " | ".join(f"x{e[d][0]:.2f}, {e[d][1]:.0f}°" if d in e else "–" for d in GAPS)
    return f"| {label} | {ate(poses, gt):.4f} | {cells} | {'' if seconds is None else f'{seconds:.1f}'} |"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["photo_room", "wall_disk", "cube_sign", "crossing", "big_mover"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--set", nargs="+", default=["smooth_trans_rel=0"], dest="settings",
                    help="NAME=VALUE settings of PoseInitConfig, one adjustment each")
    args = ap.parse_args(argv)
    settings = [parse_setting(s) for s in args.settings]

    from d2gs_np.data.suite import make_suite_scene
    from d2gs_np.pose.given import adjusted_start
    from d2gs_np.train.config import ExperimentConfig

    print("| scene, seed, poses | ATE | " + " | ".join(f"gap {d}: length ratio, direction" for d in GAPS)
          + " | seconds |")
    print("|---" * (len(GAPS) + 3) + "|")
    for scene_name in args.scenes:
        for seed in args.seeds:
            scene = make_suite_scene(scene_name, seed)
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
                print(row(label, poses, gt, scene.scene_scale, seconds), flush=True)


if __name__ == "__main__":
    main()
