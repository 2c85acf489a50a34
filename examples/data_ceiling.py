"""How well can any view-consistent model score against a suite scene's sharp frames?

A suite scene's sharp frames are ray-cast with ``SuiteConfig.supersample`` x supersample samples
per pixel from bilinear texture lookups, without mip-maps (8 x 8 since #39; 2 x 2 before). Where a
photograph's texture is finer than that sampling (a gravel floor seen at a grazing angle), each
frame's pixels are an aliased few samples of it: the pattern depends on the camera's sub-pixel
position, so it differs from frame to frame. A 3D scene rendered consistently into every view
cannot follow it: it can at best render each pixel's area-filtered colour.

This script renders every frame's view again at ``--supersample`` (default 16) x 16 samples per
pixel (a close approximation of that area-filtered colour) and scores it against the scene's
stored sharp frames, as ``d2gs eval`` scores a run (mean over frames of the per-frame PSNR,
``metrics.psnr``). That is about the best a view-consistent reconstruction can score there: a
ceiling set by the data, not by the method. It also scores the pixels of the bottom
``--bottom`` share of the image rows apart (the suite's floors).

    python examples/data_ceiling.py runs/suite/scenes/wall_disk_s0_sharp [more scene folders] \\
        [--supersample 16] [--every 1] [--out ceiling.csv]

Each folder must hold the ``suite_config.json`` that ``d2gs make-scene`` writes beside a suite
scene (the world is rebuilt from it).
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np


def ceiling(scene_dir, supersample=16, bottom=0.3, every=1):
    """Dict: scene, frames, psnr (mean over frames), psnr_bottom, psnr_top, seconds, for the views
    of the folder's frames (every ``every``-th) rendered at ``supersample`` against its stored sharp
    frames."""
    from d2gs_np.evaluation import metrics
    from d2gs_np.data import suite
    from d2gs_np.data.io import load_scene

    scene_dir = Path(scene_dir)
    cfg_path = scene_dir / "suite_config.json"
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{cfg_path} is missing: data_ceiling.py needs a suite scene folder written by "
                                "`d2gs make-scene` (it rebuilds the world from suite_config.json)")
    if isinstance(supersample, bool) or int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample must be an int >= 1; got {supersample!r}")
    if not 0.0 < bottom < 1.0:
        raise ValueError(f"bottom must be a share of the rows in (0, 1); got {bottom!r}")
    if isinstance(every, bool) or int(every) != every or every < 1:
        raise ValueError(f"every must be an int >= 1; got {every!r}")
    config = suite.SuiteConfig(**json.loads(cfg_path.read_text()))
    world = suite.build_suite_world(config)
    scene = load_scene(scene_dir)
    t0 = time.perf_counter()
    ps, pb, pt = [], [], []
    for f in scene.frames[::int(every)]:
        if f.sharp is None:
            raise ValueError(f"{scene_dir}: frame {f.file_path} has no sharp image to score against")
        pose = suite.suite_camera_pose(world, np.array([f.time]))[0]
        img, _ = suite.render_suite_view(world, pose, f.time, f.K, f.width, f.height, int(supersample))
        rows = np.zeros((f.height, f.width), bool)
        rows[int(round((1.0 - bottom) * f.height)):] = True
        ps.append(metrics.psnr(img, f.sharp))
        pb.append(metrics.psnr(img, f.sharp, mask=rows))
        pt.append(metrics.psnr(img, f.sharp, mask=~rows))
    return dict(scene=scene_dir.name, frames=len(ps), psnr=float(np.mean(ps)), psnr_bottom=float(np.mean(pb)),
                psnr_top=float(np.mean(pt)), seconds=time.perf_counter() - t0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", help="suite scene folders (with suite_config.json)")
    ap.add_argument("--supersample", type=int, default=16, help="samples per pixel side of the re-render (16)")
    ap.add_argument("--bottom", type=float, default=0.3, help="share of the image rows scored apart (0.3)")
    ap.add_argument("--every", type=int, default=1, help="score every k-th frame (1: all)")
    ap.add_argument("--out", help="also write the table as CSV here")
    args = ap.parse_args(argv)
    rows = [ceiling(s, args.supersample, args.bottom, args.every) for s in args.scenes]
    print(f"{'scene':28s} frames  ceiling dB  bottom {args.bottom:.0%} dB  rest dB  seconds")
    for r in rows:
        print(f"{r['scene']:28s} {r['frames']:6d}  {r['psnr']:10.2f}  {r['psnr_bottom']:14.2f}  {r['psnr_top']:7.2f}"
              f"  {r['seconds']:7.1f}")
    if args.out:
        with open(args.out, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return rows


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
