"""Temporal and spatial smoothness of the deformation, L_ts (docs/method.md §6, Eq. 11-13).

The deformation of a dynamic Gaussian g is D(g, t) = b(t) @ coef_g for each deformed attribute
(means, quaternions, colours; ``scene/deformation.py``, whose basis ``deform_basis`` is used
here), so both terms are linear in the coefficients before the norm:

    l_time    = mean over g of  sum_attr n( (b(t) - b(t + eps)) @ coef_g )
    l_spatial = mean over g of  mean over its k neighbours j of  sum_attr n( b(t) @ (coef_g - coef_j) )
    L_ts      = w_time l_time + w_spatial l_spatial

with the smooth norm n(u) = sqrt(|u|^2 + TS_NORM_EPS^2) - TS_NORM_EPS in place of |u| (no
gradient at u = 0 otherwise; subtracting the epsilon makes n(0) = 0). The norm is taken per
attribute and the attributes summed, so the positions (world units), the raw quaternion residual
and the colours each count on their own scale instead of being mixed into one vector.

Neighbours (``knn``) are the k nearest by base position (``dynamic.means``), self excluded,
k = min(K, N - 1): with fewer dynamic Gaussians than K + 1 every other one is a neighbour; with
one (or none) there is no spatial term (0). Coincident Gaussians are neighbours at distance 0;
their D difference is 0 where their coefficients agree, where n and its gradient are 0.

The training step evaluates both at the frame's mid-exposure time t = model.times[k] (the frame
the step renders), not at the blur model's sub-frame times.

Gradients go to every coefficient block; ``spatial_bwd`` scatters each pair's gradient to both
Gaussians with ``np.add.at`` (a fixed order, so the result does not depend on anything but the
inputs). ``d2gs_np.reference.smoothness`` is the per-Gaussian loop version of both terms and of
``knn`` (brute-force distances) that the tests compare against.
"""
from __future__ import annotations

import numbers

import numpy as np
from scipy.spatial import cKDTree

from d2gs_np.base.checks import check_int, check_number
from d2gs_np.constants import TS_NORM_EPS
from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.deformation import deform_basis

__all__ = ["smooth_norm", "knn", "check_neighbours", "time_fwd", "time_bwd", "spatial_fwd", "spatial_bwd"]


def smooth_norm(u):
    """n(u) = sqrt(|u|^2 + eps^2) - eps over the last axis, and dn/du = u / sqrt(|u|^2 + eps^2)."""
    s = np.sqrt(np.sum(u * u, axis=-1) + TS_NORM_EPS ** 2)
    return s - TS_NORM_EPS, u / s[..., None]


def knn(points, k: int):
    """Indices (N, min(k, N - 1)) int64 of each point's nearest other points, nearest first.

    points: (N, 3) float array (base positions). Ties (coincident points) may come in any order,
    but a point is never its own neighbour.
    """
    if not isinstance(points, np.ndarray) or points.ndim != 2 or points.shape[1] != 3:
        got = points.shape if isinstance(points, np.ndarray) else type(points).__name__
        raise ValueError(f"points must be an (N, 3) array; got {got}")
    check_int(k, "k", 1)
    if not np.all(np.isfinite(points)):
        raise ValueError("points contains NaN or inf; every position must be finite")
    n = points.shape[0]
    kk = min(int(k), n - 1)
    if kk <= 0:
        return np.zeros((n, 0), dtype=np.int64)
    _, idx = cKDTree(points).query(points, k=kk + 1)
    idx = np.asarray(idx, dtype=np.int64).reshape(n, kk + 1)
    other = idx != np.arange(n)[:, None]
    # among coincident points the query may not return the point itself first (or at all):
    # where it is absent, drop the farthest candidate instead
    other[other.all(axis=1), -1] = False
    return idx[other].reshape(n, kk)


