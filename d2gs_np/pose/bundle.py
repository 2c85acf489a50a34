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
points on moving objects lose their pull (docs/dataset_format.md §8), or (``solver="schur"``)
by Levenberg-Marquardt on the normal equations with the points eliminated (``_schur_lm``;
docs/method.md §5 has its measurements). The robust losses (SciPy's), the damping schedule and
the acceptance test of ``_schur_lm`` are those shared with the pose solver (``pose/lm.py``).
"""
from __future__ import annotations

from dataclasses import dataclass

import time

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from d2gs_np.base.checks import check_int
from d2gs_np.constants import BA_POINT_EIG_FLOOR, DAMPING_DIAG_FLOOR
from d2gs_np.geometry.so3 import hat, left_jacobian, left_jacobian_inv, so3_exp, so3_log
from d2gs_np.pose.config import BUNDLE_SOLVERS
from d2gs_np.pose.linalg import cholesky_solve
from d2gs_np.pose.lm import (LOSSES, Nielsen, accept_step, at_damping_limit, damping_start, finite_or_inf,
                             robust_loss)

__all__ = ["reprojection_fwd", "reprojection_bwd", "reprojection_jacobian", "pose_prior_fwd", "depth_prior_rows",
           "BundleProblem",
           "bundle_adjust", "camera_covariance", "relative_rotation_std", "poses_to_params", "params_to_poses"]

# The Schur solver's first Levenberg-Marquardt lambda (relative to diag(H)). The robust problems of
# pose_init have several local minima, and the first steps choose among them: this one chooses
# well (docs/results.md §12 compares the first lambdas).
SCHUR_DAMPING_INIT = 1e-3


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


def depth_prior_rows(saved, log_prior, log_scale, weight):
    """Rows that hold each observation's depth at a depth prior of one scale for the clip:
    ``weight (log z_o - log_scale - log_prior_o)`` (pixels per unit of log depth, beside the
    reprojection's pixels), where z_o is the point's depth in the observing camera (``saved`` of
    ``reprojection_fwd``) and log_prior_o the prior's log depth at the observed pixel; a row whose
    prior is not finite is 0 with a zero derivative. Returns (r (O,), d_cam (O, 6), d_pt (O, 3)):
    the derivatives with respect to the observation's camera (phi, t) and point, from
    d log z / dx = e_3 / z and the reprojection's dx/dphi, dx/dt = I, dx/dX = R."""
    phi, R, RX, x = saved[0], saved[1], saved[2], saved[3]
    lp, log_scale, weight = _check_depth((log_prior, log_scale, weight), x.shape[0])
    has = np.isfinite(lp) & (x[:, 2] > 0)
    z = np.where(has, x[:, 2], 1.0)
    r = np.where(has, weight * (np.log(z) - log_scale - np.where(has, lp, 0.0)), 0.0)
    g = np.where(has, weight / z, 0.0)[:, None]  # weight d log z / d x_2
    d_cam = np.concatenate([(-hat(RX) @ left_jacobian(phi))[:, 2, :] * g, np.zeros((len(z), 2)), g], axis=1)
    d_pt = R[:, 2, :] * g
    return r, d_cam, d_pt


def _check_depth(depth, num_obs):
    """``depth`` = (log_prior, log_scale, weight) checked against ``num_obs`` observations; returned
    as (float64 (O,) array, float, float)."""
    lp = np.asarray(depth[0], dtype=np.float64)
    log_scale, weight = float(depth[1]), float(depth[2])
    if lp.shape != (num_obs,):
        raise ValueError(f"the depth prior's log_prior must hold one log depth per observation: one entry per "
                         f"observation, shape ({num_obs},); got {lp.shape}")
    if not (np.isfinite(log_scale) and np.isfinite(weight) and weight > 0):
        raise ValueError(f"the depth prior's log scale must be finite and its weight > 0; got {log_scale}, {weight}")
    return lp, log_scale, weight


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


def path_smoothness_fwd(cams, sigma_c):
    """Residuals of a prior that holds the camera centres on a smooth path, and their Jacobian.

    Per interior camera k (1 .. C - 2) 3 rows: the centres' second difference
    ``(c_{k-1} - 2 c_k + c_{k+1}) / sigma_c`` (world units per frame squared; c = -R^T t), for frames
    equally spaced in time. A video's camera accelerates little from one frame to the next, while
    pose noise that is independent per frame has a second difference sqrt(6) times its own size:
    the rows hold the short baselines between neighbouring frames, which tracks through blurred
    frames leave loose (docs/method.md §5). Returns (r (C - 2, 3), J (C - 2, 3, 3, 6)): J[k, :, j]
    is the derivative of row block k with respect to camera (k + j)'s (phi, t), j = 0, 1, 2;
    dc / d phi = -R^T hat(t) J_l(phi), dc / dt = -R^T, as in ``pose_prior_fwd``.
    """
    cams = np.asarray(cams, dtype=np.float64)
    if cams.ndim != 2 or cams.shape[1] != 6:
        raise ValueError(f"cams must have shape (C, 6); got {cams.shape}")
    if not (np.isfinite(sigma_c) and sigma_c > 0):
        raise ValueError(f"the path smoothness sigma must be finite and > 0; got {sigma_c}")
    C = cams.shape[0]
    if C < 3:
        return np.zeros((0, 3)), np.zeros((0, 3, 3, 6))
    phi, t = cams[:, :3], cams[:, 3:]
    Rt = np.transpose(so3_exp(phi), (0, 2, 1))
    c = -np.einsum("cij,cj->ci", Rt, t)
    dc = np.concatenate([-(Rt @ hat(t) @ left_jacobian(phi)), -Rt], axis=2)  # (C, 3, 6)
    r = (c[:-2] - 2.0 * c[1:-1] + c[2:]) / sigma_c
    J = np.stack([dc[:-2], -2.0 * dc[1:-1], dc[2:]], axis=2) / sigma_c
    return r, J


def _smooth_dense(cams, free, sigma_c):
    """``path_smoothness_fwd`` as flat rows (3 (C - 2),) and a dense Jacobian (3 (C - 2), 6F) on the
    free cameras' columns (a fixed camera's columns are dropped)."""
    r, J = path_smoothness_fwd(cams, sigma_c)
    C, F = cams.shape[0], len(free)
    slot = np.full(C, -1, dtype=np.int64)
    slot[free] = np.arange(F)
    Jd = np.zeros((r.shape[0], 3, 6 * F))
    for j in range(3):
        cols = slot[np.arange(r.shape[0]) + j]
        ok = cols >= 0
        for a in range(6):
            Jd[np.flatnonzero(ok), :, 6 * cols[ok] + a] = J[ok, :, j, a]
    return r.ravel(), Jd.reshape(-1, 6 * F)


def _camera_rows(cams, free, prior, smooth):
    """The rows on the cameras alone (the pose prior's, the path smoothness's) as flat residuals (R,)
    and a dense Jacobian (R, 6F) on the free cameras' columns; None when there are none."""
    rows = []
    F = len(free)
    if prior is not None and F:
        rp, Jp = pose_prior_fwd(cams[free], np.asarray(prior[0], dtype=np.float64)[free], prior[1], prior[2])
        Jd = np.zeros((F, 6, F, 6))
        Jd[np.arange(F), :, np.arange(F), :] = Jp
        rows.append((rp.ravel(), Jd.reshape(6 * F, 6 * F)))
    if smooth is not None and F:
        rows.append(_smooth_dense(cams, free, smooth))
    if not rows:
        return None
    return np.concatenate([r for r, _ in rows]), np.concatenate([J for _, J in rows], axis=0)


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


def _check_solver_args(solver, loss, f_scale, max_nfev, tol):
    if not isinstance(solver, str) or solver not in BUNDLE_SOLVERS:
        raise ValueError(f"bundle_adjust: solver must be one of {BUNDLE_SOLVERS}; got {solver!r}")
    if not isinstance(loss, str) or loss not in LOSSES:
        raise ValueError(f"bundle_adjust: loss must be one of {LOSSES}; got {loss!r}")
    if isinstance(f_scale, bool) or not isinstance(f_scale, (int, float, np.floating, np.integer)):
        raise TypeError(f"bundle_adjust: f_scale must be a number (pixels); got {type(f_scale).__name__}")
    if not (np.isfinite(f_scale) and f_scale > 0):
        raise ValueError(f"bundle_adjust: f_scale must be finite and > 0 (pixels); got {f_scale}")
    check_int(max_nfev, "bundle_adjust: max_nfev", 1)
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"bundle_adjust: tol must be finite and >= 0; got {tol}")


def bundle_adjust(problem: BundleProblem, fixed_cams=(0,), refine_focal=False, loss="soft_l1", f_scale=1.0,
                  max_nfev=50, tol=1e-8, prior=None, solver="scipy", smooth=None, depth=None):
    """Robust least squares over free cameras, all points and (optionally) the shared focal length.

    fixed_cams: cameras held at their start (the gauge: fix one camera; the overall scale stays
    free and is set by the start). loss, f_scale: SciPy robust loss and its scale in pixels.
    prior: optional (prior_cams (C, 6), sigma_t, sigma_r): ``pose_prior_fwd`` rows for every free
    camera (in units of sigma, under the same robust loss); with it no camera need be fixed (the
    prior holds the gauge, the scale included).
    smooth: optional sigma_c (world units per frame squared): ``path_smoothness_fwd`` rows on every
    three consecutive cameras (in units of sigma_c, under the same robust loss), frames equally spaced.
    depth: optional (log_prior (O,), log_scale, weight): ``depth_prior_rows`` on every observation
    whose prior is finite (under the same robust loss), the scale held; the rms / median residuals
    and ``residual_px`` stay the reprojection's.
    solver: "scipy" (``least_squares``, trust region reflective with LSMR; ``max_nfev`` residual
    evaluations) or "schur" (Levenberg-Marquardt on the normal equations with the points
    eliminated, ``_schur_lm``; ``max_nfev`` residual evaluations too, one per trial step). Both
    minimise the same cost 0.5 f_scale^2 sum rho((r_i / f_scale)^2) over every residual element.
    Returns (cams (C, 6), points (P, 3), focal, info dict with cost, nfev, status, iterations, rms /
    median residual of the observations, and cost_history / seconds_history: the lowest cost after
    each residual evaluation and the seconds since the call began).
    """
    _check_solver_args(solver, loss, f_scale, max_nfev, tol)
    t_start = time.perf_counter()
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
    if smooth is not None:
        path_smoothness_fwd(cams0[:0], smooth)  # checks sigma_c
        smooth = float(smooth)
    O2 = 2 * len(problem.cam_idx)
    if depth is not None:
        depth = _check_depth(depth, len(problem.cam_idx))
    if solver == "schur":
        return _schur_lm(problem, cams0, pts0, free, refine_focal, loss, float(f_scale), int(max_nfev), float(tol),
                         None if prior is None else (prior_cams, float(sigma_t), float(sigma_r)), t_start, smooth,
                         depth)
    history = {"cost": [], "seconds": []}

    def fun(x):
        cams, pts, f = unpack(x)
        r, saved = reprojection_fwd(cams, pts, f, problem.cx, problem.cy, problem.cam_idx, problem.pt_idx, problem.uv)
        cache["key"], cache["saved"] = x.tobytes(), saved
        out = [r.ravel()]
        if prior is not None:
            rp, cache["prior_J"] = pose_prior_fwd(cams[free], prior_cams[free], sigma_t, sigma_r)
            out.append(rp.ravel())
        if smooth is not None:
            rs, cache["smooth_J"] = _smooth_dense(cams, free, smooth)
            out.append(rs)
        if depth is not None:
            rd, cache["depth_cam"], cache["depth_pt"] = depth_prior_rows(saved, *depth)
            out.append(rd)
        out = np.concatenate(out)
        # record the cost (read-only: the solver's path is unchanged)
        c = 0.5 * f_scale ** 2 * float(np.sum(robust_loss((out / f_scale) ** 2, loss)[0]))
        best = min(history["cost"][-1], c) if history["cost"] else c
        history["cost"].append(best if np.isfinite(best) else c)
        history["seconds"].append(time.perf_counter() - t_start)
        return out

    def jac(x):
        if cache.get("key") != x.tobytes():
            fun(x)
        J = [reprojection_jacobian(cache["saved"], free, refine_focal)]
        width = J[0].shape[1]
        if prior is not None:
            # the prior's rows: one 6 x 6 block per free camera, on its own columns (the first 6F)
            Jp = sp.block_diag(list(cache["prior_J"]), format="csr")
            J.append(sp.hstack([Jp, sp.csr_matrix((Jp.shape[0], width - Jp.shape[1]))], format="csr"))
        if smooth is not None:
            Js = cache["smooth_J"]
            J.append(sp.hstack([sp.csr_matrix(Js), sp.csr_matrix((Js.shape[0], width - Js.shape[1]))], format="csr"))
        if depth is not None:
            J.append(_depth_jacobian(cache["depth_cam"], cache["depth_pt"], problem.cam_idx, problem.pt_idx, free, C,
                                     width))
        return J[0] if len(J) == 1 else sp.vstack(J, format="csr")

    x0 = np.concatenate([cams0[free].ravel(), pts0.ravel()] + ([np.array([problem.focal])] if refine_focal else []))
    r0 = fun(x0)
    res = least_squares(fun, x0, jac=jac, loss=loss, f_scale=f_scale, method="trf", x_scale="jac",
                        max_nfev=max_nfev, ftol=tol, xtol=tol, gtol=tol, tr_solver="lsmr")
    cams, pts, f = unpack(res.x)
    r = res.fun[:O2].reshape(-1, 2)
    err = np.linalg.norm(r, axis=1)
    info = {"cost": float(res.cost), "nfev": int(res.nfev), "status": int(res.status),
            # rms of the observations' pixel distances, at the start as at the end
            "rms_px_start": float(np.sqrt(np.mean(np.sum(r0[:O2].reshape(-1, 2) ** 2, axis=1)))) if O2 else 0.0,
            "median_px": float(np.median(err)) if err.size else 0.0,
            "rms_px": float(np.sqrt(np.mean(err ** 2))) if err.size else 0.0, "residual_px": err,
            "solver": "scipy", "iterations": int(res.njev) if res.njev is not None else int(res.nfev),
            "cost_history": history["cost"], "seconds_history": history["seconds"]}
    return cams, pts, float(f), info


def _depth_jacobian(d_cam, d_pt, cam_idx, pt_idx, free, C, width):
    """The depth prior's rows (``depth_prior_rows``) as a sparse (O, width) Jacobian on the
    parameter vector [cams[free].ravel(), points.ravel(), (f)] (a fixed camera's columns dropped)."""
    O = d_cam.shape[0]
    slot = np.full(C, -1, dtype=np.int64)
    slot[free] = np.arange(len(free))
    s = slot[np.asarray(cam_idx)]
    has = s >= 0
    rows = [np.repeat(np.flatnonzero(has), 6), np.repeat(np.arange(O), 3)]
    cols = [(6 * s[has][:, None] + np.arange(6)).ravel(), (6 * len(free) + 3 * np.asarray(pt_idx)[:, None]
                                                            + np.arange(3)).ravel()]
    vals = [d_cam[has].ravel(), d_pt.ravel()]
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(O, width))


