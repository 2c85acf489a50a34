"""Held-out PSNR against training seconds for every cell of an experiment, one panel per scene.

Each panel holds one line per variant (the held-out PSNR its log recorded: sharp renders at the
optimised mid poses against the sharp frames, ``train/plugins.HeldOutPSNR``) and, dashed, the blurry
input's PSNR from the cell's ``metrics.json``: what training must rise above. The experiment's own
``OUT/<experiment>_error_vs_time.png`` puts every cell on one axis; this is the figure to read.

    python examples/plot_suite_curves.py OUT/runs/EXPERIMENT --out curves.png [--title TITLE]

Cell folders are ``<scene>_s<seed>_<variant>[...]`` with ``cell.json`` (``d2gs experiment``).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def cells(folder):
    """[(scene, variant, seed, seconds (R,), held-out PSNR (R,), input PSNR or None)] of the cells."""
    from d2gs_np.reporting.plots import read_log

    out = []
    for d in sorted(Path(folder).iterdir()):
        if not (d / "cell.json").is_file() or not (d / "log.csv").is_file():
            continue
        c = json.loads((d / "cell.json").read_text())
        log = read_log(d)
        held = ~np.isnan(log.get("heldout_psnr", np.full(len(log["seconds"]), np.nan)))
        m = json.loads((d / "metrics.json").read_text()) if (d / "metrics.json").is_file() else {}
        out.append((c["scene"], c["variant"], int(c["seed"]), log["seconds"][held], log["heldout_psnr"][held],
                    (m.get("input_blur") or {}).get("psnr")))
    if not out:
        raise FileNotFoundError(f"{folder} holds no experiment cells (folders with cell.json and log.csv)")
    return out


def plot(folder, out_png, title=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = cells(folder)
    scenes = list(dict.fromkeys(r[0] for r in rows))
    variants = list(dict.fromkeys(r[1] for r in rows))
    colours = {v: plt.cm.tab10(i % 10) for i, v in enumerate(variants)}
    n = len(scenes)
    cols = min(n, 3)
    fig, axes = plt.subplots((n + cols - 1) // cols, cols, figsize=(4.2 * cols, 3.2 * ((n + cols - 1) // cols)),
                             squeeze=False)
    for ax, scene in zip(axes.ravel(), scenes):
        inp = None
        for s, v, seed, t, p, i in rows:
            if s != scene:
                continue
            ax.plot(t, p, "o-", ms=3, color=colours[v], label=f"{v} (seed {seed})")
            inp = i if i is not None else inp
        if inp is not None:
            ax.axhline(inp, color="k", ls="--", lw=1, label="blurry input")
        ax.set_title(scene, fontsize=10)
        ax.set_xlabel("training time [s]")
        ax.set_ylabel("held-out PSNR [dB]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.suptitle(title or f"{Path(folder).name}: held-out PSNR against training time (JIT and evaluation excluded)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return Path(out_png)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder", help="OUT/runs/<experiment> of `d2gs experiment`")
    ap.add_argument("--out", required=True, help="PNG to write")
    ap.add_argument("--title")
    args = ap.parse_args(argv)
    print(f"wrote {plot(args.folder, args.out, args.title)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
