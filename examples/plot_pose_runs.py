"""Error against wall-clock time of runs on one scene: held-out PSNR of each run
(from RUN/log.csv) and the trajectory error after each pose-solver call of the first run (from
RUN/pose_solver.json; its first point is the ATE the run started from, after the bundle adjustment
of docs/method.md §5; that panel is left out when there is neither a solver log nor --given-ate).
The figure of README's noisy-pose table:

    python examples/plot_pose_runs.py "refined=RUN_A" "Adam alone=RUN_B" "true poses=RUN_C" \\
        --given-ate 0.0767 --out docs/pose_refinement.png
"""
from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def _heldout(run):
    rows = [r for r in csv.DictReader(open(Path(run) / "log.csv")) if r.get("heldout_psnr")]
    return [float(r["seconds"]) for r in rows], [float(r["heldout_psnr"]) for r in rows]


def _ate_curve(run):
    path = Path(run) / "pose_solver.json"
    if not path.exists():
        return None
    calls = [c for c in json.loads(path.read_text()) if "ate_after" in c]
    if not calls:
        return None
    sec = {int(r["step"]): float(r["seconds"]) for r in csv.DictReader(open(Path(run) / "log.csv"))}
    def at(step):
        return sec[max(k for k in sec if k <= step)]
    return [0.0] + [at(c["step"]) for c in calls], [calls[0]["ate_before"]] + [c["ate_after"] for c in calls]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="NAME=RUN_FOLDER, the first one with the pose solver")
    ap.add_argument("--given-ate", type=float, default=None, help="ATE of the given poses (a reference line)")
    ap.add_argument("--title", default="")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    pairs = []
    for item in a.runs:
        name, sep, run = item.partition("=")
        if not sep or not (Path(run) / "log.csv").exists():
            ap.error(f"expected NAME=RUN_FOLDER with a log.csv; got {item!r}")
        pairs.append((name, run))
    curve = _ate_curve(pairs[0][1])
    # without a pose solver and a given ATE there is no trajectory panel: held-out PSNR alone
    panels = 2 if (curve is not None or a.given_ate is not None) else 1
    fig, ax = plt.subplots(1, panels, figsize=(5.5 * panels, 4), squeeze=False)
    ax = ax[0]
    for name, run in pairs:
        ax[0].plot(*_heldout(run), marker="o", label=name)
    ax[0].set(xlabel="training seconds", ylabel="held-out PSNR [dB]", title=a.title)
    if curve is not None:
        ax[1].plot(*curve, marker="o", label=f"{pairs[0][0]}: ATE after each solver call")
    if a.given_ate is not None:
        ax[1].axhline(a.given_ate, ls="--", c="gray", label="given poses")
    if panels == 2:
        ax[1].set(xlabel="training seconds", ylabel="ATE", yscale="log",
                  title="trajectory error (0 s: start of training)")
    for x in ax:
        x.legend()
    fig.tight_layout()
    fig.savefig(a.out, dpi=90)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