def _block_diagonal(blocks):
    """(P, 3, 3) blocks -> the (3P, 3P) sparse block-diagonal matrix (CSR): the points' inverses."""
    P = blocks.shape[0]
    return sp.bsr_matrix((blocks, np.arange(P), np.arange(P + 1)), shape=(3 * P, 3 * P)).tocsr()


def _schur_lm(problem, cams0, pts0, free, refine_focal, loss, f_scale, max_nfev, tol, prior, t_start, smooth=None,
              depth=None):
    """Levenberg-Marquardt with the points eliminated (Schur complement onto the camera side).

    Unknowns x = (y, p): y = the free cameras' (phi, t) [and the focal], p = the points. Each
    iteration linearises the residuals at x and reweights them IRLS-style: element i gets the weight
    w_i = rho'(z_i), z_i = (r_i / f_scale)^2, so that H = J^T W J and g = J^T W r, and g is the exact
    gradient of the robust cost 0.5 f_scale^2 sum rho(z_i) (SciPy's scaling adds a second-order
    correction to H; the minimiser is the same, only the path differs). The damped system
        [A + lam D_y    E          ] [dy]     [g_y]
        [E^T            V + lam D_p] [dp] = - [g_p]
    with Marquardt's scaling D = diag(H) (floored at DAMPING_DIAG_FLOOR x its largest entry, so a
    parameter no residual sees is still damped and stays where it is) is solved by eliminating the
    points, whose blocks V_p (3 x 3 per point) are independent:
        S = A + lam D_y - E (V + lam D_p)^-1 E^T,  S dy = -g_y + E (V + lam D_p)^-1 g_p,
        dp = -(V + lam D_p)^-1 (g_p + E^T dy);
    S is dense (6 x free cameras [+ 1]) and Cholesky-factored (``pose.linalg.cholesky_solve``); each
    damped point block is inverted from its eigendecomposition with its eigenvalues floored at
    BA_POINT_EIG_FLOOR x the largest (a point seen once, or along one ray, has a rank-2 block: the
    damping regularises it). The damping and the acceptance are the shared ones of ``pose/lm.py``:
    a trial step is accepted only if the true cost falls (a non-finite residual counts as an
    infinite cost; a failed factorisation as a rejection); Nielsen's update of lam (``lm.Nielsen``):
    after acceptance lam *= max(1/3, 1 - (2 rho - 1)^3) with rho = actual / predicted decrease (the
    quadratic model of J^T W J), nu = 2; after a rejection lam *= nu, nu *= 2. The rotation vectors
    are updated additively, as SciPy's are.
    With ``depth`` each observation has a third row, its depth prior's (``depth_prior_rows``), on the
    same camera and point: the blocks are 3 x 6 and 3 x 3 and the elimination is unchanged.
    Stops when an accepted step lowers the cost by less than tol x cost (status 2), when a step is
    below tol x (|x| + tol) (status 3), after max_nfev residual evaluations (status 0) or when lam
    reaches LM_DAMPING_MAX (status -2, no step lowers the cost).
    """
    cx, cy = problem.cx, problem.cy
    ci = np.asarray(problem.cam_idx).astype(np.int64)
    pi = np.asarray(problem.pt_idx).astype(np.int64)
    uv = np.asarray(problem.uv, dtype=np.float64)
    C, P, O = cams0.shape[0], pts0.shape[0], ci.shape[0]
    F = len(free)
    nc = 6 * F
    ny = nc + (1 if refine_focal else 0)
    k = 7 if refine_focal else 6
    slot = np.full(C, -1, dtype=np.int64)
    slot[free] = np.arange(F)
    s = slot[ci]
    seen_free = s >= 0
    cols_y = np.empty((O, k), dtype=np.int64)  # camera-side columns of each observation (fixed: 0..5, zero blocks)
    cols_y[:, :6] = 6 * np.maximum(s, 0)[:, None] + np.arange(6)
    if refine_focal:
        cols_y[:, 6] = nc
    flat_yy = (cols_y[:, :, None] * ny + cols_y[:, None, :]).ravel()
    flat_p = (3 * pi[:, None] + np.arange(3)).ravel()
    flat_pp = (9 * pi[:, None] + np.arange(9)).ravel()
    E_rows = np.repeat(cols_y[:, :, None], 3, axis=2).ravel()
    E_cols = np.repeat((3 * pi[:, None] + np.arange(3))[:, None, :], k, axis=1).ravel()
    fs2 = f_scale * f_scale

    def split(cams, pts, f):
        return np.concatenate([cams[free].ravel()] + ([np.array([f])] if refine_focal else [])), pts

    def unpack(y, pts):
        cams = cams0.copy()
        cams[free] = y[:nc].reshape(-1, 6)
        return cams, pts, (y[nc] if refine_focal else problem.focal)

    def evaluate(y, pts):
        cams, pts, f = unpack(y, pts)
        with np.errstate(all="ignore"):
            r, saved = reprojection_fwd(cams, pts, f, cx, cy, ci, pi, uv)
            depth_d = None
            if depth is not None:  # (O, 3): the observation's depth row beside its two pixel rows
                rd, dc, dpt = depth_prior_rows(saved, *depth)
                r, depth_d = np.concatenate([r, rd[:, None]], axis=1), (dc, dpt)
            rows = _camera_rows(cams, free, prior, smooth)
            rho = robust_loss((r / f_scale) ** 2, loss)[0]
            cost = 0.5 * fs2 * float(np.sum(rho))
            if rows is not None:
                cost += 0.5 * fs2 * float(np.sum(robust_loss((rows[0] / f_scale) ** 2, loss)[0]))
        return finite_or_inf(cost), r, (saved, depth_d), rows

    def normal_equations(r, saved, rows):
        saved, depth_d = saved  # the reprojection's saved values and the depth rows' derivatives
        d_cam, d_pt, n = _blocks(saved)
        if depth_d is not None:
            dc, dpt = depth_d
            d_cam = np.concatenate([d_cam, dc[:, None, :]], axis=1)
            d_pt = np.concatenate([d_pt, dpt[:, None, :]], axis=1)
            n = np.concatenate([n, np.zeros((O, 1))], axis=1)  # the focal does not move a depth
        d_cam[~seen_free] = 0.0
        Jy = np.concatenate([d_cam, n[:, :, None]], axis=2) if refine_focal else d_cam  # (O, 2, k)
        w = robust_loss((r / f_scale) ** 2, loss)[1]  # (O, 2)
        WJy = w[:, :, None] * Jy
        WJp = w[:, :, None] * d_pt
        V = np.bincount(flat_pp, np.einsum("oia,oib->oab", WJp, d_pt).ravel(), minlength=9 * P).reshape(P, 3, 3)
        gp = np.bincount(flat_p, np.einsum("oia,oi->oa", WJp, r).ravel(), minlength=3 * P)
        if ny == 0:  # every camera fixed, focal fixed: the points alone
            A, gy, E = np.zeros((0, 0)), np.zeros(0), sp.csr_matrix((0, 3 * P))
        else:
            A = np.bincount(flat_yy, np.einsum("oia,oib->oab", WJy, Jy).ravel(), minlength=ny * ny).reshape(ny, ny)
            Eo = np.einsum("oia,oib->oab", WJy, d_pt)  # (O, k, 3)
            gy = np.bincount(cols_y.ravel(), np.einsum("oia,oi->oa", WJy, r).ravel(), minlength=ny)
            E = sp.csr_matrix((Eo.ravel(), (E_rows, E_cols)), shape=(ny, 3 * P))
        if rows is not None:
            rc, Jc = rows
            wc = robust_loss((rc / f_scale) ** 2, loss)[1]
            A[:nc, :nc] += Jc.T @ (wc[:, None] * Jc)
            gy[:nc] += Jc.T @ (wc * rc)
        return dict(Jy=Jy, Jp=d_pt, w=w, A=A, V=V, E=E, gy=gy, gp=gp, rows=rows)

    def damped_step(ne, lam):
        """(dy, dp) of the damped system, or None when S is not positive definite."""
        A, V, E, gy, gp = ne["A"], ne["V"], ne["E"], ne["gy"], ne["gp"]
        dA = np.diag(A).copy()
        dV = np.diagonal(V, axis1=1, axis2=2).copy()  # (P, 3)
        top = max(dA.max() if dA.size else 0.0, dV.max() if dV.size else 0.0, 1e-300)
        floor = DAMPING_DIAG_FLOOR * top
        Vd = V + lam * np.maximum(dV, floor)[:, :, None] * np.eye(3)
        ev, Q = np.linalg.eigh(Vd)
        ev = np.maximum(ev, BA_POINT_EIG_FLOOR * np.maximum(ev[:, -1:], floor))
        Vinv = np.einsum("pij,pj,pkj->pik", Q, 1.0 / ev, Q)
        Vinv_sp = _block_diagonal(Vinv)
        dp_rhs = Vinv_sp @ gp
        if ny:
            EV = E @ Vinv_sp
            S = A + np.diag(lam * np.maximum(dA, floor)) - (EV @ E.T).toarray()
            S = 0.5 * (S + S.T)
            rhs = -gy + E @ dp_rhs
            if not (np.all(np.isfinite(S)) and np.all(np.isfinite(rhs))):
                return None
            dy, ok = cholesky_solve(np.ascontiguousarray(S), np.ascontiguousarray(rhs))
            if not ok:
                return None
            dp = -dp_rhs - Vinv_sp @ (E.T @ dy)
        else:
            dy = np.zeros(0)
            dp = -dp_rhs
        if not (np.all(np.isfinite(dy)) and np.all(np.isfinite(dp))):
            return None
        return dy, dp

    def predicted_decrease(ne, dy, dp):
        """-(g . dx + 0.5 dx^T J^T W J dx): the decrease the reweighted quadratic model promises."""
        Jdx = np.einsum("oia,oa->oi", ne["Jy"], dy[cols_y] if ny else np.zeros((O, k))) + \
            np.einsum("oia,oa->oi", ne["Jp"], dp.reshape(P, 3)[pi])
        quad = float(np.sum(ne["w"] * Jdx ** 2))
        if ne["rows"] is not None:
            rc, Jc = ne["rows"]
            quad += float(np.sum(robust_loss((rc / f_scale) ** 2, loss)[1] * (Jc @ dy[:nc]) ** 2))
        return -(float(ne["gy"] @ dy) + float(ne["gp"] @ dp) + 0.5 * quad)

    y, pts = split(cams0, pts0, problem.focal)
    pts = pts.copy()
    cost, r, saved, rows = evaluate(y, pts)
    if not np.isfinite(cost):
        bad = np.flatnonzero(~np.all(np.isfinite(r), axis=1))
        raise ValueError(f"bundle_adjust: the residuals are not finite at the start ({bad.size} observations, e.g. "
                         f"{bad[:5].tolist()}: a point on a camera's plane z = 0, or a non-finite camera / point); "
                         f"drop those observations or start the points elsewhere")
    r0 = r[:, :2]
    nfev, iterations, status = 1, 0, 0
    cost_hist, sec_hist = [cost], [time.perf_counter() - t_start]
    damp, schedule = damping_start(SCHUR_DAMPING_INIT), Nielsen()
    ne = normal_equations(r, saved, rows)
    while nfev < max_nfev:
        step = damped_step(ne, damp.lam)
        if step is None:  # S not positive definite at this damping: more damping
            if at_damping_limit(damp):
                status = -2
                break
            damp = schedule.rejected(damp)
            continue
        dy, dp = step
        pred = predicted_decrease(ne, dy, dp)
        y_new, pts_new = y + dy, pts + dp.reshape(P, 3)
        new = evaluate(y_new, pts_new)
        nfev += 1
        small_step = np.sqrt(dy @ dy + dp @ dp) <= tol * (np.sqrt(y @ y + np.sum(pts * pts)) + tol)
        if accept_step(cost, new[0]):
            decrease = cost - new[0]
            y, pts, (cost, r, saved, rows) = y_new, pts_new, new
            iterations += 1
            damp = schedule.accepted(damp, decrease, pred)
            cost_hist.append(cost)
            sec_hist.append(time.perf_counter() - t_start)
            if decrease <= tol * cost:
                status = 2
                break
            if small_step:
                status = 3
                break
            ne = normal_equations(r, saved, rows)
        else:
            cost_hist.append(cost)
            sec_hist.append(time.perf_counter() - t_start)
            if small_step:
                status = 3
                break
            if at_damping_limit(damp):
                status = -2
                break
            damp = schedule.rejected(damp)
    cams, pts, f = unpack(y, pts)
    err = np.linalg.norm(r[:, :2], axis=1)
    info = {"cost": float(cost), "nfev": int(nfev), "status": int(status), "solver": "schur",
            "iterations": int(iterations), "damping": float(damp.lam),
            "rms_px_start": float(np.sqrt(np.mean(np.sum(r0 ** 2, axis=1)))) if O else 0.0,
            "median_px": float(np.median(err)) if err.size else 0.0,
            "rms_px": float(np.sqrt(np.mean(err ** 2))) if err.size else 0.0, "residual_px": err,
            "cost_history": cost_hist, "seconds_history": sec_hist}
    return cams, pts, float(f), info


