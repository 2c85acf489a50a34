"""Accuracy of the dynamic set's initial motion (d2gs_np/scene/motion_init.py) against the true
motion of the suite's movers, for each way a seed follows its mask track (``MotionInitConfig.warp``)
and ridge weight, with the seconds each takes.

For every dynamic seed of the default initialisation (d2gs_np/scene/initialize.py) the true surface
point it was seeded on is followed through the clip (``d2gs_np.data.suite.mover_tracks_of_seeds``);
the seed's initial trajectory (base mean plus deformation) is projected into each frame and
compared with it. Reported per scene and rule: the median over frames of the median reprojection
error (px) over the seeds whose true point is in that frame's image, its worst frame, and the
seconds of ``initialize_deformation``. Seeds on no mover (a mask's blur halo) are left out.

    python examples/motion_init_accuracy.py [--scenes big_mover,cube_sign,...] [--seed 0]
        [--from DIR]       # scene folders DIR/<preset> written by `d2gs make-scene` (same seed)
        [--ridge 1e-2 1e-4] [--out runs/motion_init_accuracy]

Without --from the scenes are made with true poses (the motion initialisation uses the given poses,
so pose error would add its own share). Writes results.json and error_vs_time.png (error against
seconds) under --out and prints a table.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from d2gs_np.data.io import load_scene
from d2gs_np.data.suite import (SUITE, SuiteConfig, build_suite_world, make_suite_scene,
                               mover_tracks_of_seeds)
from d2gs_np.evaluation.metrics import trajectory_reprojection_error
from d2gs_np.scene.initialize import initialize_points
from d2gs_np.scene.config import WARPS, MotionInitConfig
from d2gs_np.scene.motion_init import initialize_deformation
from d2gs_np.train.config import ExperimentConfig

MOVER_SCENES = [name for name in SUITE if name != "photo_room"]  # photo_room has no mover


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=",".join(MOVER_SCENES))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--from", dest="source", default=None, help="folder of scene folders (d2gs make-scene)")
    ap.add_argument("--ridge", type=float, nargs="+", default=[MotionInitConfig().ridge])
    ap.add_argument("--out", default="runs/motion_init_accuracy")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    exp = ExperimentConfig()
    rows = []
    for name in args.scenes.split(","):
        if args.source:
            folder = Path(args.source) / name
            scene = load_scene(folder)
            cfg = SuiteConfig(**json.loads((folder / "suite_config.json").read_text()))
        else:
            scene = make_suite_scene(name, args.seed, num_test_views=0, rot_noise_deg=0.0, trans_noise=0.0)
            cfg = dataclasses.replace(SUITE[name], seed=args.seed)
        world = build_suite_world(cfg)
        _, _, d_pts, _, info = initialize_points(scene, exp.init, np.random.default_rng(exp.train.seed))
        frames_of, pixels_of = info["dynamic_source_frames"], info["dynamic_source_pixels"]
        truth = mover_tracks_of_seeds(world, scene.frames, frames_of, pixels_of)
        for warp in WARPS:
            for ridge in args.ridge:
                config = dataclasses.replace(exp.motion_init, warp=warp, ridge=ridge)
                t0 = time.perf_counter()
                means, coefs, minfo = initialize_deformation(scene, d_pts, frames_of, pixels_of, exp.deform, config)
                seconds = time.perf_counter() - t0
                err = trajectory_reprojection_error(means, coefs, exp.deform, scene.frames, truth)
                row = {"scene": name, "warp": warp, "ridge": ridge, "median_px": float(np.nanmedian(err)),
                       "worst_frame_px": float(np.nanmax(err)), "seconds": seconds,
                       "tracked_seeds": int(minfo["num_tracked_seeds"]), "seeds": int(len(d_pts)),
                       "per_frame_px": [None if not np.isfinite(e) else float(e) for e in err]}
                rows.append(row)
                print(f"{name:10s} {warp:10s} ridge {ridge:7.0e}  median {row['median_px']:6.2f} px  worst frame "
                      f"{row['worst_frame_px']:6.2f} px  {seconds:5.1f} s  ({row['tracked_seeds']}/{row['seeds']} "
                      "seeds tracked)", flush=True)
    (out / "results.json").write_text(json.dumps(rows, indent=1))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for name in dict.fromkeys(r["scene"] for r in rows):
        sub = [r for r in rows if r["scene"] == name]
        ax.plot([r["seconds"] for r in sub], [r["median_px"] for r in sub], "o", label=name)
        for r in sub:
            ax.annotate(f"{r['warp'][:3]} {r['ridge']:.0e}", (r["seconds"], r["median_px"]), fontsize=6)
    ax.set_xlabel("seconds of initialize_deformation")
    ax.set_ylabel("median reprojection error of the initial motion (px)")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "error_vs_time.png", dpi=120)
    print(f"wrote {out / 'results.json'} and {out / 'error_vs_time.png'}")


if __name__ == "__main__":
    main()
