"""Diagnostic: train with the TRUE exposure endpoints, frozen, to separate two failure modes of
deblurring: endpoints that do not open (trajectory learning) versus a Gaussian set that does not
sharpen (scene learning). Needs a synthetic scene with gt_exposure_start / gt_exposure_end.

    d2gs make-scene /tmp/s --preset dynamic --frames 12 --width 160 --height 90
    python examples/oracle_endpoints.py /tmp/s --out /tmp/oracle --iters 600
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from d2gs_np.data.io import load_scene
from d2gs_np.evaluation.runs import evaluate_run
from d2gs_np.geometry import se3_inverse, se3_log
from d2gs_np.train.config import ExperimentConfig, TrainConfig
from d2gs_np.train.trainer import Trainer
from d2gs_np.blur.endpoints import CAMERA, XI_END, XI_START


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("scene")
    ap.add_argument("--out", required=True)
    ap.add_argument("--iters", type=int, default=600)
    args = ap.parse_args()
    scene = load_scene(args.scene)
    if any(f.gt_exposure_start is None or f.gt_exposure_end is None for f in scene.frames):
        raise SystemExit("the scene has no gt_exposure_start/end; use a synthetic scene")
    tr = Trainer(scene, ExperimentConfig(train=TrainConfig(iters=args.iters, quiet=True)), args.out, overwrite=True)
    if not tr.components.blur:
        raise SystemExit("the blur model is off for this scene (sharp input?)")
    # Left perturbations of the estimate that land on the true endpoints: xi = log(T_true T_est^-1).
    tr.params = {**tr.params,
                 XI_START: np.stack([se3_log(f.gt_exposure_start @ se3_inverse(f.cam_T_world)) for f in scene.frames]),
                 XI_END: np.stack([se3_log(f.gt_exposure_end @ se3_inverse(f.cam_T_world)) for f in scene.frames])}
    tr.stages = [dataclasses.replace(s, trainable=tuple(p for p in s.trainable if p != f"{CAMERA}.xi"))
                 for s in tr.stages]
    tr.run()
    m = evaluate_run(args.out)
    print(f"oracle endpoints: DVS {m['dvs']['psnr']:.2f} dB (SSIM {m['dvs']['ssim']:.3f}); blurry inputs "
          f"{m['input_blur']['psnr']:.2f} dB; {m['train_seconds']:.0f} s")


if __name__ == "__main__":
    main()
