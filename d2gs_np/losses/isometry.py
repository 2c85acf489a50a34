"""Isometry of the dynamic set over time, L_iso (docs/method.md §6): neighbouring dynamic
Gaussians keep their distance as they move, as the points of a rigid object do.

Dynamic 3D Gaussians (Luiten et al. 2024) hold each Gaussian's distance to its nearest
neighbours at every time to the distance at the first one. Here, at the step frame's time t and
a second time t' = t + eps (t - eps where t + eps > 1, so both stay in the clip):

    mu_g(s)  = A0_g + b(s) @ C_g                    (the deformed mean, scene/deformation.py)
    d_gj(s)  = sqrt(|mu_g(s) - mu_j(s)|^2 + floor^2)
    r_gj     = 2 (d_gj(t) - d_gj(t')) / (d_gj(t) + d_gj(t'))
    L_iso    = mean over g and its k neighbours j of r_gj^2

r is the pair's relative change of distance: 0 for every rigid motion of the set (each
object's own rotation and translation), and unchanged when the scene's units change with the
floor. ``floor`` (a length > 0) keeps coincident pairs finite: there d = floor at both times,
r = 0 and its gradient 0. The neighbours are those of L_ts (``losses.smoothness.knn`` on the
base positions A0), so a pair is two Gaussians near each other in the canonical frame.

Only the positions enter (base means and their deformation coefficients); rotations and
colours are free. The gradient scatters each pair's share to both Gaussians with ``np.bincount``
(a fixed order).
"""
from __future__ import annotations

import numpy as np

from d2gs_np.base.checks import check_number
from d2gs_np.losses.smoothness import check_neighbours
from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.deformation import deform_basis

__all__ = ["FLOOR_SHARE", "second_time", "pair_floor", "isometry_fwd", "isometry_bwd"]

FLOOR_SHARE = 0.01  # the training term's floor: this share of the median neighbour distance


def pair_floor(base_means, neighbours):
    """The floor the training term uses: FLOOR_SHARE x the median distance between the base
    positions of the neighbour pairs (scales with the scene's units); 1e-12 where there is none
    or it is 0."""
    if neighbours.size == 0:
        return 1e-12
    A0 = np.asarray(base_means, dtype=np.float64)
    d = np.linalg.norm(A0[:, None, :] - A0[neighbours], axis=-1)
    return max(FLOOR_SHARE * float(np.median(d)), 1e-12)


def second_time(t, eps):
    """t' of the pair of times: t + eps, or t - eps where t + eps would leave the clip (> 1)."""
    return t + eps if t + eps <= 1.0 else t - eps


def isometry_fwd(base_means, coef_means, neighbours, t, eps, floor, config: DeformConfig):
    """L_iso (module docstring) and what its backward needs.

    base_means (N, 3), coef_means (N, K, 3): the dynamic set's ``dynamic.means`` and
    ``dynamic.deform_means``; neighbours (N, k) int indices into the N Gaussians (k = 0 or
    N <= 1 gives 0); t: the step's time; eps > 0: the offset of the second time; floor > 0: a
    length. Returns (value, a Python float; saved).
    """
    if not isinstance(config, DeformConfig):
        raise TypeError(f"config must be a DeformConfig; got {type(config).__name__}")
    for name, x, nd in (("base_means", base_means, 2), ("coef_means", coef_means, 3)):
        if not isinstance(x, np.ndarray) or x.dtype not in (np.float64, np.float32) or x.ndim != nd:
            raise TypeError(f"{name} must be a float64 or float32 array with {nd} axes")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{name} contains NaN or inf; every entry must be finite")
    n = base_means.shape[0]
    if base_means.shape != (n, 3) or coef_means.shape != (n, config.num_coefs, 3):
        raise ValueError(f"base_means must be (N, 3) and coef_means (N, {config.num_coefs}, 3) for one N; got "
                         f"{base_means.shape} and {coef_means.shape}")
    check_neighbours(neighbours, n)
    check_number(t, "t", hint="a time")
    check_number(eps, "eps", 0.0, lo_open=True, hint="a time offset")
    check_number(floor, "floor", 0.0, lo_open=True, hint="a length in the scene's units")
    return _isometry_fwd(base_means, coef_means, neighbours, float(t), float(eps), float(floor), config)


def _isometry_fwd(base_means, coef_means, neighbours, t, eps, floor, config):
    """``isometry_fwd`` without validating its arguments (the training step's fast path)."""
    n, k = neighbours.shape
    t2 = second_time(t, eps)
    saved = dict(n=n, k=k, neighbours=neighbours, dtype=base_means.dtype, K=coef_means.shape[1])
    if n == 0 or k == 0:
        return 0.0, saved
    A0 = base_means.astype(np.float64, copy=False)
    C = coef_means.astype(np.float64, copy=False)
    bs = [deform_basis(s, config)[0] for s in (t, t2)]
    us, ds = [], []
    for b in bs:
        mu = A0 + np.einsum("k,nkd->nd", b, C)
        u = mu[:, None, :] - mu[neighbours]  # (N, k, 3)
        us.append(u)
        ds.append(np.sqrt(np.sum(u * u, axis=-1) + floor * floor))
    d1, d2 = ds
    s = d1 + d2
    r = 2.0 * (d1 - d2) / s
    saved.update(bs=bs, us=us, ds=ds, r=r, s=s)
    return float(np.mean(r * r)), saved


def isometry_bwd(saved, v_value=1.0):
    """Gradient of ``v_value * isometry_fwd(...)[0]``: (v_base_means (N, 3), v_coef_means (N, K, 3)),
    of the inputs' dtype."""
    n, k, nb, dt = saved["n"], saved["k"], saved["neighbours"], saved["dtype"]
    v_A0 = np.zeros((n, 3))
    v_C = np.zeros((n, saved["K"], 3))
    if n and k:
        r, s = saved["r"], saved["s"]
        d1, d2 = saved["ds"]
        v_r = v_value * 2.0 * r / (n * k)
        # r = 2 (d1 - d2) / (d1 + d2): dr/dd1 = 4 d2 / s^2, dr/dd2 = -4 d1 / s^2
        v_ds = (v_r * 4.0 * d2 / (s * s), -v_r * 4.0 * d1 / (s * s))
        for b, u, d, v_d in zip(saved["bs"], saved["us"], saved["ds"], v_ds):
            v_u = (v_d / d)[..., None] * u  # (N, k, 3)
            v_mu = v_u.sum(axis=1)  # + for g itself, - for each neighbour j (bincount: a fixed order)
            flat = v_u.reshape(-1, 3)
            v_mu -= np.stack([np.bincount(nb.ravel(), weights=flat[:, c], minlength=n) for c in range(3)], axis=1)
            v_A0 += v_mu
            v_C += b[None, :, None] * v_mu[:, None, :]
    return v_A0.astype(dt, copy=False), v_C.astype(dt, copy=False)
