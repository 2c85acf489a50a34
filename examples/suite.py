"""Train and evaluate every scene of the suite (d2gs_np/data/suite.py) and write one table.

Every quality figure of the project is judged on the whole suite, never on one scene. For each
suite scene the variants are (each a separate run with its own folder):

- ``sharp``: sharp input (exposure 0) and true poses: the upper bound of the fit;
- ``blur``: blurry input, true poses, the full method (blur model on);
- ``noblur``: blurry input, true poses, no blur model (n = 1): the deblurring baseline;
- ``noisy``: blurry input with the suite's realistic pose error (0.75 deg RMS, 1.5% of depth), full
  method (opt-in: ``--variants sharp blur noblur noisy``).

Ablation of the regularisers (docs/method.md §6, the paper's Table V), on the ``blur`` variant's
scene (blurry input, true poses), each with the method's weights (``METHOD_REGULARISER_WEIGHTS``)
and every other regulariser at weight 0: ``render_only`` (L_render alone), ``+ts``, ``+gs``,
``+freq`` (L_render plus one term) and ``all``. They get their own table (OUT/ablation.md):
deblurring-view and novel-view PSNR / SSIM, ATE, number of Gaussians, steps and wall time.

    python examples/suite.py --out runs/ablation --scenes wall_disk cube_sign \
        --variants render_only +ts +gs +freq all --iters 300 --size 0.5 --jobs 1 --threads 1

Cells already finished (RUN/metrics.json present) are not recomputed, so an interrupted sweep
resumes. Cells run in parallel processes (``--jobs``) with ``--threads`` Numba threads each.

    python examples/suite.py --out runs/suite --budget 600 --jobs 2 --threads 1
    python examples/suite.py --out runs/suite_small --scenes photo_room cube_sign --budget 120 --size 0.5

Writes OUT/suite.md (the table), OUT/suite.csv (one row per cell) and OUT/error_vs_time.png
(held-out PSNR against training seconds, every cell).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

VARIANTS = ("sharp", "blur", "noblur", "noisy")
# Regulariser ablation: variant -> the LossConfig weights it turns on (the method's values); the
# rest are set to 0. "+reproj": L_reproj on the rendered depth (the suite's scenes here have true
# poses, so the pose solver stays out).
ABLATION = {
    "render_only": (),
    "+ts": ("lambda_ts",),
    "+gs": ("lambda_gs",),
    "+freq": ("lambda_freq",),
    "+reproj": ("lambda_reproj",),
    "all": ("lambda_ts", "lambda_gs", "lambda_freq", "lambda_reproj"),
}
ALL_VARIANTS = VARIANTS + tuple(ABLATION)


def loss_overrides(variant):
    """LossConfig fields of a variant: for an ablation variant every regulariser weight (method's
    value if the variant has the term, else 0); {} for the other variants (the config's loss)."""
    from d2gs_np.train.config import METHOD_REGULARISER_WEIGHTS

    if variant not in ABLATION:
        return {}
    return {k: (v if k in ABLATION[variant] else 0.0) for k, v in METHOD_REGULARISER_WEIGHTS.items()}


def scene_overrides(variant, size):
    """SuiteConfig overrides of a variant's scene (input kind, poses) at a size factor."""
    o = {}
    if variant == "sharp":
        o.update(exposure_fraction=0.0, rot_noise_deg=0.0, trans_noise=0.0)
    elif variant in ("blur", "noblur") or variant in ABLATION:
        o.update(rot_noise_deg=0.0, trans_noise=0.0)
    if size != 1.0:
        o.update(width=max(16, int(round(240 * size))), height=max(16, int(round(135 * size))))
    return o


def scene_folder(out, scene, variant, seed):
    kind = {"sharp": "sharp_true", "blur": "blurry_true", "noblur": "blurry_true", "noisy": "blurry_noisy",
            **{v: "blurry_true" for v in ABLATION}}[variant]
    return Path(out) / "scenes" / f"{scene}_s{seed}_{kind}"


def run_cell(out, scene, variant, seed, budget, iters, size, threads, config_path):
    """Make the scene (if needed), train, evaluate; returns the cell's record. Runs in a worker."""
    import dataclasses

    import numba

    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))

    from d2gs_np.data.io import load_scene
    from d2gs_np.data.suite import write_suite_scene
    from d2gs_np.evaluate import evaluate_run
    from d2gs_np.experiments import flatten
    from d2gs_np.train.config import ExperimentConfig
    from d2gs_np.train.trainer import Trainer

    sdir = scene_folder(out, scene, variant, seed)
    lock = sdir.with_suffix(".done")
    if not lock.exists():
        write_suite_scene(sdir, scene, seed, overwrite=True, **scene_overrides(variant, size))
        lock.write_text("ok\n")
    run_dir = Path(out) / "runs" / f"{scene}_s{seed}_{variant}"
    metrics_path = run_dir / "metrics.json"
    if not metrics_path.exists():
        cfg = ExperimentConfig.load(config_path) if config_path else ExperimentConfig()
        train = dataclasses.replace(cfg.train, quiet=True, seed=seed, time_budget=budget,
                                    iters=iters if iters else cfg.train.iters,
                                    blur="off" if variant == "noblur" else cfg.train.blur)
        cfg = cfg.replace(train=train, loss=dataclasses.replace(cfg.loss, **loss_overrides(variant)))
        t0 = time.perf_counter()
        trainer = Trainer(load_scene(sdir), cfg, run_dir)
        trainer.run()
        wall = time.perf_counter() - t0
        result = evaluate_run(run_dir)
        result["wall_seconds"] = wall
        result["num_gaussians"] = trainer.num_gaussians()
        metrics_path.write_text(json.dumps(result, indent=1, allow_nan=False, default=_none_for_nan) + "\n")
    return {"scene": scene, "variant": variant, "seed": seed, "run": str(run_dir),
            **flatten(json.loads(metrics_path.read_text()))}


