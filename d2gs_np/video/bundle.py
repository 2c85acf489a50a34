"""Bundle adjustment: reprojection residuals, their sparse Jacobian, a robust solver (docs/dataset_format.md §8).

Unknowns
- cameras (C, 6): per camera (phi, t) with cam_T_world = [[exp(phi), t], [0, 1]] (OpenCV axes,
  world -> camera); phi is a rotation vector (``so3_exp``).
- points (P, 3): world positions.
- focal f (optional, shared): fx = fy = f; the principal point is fixed.

Residual of observation o (camera c_o sees point p_o at pixel uv_o, our pixel convention):
    x = exp(phi_c) X_p + t_c,  r_o = (f x_0 / x_2 + cx - u_o,  f x_1 / x_2 + cy - v_o).
Derivatives: dx/dphi = -hat(R X) J_l(phi) (left Jacobian: exp(phi + d) = exp(J_l(phi) d) exp(phi)),
dx/dt = I, dx/dX = R, d(uv)/dx = f [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]], d(uv)/df = (x/z, y/z).

The same kind of least-squares problem as the endpoint refinement of the trajectory: a sum of
squared image-space errors over poses, solved here by SciPy's trust-region ``least_squares``
with the analytic sparse Jacobian and a robust loss (``soft_l1``), so that mismatches and
points on moving objects lose their pull (docs/dataset_format.md §8).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from d2gs_np.geometry.so3 import hat, left_jacobian, left_jacobian_inv, so3_exp, so3_log

__all__ = ["reprojection_fwd", "reprojection_bwd", "reprojection_jacobian", "pose_prior_fwd", "BundleProblem",
           "bundle_adjust", "poses_to_params", "params_to_poses"]


def poses_to_params(cam_T_world):
    """(C, 4, 4) rigid world-to-camera poses -> (C, 6) (phi, t)."""
    T = np.asarray(cam_T_world, dtype=np.float64)
    return np.concatenate([so3_log(T[:, :3, :3]), T[:, :3, 3]], axis=1)


def params_to_poses(cams):
    """(C, 6) (phi, t) -> (C, 4, 4) world-to-camera poses."""
    cams = np.asarray(cams, dtype=np.float64)
    T = np.tile(np.eye(4), (cams.shape[0], 1, 1))
    T[:, :3, :3] = so3_exp(cams[:, :3])
    T[:, :3, 3] = cams[:, 3:]
    return T


def _check_obs(cams, points, cam_idx, pt_idx, uv):
    cams = np.asarray(cams, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    if cams.ndim != 2 or cams.shape[1] != 6:
        raise ValueError(f"cams must have shape (C, 6) (rotation vector, translation); got {cams.shape}")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (P, 3); got {points.shape}")
    cam_idx = np.asarray(cam_idx)
    pt_idx = np.asarray(pt_idx)
    uv = np.asarray(uv, dtype=np.float64)
    if cam_idx.ndim != 1 or pt_idx.shape != cam_idx.shape or uv.shape != (cam_idx.shape[0], 2):
        raise ValueError(f"cam_idx (O,), pt_idx (O,) and uv (O, 2) must agree; got {cam_idx.shape}, "
                         f"{pt_idx.shape}, {uv.shape}")
    if not (np.issubdtype(cam_idx.dtype, np.integer) and np.issubdtype(pt_idx.dtype, np.integer)):
        raise TypeError("cam_idx and pt_idx must be integer arrays")
    if cam_idx.size and (cam_idx.min() < 0 or cam_idx.max() >= cams.shape[0]
                         or pt_idx.min() < 0 or pt_idx.max() >= points.shape[0]):
        raise ValueError("cam_idx / pt_idx index outside cams / points")
    return cams, points, cam_idx.astype(np.int64), pt_idx.astype(np.int64), uv


def reprojection_fwd(cams, points, focal, cx, cy, cam_idx, pt_idx, uv):
    """Residuals (O, 2) = projection - observation, in pixels; saved for the backward pass."""
    cams, points, cam_idx, pt_idx, uv = _check_obs(cams, points, cam_idx, pt_idx, uv)
    phi = cams[cam_idx, :3]
    R = so3_exp(phi)  # (O, 3, 3)
    RX = np.einsum("oij,oj->oi", R, points[pt_idx])
    x = RX + cams[cam_idx, 3:]
    z = x[:, 2]
    n = x[:, :2] / z[:, None]
    r = focal * n + np.array([cx, cy]) - uv
    saved = (phi, R, RX, x, n, float(focal), cam_idx, pt_idx, cams.shape[0], points.shape[0])
    return r, saved


def _blocks(saved):
    """Per-observation Jacobian blocks: d r / d cam (O, 2, 6), d r / d point (O, 2, 3), d r / d f (O, 2)."""
    phi, R, RX, x, n, f, _, _, _, _ = saved
    z = x[:, 2]
    O = x.shape[0]
    dproj = np.zeros((O, 2, 3))
    dproj[:, 0, 0] = f / z
    dproj[:, 1, 1] = f / z
    dproj[:, :, 2] = -f * n / z[:, None]
    dx_dphi = -hat(RX) @ left_jacobian(phi)
    d_cam = np.concatenate([dproj @ dx_dphi, dproj], axis=2)
    d_pt = dproj @ R
    return d_cam, d_pt, n


def reprojection_bwd(saved, v_residuals):
    """Cotangents of (cams (C, 6), points (P, 3), focal) from v_residuals (O, 2): J^T v."""
    _, _, _, _, _, _, cam_idx, pt_idx, C, P = saved
    d_cam, d_pt, n = _blocks(saved)
    v = np.asarray(v_residuals, dtype=np.float64)
    v_cams = np.zeros((C, 6))
    np.add.at(v_cams, cam_idx, np.einsum("oij,oi->oj", d_cam, v))
    v_points = np.zeros((P, 3))
    np.add.at(v_points, pt_idx, np.einsum("oij,oi->oj", d_pt, v))
    v_focal = float(np.sum(n * v))
    return v_cams, v_points, v_focal


def reprojection_jacobian(saved, free_cams, with_focal):
    """Sparse Jacobian (2 O, 6 |free cams| + 3 P [+ 1]) of the flattened residuals with respect to
    the parameter vector [cams[free_cams].ravel(), points.ravel(), (f)]."""
    _, _, _, _, _, _, cam_idx, pt_idx, C, P = saved
    d_cam, d_pt, n = _blocks(saved)
    O = cam_idx.shape[0]
    slot = np.full(C, -1, dtype=np.int64)
    slot[free_cams] = np.arange(len(free_cams))
    nc = 6 * len(free_cams)
    rows_o = np.arange(2 * O).reshape(O, 2)
    s = slot[cam_idx]
    has = s >= 0
    r_cam = np.repeat(rows_o[has][:, :, None], 6, axis=2)
    c_cam = np.broadcast_to((6 * s[has])[:, None, None] + np.arange(6), r_cam.shape)
    r_pt = np.repeat(rows_o[:, :, None], 3, axis=2)
    c_pt = np.broadcast_to((nc + 3 * pt_idx)[:, None, None] + np.arange(3), r_pt.shape)
    rows = [r_cam.ravel(), r_pt.ravel()]
    cols = [c_cam.ravel(), c_pt.ravel()]
    vals = [d_cam[has].ravel(), d_pt.ravel()]
    ncols = nc + 3 * P
    if with_focal:
        rows.append(np.arange(2 * O))
        cols.append(np.full(2 * O, ncols))
        vals.append(n.ravel())
        ncols += 1
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(2 * O, ncols))


def _check_prior_sigmas(sigma_t, sigma_r):
    if not (np.isfinite(sigma_t) and sigma_t > 0 and np.isfinite(sigma_r) and sigma_r > 0):
        raise ValueError(f"pose prior sigmas must be finite and > 0; got sigma_t={sigma_t}, sigma_r={sigma_r}")


def pose_prior_fwd(cams, prior_cams, sigma_t, sigma_r):
    """Residuals of a prior that holds cameras near given poses, and their Jacobian blocks.

    Per camera 6 rows: ``(c - c_g) / sigma_t`` on the camera centre c = -R^T t (world units) and
    ``log(R R_g^T) / sigma_r`` on the rotation (radians). Returns (r (C, 6), J (C, 6, 6)) with J the
    derivative of each camera's rows with respect to its (phi, t): with a perturbation
    exp(phi + d) = exp(J_l(phi) d) exp(phi), d log(R R_g^T) / d phi = J_l(log(R R_g^T))^-1 J_l(phi),
    dc / d phi = -R^T hat(t) J_l(phi), dc / dt = -R^T.
    """
    cams = np.asarray(cams, dtype=np.float64)
    prior = np.asarray(prior_cams, dtype=np.float64)
    if cams.ndim != 2 or cams.shape[1] != 6 or prior.shape != cams.shape:
        raise ValueError(f"cams and prior_cams must both have shape (C, 6); got {cams.shape}, {prior.shape}")
    _check_prior_sigmas(sigma_t, sigma_r)
    phi, t = cams[:, :3], cams[:, 3:]
    R, Rg = so3_exp(phi), so3_exp(prior[:, :3])
    Rt = np.transpose(R, (0, 2, 1))
    c = -np.einsum("cij,cj->ci", Rt, t)
    cg = -np.einsum("cji,cj->ci", Rg, prior[:, 3:])
    e = so3_log(R @ np.transpose(Rg, (0, 2, 1)))
    Jl = left_jacobian(phi)
    r = np.concatenate([(c - cg) / sigma_t, e / sigma_r], axis=1)
    J = np.zeros((cams.shape[0], 6, 6))
    J[:, :3, :3] = -(Rt @ hat(t) @ Jl) / sigma_t
    J[:, :3, 3:] = -Rt / sigma_t
    J[:, 3:, :3] = (left_jacobian_inv(e) @ Jl) / sigma_r
    return r, J


@dataclass
class BundleProblem:
    """Observations and the starting point of a bundle adjustment."""

    cams: np.ndarray  # (C, 6)
    points: np.ndarray  # (P, 3)
    focal: float
    cx: float
    cy: float
    cam_idx: np.ndarray  # (O,) int
    pt_idx: np.ndarray  # (O,) int
    uv: np.ndarray  # (O, 2) observed pixels, our convention


def bundle_adjust(problem: BundleProblem, fixed_cams=(0,), refine_focal=False, loss="soft_l1", f_scale=1.0,
                  max_nfev=50, tol=1e-8, prior=None):
    """Robust least squares over free cameras, all points and (optionally) the shared focal length.

    fixed_cams: cameras held at their start (the gauge: fix one camera; the overall scale stays
    free and is set by the start). loss, f_scale: SciPy robust loss and its scale in pixels.
    prior: optional (prior_cams (C, 6), sigma_t, sigma_r): ``pose_prior_fwd`` rows for every free
    camera (in units of sigma, under the same robust loss); with it no camera need be fixed (the
    prior holds the gauge, the scale included).
    Returns (cams (C, 6), points (P, 3), focal, info dict with cost, nfev, rms / median residual
    of the observations).
    """
    cams0 = np.asarray(problem.cams, dtype=np.float64).copy()
    pts0 = np.asarray(problem.points, dtype=np.float64)
    _check_obs(cams0, pts0, problem.cam_idx, problem.pt_idx, problem.uv)
    C, P = cams0.shape[0], pts0.shape[0]
    free = np.array([c for c in range(C) if c not in set(fixed_cams)], dtype=np.int64)
    nc = 6 * len(free)

    def unpack(x):
        cams = cams0.copy()
        cams[free] = x[:nc].reshape(-1, 6)
        pts = x[nc:nc + 3 * P].reshape(P, 3)
        f = x[-1] if refine_focal else problem.focal
        return cams, pts, f

    cache = {}

    if prior is not None:
        prior_cams, sigma_t, sigma_r = prior
        prior_cams = np.asarray(prior_cams, dtype=np.float64)
        if prior_cams.shape != cams0.shape:
            raise ValueError(f"prior cams must have the shape of the problem's cams {cams0.shape}; got "
                             f"{prior_cams.shape}")
        _check_prior_sigmas(sigma_t, sigma_r)
    O2 = 2 * len(problem.cam_idx)

    def fun(x):
        cams, pts, f = unpack(x)
        r, saved = reprojection_fwd(cams, pts, f, problem.cx, problem.cy, problem.cam_idx, problem.pt_idx, problem.uv)
        cache["key"], cache["saved"] = x.tobytes(), saved
        if prior is None:
            return r.ravel()
        rp, cache["prior_J"] = pose_prior_fwd(cams[free], prior_cams[free], sigma_t, sigma_r)
        return np.concatenate([r.ravel(), rp.ravel()])

    def jac(x):
        if cache.get("key") != x.tobytes():
            fun(x)
        J = reprojection_jacobian(cache["saved"], free, refine_focal)
        if prior is None:
            return J
        # the prior's rows: one 6 x 6 block per free camera, on its own columns (the first 6F)
        Jp = sp.block_diag(list(cache["prior_J"]), format="csr")
        Jp = sp.hstack([Jp, sp.csr_matrix((Jp.shape[0], J.shape[1] - Jp.shape[1]))], format="csr")
        return sp.vstack([J, Jp], format="csr")

    x0 = np.concatenate([cams0[free].ravel(), pts0.ravel()] + ([np.array([problem.focal])] if refine_focal else []))
    r0 = fun(x0)
    res = least_squares(fun, x0, jac=jac, loss=loss, f_scale=f_scale, method="trf", x_scale="jac",
                        max_nfev=max_nfev, ftol=tol, xtol=tol, gtol=tol, tr_solver="lsmr")
    cams, pts, f = unpack(res.x)
    r = res.fun[:O2].reshape(-1, 2)
    err = np.linalg.norm(r, axis=1)
    info = {"cost": float(res.cost), "nfev": int(res.nfev), "status": int(res.status),
            "rms_px_start": float(np.sqrt(np.mean(r0[:O2] ** 2))) if O2 else 0.0, "median_px": float(np.median(err)) if err.size else 0.0,
            "rms_px": float(np.sqrt(np.mean(err ** 2))) if err.size else 0.0, "residual_px": err}
    return cams, pts, float(f), info
