"""The README's overview figure: blurry input | without the blur model | with it | sharp truth.

    python examples/make_overview.py SCENE BLUR_RUN NOBLUR_RUN --out docs/overview.png [--frames 5 11 23]

SCENE is a scene folder with sharp frames (e.g. from ``d2gs make-scene SCENE --preset dynamic``);
the runs are ``d2gs train SCENE --out BLUR_RUN`` and ``d2gs train SCENE --out NOBLUR_RUN --blur off``.
Each row is one training frame rendered at its optimised mid-exposure pose; the per-image PSNR
against the sharp frame is printed (the picture itself carries no text).
"""
from __future__ import annotations

import argparse

import numpy as np

from d2gs_np.data.io import load_scene
from d2gs_np.evaluation.runs import load_run
from d2gs_np.evaluation.metrics import psnr
from d2gs_np.reporting.plots import comparison_strip, save_image


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("blur_run")
    ap.add_argument("noblur_run")
    ap.add_argument("--out", required=True, help="output PNG")
    ap.add_argument("--frames", type=int, nargs="+", default=[5, 11, 23])
    args = ap.parse_args(argv)
    scene = load_scene(args.scene)
    if not scene.has_sharp:
        raise SystemExit(f"{args.scene} has no sharp frames; use a synthetic scene (d2gs make-scene)")
    bad = [k for k in args.frames if not 0 <= k < scene.num_frames]
    if bad:
        raise SystemExit(f"--frames {bad} out of range: the scene has {scene.num_frames} frames")
    runs = {"no blur": load_run(args.noblur_run), "blur": load_run(args.blur_run)}
    rows = []
    print("| frame | input dB | no blur dB | blur dB |\n|---|---|---|---|")
    for k in args.frames:
        f = scene.frames[k]
        renders = [r.model.render(k) for r in runs.values()]  # at frame k's mid-exposure pose and time
        rows.append([f.image, *renders, f.sharp])
        print(f"| {k} | {psnr(f.image, f.sharp):.2f} | " + " | ".join(f"{psnr(x, f.sharp):.2f}" for x in renders)
              + " |")
    save_image(args.out, comparison_strip(rows))
    print(f"wrote {args.out} (columns: blurry input | no blur model | blur model | sharp truth)")


if __name__ == "__main__":
    main()