def _none_for_nan(x):
    return None


def fmt(x, spec=".2f"):
    return "" if x is None else format(x, spec)


def table(rows, scenes, seed):
    """One line per scene: input, deblurred, no-blur baseline, sharp-input bound, SSIM, ATE, time."""
    cell = {(r["scene"], r["variant"]): r for r in rows if r["seed"] == seed}
    lines = [
        "| scene | input dB | deblurred dB | no-blur dB | sharp-input bound dB | deblurred - input dB | "
        "SSIM input -> deblurred | noisy poses: deblurred dB | ATE initial -> trained | steps (blur) | "
        "train s (blur) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scenes:
        b, nb, sh, no = (cell.get((s, v), {}) for v in ("blur", "noblur", "sharp", "noisy"))
        inp = b.get("input_psnr") or nb.get("input_psnr") or no.get("input_psnr")
        gain = None if (b.get("dvs_psnr") is None or inp is None) else b["dvs_psnr"] - inp
        ssim_in = b.get("input_ssim") or nb.get("input_ssim")
        lines.append(
            f"| {s} | {fmt(inp)} | {fmt(b.get('dvs_psnr'))} | {fmt(nb.get('dvs_psnr'))} | {fmt(sh.get('dvs_psnr'))} | "
            f"{fmt(gain, '+.2f')} | {fmt(ssim_in, '.3f')} -> {fmt(b.get('dvs_ssim'), '.3f')} | "
            f"{fmt(no.get('dvs_psnr'))} | {fmt(no.get('ate_initial'), '.4f')} -> {fmt(no.get('ate'), '.4f')} | "
            f"{fmt(b.get('steps'), 'd')} | {fmt(b.get('train_seconds'), '.0f')} |")
    return "\n".join(lines)


def ablation_table(rows, scenes, seed):
    """One line per (scene, ablation variant), in ABLATION's order: DVS and NVS PSNR / SSIM, ATE,
    Gaussians, steps, wall time; and the change of DVS PSNR against render_only."""
    cell = {(r["scene"], r["variant"]): r for r in rows if r["seed"] == seed}
    lines = ["| scene | variant | DVS PSNR dB | vs render_only dB | DVS SSIM | NVS PSNR dB | NVS SSIM | ATE | "
             "Gaussians | steps | wall s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in scenes:
        base = cell.get((s, "render_only"), {}).get("dvs_psnr")
        for v in ABLATION:
            r = cell.get((s, v))
            if r is None:
                continue
            d = None if (base is None or r.get("dvs_psnr") is None) else r["dvs_psnr"] - base
            lines.append(f"| {s} | {v} | {fmt(r.get('dvs_psnr'))} | {fmt(d, '+.2f')} | "
                         f"{fmt(r.get('dvs_ssim'), '.3f')} | {fmt(r.get('nvs_psnr'))} | {fmt(r.get('nvs_ssim'), '.3f')} | {fmt(r.get('ate'), '.4f')} | "
                         f"{fmt(r.get('num_gaussians'), 'd')} | {fmt(r.get('steps'), 'd')} | "
                         f"{fmt(r.get('wall_seconds'), '.0f')} |")
    return "\n".join(lines)


def main(argv=None):
    from d2gs_np.data.suite import SUITE

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/suite")
    ap.add_argument("--scenes", nargs="+", default=list(SUITE), help=f"suite scenes (default all: {list(SUITE)})")
    ap.add_argument("--variants", nargs="+", default=["sharp", "blur", "noblur"], choices=ALL_VARIANTS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--budget", type=float, default=600.0, help="seconds of training per cell (default 600)")
    ap.add_argument("--iters", type=int, default=None, help="steps per cell (default: the config's)")
    ap.add_argument("--size", type=float, default=1.0, help="image size factor on 240x135 (default 1)")
    ap.add_argument("--config", default=None, help="experiment config JSON for every cell")
    ap.add_argument("--jobs", type=int, default=1, help="cells in parallel (processes)")
    ap.add_argument("--threads", type=int, default=None, help="Numba threads per cell (default cores / jobs)")
    args = ap.parse_args(argv)
    unknown = sorted(set(args.scenes) - set(SUITE))
    if unknown:
        ap.error(f"unknown suite scene(s) {unknown}; choose from {sorted(SUITE)}")
    if args.jobs < 1 or args.budget <= 0 or args.size <= 0:
        ap.error("--jobs must be >= 1, --budget and --size > 0")
    threads = args.threads or max(1, (os.cpu_count() or 1) // args.jobs)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cells = [(s, v) for s in args.scenes for v in args.variants]
    rows, failed = [], []
    t0 = time.perf_counter()
    def record(s, v, get):
        try:
            r = get()
            rows.append(r)
            print(f"[{time.perf_counter() - t0:7.0f}s] {s}/{v}: DVS {fmt(r['dvs_psnr'])} dB "
                  f"(input {fmt(r['input_psnr'])} dB), {r['steps']} steps", flush=True)
        except Exception as e:  # a failed cell is reported, never silently dropped
            failed.append((s, v, repr(e)))
            print(f"FAILED {s}/{v}: {e!r}", file=sys.stderr, flush=True)

    job = (str(out), args.seed, args.budget, args.iters, args.size, threads, args.config)
    if args.jobs == 1:  # in this process, one cell after another
        for s, v in cells:
            record(s, v, lambda: run_cell(job[0], s, v, *job[1:]))
    else:
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            futs = {pool.submit(run_cell, job[0], s, v, *job[1:]): (s, v) for s, v in cells}
            for f in as_completed(futs):
                record(*futs[f], f.result)
    rows.sort(key=lambda r: (args.scenes.index(r["scene"]), ALL_VARIANTS.index(r["variant"])))
    with open(out / "suite.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["scene"])
        w.writeheader()
        w.writerows(rows)
    md = table(rows, args.scenes, args.seed)
    cmd = "python examples/suite.py " + " ".join(argv if argv is not None else sys.argv[1:])
    (out / "suite.md").write_text(f"`{cmd}`\n\n{md}\n")
    print("\n" + md)
    if any(r["variant"] in ABLATION for r in rows):
        amd = ablation_table(rows, args.scenes, args.seed)
        (out / "ablation.md").write_text(f"`{cmd}`\n\n{amd}\n")
        print("\n" + amd)
    if rows:
        from d2gs_np.report import plot_error_vs_time

        plot_error_vs_time([r["run"] for r in rows], out / "error_vs_time.png",
                           labels=[f"{r['scene']}/{r['variant']}" for r in rows],
                           title="suite: held-out PSNR against training seconds")
    if failed:
        print(f"{len(failed)} cell(s) failed: {failed}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
