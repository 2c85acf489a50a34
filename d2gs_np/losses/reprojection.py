"""L_reproj as a loss on rendered depth (docs/method.md §5 residuals, §6 the term).

The pose solver (``pose/gauss_newton.py``) refines the cameras on the cycle residuals of matched
pixels; the same residuals, with the poses held, are a loss on the rendered depths, and through
them on the Gaussians (Eq. 10 enters the total with lambda_reproj). For a match ``p_a`` in frame a
and ``p_b`` in frame b, mid-exposure poses ``M_a``, ``M_b`` (cam_T_world), intrinsics ``K_a``,
``K_b`` and depths ``d_a = D_a(p_a)``, ``d_b = D_b(p_b)`` (camera z of the rendered expected
depth):

    X      = M_b M_a^-1 (d_a K_a^-1 (p_a, 1))          the lifted point in camera b
    r_pix  = pi(K_b X) - p_b                           2 rows, pixels
    r_dep  = beta (X_z - d_b) / d_b                     1 row
    cost   = sum over rows of  s^2/2 log(1 + (r / s)^2)  (Cauchy, scale s pixels; elementwise,
                                                          as the solver's IRLS and SciPy's
                                                          loss="cauchy", f_scale = s)

``cycle_fwd`` / ``cycle_bwd`` hold one direction (lift from a, compare in b) on plain arrays, with
the gradient on both depths; the poses and pixels are constants. A row is valid when both depths
are finite and > 0 and the lifted point lies in front of camera b (X_z > GN_MIN_DEPTH); an invalid
match contributes nothing (its residual is reported as NaN) and is counted. The depth maps are read
at the matched pixels by ``geometry.sampling.bilinear_fwd`` / ``bilinear_bwd``.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.constants import GN_MIN_DEPTH

__all__ = ["cycle_fwd", "cycle_bwd", "cauchy"]


def cauchy(r, scale):
    """Elementwise Cauchy cost s^2/2 log(1 + (r/s)^2) and its derivative r / (1 + (r/s)^2)."""
    q = (r / scale) ** 2
    return 0.5 * scale * scale * np.log1p(q), r / (1.0 + q)


def cycle_fwd(d_a, pts_a, K_a, M_a, d_b, pts_b, K_b, M_b, beta, scale):
    """Robust cycle cost of M matches lifted from frame a into frame b (module docstring).

    d_a, d_b: (M,) depths at the matches; pts_a, pts_b: (M, 2) pixels; K_a, K_b: (3, 3);
    M_a, M_b: (4, 4) cam_T_world; beta: weight of the relative depth row; scale: Cauchy scale.
    Returns (cost: float, the sum over valid matches, saved). saved["residuals"] (M, 3) holds
    the residuals (NaN rows: invalid), saved["valid"] (M,) bool.
    """
    d_a = np.asarray(d_a, dtype=np.float64)
    d_b = np.asarray(d_b, dtype=np.float64)
    pts_a = np.asarray(pts_a, dtype=np.float64).reshape(-1, 2)
    pts_b = np.asarray(pts_b, dtype=np.float64).reshape(-1, 2)
    m = pts_a.shape[0]
    if d_a.shape != (m,) or d_b.shape != (m,) or pts_b.shape != (m, 2):
        raise ValueError(f"cycle_fwd: d_a, d_b must be ({m},) and pts_b ({m}, 2) like pts_a; got {d_a.shape}, "
                         f"{d_b.shape}, {pts_b.shape}")
    T = np.asarray(M_b, dtype=np.float64) @ np.linalg.inv(np.asarray(M_a, dtype=np.float64))
    R, t = T[:3, :3], T[:3, 3]
    rays = np.linalg.solve(np.asarray(K_a, dtype=np.float64), np.c_[pts_a, np.ones(m)].T).T  # (M, 3), z = 1
    a = rays @ R.T  # d X / d d_a
    with np.errstate(invalid="ignore", over="ignore"):
        X = d_a[:, None] * a + t
        ok = (np.isfinite(d_a) & (d_a > 0.0) & np.isfinite(d_b) & (d_b > 0.0)
              & np.isfinite(X).all(axis=1) & (X[:, 2] > GN_MIN_DEPTH))
    Kb = np.asarray(K_b, dtype=np.float64)
    fx, fy, cx, cy = Kb[0, 0], Kb[1, 1], Kb[0, 2], Kb[1, 2]
    r = np.full((m, 3), np.nan)
    Xv, z = X[ok], X[ok, 2]
    r[ok, 0] = fx * Xv[:, 0] / z + cx - pts_b[ok, 0]
    r[ok, 1] = fy * Xv[:, 1] / z + cy - pts_b[ok, 1]
    r[ok, 2] = beta * (z - d_b[ok]) / d_b[ok]
    rho, drho = cauchy(r[ok], scale)
    saved = {"residuals": r, "valid": ok, "drho": drho, "X": Xv, "a": a[ok], "d_b": d_b[ok], "fx": fx, "fy": fy,
             "beta": float(beta), "m": m}
    return float(rho.sum()), saved


def cycle_bwd(saved, v_cost=1.0):
    """Gradients (v_d_a, v_d_b), each (M,), of v_cost * cost; zero on invalid matches."""
    ok, g = saved["valid"], v_cost * saved["drho"]  # (V, 3) d cost / d r
    X, a, d_b, beta = saved["X"], saved["a"], saved["d_b"], saved["beta"]
    z = X[:, 2]
    # d r / d d_a through X = d_a a + t; d r / d d_b on the depth row only
    dux = saved["fx"] * (a[:, 0] * z - X[:, 0] * a[:, 2]) / z ** 2
    duy = saved["fy"] * (a[:, 1] * z - X[:, 1] * a[:, 2]) / z ** 2
    dz = beta * a[:, 2] / d_b
    v_d_a = np.zeros(saved["m"])
    v_d_b = np.zeros(saved["m"])
    v_d_a[ok] = g[:, 0] * dux + g[:, 1] * duy + g[:, 2] * dz
    v_d_b[ok] = g[:, 2] * (-beta * z / d_b ** 2)
    return v_d_a, v_d_b
