"""Contact sheet of the synthetic presets: blurry | sharp | mask for a few frames of each.

    python examples/make_scene_gallery.py --out gallery.png [--seed 0] [--frames 0 8 16 23]

Generates "static", "sharp" and "dynamic" at the default size (240x135, 24 frames), prints the
generation time of each, and saves one PNG: per preset, one row per chosen frame with the
blurry input, the sharp mid-exposure ground truth and the motion mask (white = dynamic), plus
the PSNR of blurry against sharp and the mask's pixel count in the row label.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="output PNG path")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, nargs="+", default=[0, 8, 16, 23])
    parser.add_argument("--presets", nargs="+", default=["static", "sharp", "dynamic"])
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from d2gs_np.data.synthetic import make_scene

    scenes = {}
    for name in args.presets:
        t0 = time.perf_counter()
        scenes[name] = make_scene(name, seed=args.seed)
        sc = scenes[name]
        print(f"{name:8s}: {sc.num_frames} frames {sc.frames[0].width}x{sc.frames[0].height}, "
              f"{sc.blur_subframes} sub-frames, generated in {time.perf_counter() - t0:.1f} s")

    rows = [(name, k) for name in args.presets for k in args.frames if k < scenes[name].num_frames]
    fig, axes = plt.subplots(len(rows), 3, figsize=(3 * 3.2, len(rows) * 1.95), squeeze=False)
    for r, (name, k) in enumerate(rows):
        fr = scenes[name].frames[k]
        mse = float(np.mean((fr.image - fr.sharp) ** 2))
        psnr = float("inf") if mse == 0 else -10.0 * np.log10(mse)
        panels = [(fr.image, "blurry"), (fr.sharp, "sharp"), (fr.mask.astype(float), "mask")]
        for c, (img, title) in enumerate(panels):
            ax = axes[r, c]
            ax.imshow(img, cmap="gray" if img.ndim == 2 else None, vmin=0, vmax=1, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=9)
        axes[r, 0].set_ylabel(f"{name} k={k}\nPSNR {psnr:.1f}\nmask {int(fr.mask.sum())}", fontsize=7)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"saved {args.out}")


if __name__ == "__main__":
    main()
