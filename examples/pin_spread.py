"""How far the pinned fixed-seed run (tests/train/test_split_equivalence.py) moves with the machine.

The run's last bits follow the CPU (NumPy's SIMD kernels, LLVM's vector width for the Numba
kernels), the thread count and the rasteriser's precision, and 16 steps of densification and
pruning amplify one-ulp differences. This script runs the pinned config in fresh processes under
several of them and prints each run's held-out PSNR and ATE against the first, so the test's
cross-machine tolerances can be set from a measured spread. Other CPU kinds are emulated on this
one (``emulate``): ``NUMBA_CPU_NAME`` makes LLVM generate the Numba kernels for that CPU,
``OPENBLAS_CORETYPE`` picks OpenBLAS's kernels for it, and ``NPY_DISABLE_CPU_FEATURES`` /
``OPENCV_CPU_DISABLE`` stop NumPy and OpenCV dispatching to the instruction sets it lacks.

    python examples/pin_spread.py [--out spread.json]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PINNED = ROOT / "tests" / "train" / "test_split_equivalence.py"
AVX512 = "AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR"
CV_AVX512 = "AVX512_COMMON,AVX512_SKX,AVX512_KNL,AVX512_KNM,AVX512_CNL,AVX512_CLX,AVX512_ICL"


def emulate(numba_cpu: str, blas_core: str, npy_off: str, cv_off: str, threads: int) -> dict:
    """Environment that makes this machine compute like another CPU kind: LLVM's target for the
    Numba kernels, OpenBLAS's kernel family, and the instruction sets NumPy and OpenCV may dispatch to."""
    return {"NUMBA_NUM_THREADS": str(threads), "NUMBA_CPU_NAME": numba_cpu, "OPENBLAS_CORETYPE": blas_core,
            "NPY_DISABLE_CPU_FEATURES": npy_off, "OPENCV_CPU_DISABLE": cv_off}


# name -> (environment, extra arguments)
VARIANTS = {
    "host, 2 threads": ({"NUMBA_NUM_THREADS": "2"}, []),
    "host, 1 thread": ({"NUMBA_NUM_THREADS": "1"}, []),
    "AVX2 (Haswell), 2 threads": (emulate("haswell", "Haswell", AVX512, CV_AVX512, 2), []),
    "AVX2 (Haswell), 1 thread": (emulate("haswell", "Haswell", AVX512, CV_AVX512, 1), []),
    "AVX2 (Zen), 2 threads": (emulate("znver2", "Zen", AVX512, CV_AVX512, 2), []),
    "SSE4 (Nehalem), 2 threads": (emulate("nehalem", "Nehalem", AVX512 + " AVX AVX2 FMA3 F16C AVX512_SKX",
                                          CV_AVX512 + ",AVX,AVX2,FP16,FMA3", 2), []),
    "host, 2 threads, float64 raster": ({"NUMBA_NUM_THREADS": "2"}, ["--raster-float64"]),
    "AVX2 (Haswell), 2 threads, float64 raster": (emulate("haswell", "Haswell", AVX512, CV_AVX512, 2),
                                                  ["--raster-float64"]),
}


def run_variant(env_extra: dict, args: list, cache_root: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_", "NPY_", "OPENBLAS_", "OPENCV_"))}
    # one compile cache per code-generation target, so no variant loads another's machine code
    env.update(env_extra, NUMBA_CACHE_DIR=str(cache_root / env_extra.get("NUMBA_CPU_NAME", "host")),
               PYTHONPATH=os.pathsep.join([str(ROOT / "tests"), str(ROOT)]))
    out = subprocess.run([sys.executable, str(PINNED), *args], env=env, capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="write the table as JSON here")
    ap.add_argument("--cache", type=Path, default=None, help="Numba cache root (default: a temporary folder)")
    a = ap.parse_args(argv)
    cache = a.cache or Path(tempfile.mkdtemp(prefix="pin_spread_"))
    rows = {}
    for name, (env, args) in VARIANTS.items():
        rows[name] = run_variant(env, args, cache)
        print(f"{name:34s} dvs {rows[name]['dvs_psnr']:.6f} dB  ate {rows[name]['ate']:.9f}  "
              f"hash {rows[name]['params_sha256'][:12]}  machine {rows[name]['machine']}", flush=True)
    base = next(iter(rows.values()))
    print("\nagainst the first row:")
    for name, r in rows.items():
        print(f"{name:34s} |d dvs| {abs(r['dvs_psnr'] - base['dvs_psnr']):.2e} dB  "
              f"|d ate|/ate {abs(r['ate'] - base['ate']) / base['ate']:.2e}")
    if a.out:
        a.out.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
