"""Profile of the fast renderer's forward + backward, stage by stage, optionally against an older commit.

Stages timed (float64, after JIT warm-up, median over --reps): projection forward, tile
binning + depth sort (``build_intersections``), rasterise forward, rasterise backward (the
compositing backward and the per-Gaussian reduction), projection backward, and the whole
forward + backward. Counts (from the forward's saved state):

- ``box_isect``: tile-Gaussian pairs of the 3.33-sigma boxes (gsplat's binning, the
  ``num_intersections`` output), ``listed_isect``: pairs actually in the tile lists;
- Gaussians per non-empty tile (mean, max);
- ``evals``: (Gaussian, pixel) sigma evaluations of the forward kernel;
- ``contrib``: evaluations that composite (alpha >= 1/255, before the pixel stops): the rest
  (``skipped`` = evals - contrib) is work that changes nothing.

Scenes: ``small`` = examples/bench_render.py scene (a) (5 000 random Gaussians, 256 x 256, 1-6 px
standard deviations), ``large`` = the same with 4x the scales (large, heavily overlapping
Gaussians), ``train_init`` = the initial model of a suite scene (``--scene``, e.g. made by
``d2gs make-scene /tmp/sc --preset cube_sign --seed 0``; the first virtual view of frame 0 at
full resolution), ``train_mid`` = the same view of a trained run (``--run``, e.g. after
``d2gs train /tmp/sc --out /tmp/run --iters 300``).

With ``--baseline REV`` the renderer package of git revision REV (d2gs_np/render/*.py) is copied
into a temporary package and profiled in the same process, alternating old and new on every
repetition; the table then gives new/old time ratios (timings on a shared machine are noisy:
compare ratios, not absolute times). The outputs of old and new are compared too (max |diff|
over the image and every gradient).

Every scene is rendered in float64 unless ``--raster-float32`` (the mixed precision of training
steps, ``RenderConfig.raster_float32``: binning and compositing in float32). A baseline revision
without that option renders in float64 then.

Usage:
    NUMBA_NUM_THREADS=1 python examples/profile_step.py [--scene /tmp/sc] [--run /tmp/run]
        [--baseline b861d9c] [--reps 7] [--threads 1] [--raster-float32] [--out profile.json]
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from numba import njit

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_render import cotangents, random_scene  # noqa: E402

STAGES = ("project_fwd", "build_intersections", "rasterize_fwd", "rasterize_bwd", "project_bwd")


# ---------------------------------------------------------------------------------------------
# the renderer of another revision, as a separate package
# ---------------------------------------------------------------------------------------------


def load_render_package(rev):
    """Import d2gs_np/render of git revision ``rev`` as the package ``_d2gs_render_<rev>``.

    Files are written only when their text changed, so Numba's cache (keyed by file and time
    stamp) is reused across runs."""
    root = HERE.parent
    sha = subprocess.run(["git", "rev-parse", "--short", rev], cwd=root, capture_output=True, text=True,
                         check=True).stdout.strip()
    name = f"_d2gs_render_{sha}"
    base = Path(tempfile.gettempdir()) / "d2gs_render_revisions"
    pkg = base / name
    pkg.mkdir(parents=True, exist_ok=True)
    files = subprocess.run(["git", "ls-tree", "--name-only", sha, "d2gs_np/render/"], cwd=root, capture_output=True,
                           text=True, check=True).stdout.split()
    for f in (Path(f).name for f in files if f.endswith(".py")):  # the render package's modules at that revision
        text = subprocess.run(["git", "show", f"{sha}:d2gs_np/render/{f}"], cwd=root, capture_output=True,
                              text=True, check=True).stdout
        text = text.replace("d2gs_np.render.", f"{name}.")
        path = pkg / f
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
    if str(base) not in sys.path:
        sys.path.insert(0, str(base))
    importlib.import_module(name)
    return importlib.import_module(f"{name}.api"), sha


# ---------------------------------------------------------------------------------------------
# scenes
# ---------------------------------------------------------------------------------------------


def _call_of_render(model):
    """Render inputs (kwargs of render_fwd) of the first virtual view of frame 0 of ``model``."""
    import d2gs_np.render.api as api
    from d2gs_np.train.model import frame_render_fwd

    captured = []
    original = api._render

    def capture(inputs, width, height, config, dtype):
        captured.append(dict(inputs, width=width, height=height, config=config))
        return original(inputs, width, height, config, dtype)

    api._render = capture
    try:
        frame_render_fwd(model, 0, model.Ks[0], model.widths[0], model.heights[0])
    finally:
        api._render = original
    return {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in captured[0].items()}


def training_scene(scene_dir=None, run_dir=None):
    from d2gs_np.data.io import load_scene
    from d2gs_np.train.components import decide_components
    from d2gs_np.train.config import ExperimentConfig
    from d2gs_np.train.model import Model

    if run_dir is not None:
        from d2gs_np.evaluation.runs import load_run

        return _call_of_render(load_run(run_dir).model)
    scene = load_scene(scene_dir)
    config = ExperimentConfig()
    return _call_of_render(Model.from_scene(scene, config, decide_components(scene, config)))


def scenes(args):
    out = {}
    small = random_scene(5_000, 256, 256)
    out["small"] = small
    large = dict(small)
    large["scales"] = 4.0 * small["scales"]
    out["large"] = large
    if args.scene:
        out["train_init"] = training_scene(scene_dir=args.scene)
    if args.run:
        out["train_mid"] = training_scene(run_dir=args.run)
    return out


# ---------------------------------------------------------------------------------------------
# counting (plain loops; measurement only)
# ---------------------------------------------------------------------------------------------


@njit(cache=True)
def _count_contrib(means2d, conics, opac_eff, isect_gauss, tile_offsets, last_idx, grid_w, tile_size, athr,
                   amax):
    """Number of (Gaussian, pixel) pairs that composite: list positions up to the pixel's last
    contributor with alpha >= 1/255 (the pixel has not stopped before its last contributor)."""
    H, W = last_idx.shape
    total = 0
    for i in range(H):
        for j in range(W):
            t = (i // tile_size) * grid_w + j // tile_size
            last = last_idx[i, j]
            for pos in range(tile_offsets[t], last + 1):
                g = isect_gauss[pos]
                dx = means2d[g, 0] - (j + 0.5)
                dy = means2d[g, 1] - (i + 0.5)
                sigma = 0.5 * (conics[g, 0] * dx * dx + conics[g, 2] * dy * dy) + conics[g, 1] * dx * dy
                if sigma < 0:
                    continue
                alpha = min(amax, opac_eff[g] * np.exp(-sigma))
                if alpha >= athr:
                    total += 1
    return total


def counts(out, saved):
    from d2gs_np import constants as C

    isect, raster, proj = saved.isect, saved.raster, saved.proj
    per_tile = np.diff(isect["tile_offsets"])
    busy = per_tile[per_tile > 0]
    contrib = _count_contrib(proj["means2d"], proj["conics"], proj["opac_eff"], isect["isect_gauss"],
                             isect["tile_offsets"], raster["last_idx"], isect["grid_w"],
                             int(saved.config.tile_size), C.ALPHA_THRESHOLD, C.ALPHA_MAX)
    evals = int(raster["n_eval_tile"].sum())
    return dict(box_isect=int(out["num_intersections"]), listed_isect=int(isect["n_isect"]),
                per_tile_mean=float(busy.mean()) if busy.size else 0.0,
                per_tile_max=int(busy.max()) if busy.size else 0, evals=evals, contrib=int(contrib),
                skipped=evals - int(contrib), visible=int(np.count_nonzero(out["radii"][:, 0])),
                n=int(out["radii"].shape[0]), pixels=int(raster["last_idx"].size))


# ---------------------------------------------------------------------------------------------
# timing
# ---------------------------------------------------------------------------------------------


class StageTimer:
    """Wraps the stage functions in an api module's namespace with timers (restored by close)."""

    def __init__(self, api):
        self.api = api
        self.times = {s: 0.0 for s in STAGES}
        self.original = {s: getattr(api, s) for s in STAGES}
        for s in STAGES:
            setattr(api, s, self._wrap(s, self.original[s]))

    def _wrap(self, name, fn):
        def timed(*a, **k):
            t0 = time.perf_counter()
            r = fn(*a, **k)
            self.times[name] += time.perf_counter() - t0
            return r
        return timed

    def reset(self):
        for s in STAGES:
            self.times[s] = 0.0

    def close(self):
        for s in STAGES:
            setattr(self.api, s, self.original[s])


