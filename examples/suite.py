"""Train and evaluate every scene of the suite (d2gs_np/data/suite.py) and write one table.

Every quality figure of the project is judged on the whole suite, never on one scene. For each
suite scene the variants are (each a separate run with its own folder):

- ``sharp``: sharp input (exposure 0) and true poses: the upper bound of the fit;
- ``blur``: blurry input, true poses, the full method (blur model on);
- ``noblur``: blurry input, true poses, no blur model (n = 1): the deblurring baseline;
- ``noisy``: blurry input with the suite's realistic pose error (0.75 deg RMS, 1.5% of depth), full
  method, and ``noisy_noblur`` its no-blur baseline of the same budget (opt-in:
  ``--variants sharp blur noblur noisy noisy_noblur``).

Ablation of the regularisers (docs/method.md §6, the paper's Table V), on the ``blur`` variant's
scene (blurry input, true poses), each with the method's weights (``METHOD_REGULARISER_WEIGHTS``)
and every other regulariser at weight 0: ``render_only`` (L_render alone), ``+ts``, ``+gs``,
``+freq``, ``+reproj`` (L_render plus one term) and ``all``. They get their own table
(OUT/ablation_by_scene.md): deblurring-view and novel-view PSNR / SSIM, ATE, number of Gaussians,
steps and wall time.

    python examples/suite.py --out runs/ablation --scenes wall_disk cube_sign \
        --variants render_only +ts +gs +freq all --iters 300 --size 0.5 --jobs 1 --threads 1

The cells are those of ``d2gs experiment suite`` and ``d2gs experiment suite-ablation``
(``d2gs_np/experiments/sweep.py``): run on Dask's local process pool (``--jobs`` at once, ``--threads``
Numba threads each), never recomputed once finished (an interrupted sweep resumes), a failed one
retried and then reported.

    python examples/suite.py --out runs/suite --budget 600 --jobs 2 --threads 1
    python examples/suite.py --out runs/suite_small --scenes photo_room cube_sign --budget 120 --size 0.5

Writes OUT/suite_by_scene.md (the table: one row per scene), and from the experiments
OUT/suite.md and OUT/suite.csv (one row per cell) and OUT/suite_error_vs_time.png (held-out PSNR
against training seconds, every cell); likewise suite-ablation.* for the ablation.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from d2gs_np.experiments.sweep import EXPERIMENTS, default_threads, run_experiment

VARIANTS = tuple(v.name for v in EXPERIMENTS["suite"])  # sharp, blur, noblur, noisy, noisy_noblur
# Regulariser ablation (``d2gs experiment suite-ablation``): each variant turns on the method's
# weight of its terms and sets the rest to 0, on the blur variant's scene (true poses, so the pose
# solver stays out; "+reproj" is L_reproj on the rendered depth).
ABLATION = tuple(v.name for v in EXPERIMENTS["suite-ablation"])
ALL_VARIANTS = VARIANTS + ABLATION


def fmt(x, spec=".2f"):
    return "" if x is None else format(x, spec)


def table(rows, scenes, seed):
    """One line per scene: input, deblurred, no-blur baseline, sharp-input bound, SSIM, ATE, time."""
    cell = {(r["scene"], r["variant"]): r for r in rows if r["seed"] == seed}
    lines = [
        "| scene | input dB | deblurred dB | no-blur dB | sharp-input bound dB | deblurred - input dB | "
        "SSIM input -> deblurred | noisy poses: deblurred dB | noisy poses: no-blur dB | ATE initial -> trained | "
        "steps (blur) | train s (blur) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scenes:
        b, nb, sh, no, nn = (cell.get((s, v), {}) for v in ("blur", "noblur", "sharp", "noisy", "noisy_noblur"))
        inp = b.get("input_psnr") or nb.get("input_psnr") or no.get("input_psnr")
        gain = None if (b.get("dvs_psnr") is None or inp is None) else b["dvs_psnr"] - inp
        ssim_in = b.get("input_ssim") or nb.get("input_ssim")
        lines.append(
            f"| {s} | {fmt(inp)} | {fmt(b.get('dvs_psnr'))} | {fmt(nb.get('dvs_psnr'))} | {fmt(sh.get('dvs_psnr'))} | "
            f"{fmt(gain, '+.2f')} | {fmt(ssim_in, '.3f')} -> {fmt(b.get('dvs_ssim'), '.3f')} | "
            f"{fmt(no.get('dvs_psnr'))} | {fmt(nn.get('dvs_psnr'))} | "
            f"{fmt(no.get('ate_initial'), '.4f')} -> {fmt(no.get('ate'), '.4f')} | "
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
    threads = args.threads or default_threads(args.jobs)
    out = Path(args.out)
    cmd = "python examples/suite.py " + " ".join(argv if argv is not None else sys.argv[1:])
    kw = dict(seeds=[args.seed], budget=args.budget, iters=args.iters, size=args.size, jobs=args.jobs,
              threads=threads, config_path=args.config, command=cmd)
    records = []
    for name, names in (("suite", VARIANTS), ("suite-ablation", ABLATION)):
        chosen = [v for v in args.variants if v in names]
        if chosen:
            records += run_experiment(name, out, args.scenes, variants=chosen, **kw)
    rows = [r for r in records if r["status"] == "ok"]
    failed = [(r["scene"], r["variant"], r.get("error")) for r in records if r["status"] != "ok"]
    for s, v, e in failed:  # a failed cell is reported, never silently dropped
        print(f"FAILED {s}/{v}: {e}", file=sys.stderr, flush=True)
    rows.sort(key=lambda r: (args.scenes.index(r["scene"]), ALL_VARIANTS.index(r["variant"])))
    md = table(rows, args.scenes, args.seed)
    (out / "suite_by_scene.md").write_text(f"`{cmd}`\n\n{md}\n")
    print("\n" + md)
    if any(r["variant"] in ABLATION for r in rows):
        amd = ablation_table(rows, args.scenes, args.seed)
        (out / "ablation_by_scene.md").write_text(f"`{cmd}`\n\n{amd}\n")
        print("\n" + amd)
    if failed:
        print(f"{len(failed)} cell(s) failed: {failed}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
