"""Plots of runs: error against wall-clock time, and image comparisons."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


def read_log(run_dir) -> dict:
    """Columns of RUN/log.csv as float arrays (missing values are NaN) plus the stage names."""
    path = Path(run_dir) / "log.csv"
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist; is {run_dir} a training run?")
    with open(path) as f:
        rows = list(csv.DictReader(f))
    cols = {}
    for key in rows[0].keys() if rows else []:
        if key == "stage":
            cols[key] = [r[key] for r in rows]
        else:
            cols[key] = np.array([float(r[key]) if r[key] not in ("", "None") else np.nan for r in rows])
    return cols


def plot_error_vs_time(run_dirs, out_png, labels=None, title="error against wall-clock time"):
    """PSNR (train, and held-out where logged) against training seconds for one or more runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run_dirs = [run_dirs] if isinstance(run_dirs, (str, Path)) else list(run_dirs)
    labels = labels or [Path(r).name for r in run_dirs]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for run, label in zip(run_dirs, labels):
        c = read_log(run)
        line, = ax.plot(c["seconds"], c["train_psnr"], alpha=0.35, lw=1)
        held = ~np.isnan(c["heldout_psnr"])
        if held.any():
            ax.plot(c["seconds"][held], c["heldout_psnr"][held], "o-", color=line.get_color(),
                    label=f"{label}: held-out (sharp GT)")
        ax.plot([], [], color=line.get_color(), alpha=0.35, label=f"{label}: train (blurry target)")
    ax.set_xlabel("training time [s] (JIT warm-up and evaluation excluded)")
    ax.set_ylabel("PSNR [dB]")
    ax.set_title(title)
    return _save(fig, ax, out_png)


def heldout_curve(run_dir):
    """(seconds (R,), held-out PSNR (R,)) of a run's logged held-out rows (empty when it logged none)."""
    c = read_log(run_dir)
    held = ~np.isnan(c.get("heldout_psnr", np.full(len(c["seconds"]), np.nan)))
    return c["seconds"][held], c["heldout_psnr"][held]


def plot_curves_by_scene(rows, out_png, title="held-out PSNR against training time"):
    """One panel per scene: held-out PSNR against training seconds, a line per variant and seed, and
    the blurry input's PSNR dashed (what training must rise above). An experiment's cells on one axis
    cannot be read past a few; this is its figure.

    rows: (scene, variant, seed, seconds (R,), held-out PSNR (R,), input PSNR or None) per cell.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(rows)
    if not rows:
        raise ValueError("plot_curves_by_scene: no cells to plot")
    scenes = list(dict.fromkeys(r[0] for r in rows))
    colours = {v: plt.cm.tab10(i % 10) for i, v in enumerate(dict.fromkeys(r[1] for r in rows))}
    n, cols = len(scenes), min(len(scenes), 3)
    nrows = (n + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(4.2 * cols, 3.2 * nrows), squeeze=False)
    for ax, scene in zip(axes.ravel(), scenes):
        inp = None
        for s, v, seed, t, p, i in rows:
            if s == scene:
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
    fig.suptitle(f"{title} (JIT and evaluation excluded)", fontsize=10)
    fig.tight_layout()
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return Path(out_png)


def plot_loss_terms(run_dir, out_png, title=None):
    """Each loss term's unweighted value (log columns ``loss_<name>``, docs/method.md §6) against
    training seconds, on a log axis (the terms differ by orders of magnitude)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = read_log(run_dir)
    names = [k for k in c if k.startswith("loss_")]
    if not names:
        raise ValueError(f"{Path(run_dir) / 'log.csv'} has no loss_<name> columns; it is not a run with loss terms")
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for name in names:
        v = c[name]
        ok = np.isfinite(v) & (v > 0)
        if ok.any():
            ax.plot(c["seconds"][ok], v[ok], lw=1, label=name[len("loss_"):])
    ax.set_yscale("log")
    ax.set_xlabel("training time [s]")
    ax.set_ylabel("term value (unweighted)")
    ax.set_title(title or f"loss terms of {Path(run_dir).name}")
    return _save(fig, ax, out_png)


def _save(fig, ax, out_png):
    """Grid, legend, tight layout; write out_png (its folder made) at 120 dpi and close the figure."""
    import matplotlib.pyplot as plt

    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=120)
    plt.close(fig)
    return Path(out_png)


def save_image(path, image):
    """Write an (H, W, 3) float image in [0, 1] as 8-bit PNG."""
    import cv2

    img = np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), (img[..., ::-1] * 255.0 + 0.5).astype(np.uint8)):
        raise OSError(f"could not write image {path}")


def comparison_strip(rows, labels=None):
    """Stack rows of images side by side with a 2-pixel white gap: list of lists -> one image."""
    gap = 2
    lines = []
    for row in rows:
        h = row[0].shape[0]
        parts = []
        for img in row:
            parts += [np.clip(img, 0, 1), np.ones((h, gap, 3))]
        lines += [np.concatenate(parts[:-1], axis=1), np.ones((gap, sum(p.shape[1] for p in parts[:-1]), 3))]
    return np.concatenate(lines[:-1], axis=0)