def run_once(api, call, cot):
    inputs = {k: call[k] for k in ("means", "quats", "scales", "opacities", "colors", "cam_T_world", "K",
                                   "background")}
    config = call.get("config")
    if config is None:
        config = api.RenderConfig()
    else:  # the same settings in this package's RenderConfig class (an older one may lack some)
        known = {f.name for f in dataclasses.fields(api.RenderConfig)}
        config = api.RenderConfig(**{k: v for k, v in dataclasses.asdict(config).items() if k in known})
    t0 = time.perf_counter()
    out, saved = api._render(inputs, call["width"], call["height"], config, call["means"].dtype)
    grads = api._render_bwd(saved, cot["v_image"], cot["v_alpha"])
    return time.perf_counter() - t0, out, saved, grads


def profile(apis, call, reps):
    """Alternating runs of every api on one scene; returns per-api median stage times and counts."""
    cot = cotangents(call["width"], call["height"], call["means"].dtype)
    res = {}
    timers = {name: StageTimer(api) for name, api in apis.items()}
    samples = {name: {s: [] for s in STAGES + ("total",)} for name in apis}
    outputs = {}
    try:
        for name, api in apis.items():  # warm-up (JIT or cache load)
            total, out, saved, grads = run_once(api, call, cot)
            outputs[name] = (out, saved, grads)
        for _ in range(reps):
            for name, api in apis.items():
                timers[name].reset()
                total, _, _, _ = run_once(api, call, cot)
                for s in STAGES:
                    samples[name][s].append(timers[name].times[s])
                samples[name]["total"].append(total)
    finally:
        for t in timers.values():
            t.close()
    for name in apis:
        out, saved, grads = outputs[name]
        res[name] = dict(times_ms={s: 1e3 * float(np.median(v)) for s, v in samples[name].items()},
                         counts=counts(out, saved))
    if len(apis) == 2:
        (na, (oa, _, ga)), (nb, (ob, _, gb)) = list(outputs.items())
        diffs = {"image": float(np.abs(oa["image"] - ob["image"]).max(initial=0.0))}
        shared = [k for k in ga if k in gb]  # a gradient one revision does not return is not compared
        for k in shared:
            diffs[k] = float(np.abs(ga[k] - gb[k]).max(initial=0.0))
        res["max_abs_diff"] = diffs
        res["bitwise_equal"] = bool(np.array_equal(oa["image"], ob["image"])
                                    and all(np.array_equal(ga[k], gb[k]) for k in shared))
        res["ratio_new_over_old"] = {s: res[na]["times_ms"][s] / max(res[nb]["times_ms"][s], 1e-9)
                                     for s in STAGES + ("total",)}
    return res


