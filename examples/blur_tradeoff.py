"""Benchmark: the accuracy / cost trade-off of the blur model's n virtual sub-frames (Eq. 6).

Run:  python examples/blur_tradeoff.py --out-dir runs/blur_tradeoff
      (options: --gaussians 3000 --size 128 --repeats 5 --ref-samples 256 --seed 0
       --renderer auto|fast|reference)

A fixed random scene (static Gaussians in a slab in front of the camera plus a dynamic set
with non-zero deformation coefficients), one exposure with real camera motion (start / end
perturbations of a few degrees and centimetres around the estimated pose) and object motion
(tau > 0). For n in {1, 2, 4, 8, 16, 32} the n-sample blurry render (d2gs_np.blur.render) is compared
with a --ref-samples (default 256) render of the same scene and trajectory: PSNR, RMSE and max
abs error of the image, and the wall time per blurry render (forward, and forward + backward),
median of --repeats after a warm-up call that triggers (or loads) the Numba compilation.
n = 1 is the sharp camera at the estimated pose (no blur model). The grid u_i = i / (n - 1)
includes both endpoints with equal weights, so the mean converges to the exposure integral like
1/n (not 1/n^2 as a trapezoid or midpoint rule would); the n = 256 reference itself carries that
O(1/256) bias, small against the errors of the rows compared.

Prints a markdown table and writes blur_tradeoff.json and blur_tradeoff.png (error against time,
log-log) to --out-dir. Timings are of the machine it runs on and noisy on shared cores; the
ratios between rows of one run are the meaningful figures.
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import numpy as np

from d2gs_np.blur.config import BlurConfig
from d2gs_np.blur.render import blur_render_bwd, blur_render_fwd
from d2gs_np.geometry.camera import look_at, make_intrinsics
from d2gs_np.evaluation.metrics import psnr
from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.gaussians import init_params, logit

NS = (1, 2, 4, 8, 16, 32)


def make_scene(rng, num_gaussians, size, dynamic_fraction=0.15):
    """Scene params, camera and exposure: a dict of blur_render_fwd arguments."""
    deform = DeformConfig()
    nd = int(round(dynamic_fraction * num_gaussians))
    ns = num_gaussians - nd
    # static: a slab 4..7 units in front of a camera at the origin looking down +z
    static = np.stack([rng.uniform(-2.5, 2.5, ns), rng.uniform(-2.5, 2.5, ns), rng.uniform(4.0, 7.0, ns)], 1)
    dynamic = np.stack([rng.uniform(-1.0, 1.0, nd), rng.uniform(-1.0, 1.0, nd), rng.uniform(3.0, 4.0, nd)], 1)
    params = init_params(static, rng.uniform(size=(ns, 3)), dynamic, rng.uniform(size=(nd, 3)),
                         deform_config=deform, rng=rng, deform_init_std=0.0)
    for prefix, n in (("static", ns), ("dynamic", nd)):
        params[f"{prefix}.opacity_logits"] = logit(rng.uniform(0.3, 0.9, n))
        params[f"{prefix}.quats"] = rng.normal(size=(n, 4))
        params[f"{prefix}.log_scales"] = params[f"{prefix}.log_scales"] + rng.normal(0.0, 0.3, (n, 3))
    K = deform.num_coefs
    # object motion: ~0.3 units of position change per unit of time derivative, colour flicker
    params["dynamic.deform_means"] = 0.3 * rng.normal(size=(nd, K, 3))
    params["dynamic.deform_quats"] = 0.2 * rng.normal(size=(nd, K, 4))
    params["dynamic.deform_colors"] = 0.1 * rng.normal(size=(nd, K, 3))
    f = 1.1 * size
    deg, cm = math.pi / 180.0, 0.01
    xi_start = np.r_[rng.normal(0.0, 3 * cm, 3), rng.normal(0.0, 2 * deg, 3)]
    xi_end = np.r_[rng.normal(0.0, 3 * cm, 3), rng.normal(0.0, 2 * deg, 3)]
    return dict(
        params=params, frame_time=0.4, tau=0.05, pose_est=look_at([0.0, 0.0, 0.0], [0.0, 0.0, 5.0]),
        xi_start=xi_start, xi_end=xi_end, K=make_intrinsics(f, f, size / 2, size / 2), width=size,
        height=size, background=np.array([0.1, 0.1, 0.1]), deform_config=deform,
    )


def pick_renderer(name):
    if name in ("auto", "fast"):
        try:
            import d2gs_np.render as fast
            return fast, "d2gs_np.render (Numba)"
        except ImportError:
            if name == "fast":
                raise
    import d2gs_np.reference as reference
    return reference, "d2gs_np.reference (NumPy)"


def median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out-dir", type=Path, default=Path("runs/blur_tradeoff"))
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--ref-samples", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--renderer", choices=("auto", "fast", "reference"), default="auto")
    args = ap.parse_args(argv)

    renderer, renderer_name = pick_renderer(args.renderer)
    rng = np.random.default_rng(args.seed)
    case = make_scene(rng, args.gaussians, args.size)
    H = W = args.size
    v_image = np.random.default_rng(args.seed + 1).normal(size=(H, W, 3))

    def fwd(n):
        return blur_render_fwd(**case, blur_config=BlurConfig(num_virtual=n), renderer=renderer)

    t0 = time.perf_counter()
    _, saved = fwd(2)
    blur_render_bwd(saved, v_image)
    warmup = time.perf_counter() - t0
    print(f"renderer: {renderer_name}; warm-up (first n=2 forward+backward, JIT compile or cache load): "
          f"{warmup:.2f} s")

    t0 = time.perf_counter()
    ref_out, _ = fwd(args.ref_samples)
    ref_time = time.perf_counter() - t0
    ref = ref_out["image"]
    sharp = fwd(1)[0]["image"]
    print(f"reference: n = {args.ref_samples} in {ref_time:.2f} s; blur strength "
          f"(PSNR of the sharp render against it) {psnr(sharp, ref):.2f} dB")

    rows = []
    for n in NS:
        out, saved = fwd(n)
        err = out["image"] - ref
        t_fwd = median_time(lambda: fwd(n), args.repeats)

        def fwd_bwd():
            _, s = fwd(n)
            blur_render_bwd(s, v_image)

        t_fb = median_time(fwd_bwd, args.repeats)
        p = psnr(out["image"], ref)
        # psnr_db None: identical to the reference (JSON has no inf)
        rows.append(dict(n=n, psnr_db=p if math.isfinite(p) else None, rmse=float(np.sqrt(np.mean(err ** 2))),
                         max_abs=float(np.abs(err).max()), time_fwd_s=t_fwd, time_fwd_bwd_s=t_fb))

    base = rows[0]
    print()
    print(f"| n | PSNR vs n={args.ref_samples} (dB) | RMSE | max abs | fwd (ms) | fwd+bwd (ms) | fwd+bwd / n=1 |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        p = "inf" if r["psnr_db"] is None else f"{r['psnr_db']:.2f}"
        print(f"| {r['n']} | {p} | {r['rmse']:.2e} | {r['max_abs']:.2e} | {1e3 * r['time_fwd_s']:.1f} "
              f"| {1e3 * r['time_fwd_bwd_s']:.1f} | {r['time_fwd_bwd_s'] / base['time_fwd_bwd_s']:.1f} |")

    args.out_dir.mkdir(parents=True, exist_ok=True)
    record = dict(
        renderer=renderer_name, warmup_s=warmup, reference_samples=args.ref_samples, reference_time_s=ref_time,
        gaussians=args.gaussians, size=args.size, repeats=args.repeats, seed=args.seed,
        tau=case["tau"], xi_start=case["xi_start"].tolist(), xi_end=case["xi_end"].tolist(),
        sharp_psnr_db=psnr(sharp, ref), machine=platform.platform(), rows=rows,
    )
    (args.out_dir / "blur_tradeoff.json").write_text(json.dumps(record, indent=2))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    t = [r["time_fwd_bwd_s"] for r in rows]
    for key, label in (("rmse", "RMSE"), ("max_abs", "max abs error")):
        ax.loglog(t, [r[key] for r in rows], "o-", label=label)
        for r, ti in zip(rows, t):
            ax.annotate(f"n={r['n']}", (ti, r[key]), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_xlabel("wall time per blurry render, forward + backward (s)")
    ax.set_ylabel(f"image error against n = {args.ref_samples}")
    ax.set_title(f"Blur model trade-off (Eq. 6), {args.gaussians} Gaussians, {W}x{H}")
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out_dir / "blur_tradeoff.png", dpi=120)
    print(f"\nwrote {args.out_dir / 'blur_tradeoff.json'} and {args.out_dir / 'blur_tradeoff.png'}")


if __name__ == "__main__":
    main()
