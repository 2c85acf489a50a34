"""Held-out PSNR against training seconds for every cell of an experiment, one panel per scene.

Each panel holds one line per variant (the held-out PSNR its log recorded: sharp renders at the
optimised mid poses against the sharp frames, ``train/plugins.HeldOutPSNR``) and, dashed, the blurry
input's PSNR from the cell's ``metrics.json``: what training must rise above. ``d2gs experiment``
draws the same figure as ``OUT/<experiment>_error_vs_time.png`` when it ends; this redraws it from
the cell folders (an experiment still running, or cells gathered from several).

    python examples/plot_suite_curves.py OUT/runs/EXPERIMENT --out curves.png [--title TITLE]
    python examples/plot_suite_curves.py "1 thread=OUT1/runs/EXP" "2 threads=OUT2/runs/EXP" --out c.png

Several folders go on the same panels; ``LABEL=FOLDER`` tags each of its lines "variant (LABEL)".

Cell folders are ``<scene>_s<seed>_<variant>[...]`` with ``cell.json`` (``d2gs experiment``).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def cells(folder, label=None):
    """[(scene, variant, seed, seconds (R,), held-out PSNR (R,), input PSNR or None)] of the cells;
    ``label`` appended to each variant as "variant (label)"."""
    from d2gs_np.reporting.plots import heldout_curve

    out = []
    for d in sorted(Path(folder).iterdir()):
        if not (d / "cell.json").is_file() or not (d / "log.csv").is_file():
            continue
        c = json.loads((d / "cell.json").read_text())
        m = json.loads((d / "metrics.json").read_text()) if (d / "metrics.json").is_file() else {}
        variant = c["variant"] if label is None else f"{c['variant']} ({label})"
        out.append((c["scene"], variant, int(c["seed"]), *heldout_curve(d), (m.get("input_blur") or {}).get("psnr")))
    if not out:
        raise FileNotFoundError(f"{folder} holds no experiment cells (folders with cell.json and log.csv)")
    return out


def plot(folders, out_png, title=None):
    """``folders``: one folder, or several, each a path or ``LABEL=PATH``."""
    from d2gs_np.reporting.plots import plot_curves_by_scene

    folders = [_labelled(f) for f in ([folders] if isinstance(folders, (str, Path)) else folders)]
    rows = [row for label, path in folders for row in cells(path, label)]
    return plot_curves_by_scene(rows, out_png,
                                title or f"{Path(folders[0][1]).name}: held-out PSNR against training time")


def _labelled(arg):
    """(label or None, folder) of a ``LABEL=FOLDER`` or ``FOLDER`` argument."""
    label, _, path = str(arg).rpartition("=")
    return label or None, path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+", help="OUT/runs/<experiment> of `d2gs experiment`, or LABEL=FOLDER")
    ap.add_argument("--out", required=True, help="PNG to write")
    ap.add_argument("--title")
    args = ap.parse_args(argv)
    print(f"wrote {plot(args.folders, args.out, args.title)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
