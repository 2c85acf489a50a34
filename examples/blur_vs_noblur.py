"""Training with the blur model against training without it (n = 1, the paper's GaussianFlow row),
same scene, same iterations; prints both runs' metrics and error-against-time tables, and plots
held-out PSNR against training seconds for both.

    python examples/blur_vs_noblur.py --out runs/blur_vs_noblur --iters 1500
"""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from d2gs_np.data.io import load_scene
from d2gs_np.data.synthetic import write_synthetic_scene
from d2gs_np.evaluation.runs import evaluate_run
from d2gs_np.reporting.plots import plot_error_vs_time, read_log
from d2gs_np.train.config import ExperimentConfig, TrainConfig
from d2gs_np.train.trainer import Trainer


def error_vs_time_table(run_dir, every=1) -> str:
    c = read_log(run_dir)
    lines = ["| step | seconds | train PSNR | held-out PSNR |", "|---|---|---|---|"]
    for i in range(len(c["step"])):
        h = c["heldout_psnr"][i]
        if h == h:  # rows with a held-out evaluation
            lines.append(f"| {int(c['step'][i])} | {c['seconds'][i]:.1f} | {c['train_psnr'][i]:.2f} | {h:.2f} |")
    return "\n".join(lines[:2] + lines[2::every])


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="runs/blur_vs_noblur")
    ap.add_argument("--preset", default="dynamic")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--iters", type=int, default=1500)
    ap.add_argument("--n", type=int, default=8, help="virtual views of the blur model")
    args = ap.parse_args()
    out = Path(args.out)
    scene_dir = write_synthetic_scene(out / "scene", args.preset, args.seed, overwrite=True)
    scene = load_scene(scene_dir)
    base = ExperimentConfig(train=TrainConfig(iters=args.iters, quiet=True, seed=args.seed))
    runs = {
        f"blur (n = {args.n})": base.replace(blur=dataclasses.replace(base.blur, num_virtual=args.n)),
        "no blur (n = 1)": base.replace(train=dataclasses.replace(base.train, blur="off")),
    }
    results = {}
    for name, cfg in runs.items():
        run_dir = out / ("blur" if name.startswith("blur") else "noblur")
        Trainer(scene, cfg, run_dir, overwrite=True).run()
        results[name] = evaluate_run(run_dir)
        print(f"\n## {name}\n\n```json\n{json.dumps(results[name], indent=1)}\n```\n")
        print(error_vs_time_table(run_dir))
    plot_error_vs_time([out / "blur", out / "noblur"], out / "error_vs_time.png", labels=list(runs))
    print("\n| run | DVS PSNR | DVS SSIM | NVS PSNR | ATE | train s |\n|---|---|---|---|---|---|")
    for name, r in results.items():
        print(f"| {name} | {r['dvs']['psnr']:.2f} | {r['dvs']['ssim']:.3f} | {r.get('nvs', {}).get('psnr', float('nan')):.2f}"
              f" | {r.get('trajectory', {}).get('ate', float('nan')):.4f} | {r['train_seconds']:.0f} |")
    first = next(iter(results.values()))
    print(f"| blurry inputs | {first['input_blur']['psnr']:.2f} | {first['input_blur']['ssim']:.3f} | | | |")
    print(f"\nplot: {out / 'error_vs_time.png'}")


if __name__ == "__main__":
    main()
