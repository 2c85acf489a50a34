"""Benchmark of the Numba splatter (d2gs_np.render) against the NumPy reference.

Times render_fwd and render_fwd + render_bwd in float64, float32 and "mixed" (float64 inputs with
RenderConfig(raster_float32=True), what training steps use) with 1 and 2 Numba threads, after JIT
warm-up, on
  (a) N = 5 000 random Gaussians at 256 x 256,
  (b) N = 50 000 random Gaussians at 512 x 512,
  (c) scene (a) with 4x the scales (large, heavily overlapping Gaussians),
and the plain NumPy reference (d2gs_np.reference, memory O(N H W)) on a reduced scene
  (r) N = 312 at 64 x 64 (the Gaussian density per pixel of (a), 1/16 of its area),
with the fast path timed on (r) in the same run for the ratio.

Compile costs are measured in fresh subprocesses: first with an empty NUMBA_CACHE_DIR (JIT
compile + cache write), then with that cache filled (cache load only).

Random scenes: Gaussians drawn in the camera frame with pixel position uniform over the image
(plus a 4 px border), camera depth uniform in [2, 6], per-axis projected standard deviation
uniform in [1, 6] px, random rotations, opacity uniform in [0.05, 0.95], colours uniform in
[0, 1]; a random camera pose (rotation up to 0.6 rad) maps them to world coordinates.

The backward pass gets a random v_image and v_alpha (v_depth and v_expected_depth None).
Reported: median and min wall times over --reps repetitions, Gaussian-pixel evaluations per
second of the forward pass (evaluations = sigma evaluations inside footprints), tile
intersections, the bytes kept in ``saved`` (O(N + n_isect + pixels)), and the float32 and mixed
paths' relative error vs float64 (max |x32 - x64| / max |x64| over image and over each gradient).
fastmath is off everywhere (not measured).

Usage: python examples/bench_render.py [--out bench_render.json] [--reps 5] [--no-compile]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import textwrap
import time

import numpy as np

SIGMA_PX = (1.0, 6.0)
DEPTH = (2.0, 6.0)
OPACITY = (0.05, 0.95)
BORDER_PX = 4.0
SCENES = {"a": (5_000, 256, 256), "b": (50_000, 512, 512), "c": (5_000, 256, 256), "r": (312, 64, 64)}
SCALE = {"c": 4.0}  # scale factor of a scene's Gaussians (1 if absent)
TARGETS_MS = {("a", "fwd"): 30.0, ("a", "fwd+bwd"): 100.0, ("b", "fwd+bwd"): 1000.0}  # float64, 2 threads


def _rotation(rng, max_angle):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0.0, max_angle)
    W = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * W + (1.0 - np.cos(angle)) * W @ W


def random_scene(n, width, height, seed=0, dtype=np.float64, scale=1.0):
    """A random scene (see the module docstring) as keyword arguments of render_fwd; ``scale``
    multiplies every Gaussian's scales (after drawing, so the rest of the scene is unchanged)."""
    rng = np.random.default_rng(seed)
    f = max(width, height)
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    R_v = _rotation(rng, 0.6)
    t_v = rng.normal(size=3)
    T = np.eye(4)
    T[:3, :3] = R_v
    T[:3, 3] = t_v
    u = rng.uniform(-BORDER_PX, width + BORDER_PX, n)
    v = rng.uniform(-BORDER_PX, height + BORDER_PX, n)
    z = rng.uniform(*DEPTH, n)
    p_c = np.stack([(u - K[0, 2]) * z / f, (v - K[1, 2]) * z / f, z], axis=1)
    scene = dict(
        means=(p_c - t_v) @ R_v,
        quats=rng.normal(size=(n, 4)),
        scales=scale * rng.uniform(*SIGMA_PX, size=(n, 3)) * z[:, None] / f,
        opacities=rng.uniform(*OPACITY, n),
        colors=rng.uniform(0.0, 1.0, (n, 3)),
        cam_T_world=T,
        K=K,
        width=width,
        height=height,
        background=rng.uniform(0.0, 1.0, 3),
    )
    return {k: (np.asarray(x, dtype) if isinstance(x, np.ndarray) else x) for k, x in scene.items()}