def camera_covariance(problem: BundleProblem, cams, points, fixed_cams=(), loss="soft_l1", f_scale=1.0, prior=None,
                      smooth=None):
    """Covariance (6F, 6F) of the free cameras' (phi, t) at a solution (cams (C, 6), points (P, 3)),
    from the Gauss-Newton approximation of the cost ``bundle_adjust`` minimises: H = J^T W J (+ the
    prior's and the path smoothness's J^T W J), W the robust weights rho'(z) at the solution, the points eliminated (Schur
    complement), Sigma = S^-1. A residual of 1 px counts as one standard deviation, as the cost
    weighs it. Returns (Sigma, free (F,) camera indices).

    A rank-deficient S (no prior and too few fixed cameras: the gauge is free) is inverted on its
    range (eigenvalues below 1e-12 x the largest count as zero), so the free directions get zero
    variance rather than an overflow; with a prior S is positive definite.
    """
    cams = np.asarray(cams, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    C, P = cams.shape[0], pts.shape[0]
    free = np.array([c for c in range(C) if c not in set(fixed_cams)], dtype=np.int64)
    nc = 6 * len(free)
    r, saved = reprojection_fwd(cams, pts, problem.focal, problem.cx, problem.cy, problem.cam_idx, problem.pt_idx,
                                problem.uv)
    J = reprojection_jacobian(saved, free, False)
    w = robust_loss((r / f_scale) ** 2, loss)[1].ravel()
    H = (J.T @ sp.diags(w) @ J).tocsr()
    A = H[:nc, :nc].toarray()
    rows = _camera_rows(cams, free, prior, smooth)
    if rows is not None:
        rc, Jc = rows
        A += Jc.T @ (robust_loss((rc / f_scale) ** 2, loss)[1][:, None] * Jc)
    if P:
        # the points' blocks are 3 x 3 and independent: invert each on its range (a point seen along
        # one ray has a rank-2 block), as _schur_lm's damped step does
        d_pt = _blocks(saved)[1]
        wo = w.reshape(-1, 2)
        Vb = np.zeros((P, 3, 3))
        np.add.at(Vb, np.asarray(problem.pt_idx), np.einsum("oia,oi,oib->oab", d_pt, wo, d_pt))
        ev, Q = np.linalg.eigh(Vb)
        top = np.maximum(ev[:, -1:], 1e-300)
        inv_ev = np.where(ev > BA_POINT_EIG_FLOOR * top, 1.0 / np.maximum(ev, 1e-300), 0.0)
        Vinv = _block_diagonal(np.einsum("pij,pj,pkj->pik", Q, inv_ev, Q))
        E = H[:nc, nc:]
        A = A - (E @ Vinv @ E.T).toarray()
    S = 0.5 * (A + A.T)
    ev, Q = np.linalg.eigh(S)
    keep = ev > 1e-12 * max(float(ev[-1]) if ev.size else 0.0, 1e-300)
    Sigma = (Q[:, keep] / ev[keep]) @ Q[:, keep].T
    return Sigma, free


def relative_rotation_std(Sigma, free, num_cams):
    """(num_cams,) standard deviation (radians, RMS over the three axes) of each free camera's
    rotation relative to the free cameras' mean rotation, from ``camera_covariance``: the part of
    its uncertainty that moves it against the others, with the common turn of the whole trajectory
    (the gauge the prior holds, which no image shows) taken out. NaN for fixed cameras.

    With delta_i the rotation block of camera i, the relative rotation is delta_i - mean_j delta_j
    (exact to first order for a path whose orientations differ by a few degrees: the cameras'
    left perturbations of a common world turn then agree)."""
    F = len(free)
    out = np.full(num_cams, np.nan)
    if F == 0:
        return out
    rot = (6 * np.arange(F)[:, None] + np.arange(3)).ravel()
    Sr = Sigma[np.ix_(rot, rot)].reshape(F, 3, F, 3)
    mean_row = Sr.mean(axis=2)  # (F, 3, 3): Cov(delta_i, mean delta)
    mean_all = Sr.mean(axis=(0, 2))  # (3, 3): Var(mean delta)
    diag = np.einsum("iaib->iab", Sr)
    rel = diag - mean_row - np.transpose(mean_row, (0, 2, 1)) + mean_all[None]
    out[free] = np.sqrt(np.maximum(np.trace(rel, axis1=1, axis2=2), 0.0) / 3.0)
    return out
