"""PSNR of a run's deblurred renders, and of the blurry inputs, split by the true motion masks:
over the moving pixels and over the static pixels of all training frames (README, "The scene
suite"). Needs a scene with sharp frames and masks (the suite's).

    python examples/mask_split.py runs/big_mover runs/wall_disk
"""
from __future__ import annotations

import argparse

import numpy as np

from d2gs_np.data.io import load_scene
from d2gs_np.evaluation.runs import load_run


def _psnr(squared_error_sum, count):
    return float(10.0 * np.log10(count / squared_error_sum)) if squared_error_sum > 0 else float("inf")


def mask_split(run_dir, scene_dir=None):
    """dict(moving_share, moving_render, moving_input, static_render, static_input): PSNR in dB
    over all frames' pixels inside / outside the masks (a frame without a mask is all static)."""
    run = load_run(run_dir)
    scene = load_scene(scene_dir if scene_dir is not None else run.meta["scene_root"])
    if any(f.sharp is None for f in scene.frames):
        raise SystemExit(f"{scene_dir or run.meta['scene_root']}: the scene has no sharp frames to score against")
    model = run.model
    mids = model.mid_poses()
    sums = np.zeros(4)  # render moving, input moving, render static, input static
    counts = np.zeros(2)
    for k, f in enumerate(scene.frames):
        render = model.render(mids[k], f.time, f.K, f.width, f.height)
        moving = f.mask if f.mask is not None else np.zeros(render.shape[:2], bool)
        e_render = ((render - f.sharp) ** 2).sum(-1)
        e_input = ((f.image - f.sharp) ** 2).sum(-1)
        sums += [e_render[moving].sum(), e_input[moving].sum(), e_render[~moving].sum(), e_input[~moving].sum()]
        counts += [3 * moving.sum(), 3 * (~moving).sum()]
    return {"moving_share": float(counts[0] / counts.sum()),
            "moving_render": _psnr(sums[0], counts[0]), "moving_input": _psnr(sums[1], counts[0]),
            "static_render": _psnr(sums[2], counts[1]), "static_input": _psnr(sums[3], counts[1])}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+")
    args = ap.parse_args()
    print("| run | moving pixels | moving: input -> render dB | static: input -> render dB |")
    print("|---|---|---|---|")
    for r in args.runs:
        m = mask_split(r)
        print(f"| {r} | {100 * m['moving_share']:.0f} % | {m['moving_input']:.2f} -> {m['moving_render']:.2f} | "
              f"{m['static_input']:.2f} -> {m['static_render']:.2f} |")


if __name__ == "__main__":
    main()