def cotangents(width, height, dtype, seed=1):
    rng = np.random.default_rng(seed)
    return dict(v_image=rng.normal(size=(height, width, 3)).astype(dtype),
                v_alpha=rng.normal(size=(height, width)).astype(dtype))


def _timeit(fn, reps):
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), float(np.min(times))


def _nbytes(obj):
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, dict):
        return sum(_nbytes(v) for v in obj.values())
    return 0


def saved_bytes(saved):
    """Bytes of the arrays ``saved`` owns (inputs excluded)."""
    return _nbytes(saved.proj) + _nbytes(saved.isect) + _nbytes(saved.raster)


def rel(a, b, q=None):
    """max (or the q-quantile, if given) of |a - b| / max |b|."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    scale = np.abs(b).max(initial=0.0)
    if scale == 0 or a.size == 0:
        return 0.0
    d = np.abs(a - b)
    return float((d.max() if q is None else np.quantile(d, q)) / scale)


# ---------------------------------------------------------------------------------------------
# compile / cache-load timing in fresh processes
# ---------------------------------------------------------------------------------------------

_FIRST_CALL = textwrap.dedent("""
    import json, sys, time
    t0 = time.perf_counter()
    import numpy as np
    sys.path.insert(0, sys.argv[1])
    from bench_render import random_scene, cotangents
    from d2gs_np.render import render_bwd, render_fwd
    res = {"import_s": time.perf_counter() - t0}
    for dtype in (np.float64, np.float32):
        scene = random_scene(50, 40, 30, dtype=dtype)
        cot = cotangents(40, 30, dtype)
        t0 = time.perf_counter()
        out, saved = render_fwd(**scene)
        t1 = time.perf_counter()
        render_bwd(saved, **cot)
        t2 = time.perf_counter()
        res[np.dtype(dtype).name] = {"fwd_s": t1 - t0, "bwd_s": t2 - t1}
    print(json.dumps(res))
