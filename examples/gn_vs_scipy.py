"""The pose solver (d2gs_np/pose/gauss_newton.py) against scipy.optimize.least_squares on the
same residuals and Jacobian: robust cost against wall time for Levenberg-Marquardt (ours), plain
Gauss-Newton (ours with the damping at its floor) and scipy's trust-region reflective solver with
the same robust loss; prints a table (final cost, pose error, wall time, and each as a ratio to
scipy measured in the same run) and plots cost against time.

    python examples/gn_vs_scipy.py --frames 8 --points 200 --noise 0.5 --outliers 0.2 --out runs/gn_vs_scipy.png
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.optimize import least_squares

from d2gs_np.constants import LM_DAMPING_MIN
from d2gs_np.geometry.se3 import se3_inverse, se3_log
from d2gs_np.pose import gauss_newton as gn
from d2gs_np.pose.config import ROBUST_LOSSES, GaussNewtonConfig
from d2gs_np.pose.lm import SCIPY_LOSS, robust_cost
from d2gs_np.pose.toy import toy_problem


def pose_error(mids, truth):
    """Max over frames of |log(M T^-1)| (rad / world units)."""
    return max(float(np.abs(se3_log(mids[k] @ se3_inverse(truth[k]))).max()) for k in range(len(truth)))


def run_scipy(problem, cfg):
    """least_squares with the same loss; returns (x, trace of (seconds, cost) per evaluation)."""
    trace, t0 = [], time.perf_counter()
    loss = SCIPY_LOSS[cfg.robust]
    n = 3 * problem.num_matches

    def fun(x):
        r = problem.residuals(x, cfg.beta, cfg.spread_sigma, False)[0]
        data, _ = robust_cost(r[:n], cfg.robust, cfg.robust_scale)
        trace.append((time.perf_counter() - t0, data + 0.5 * float(np.sum(r[n:] ** 2))))
        return r

    def jac(x):
        return problem.residuals(x, cfg.beta, cfg.spread_sigma)[1]

    res = least_squares(fun, np.zeros(problem.num_params), jac=jac, method="trf", loss=loss,
                        f_scale=cfg.robust_scale, xtol=1e-12, ftol=1e-10, gtol=1e-12, max_nfev=200)
    return res.x, trace


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--points", type=int, default=200)
    ap.add_argument("--noise", type=float, default=0.5, help="pixel noise std of the matches")
    ap.add_argument("--outliers", type=float, default=0.2, help="fraction of matches replaced by outliers")
    ap.add_argument("--robust", default="cauchy", choices=ROBUST_LOSSES)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="PNG of cost against wall time")
    args = ap.parse_args(argv)

    problem, truth = toy_problem(args.frames, args.points, args.noise, args.outliers, rot_error=0.02,
                                 trans_error=0.05, seed=args.seed)
    cfg = GaussNewtonConfig(robust=args.robust, robust_scale=1.0, max_iters=50, ftol=1e-10)
    gn.solve(problem, dataclasses_replace(cfg, max_iters=1))  # build and cache the CasADi functions first
    rows, curves = [], {}
    for name, c in (("LM (ours)", cfg), ("GN (ours, lambda at floor)", dataclasses_replace(cfg, damping_init=LM_DAMPING_MIN))):
        t0 = time.perf_counter()
        res = gn.solve(problem, c)
        wall = time.perf_counter() - t0
        rows.append((name, res.costs[-1], pose_error(res.mids, truth), wall, res.iterations, res.status))
        curves[name] = (res.times, res.costs)
    t0 = time.perf_counter()
    x, trace = run_scipy(problem, cfg)
    wall = time.perf_counter() - t0
    mids = problem.poses(x)[2]
    rows.append(("scipy least_squares trf", trace[-1][1], pose_error(mids, truth), wall, len(trace), "-"))
    curves["scipy least_squares trf"] = ([t for t, _ in trace], [c for _, c in trace])
    start = pose_error(problem.poses(np.zeros(problem.num_params))[2], truth)
    print(f"{args.frames} frames, {problem.num_matches} matches, {problem.num_params} unknowns, noise {args.noise} px, "
          f"{args.outliers:.0%} outliers, loss {args.robust}; initial pose error {start:.3g}")
    ref_wall = rows[-1][3]
    print("| solver | final cost | pose error | wall s | wall / scipy | iterations (scipy: evaluations) | status |")
    print("|---|---|---|---|---|---|---|")
    for name, cost, err, w, it, st in rows:
        print(f"| {name} | {cost:.6g} | {err:.3g} | {w:.3f} | {w / ref_wall:.2f} | {it} | {st} |")
    if args.out:
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for name, (t, c) in curves.items():
            ax.semilogy(t, np.asarray(c) - min(r[1] for r in rows) + 1e-9, marker="o", ms=3, label=name)
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel("cost - best final cost")
        ax.legend()
        ax.set_title("pose solver: cost against time")
        fig.tight_layout()
        fig.savefig(args.out, dpi=120)
        print(f"wrote {args.out}")


def dataclasses_replace(cfg, **kw):
    import dataclasses

    return dataclasses.replace(cfg, **kw)


if __name__ == "__main__":
    main()
