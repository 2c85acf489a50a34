"""Symbolic SE(3) and the pose solver's residual functions, in CasADi (docs/method.md §5).

The solver (``pose/gauss_newton.py``, whose docstring defines the unknowns and the residuals)
evaluates three ``casadi.Function`` objects, built once per process, with exact Jacobians:

- ``mid_function``: (x_k 12, T_s,k 12, T_e,k 12) -> (M_k as 12 numbers, dM_k/dx_k 12x12, the
  perturbed start and end): the geodesic mid pose ``M_k = T_s exp(log(T_s^-1 T_e) / 2)`` of the
  endpoints moved on the LEFT, ``exp(a_k) T_s,k`` and ``exp(b_k) T_e,k``, x_k = (a_k, b_k);
- ``match_function``: (M_k, M_j, intrinsics 8, observation 7) -> (r 3, dr/dM_k 3x12, dr/dM_j 3x12):
  the pixel and relative-depth residuals of one match;
- ``prior_function``: (M, G, sigma 2) -> (r 6, dr/dM 6x12): the pose-prior rows (camera centres,
  then the rotation log, over their sigmas).

``mapped(kind, n)`` evaluates n columns in one call (cached per n). The chain rule
dr/dx_k = dr/dM_k dM_k/dx_k is then one matrix product per match.

SO(3)/SE(3) exp and log follow ``geometry/se3.py`` (xi = (rho, phi), translation first, left
perturbations) and are written with explicit small-angle branches (``casadi.if_else``): the series
of ``geometry/so3.py`` below SERIES_ANGLE2, the closed forms above, with a dummy angle in the branch
not taken so that no NaN is ever formed. Poses travel as 12 numbers: R row-major, then t
(``pose_to_flat`` / ``flat_to_pose``).
"""
from __future__ import annotations

import functools

import casadi as ca
import numpy as np

from d2gs_np.constants import GN_LOG_SERIES_SIN2, SERIES_ANGLE2
from d2gs_np.geometry.so3 import _A_COEFFS, _B_COEFFS, _C_COEFFS, _D_COEFFS

__all__ = ["NUM_VARS", "pose_to_flat", "flat_to_pose", "mid_function", "match_function", "prior_function", "mapped"]

NUM_VARS = 12  # per frame: a (6) on the exposure start, b (6) on the exposure end


def _hat(v):
    return ca.vertcat(ca.horzcat(0, -v[2], v[1]), ca.horzcat(v[2], 0, -v[0]), ca.horzcat(-v[1], v[0], 0))


def _horner(t2, coeffs):
    out = coeffs[-1]
    for c in coeffs[-2::-1]:
        out = out * t2 + c
    return out


def _coef(t2, coeffs, closed):
    """Series below SERIES_ANGLE2, closed form (a function of theta) above; the closed form sees
    a dummy angle 1 where the series is taken, so neither branch ever forms NaN."""
    small = t2 < SERIES_ANGLE2
    safe = ca.if_else(small, 1.0, t2)
    return ca.if_else(small, _horner(t2, coeffs), closed(ca.sqrt(safe)))


def _so3_exp_sym(phi):
    t2 = ca.dot(phi, phi)
    A = _coef(t2, _A_COEFFS, lambda t: ca.sin(t) / t)
    B = _coef(t2, _B_COEFFS, lambda t: (1 - ca.cos(t)) / (t * t))
    C = _coef(t2, _C_COEFFS, lambda t: (t - ca.sin(t)) / (t * t * t))
    P = _hat(phi)
    P2 = ca.mtimes(P, P)
    return ca.SX.eye(3) + A * P + B * P2, ca.SX.eye(3) + B * P + C * P2  # R, J_l


def _se3_exp_sym(xi):
    R, Jl = _so3_exp_sym(xi[3:6])
    return R, ca.mtimes(Jl, xi[0:3])


def _se3_log_sym(R, t):
    """(R, t) near the identity -> xi (6). The angle comes from atan2(|w|, c) with w the skew part
    and c = (tr R - 1) / 2; below |w|^2 = GN_LOG_SERIES_SIN2 (and c > 0) theta / sin(theta) is its
    series in sin^2. Valid for rotation angles below pi (the solver only takes the log of
    T_s^-1 T_e, the small endpoint spread)."""
    w = 0.5 * ca.vertcat(R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1])
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1)
    s2 = ca.dot(w, w)
    small = ca.logic_and(s2 < GN_LOG_SERIES_SIN2, c > 0)
    safe = ca.if_else(small, 1.0, s2)
    s = ca.sqrt(safe)
    factor = ca.if_else(small, 1 + s2 / 6 + 3 * s2 * s2 / 40 + 5 * s2 * s2 * s2 / 112, ca.atan2(s, c) / s)
    phi = factor * w
    t2 = ca.dot(phi, phi)
    D = _coef(t2, _D_COEFFS, lambda th: 1 / (th * th) - (1 + ca.cos(th)) / (2 * th * ca.sin(th)))
    P = _hat(phi)
    Jl_inv = ca.SX.eye(3) - 0.5 * P + D * ca.mtimes(P, P)
    return ca.vertcat(ca.mtimes(Jl_inv, t), phi)


