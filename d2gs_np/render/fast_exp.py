"""exp(-s) in plain arithmetic, for the rasteriser's vectorised loops (``exp_neg``).

``math.exp`` is a scalar library call, so a loop that calls it stays scalar; ``exp_neg`` is a range
reduction and a polynomial that LLVM vectorises (the method and its error bound: ``exp_consts``).
A kernel unpacks the constants of its dtype once, outside its loops (``unpack_exp_consts``).

Numba caches a kernel under its own file's time stamp only: the kernels of rasterize.py that call
``exp_neg`` are not recompiled when only this file changes. After editing it, clear the cache
(NUMBA_CACHE_DIR).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from d2gs_np import constants as C


@njit(cache=True, fastmath={"contract"})  # Horner steps as fused multiply-adds (deterministic)
def exp_neg(s, ec):
    """exp(-s) for s in [0, EXP_ARG_MAX] (clamped into it), within 3 ulp; plain arithmetic so that
    a loop calling it vectorises (``math.exp`` is a scalar library call). ``ec``: ``exp_consts``
    unpacked into a tuple (see there for the method and the error bound)."""
    (inv_ln2, ln2_hi, ln2_lo, s_max, half, one, zero, p1, p2, p4, p8, eight, four, two,
     c2, c3, c4, c5, c6, c7, c8, c9, c10, c11, c12, c13) = ec
    s = s_max if s > s_max else s
    s = zero if s < zero else s
    kf = np.floor(s * inv_ln2 + half)  # k = round(s / ln 2), 0 <= k <= 12
    r = (kf * ln2_hi - s) + kf * ln2_lo  # k ln2 - s in [-ln2/2, ln2/2]; k ln2_hi is exact
    p = c13
    p = p * r + c12
    p = p * r + c11
    p = p * r + c10
    p = p * r + c9
    p = p * r + c8
    p = p * r + c7
    p = p * r + c6
    p = p * r + c5
    p = p * r + c4
    p = p * r + c3
    p = p * r + c2
    p = p * r + one
    p = p * r + one  # exp(r)
    scale = one  # 2^-k from the bits of k (exact powers of two)
    if kf >= eight:
        kf = kf - eight
        scale = p8
    if kf >= four:
        kf = kf - four
        scale = scale * p4
    if kf >= two:
        kf = kf - two
        scale = scale * p2
    if kf >= one:
        scale = scale * p1
    return p * scale


def exp_consts(dtype):
    """Constants of ``exp_neg`` in ``dtype``: exp(-s) = 2^-k exp(r) with k = round(s / ln 2) and
    r = k ln 2 - s in [-ln2/2, ln2/2] (Cody-Waite: ln 2 = ln2_hi + ln2_lo with ln2_hi holding 12
    trailing zero bits, so k ln2_hi is exact for k <= 4096), exp(r) by its Taylor polynomial of
    degree 13 (remainder <= (ln2/2)^14 / 14! < 5e-18, far below float64 rounding; measured within
    3 ulp of numpy.exp in float64 and 1.1 ulp in float32 over [0, EXP_ARG_MAX], checked by
    tests/render/test_fast_exp.py). Not bitwise ``math.exp``: results differ from a libm exp
    in the last bits (see docs/conventions.md §6)."""
    ln2 = math.log(2.0)
    ln2_hi = 0.693145751953125
    vals = [1.0 / ln2, ln2_hi, ln2 - ln2_hi, C.EXP_ARG_MAX, 0.5, 1.0, 0.0, 0.5, 0.25, 1.0 / 16.0, 1.0 / 256.0,
            8.0, 4.0, 2.0] + [1.0 / math.factorial(n) for n in range(2, 14)]
    return np.array(vals, dtype=dtype)


@njit(cache=True)
def unpack_exp_consts(e):
    """The (26,) array of ``exp_consts`` as a tuple (loop invariants LLVM keeps in registers)."""
    return (e[0], e[1], e[2], e[3], e[4], e[5], e[6], e[7], e[8], e[9], e[10], e[11], e[12], e[13], e[14], e[15],
            e[16], e[17], e[18], e[19], e[20], e[21], e[22], e[23], e[24], e[25])
