"""The bundle adjustment before training (d2gs_np/pose/given.py, docs/method.md §5) with both solvers
of ``pose.bundle.bundle_adjust``: SciPy's trust region ("scipy") and Levenberg-Marquardt with the
points eliminated ("schur"), on the real problem pose_init builds from a scene's blurry frames and
noisy given poses (the same KLT tracks for every run). Prints per scene and solver setting: the final
cost of each round, the inlier rms (px), the ATE of the adjusted poses against the true ones, the
solver seconds (both rounds), and each as a ratio to the first setting measured in the same run; plots
the cost against seconds (round 1 and round 2) to --out.

    python examples/bench_bundle.py SCENE [SCENE ...] --settings scipy:60 schur:60 schur:200 \
        --out runs/bench_bundle.png

SCENE: a scene folder with noisy given poses and the true ones (``gt_cam_T_world``), e.g. a suite
scene written by ``d2gs make-scene`` with pose noise (docs/dataset_format.md).
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from d2gs_np.evaluation import metrics
from d2gs_np.data.io import load_scene
from d2gs_np.pose.config import PoseInitConfig
from d2gs_np.pose.given import adjust_given_poses
from d2gs_np.pose.tracks import klt_tracks


def parse_setting(text):
    """"solver:max_nfev" -> (solver, max_nfev)."""
    name, _, n = text.partition(":")
    if not n.isdigit():
        raise SystemExit(f"--settings: expected solver:max_nfev (e.g. schur:60); got {text!r}")
    return name, int(n)


def run_scene(path, settings, seed):
    scene = load_scene(path)
    fr = scene.frames
    images = [f.image for f in fr]
    masks = [f.mask for f in fr] if all(f.mask is not None for f in fr) else None
    given = np.stack([f.cam_T_world for f in fr]).astype(np.float64)
    truth = np.stack([f.gt_cam_T_world for f in fr]).astype(np.float64)
    K = np.asarray(fr[0].K, dtype=np.float64)
    base = PoseInitConfig()
    t = time.perf_counter()
    tracks = klt_tracks(images, base.tracks, masks=masks, seed=seed)
    t_tracks = time.perf_counter() - t
    rows = []
    for solver, nfev in settings:
        cfg = dataclasses.replace(base, solver=solver, max_nfev=nfev)
        poses, info = adjust_given_poses(images, masks, given, K, cfg, seed=seed, tracks=tracks)
        rounds = info.get("rounds", [])
        rows.append({"setting": f"{solver}:{nfev}", "kept": info["kept"], "reason": info.get("reason", ""),
                     "ate": float(metrics.ate(poses, truth)),  # the given poses when not kept
                     "rms_px": rounds[-1]["rms_px"] if rounds else float("nan"),
                     "cost": [r["cost"] for r in rounds], "nfev": [r["nfev"] for r in rounds],
                     "iterations": [r["iterations"] for r in rounds],
                     "seconds": float(sum(r["seconds_history"][-1] for r in rounds)),
                     "histories": [(r["seconds_history"], r["cost_history"]) for r in rounds]})
    return {"scene": path.rstrip("/").split("/")[-1], "ate_given": float(metrics.ate(given, truth)),
            "tracks_seconds": t_tracks, "rows": rows}


def report(res):
    print(f"\n{res['scene']}: ATE given {res['ate_given']:.4f}; KLT tracks {res['tracks_seconds']:.1f}s "
          f"(shared, not counted)")
    b = res["rows"][0]
    print(f"{'setting':>12} {'kept':>5} {'ATE':>8} {'xATE':>6} {'rms px':>7} {'cost r1':>10} {'cost r2':>10} "
          f"{'xcost2':>7} {'nfev':>9} {'iters':>9} {'seconds':>8} {'xsec':>6}")
    for r in res["rows"]:
        print(f"{r['setting']:>12} {str(r['kept']):>5} {r['ate']:8.4f} {r['ate'] / b['ate']:6.2f} {r['rms_px']:7.3f} "
              f"{r['cost'][0]:10.1f} {r['cost'][-1]:10.1f} {r['cost'][-1] / b['cost'][-1]:7.4f} "
              f"{str(r['nfev']):>9} {str(r['iterations']):>9} {r['seconds']:8.2f} {r['seconds'] / b['seconds']:6.2f}"
              + ("" if r["kept"] else f"  ({r['reason']})"))


def plot(results, out):
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, len(results), figsize=(4.5 * len(results), 6.5), squeeze=False)
    for j, res in enumerate(results):
        for i in range(2):
            ax = axes[i, j]
            for r in res["rows"]:
                if i < len(r["histories"]):
                    sec, cost = r["histories"][i]
                    ax.plot(sec, cost, label=r["setting"])
            ax.set_yscale("log")
            ax.set_xlabel("seconds")
            ax.set_ylabel(f"round {i + 1} cost")
            ax.set_title(res["scene"], fontsize=8)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(f"\nplot: {out}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", help="scene folders with noisy given poses and true ones (gt_cam_T_world)")
    ap.add_argument("--settings", nargs="+", default=["scipy:60", "schur:60"],
                    help="solver:max_nfev pairs; the first is the baseline of the ratios")
    ap.add_argument("--seed", type=int, default=0, help="KLT seed (pose_init uses the training seed)")
    ap.add_argument("--out", default=None, help="cost-against-seconds plot (png)")
    args = ap.parse_args(argv)
    settings = [parse_setting(s) for s in args.settings]
    results = []
    for path in args.scenes:
        res = run_scene(path, settings, args.seed)
        report(res)
        results.append(res)
    if args.out:
        plot(results, args.out)
    return results


if __name__ == "__main__":
    main()
