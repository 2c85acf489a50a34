"""Time of L_freq's forward + backward: the fast path against the full-spectrum NumPy reference.

Per image size: the reference (``d2gs_np.reference.frequency``: two complex ``fft2``, NumPy
elementwise, ``ifft2``), the fast path (``d2gs_np.losses.frequency``: real-input half spectrum,
one Numba pass over the bins, ``irfft2``) computing the target's spectrum too, and the fast path
given the target's spectrum (what training does from a frame's second visit on: the ``Frequency``
term keeps it per frame). Median of ``--repeats`` calls each, after one untimed call (JIT warm-up
is reported apart), and each as a ratio to the reference measured in the same run. It also
checks that the three agree (value and gradient, relative to the reference).

    NUMBA_NUM_THREADS=1 python examples/bench_freq.py [--sizes 135x240 270x480] [--repeats 30]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
import timeit

import numpy as np


def bench(height, width, repeats=30, seed=0):
    """Dict of the three timings (s), their ratios to the reference and the agreement."""
    from d2gs_np.losses import frequency as fast
    from d2gs_np.reference import frequency as ref

    rng = np.random.default_rng(seed)
    render = rng.uniform(0.2, 0.8, (height, width, 3))
    target = rng.uniform(0.2, 0.8, (height, width, 3))
    t0 = time.perf_counter()
    fast.frequency_bwd(fast.frequency_fwd(render, target)[1])  # JIT warm-up (or cache load)
    warm = time.perf_counter() - t0
    spectrum = fast.target_spectrum(target)
    runs = {
        "reference": lambda: ref.frequency_bwd(ref.frequency_fwd(render, target)[1]),
        "fast": lambda: fast.frequency_bwd(fast.frequency_fwd(render, target)[1]),
        "fast_cached_target": lambda: fast.frequency_bwd(fast.frequency_fwd(render, target, target_fft=spectrum)[1]),
    }
    for fn in runs.values():
        fn()
    out = {name: statistics.median(timeit.repeat(fn, number=1, repeat=repeats)) for name, fn in runs.items()}
    v_ref, s_ref = ref.frequency_fwd(render, target)
    v_fast, s_fast = fast.frequency_fwd(render, target, target_fft=spectrum)
    g_ref, g_fast = ref.frequency_bwd(s_ref), fast.frequency_bwd(s_fast)
    return dict(size=f"{height}x{width}", warm_up_s=warm, **{f"{k}_ms": 1e3 * v for k, v in out.items()},
                **{f"{k}_ratio": v / out["reference"] for k, v in out.items() if k != "reference"},
                value_rel_err=abs(v_fast - v_ref) / abs(v_ref),
                grad_rel_err=float(np.abs(g_fast - g_ref).max() / np.abs(g_ref).max()))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["135x240", "270x480"], help="HxW image sizes")
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args(argv)
    print("| size | reference ms | fast ms (ratio) | fast, target cached ms (ratio) | value / gradient rel. err. | "
          "first call s |")
    print("|---|---|---|---|---|---|")
    for s in args.sizes:
        h, w = (int(x) for x in s.split("x"))
        r = bench(h, w, args.repeats)
        print(f"| {r['size']} | {r['reference_ms']:.2f} | {r['fast_ms']:.2f} ({r['fast_ratio']:.2f}) | "
              f"{r['fast_cached_target_ms']:.2f} ({r['fast_cached_target_ratio']:.2f}) | "
              f"{r['value_rel_err']:.1e} / {r['grad_rel_err']:.1e} | {r['warm_up_s']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
