"""How high can any reconstruction score on a scene's novel views, given what no training frame saw?

A suite test view sits beside the camera path, so a few per cent of its pixels show surfaces that
no training frame saw (``evaluation.runs.seen_by_training``, with the true poses and depths). No
model can know their texture. This script gives each test view two ceilings, each with every seen
pixel exact:

- ``mean``: the unseen pixels rendered at their own true mean colour (an oracle that knows only
  the unseen region's average colour);
- ``lowpass``: the unseen pixels rendered as the true view blurred by a Gaussian of ``--sigma``
  pixels (an oracle that knows the region's coarse content, only its fine texture missing).

Given a run folder whose ``metrics.json`` has ``dvs`` and ``nvs``, it also prints the run's deblurred
and novel views and the novel views the ceilings allow (``d2gs eval`` scores novel views as the mean
over views of the per-view PSNR; a view is taken at most at its ceiling and at most at the deblurred
views' PSNR, which no view is expected to beat), beside DVS − 3 dB (issue #40's first line: novel
views within 3 dB of the deblurred ones).

    python examples/nvs_ceiling.py SCENE_OR_RUN [more] [--sigma 2] [--out ceiling.csv]

SCENE_OR_RUN: a scene folder with true poses and depth (a suite scene), or a run folder (its
scene is the one it records).
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np


def view_ceilings(image, seen, sigma):
    """(unseen share, mean-colour ceiling dB, low-pass ceiling dB) of one view: (H, W, 3) image in
    [0, 1], (H, W) bool seen mask, the low-pass oracle's Gaussian sigma in pixels. A view whose
    every pixel was seen has no ceiling below exact (inf)."""
    import cv2

    unseen = ~seen
    share = float(unseen.mean())
    if share == 0.0:
        return 0.0, float("inf"), float("inf")
    img = np.asarray(image, np.float64)
    px = img[unseen]  # (U, 3)
    mse_mean = float(((px - px.mean(axis=0)) ** 2).mean()) * share
    low = cv2.GaussianBlur(img, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
    mse_low = float(((img - low)[unseen] ** 2).mean()) * share

    def db(m):
        return float("inf") if m <= 0 else float(-10.0 * np.log10(m))
    return share, db(mse_mean), db(mse_low)


def scene_ceilings(scene, sigma=2.0):
    """Per test view dicts (time, unseen share, the two ceilings) of a loaded scene."""
    from d2gs_np.evaluation.runs import seen_by_training

    if not scene.test_frames:
        raise ValueError("the scene has no test views; make a suite scene (d2gs make-scene) to have them")
    if not (scene.has_gt_poses and scene.has_depth and all(f.depth is not None for f in scene.test_frames)):
        raise ValueError("the ceilings need true poses and depth for every frame and test view (a suite scene)")
    rows = []
    for f in scene.test_frames:
        seen = seen_by_training(f.cam_T_world, f, scene.frames)
        share, c_mean, c_low = view_ceilings(f.image, seen, sigma)
        rows.append({"time": float(f.time), "unseen_share": share, "ceiling_mean": c_mean, "ceiling_lowpass": c_low})
    return rows


def _resolve(path):
    """(scene folder, metrics dict or None) of a scene or run folder."""
    p = Path(path)
    if (p / "metrics.json").exists() or (p / "final.npz").exists():
        from d2gs_np.evaluation.runs import load_run
        root = load_run(p).meta.get("scene_root")
        if root is None:
            raise ValueError(f"run {p} does not record its scene folder")
        m = json.loads((p / "metrics.json").read_text()) if (p / "metrics.json").exists() else None
        return Path(root), m
    return p, None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+", help="scene or run folders")
    ap.add_argument("--sigma", type=float, default=2.0, help="the low-pass oracle's Gaussian sigma, pixels")
    ap.add_argument("--out", default=None, help="CSV of every view's figures")
    args = ap.parse_args(argv)
    if not (np.isfinite(args.sigma) and args.sigma > 0):
        ap.error(f"--sigma must be a positive number of pixels; got {args.sigma}")
    from d2gs_np.data.io import load_scene

    out_rows = []
    for path in args.paths:
        scene_dir, m = _resolve(path)
        rows = scene_ceilings(load_scene(scene_dir), args.sigma)
        views = " / ".join(f"{r['unseen_share'] * 100:.1f} % {r['ceiling_mean']:.1f} {r['ceiling_lowpass']:.1f}"
                           for r in rows)
        line = f"{Path(path).name}: views (unseen share, mean-colour and low-pass ceilings dB): {views}"
        if m and "dvs" in m and "nvs" in m:
            dvs, nvs = m["dvs"]["psnr"], m["nvs"]["psnr"]
            # no view is taken to beat the training views' own fit: each at most the DVS and its ceiling
            allowed = {k: float(np.mean([min(r[k], dvs) for r in rows])) for k in ("ceiling_mean", "ceiling_lowpass")}
            line += (f"; run DVS {dvs:.2f}, NVS {nvs:.2f}, seen px {m['nvs'].get('seen_psnr') or float('nan'):.2f}; "
                     f"NVS allowed with every view at most the DVS: {allowed['ceiling_mean']:.2f} (mean colour), "
                     f"{allowed['ceiling_lowpass']:.2f} (low-pass), against DVS - 3 = {dvs - 3:.2f}")
        print(line, flush=True)
        for r in rows:
            out_rows.append({"path": str(path), **r})
    if args.out:
        with open(args.out, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(out_rows[0]))
            w.writeheader()
            w.writerows(out_rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
