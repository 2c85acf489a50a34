"""What the static world past the frames' borders (scene/border.py) does to finished runs.

Training adds it after its last step, outside the training clock, and it changes no training view,
so a run trained without it (older runs, or ``border.margin = 0``) gives exactly what the same run
with it would: this script adds it to each run's finished model and evaluates both as ``d2gs eval``
does (``evaluation.runs.evaluate``): deblurred views, novel views at the aligned test pose and
beside their frame's camera, and each test view; it also checks that no training view moved.

    python examples/border_effect.py RUN [more runs] [--margin 0.12] [--out border.csv]

A run that already holds the copies gets none more (the second pass adds nothing).
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import sys
import time

import numpy as np


def border_effect(run_dir, config=None):
    """Dict of one run's figures without and with the border copies."""
    from d2gs_np.data.io import load_scene
    from d2gs_np.evaluation.runs import LoadedRun, evaluate, load_run
    from d2gs_np.scene.border import border_gaussians, static_renders
    from d2gs_np.scene.config import BorderConfig
    from d2gs_np.scene.gaussians import STATIC, append_gaussians

    cfg = BorderConfig() if config is None else config
    run = load_run(run_dir)
    scene = load_scene(run.meta["scene_root"])
    model = run.model
    t0 = time.perf_counter()
    poses = model.mid_poses()
    new, info = border_gaussians(*static_renders(model, poses), poses, model.Ks, cfg,
                                 existing=model.params[f"{STATIC}.means"], eps2d=model.config.render.eps2d)
    seconds = time.perf_counter() - t0
    with_border = model if new is None else model.replace(params=append_gaussians(model.params, new))
    moved = max(float(np.abs(with_border.render(k) - model.render(k)).max()) for k in range(model.num_frames))
    before = evaluate(run, scene)
    after = evaluate(LoadedRun(run.run_dir, with_border, run.meta), scene)

    def nvs(m, key="nvs"):
        return m.get(key, {}).get("psnr", float("nan"))
    return {"run": str(run_dir), "added": info["added"], "static_before": int(model.params[f"{STATIC}.means"].shape[0]),
            "seconds": seconds, "training_views_max_change": moved,
            "dvs_before": before["dvs"]["psnr"], "dvs_after": after["dvs"]["psnr"],
            "nvs_before": nvs(before), "nvs_after": nvs(after),
            "nvs_rig_before": nvs(before, "nvs_rig"), "nvs_rig_after": nvs(after, "nvs_rig"),
            "nvs_moving_before": before["nvs"].get("moving_psnr"), "nvs_moving_after": after["nvs"].get("moving_psnr"),
            "views_before": [v["psnr"] for v in before["nvs"]["views"]],
            "views_after": [v["psnr"] for v in after["nvs"]["views"]]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--margin", type=float, default=None, help="BorderConfig.margin (default: the config's)")
    ap.add_argument("--out", default=None, help="CSV of the figures")
    args = ap.parse_args(argv)
    from d2gs_np.scene.config import BorderConfig
    cfg = BorderConfig() if args.margin is None else dataclasses.replace(BorderConfig(), margin=args.margin)
    rows = []
    for run_dir in args.runs:
        r = border_effect(run_dir, cfg)
        rows.append(r)
        mv = "" if r["nvs_moving_before"] is None else \
            f", moving px {r['nvs_moving_before']:.2f} -> {r['nvs_moving_after']:.2f}"
        views = " / ".join(f"{a:.1f} -> {b:.1f}" for a, b in zip(r["views_before"], r["views_after"]))
        print(f"{run_dir}: +{r['added']} Gaussians ({r['added'] / max(r['static_before'], 1) * 100:.0f} % of the "
              f"static set, {r['seconds']:.1f}s); DVS {r['dvs_before']:.2f} -> {r['dvs_after']:.2f} (training views' "
              f"largest change {r['training_views_max_change']:.1e}); NVS {r['nvs_before']:.2f} -> "
              f"{r['nvs_after']:.2f}{mv}; beside its frame {r['nvs_rig_before']:.2f} -> {r['nvs_rig_after']:.2f}; "
              f"views {views}", flush=True)
    if args.out:
        with open(args.out, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