""")


def first_call_times(cache_dir):
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    here = os.path.dirname(os.path.abspath(__file__))
    proc = subprocess.run([sys.executable, "-c", _FIRST_CALL, here], env=env, capture_output=True, text=True,
                          check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------


# precisions timed: (label, input dtype, RenderConfig.raster_float32); "mixed" is what training
# steps use (float64 in and out, binning and compositing in float32)
PRECISIONS = (("float64", np.float64, False), ("float32", np.float32, False), ("mixed", np.float64, True))


def bench_fast(name, precision, threads, reps):
    import numba

    from d2gs_np.render import RenderConfig, render_bwd, render_fwd

    label, dtype, raster32 = next(p for p in PRECISIONS if p[0] == precision)
    n, W, H = SCENES[name]
    numba.set_num_threads(threads)
    scene = dict(random_scene(n, W, H, dtype=dtype, scale=SCALE.get(name, 1.0)),
                 config=RenderConfig(raster_float32=raster32))
    cot = cotangents(W, H, dtype)
    out, saved = render_fwd(**scene)  # warm-up (JIT or cache load)
    render_bwd(saved, **cot)
    t_fwd, t_fwd_min = _timeit(lambda: render_fwd(**scene), reps)
    t_both, t_both_min = _timeit(lambda: render_bwd(render_fwd(**scene)[1], **cot), reps)
    n_eval = saved.num_evaluations
    return dict(scene=name, n=n, width=W, height=H, dtype=label, threads=threads,
                fwd_ms=1e3 * t_fwd, fwd_min_ms=1e3 * t_fwd_min, fwd_bwd_ms=1e3 * t_both,
                fwd_bwd_min_ms=1e3 * t_both_min, evaluations=n_eval, evals_per_s=n_eval / t_fwd,
                intersections=out["num_intersections"], saved_mb=saved_bytes(saved) / 2**20)


def float32_errors(name, precision="float32"):
    """float32 (or "mixed") vs float64 on scene ``name``: max and 99.9 % quantile of the relative
    errors, and the number of pixels whose set of contributors differs (a threshold decision
    flipped)."""
    from d2gs_np.render import RenderConfig, render_bwd, render_fwd

    n, W, H = SCENES[name]
    outs, grads, saves = {}, {}, {}
    for label, dtype, raster32 in (PRECISIONS[0], next(p for p in PRECISIONS if p[0] == precision)):
        out, saved = render_fwd(**random_scene(n, W, H, dtype=dtype, scale=SCALE.get(name, 1.0)),
                                config=RenderConfig(raster_float32=raster32))
        outs[label], saves[label] = out, saved
        grads[label] = render_bwd(saved, **cotangents(W, H, dtype))
    i32, i64 = outs[precision]["image"], outs["float64"]["image"]
    g32, g64 = grads[precision], grads["float64"]
    last32, last64 = saves[precision].raster["last_idx"], saves["float64"].raster["last_idx"]
    return dict(image=rel(i32, i64), image_q999=rel(i32, i64, q=0.999),
                grads_max=max(rel(g32[k], g64[k]) for k in g64),
                grads_q999=max(rel(g32[k], g64[k], q=0.999) for k in g64),
                pixels_last_contributor_differs=int(np.count_nonzero(last32 != last64)))


def bench_reference(threads, reps):
    import numba

    from d2gs_np import reference as ref
    from d2gs_np.render import render_bwd, render_fwd

    n, W, H = SCENES["r"]
    scene = random_scene(n, W, H)
    cot = cotangents(W, H, np.float64)
    numba.set_num_threads(threads)
    render_bwd(render_fwd(**scene)[1], **cot)
    ref_fwd, _ = _timeit(lambda: ref.render_fwd(**scene), max(1, reps // 2))
    ref_both, _ = _timeit(lambda: ref.render_bwd(ref.render_fwd(**scene)[1], **cot), max(1, reps // 2))
    fast_fwd, _ = _timeit(lambda: render_fwd(**scene), reps)
    fast_both, _ = _timeit(lambda: render_bwd(render_fwd(**scene)[1], **cot), reps)
    return dict(scene="r", n=n, width=W, height=H, threads=threads, ref_fwd_ms=1e3 * ref_fwd,
                ref_fwd_bwd_ms=1e3 * ref_both, fast_fwd_ms=1e3 * fast_fwd, fast_fwd_bwd_ms=1e3 * fast_both,
                ratio_fwd=ref_fwd / fast_fwd, ratio_fwd_bwd=ref_both / fast_both)


def markdown(results):
    lines = []
    lines.append(f"Load average at the end (1, 5, 15 min): {results['load_average_1_5_15min']} "
                 f"on {results['machine']['cpu_count']} cores (shared machine: 2-thread timings suffer "
                 f"when another process holds a core).")
    lines.append("")
    if "compile" in results:
        c = results["compile"]
        lines += ["### First call in a fresh process (tiny scene: N = 50, 40 x 30)", "",
                  "| cache | import (s) | float64 fwd (s) | float64 bwd (s) | float32 fwd (s) | float32 bwd (s) |",
                  "|---|---|---|---|---|---|"]
        for label in ("empty (JIT compile)", "filled (cache load)"):
            r = c[label]
            lines.append(f"| {label} | {r['import_s']:.2f} | {r['float64']['fwd_s']:.2f} | "
                         f"{r['float64']['bwd_s']:.2f} | {r['float32']['fwd_s']:.2f} | {r['float32']['bwd_s']:.2f} |")
        lines.append("")
    lines += ["### Warm timings (median of reps; min in parentheses)", "",
              "| scene | N | image | dtype | threads | fwd (ms) | fwd+bwd (ms) | evals/s (fwd) | evaluations | "
              "tile isects | saved (MB) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results["fast"]:
        lines.append(f"| {r['scene']} | {r['n']} | {r['width']}x{r['height']} | {r['dtype']} | {r['threads']} | "
                     f"{r['fwd_ms']:.1f} ({r['fwd_min_ms']:.1f}) | {r['fwd_bwd_ms']:.1f} ({r['fwd_bwd_min_ms']:.1f}) | "
                     f"{r['evals_per_s'] / 1e6:.0f} M | {r['evaluations']:,} | {r['intersections']:,} | "
                     f"{r['saved_mb']:.1f} |")
    lines += ["", "### NumPy reference vs fast (same run, reduced scene r; float64)", "",
              "| scene | N | image | threads | ref fwd (ms) | fast fwd (ms) | ratio | ref fwd+bwd (ms) | "
              "fast fwd+bwd (ms) | ratio |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results["reference"]:
        lines.append(f"| {r['scene']} | {r['n']} | {r['width']}x{r['height']} | {r['threads']} | {r['ref_fwd_ms']:.0f} | "
                     f"{r['fast_fwd_ms']:.2f} | {r['ratio_fwd']:.0f}x | {r['ref_fwd_bwd_ms']:.0f} | "
                     f"{r['fast_fwd_bwd_ms']:.2f} | {r['ratio_fwd_bwd']:.0f}x |")
    lines += ["", "### float32 and mixed vs float64 (|x - x64| / max |x64|: max, and 99.9 % quantile)", "",
              "| scene | precision | image max | image q99.9 | worst gradient max | worst gradient q99.9 | "
              "pixels whose last contributor differs |", "|---|---|---|---|---|---|---|"]
    for key, e in results["float32_error"].items():
        name, precision = key.split(":") if ":" in key else (key, "float32")
        lines.append(f"| {name} | {precision} | {e['image']:.1e} | {e['image_q999']:.1e} | {e['grads_max']:.1e} | "
                     f"{e['grads_q999']:.1e} | {e['pixels_last_contributor_differs']} |")
    lines += ["", "### Targets (float64, 2 threads; met = median within target)", "",
              "| scene | measure | target (ms) | median (ms) | min (ms) | met |", "|---|---|---|---|---|---|"]
    for t in results["targets"]:
        lines.append(f"| {t['scene']} | {t['measure']} | {t['target_ms']:.0f} | {t['measured_ms']:.1f} | "
                     f"{t['min_ms']:.1f} | {'yes' if t['met'] else 'NO'} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="bench_render.json", help="JSON output path")
    parser.add_argument("--reps", type=int, default=5, help="repetitions per timing (scene b uses max(2, reps // 2))")
    parser.add_argument("--no-compile", action="store_true", help="skip the fresh-process compile timings")
    args = parser.parse_args(argv)

    import numba

    results = {"load_average_start": list(os.getloadavg()), "machine": {"python": platform.python_version(), "numba": numba.__version__,
                           "numpy": np.__version__, "cpu_count": os.cpu_count(),
                           "numba_threading_layer_max_threads": numba.config.NUMBA_NUM_THREADS},
               "fastmath": False, "scenes": {k: dict(n=v[0], width=v[1], height=v[2]) for k, v in SCENES.items()}}
    if not args.no_compile:
        with tempfile.TemporaryDirectory(prefix="bench_numba_cache_") as cache:
            compile_run = first_call_times(cache)
            cached_run = first_call_times(cache)
        results["compile"] = {"empty (JIT compile)": compile_run, "filled (cache load)": cached_run}

    max_threads = min(2, numba.config.NUMBA_NUM_THREADS)
    results["fast"] = []
    for name in ("a", "c", "b"):
        reps = args.reps if name == "a" else max(2, args.reps // 2)
        for precision, _, _ in PRECISIONS:
            for threads in sorted({1, max_threads}):
                results["fast"].append(bench_fast(name, precision, threads, reps))
    results["reference"] = [bench_reference(max_threads, args.reps)]
    results["float32_error"] = {f"{name}:{precision}": float32_errors(name, precision)
                                for name in ("a", "c", "b") for precision in ("float32", "mixed")}
    results["targets"] = []
    for (name, measure), target in TARGETS_MS.items():
        row = next(r for r in results["fast"]
                   if r["scene"] == name and r["dtype"] == "float64" and r["threads"] == max_threads)
        measured = row["fwd_ms"] if measure == "fwd" else row["fwd_bwd_ms"]
        best = row["fwd_min_ms"] if measure == "fwd" else row["fwd_bwd_min_ms"]
        results["targets"].append(dict(scene=name, measure=measure, target_ms=target, measured_ms=measured,
                                       min_ms=best, met=measured <= target))
    results["load_average_1_5_15min"] = list(os.getloadavg())
    table = markdown(results)
    print(table)
    with open(args.out, "w") as fh:
        json.dump(results, fh, indent=2)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