def _check(coefs, t, config):
    if not isinstance(config, DeformConfig):
        raise TypeError(f"config must be a DeformConfig; got {type(config).__name__}")
    if not isinstance(coefs, (tuple, list)) or not coefs:
        raise TypeError("coefs must be a non-empty tuple of (N, K, D) coefficient blocks")
    n, K = None, config.num_coefs
    for i, c in enumerate(coefs):
        if not isinstance(c, np.ndarray) or c.dtype not in (np.float64, np.float32):
            raise TypeError(f"coefs[{i}] must be a float64 or float32 array")
        if c.ndim != 3 or c.shape[1] != K or (n is not None and c.shape[0] != n):
            raise ValueError(f"coefs[{i}] must have shape (N, {K}, D) with one N for all blocks; got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError(f"coefs[{i}] contains NaN or inf")
        n = c.shape[0]
    check_number(t, "t", hint="a time")
    return n


def time_fwd(coefs, t, eps, config: DeformConfig):
    """l_time at time t with offset eps (module docstring).

    coefs: tuple of (N, K, D_i) coefficient blocks (e.g. deform_means, deform_quats, deform_colors).
    Returns (value, a Python float; saved). N = 0 gives 0.
    """
    n = _check(coefs, t, config)
    if isinstance(eps, bool) or not isinstance(eps, numbers.Real) or not (np.isfinite(eps) and eps != 0.0):
        raise ValueError(f"eps must be a finite non-zero time offset; got {eps!r}")
    return _time_fwd(coefs, float(t), float(eps), config, n)


def _time_fwd(coefs, t, eps, config, n):
    db = deform_basis(t, config)[0] - deform_basis(t + eps, config)[0]  # (K,)
    value, dirs = 0.0, []
    for c in coefs:
        u = np.einsum("k,nkd->nd", db, c.astype(np.float64, copy=False))
        nrm, d = smooth_norm(u)
        value += float(nrm.sum())
        dirs.append(d)
    value = value / n if n else 0.0
    return value, dict(db=db, dirs=dirs, n=n, dtypes=[c.dtype for c in coefs])


def time_bwd(saved, v_value=1.0):
    """Gradient of ``v_value * time_fwd(...)[0]``: a tuple of (N, K, D_i) arrays, one per block."""
    n, db = saved["n"], saved["db"]
    scale = v_value / n if n else 0.0
    return tuple((scale * db[None, :, None] * d[:, None, :]).astype(dt, copy=False)
                 for d, dt in zip(saved["dirs"], saved["dtypes"]))


def spatial_fwd(coefs, neighbours, t, config: DeformConfig):
    """l_spatial at time t over the neighbour lists (module docstring).

    coefs: tuple of (N, K, D_i) coefficient blocks; neighbours: (N, k) int indices into the N
    Gaussians (``knn``; k = 0 gives 0).
    Returns (value, a Python float; saved).
    """
    n = _check(coefs, t, config)
    check_neighbours(neighbours, n)
    return _spatial_fwd(coefs, neighbours, float(t), config, n)


def check_neighbours(neighbours, n):
    """Refuse neighbour lists that are not an (n, k) integer array of indices into n Gaussians."""
    if not isinstance(neighbours, np.ndarray) or neighbours.ndim != 2 or neighbours.shape[0] != n:
        got = neighbours.shape if isinstance(neighbours, np.ndarray) else type(neighbours).__name__
        raise ValueError(f"neighbours must be an ({n}, k) index array for the {n} Gaussians; got {got}; "
                         "rebuild it with knn after the number of Gaussians changed")
    if neighbours.size and (not np.issubdtype(neighbours.dtype, np.integer) or neighbours.min() < 0
                            or neighbours.max() >= n):
        raise ValueError(f"neighbours must hold integer indices in [0, {n}); rebuild it with knn")


def _spatial_fwd(coefs, neighbours, t, config, n):
    b = deform_basis(t, config)[0]
    k = neighbours.shape[1]
    value, dirs = 0.0, []
    if n and k:
        for c in coefs:
            Dc = np.einsum("k,nkd->nd", b, c.astype(np.float64, copy=False))  # (N, D): D_g(t)
            u = Dc[:, None, :] - Dc[neighbours]  # (N, k, D)
            nrm, d = smooth_norm(u)
            value += float(nrm.sum())
            dirs.append(d)
        value /= n * k
    return value, dict(b=b, dirs=dirs, neighbours=neighbours, n=n, k=k,
                       shapes=[c.shape for c in coefs], dtypes=[c.dtype for c in coefs])


def spatial_bwd(saved, v_value=1.0):
    """Gradient of ``v_value * spatial_fwd(...)[0]``: a tuple of (N, K, D_i) arrays, one per block."""
    n, k, b, nb = saved["n"], saved["k"], saved["b"], saved["neighbours"]
    out = []
    for i, (shape, dt) in enumerate(zip(saved["shapes"], saved["dtypes"])):
        if not (n and k):
            out.append(np.zeros(shape, dtype=dt))
            continue
        d = (v_value / (n * k)) * saved["dirs"][i]  # (N, k, D): d value / d u
        v_D = d.sum(axis=1)  # + for g itself
        np.add.at(v_D, nb.ravel(), -d.reshape(-1, d.shape[-1]))  # - for each neighbour j
        out.append((b[None, :, None] * v_D[:, None, :]).astype(dt, copy=False))
    return tuple(out)