def table(results, names):
    lines = []
    for scene, res in results["scenes"].items():
        lines.append(f"\n### {scene}")
        c0 = res[names[0]]["counts"]
        lines.append(f"N = {c0['n']} ({c0['visible']} visible), {c0['pixels']} pixels")
        lines.append("")
        head = "| stage | " + " | ".join(f"{n} (ms)" for n in names)
        if len(names) == 2:
            head += f" | {names[0]}/{names[1]}"
        lines.append(head + " |")
        lines.append("|---" * (len(names) + 1 + (len(names) == 2)) + "|")
        for s in STAGES + ("total",):
            row = f"| {s} | " + " | ".join(f"{res[n]['times_ms'][s]:.2f}" for n in names)
            if len(names) == 2:
                row += f" | {res['ratio_new_over_old'][s]:.3f}"
            lines.append(row + " |")
        lines.append("")
        lines.append("| count | " + " | ".join(names) + " |")
        lines.append("|---" * (len(names) + 1) + "|")
        for k in ("box_isect", "listed_isect", "per_tile_mean", "per_tile_max", "evals", "contrib", "skipped"):
            vals = [res[n]["counts"][k] for n in names]
            lines.append(f"| {k} | " + " | ".join(f"{v:,.1f}" if isinstance(v, float) else f"{v:,}" for v in vals)
                         + " |")
        if "max_abs_diff" in res:
            lines.append("")
            lines.append(f"bitwise equal: {res['bitwise_equal']}; max |diff|: "
                         + ", ".join(f"{k} {v:.1e}" for k, v in res["max_abs_diff"].items()))
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", help="scene folder: adds the training-state scene train_init")
    parser.add_argument("--run", help="run folder: adds the training-state scene train_mid")
    parser.add_argument("--baseline", help="git revision whose renderer is profiled alongside (e.g. main)")
    parser.add_argument("--reps", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="profile_step.json")
    parser.add_argument("--raster-float32", action="store_true",
                        help="profile the new renderer with RenderConfig(raster_float32=True), the precision of "
                             "training steps (a baseline without the option runs float64); default: float64")
    args = parser.parse_args(argv)

    import numba

    import d2gs_np.render.api as new_api

    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    apis = {"new": new_api}
    if args.baseline:
        t0 = time.perf_counter()
        old_api, sha = load_render_package(args.baseline)
        apis = {"new": new_api, f"old@{sha}": old_api}
        print(f"loaded the renderer of {sha} in {time.perf_counter() - t0:.1f}s")
    results = {"threads": numba.get_num_threads(), "reps": args.reps, "load_average_start": list(os.getloadavg()),
               "scenes": {}}
    from d2gs_np.render import RenderConfig

    results["raster_float32"] = args.raster_float32
    for name, call in scenes(args).items():
        base = call.get("config") or RenderConfig()
        call = dict(call, config=dataclasses.replace(base, raster_float32=args.raster_float32))
        results["scenes"][name] = profile(apis, call, args.reps)
        print(f"{name} done", flush=True)
    results["load_average_end"] = list(os.getloadavg())
    text = table(results, list(apis))
    print(f"threads {results['threads']}, reps {args.reps} (medians), load average {results['load_average_start']}"
          f" -> {results['load_average_end']}")
    print(text)
    with open(args.out, "w") as fh:
        json.dump(results, fh, indent=2)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
