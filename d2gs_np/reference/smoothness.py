"""Reference L_ts terms (docs/method.md §6): per-Gaussian loops and brute-force neighbours, float64.

Same definitions as ``d2gs_np.losses.smoothness`` (smooth norm sqrt(|u|^2 + eps^2) - eps per
attribute, summed over attributes; neighbours by base position, self excluded), written from the
equations with the residual D(t) of ``reference.deformation``. It does not import the fast path.
"""
from __future__ import annotations

import math

import numpy as np

from d2gs_np.constants import TS_NORM_EPS
from d2gs_np.reference.deformation import _residual


def _n(u):
    return math.sqrt(float(np.dot(u, u)) + TS_NORM_EPS ** 2) - TS_NORM_EPS


def knn(points, k):
    """(N, min(k, N - 1)) indices of each point's nearest other points, by a full distance matrix."""
    n = len(points)
    kk = min(k, n - 1)
    out = np.zeros((n, max(kk, 0)), dtype=np.int64)
    for g in range(n):
        d = [(float(np.sum((points[g] - points[j]) ** 2)), j) for j in range(n) if j != g]
        d.sort()
        out[g] = [j for _, j in d[:kk]]
    return out


def time_term(coefs, t, eps, degree, order, omega):
    """l_time: mean over g of sum over blocks of n(D_g(t) - D_g(t + eps))."""
    n = coefs[0].shape[0]
    if n == 0:
        return 0.0
    total = 0.0
    for g in range(n):
        for c in coefs:
            total += _n(_residual(c[g], t, degree, order, omega) - _residual(c[g], t + eps, degree, order, omega))
    return total / n


def spatial_term(coefs, neighbours, t, degree, order, omega):
    """l_spatial: mean over g of the mean over its neighbours j of sum over blocks of n(D_g(t) - D_j(t))."""
    n, k = neighbours.shape
    if n == 0 or k == 0:
        return 0.0
    total = 0.0
    for g in range(n):
        acc = 0.0
        for j in neighbours[g]:
            for c in coefs:
                acc += _n(_residual(c[g], t, degree, order, omega) - _residual(c[j], t, degree, order, omega))
        total += acc / k
    return total / n
