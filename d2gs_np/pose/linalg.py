"""Small dense linear algebra shared by the solvers (``pose/gauss_newton.py``, ``pose/bundle.py``).

Their normal equations are small (6 x frames, or 6 x cameras + 1) and solved many times per call.
A plain single-threaded Numba factorisation is used on purpose: on a 2-core machine whose cores
are shared, a threaded LAPACK call on these sizes cost hundreds of times more (docs/results.md §12).
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["cholesky_solve"]


@njit(cache=True)
def cholesky_solve(A, b):
    """x with A x = b for a symmetric positive definite A (n, n), and True; (zeros, False) as
    soon as a pivot is not positive and finite (A not positive definite, or non-finite)."""
    n = A.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0) or not np.isfinite(s):
            return np.zeros(n), False
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / L[j, j]
    y = np.zeros(n)
    for i in range(n):
        t = b[i]
        for k in range(i):
            t -= L[i, k] * y[k]
        y[i] = t / L[i, i]
    x = np.zeros(n)
    for i in range(n - 1, -1, -1):
        t = y[i]
        for k in range(i + 1, n):
            t -= L[k, i] * x[k]
        x[i] = t / L[i, i]
    return x, True