def _pose_sym(m):
    """12 numbers (R row-major, t) -> (R 3x3, t 3)."""
    return ca.reshape(m[0:9], 3, 3).T, m[9:12]


def _pose_flat(R, t):
    return ca.vertcat(ca.reshape(R.T, 9, 1), t)


def pose_to_flat(T):
    """(..., 4, 4) -> (..., 12): R row-major, then t (the symbolic functions' pose layout)."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :3, :3].reshape(T.shape[:-2] + (9,)), T[..., :3, 3]], axis=-1)


def flat_to_pose(m):
    """(..., 12) -> (..., 4, 4): the inverse of ``pose_to_flat``."""
    m = np.asarray(m, dtype=np.float64)
    T = np.zeros(m.shape[:-1] + (4, 4))
    T[..., :3, :3] = m[..., :9].reshape(m.shape[:-1] + (3, 3))
    T[..., :3, 3] = m[..., 9:12]
    T[..., 3, 3] = 1.0
    return T


@functools.lru_cache(maxsize=None)
def mid_function() -> ca.Function:
    """(x 12, T_s 12, T_e 12) -> (mid pose 12, d mid / dx 12x12, start 12, end 12)."""
    x, ms, me = ca.SX.sym("x", NUM_VARS), ca.SX.sym("Ts", 12), ca.SX.sym("Te", 12)
    Rs0, ts0 = _pose_sym(ms)
    Re0, te0 = _pose_sym(me)
    Ra, ta = _se3_exp_sym(x[0:6])
    Rb, tb = _se3_exp_sym(x[6:12])
    Rs, ts = ca.mtimes(Ra, Rs0), ca.mtimes(Ra, ts0) + ta  # exp(a) T_s
    Re, te = ca.mtimes(Rb, Re0), ca.mtimes(Rb, te0) + tb  # exp(b) T_e
    Rd = ca.mtimes(Rs.T, Re)  # T_s^-1 T_e
    td = ca.mtimes(Rs.T, te - ts)
    half = 0.5 * _se3_log_sym(Rd, td)
    Rh, th = _se3_exp_sym(half)
    Rm, tm = ca.mtimes(Rs, Rh), ca.mtimes(Rs, th) + ts  # T_s exp(xi / 2)
    mid = _pose_flat(Rm, tm)
    return ca.Function("gn_mid", [x, ms, me], [mid, ca.jacobian(mid, x), _pose_flat(Rs, ts), _pose_flat(Re, te)],
                       ["x", "Ts", "Te"], ["mid", "dmid", "start", "end"])


@functools.lru_cache(maxsize=None)
def match_function() -> ca.Function:
    """(M_k 12, M_j 12, cam 8 = fx_k fy_k cx_k cy_k fx_j fy_j cx_j cy_j, obs 7 = u v u' v' D_k D_j beta)
    -> (r 3, dr/dM_k 3x12, dr/dM_j 3x12)."""
    mk, mj, cam, obs = ca.SX.sym("Mk", 12), ca.SX.sym("Mj", 12), ca.SX.sym("cam", 8), ca.SX.sym("obs", 7)
    Rk, tk = _pose_sym(mk)
    Rj, tj = _pose_sym(mj)
    u, v, u1, v1, Dk, Dj, beta = (obs[i] for i in range(7))
    Xj = Dj * ca.vertcat((u1 - cam[6]) / cam[4], (v1 - cam[7]) / cam[5], 1)  # lifted in camera j
    Xw = ca.mtimes(Rj.T, Xj - tj)
    Xk = ca.mtimes(Rk, Xw) + tk
    z = Xk[2]
    r = ca.vertcat(cam[0] * Xk[0] / z + cam[2] - u, cam[1] * Xk[1] / z + cam[3] - v, beta * (z - Dk) / Dk)
    return ca.Function("gn_match", [mk, mj, cam, obs], [r, ca.jacobian(r, mk), ca.jacobian(r, mj)],
                       ["Mk", "Mj", "cam", "obs"], ["r", "dr_dMk", "dr_dMj"])


@functools.lru_cache(maxsize=None)
def prior_function() -> ca.Function:
    """(M 12, G 12, sigma 2 = sigma_t sigma_r) -> (r 6, dr/dM 6x12): the pose prior rows of the
    module docstring, camera centres c = -R^T t first, then the rotation log."""
    m, g, sig = ca.SX.sym("M", 12), ca.SX.sym("G", 12), ca.SX.sym("sigma", 2)
    Rm, tm = _pose_sym(m)
    Rg, tg = _pose_sym(g)
    dc = -ca.mtimes(Rm.T, tm) + ca.mtimes(Rg.T, tg)
    phi = _se3_log_sym(ca.mtimes(Rm, Rg.T), ca.SX.zeros(3))[3:6]
    r = ca.vertcat(dc / sig[0], phi / sig[1])
    return ca.Function("gn_prior", [m, g, sig], [r, ca.jacobian(r, m)], ["M", "G", "sigma"], ["r", "dr_dM"])


@functools.lru_cache(maxsize=64)
def mapped(kind: str, n: int) -> ca.Function:
    """``kind`` ("mid", "match" or "prior") evaluated on n columns in one call, built once per n."""
    base = {"mid": mid_function, "match": match_function, "prior": prior_function}[kind]()
    return base.map(n, "serial")
