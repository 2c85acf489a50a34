"""The virtual poses and sub-frame times of one exposure (docs/method.md §4, the paper's Eq. 9).

Frame k has an estimated mid-exposure pose T̂_k (cam_T_world) and time t_k. The camera moves
during the exposure from T_s = exp(xi_s) T̂_k to T_e = exp(xi_e) T̂_k (LEFT perturbations,
xi = (rho, phi), translation first, as in d2gs_np.geometry.se3; d2gs_np.blur.endpoints gives
xi_s, xi_e). The n virtual views sit on the geodesic and at sub-frame times:

    T(u_i) = T_s exp(u_i log(T_s^-1 T_e)),   u_i = i / (n - 1),  i = 0 .. n-1       (Eq. 9)
    t_i    = t_k + (u_i - 1/2) tau                                                  (objects move)

and d2gs_np.blur.render averages the renders at them (Eq. 6). Choices made here (the paper
leaves them open or states them loosely; docs/method.md §4):

- n = 1 is a sharp camera at the ESTIMATED pose T̂_k and time t_k (u = [1/2]): xi_s, xi_e are
  ignored (their gradients are zero) and so is tau. Note that it is *not* T(1/2), the geodesic
  midpoint of the endpoints, which differs from T̂_k once the endpoints have moved
  asymmetrically.
- The virtual poses are evaluated as T(u) = exp(xi_s) exp(u delta) T̂ with
  delta = log(exp(-xi_s) exp(xi_e)). This is Eq. 9 exactly, because
  T_s^-1 T_e = T̂^-1 exp(-xi_s) exp(xi_e) T̂ and conjugation commutes with log (it preserves the
  rotation angle), but it never forms T̂^-1 T̂ and so with xi_s = xi_e = 0 every virtual pose is
  T̂ to the last bit. The geodesic is the one of the rotation log with angle <= pi; at exactly
  pi (a half turn between start and end, never a real exposure) it is ambiguous.
- Pose arithmetic is done in float64 and cast to the dtype of T̂ (float32 poses get float32
  virtual poses; the tangents must share it).

Endpoint derivative (hand derived, checked against finite differences in
tests/blur/test_virtual_poses.py). Write A = exp(xi_s), B = exp(xi_e), delta = log(A^-1 B),
L(u) = A exp(u delta), so T(u) = L(u) T̂ and a left perturbation of L(u) is the same left
perturbation of T(u). Left-perturb A by eps_s and B by eps_e:
    A^-1 B -> A^-1 B exp(Ad_{B^-1} (eps_e - eps_s))        =>  d delta = J_r^-1(delta) Ad_{B^-1} (eps_e - eps_s)
    A exp(u delta + u d delta) = L(u) exp(u J_r(u delta) d delta) = exp(u Ad_{L(u)} J_r(u delta) d delta) L(u)
so the left perturbation of T(u) is
    eps(u) = eps_s + M(u) (eps_e - eps_s),   M(u) = u Ad_{L(u)} J_r(u delta) J_r^-1(delta) Ad_{B^-1}
(M(0) = 0, M(1) = I), and exp(xi + d xi) = exp(J_l(xi) d xi) exp(xi) gives eps_s = J_l(xi_s) d xi_s,
eps_e = J_l(xi_e) d xi_e. For tangent gradients g_i on T(u_i):
    v_xi_e = J_l(xi_e)^T sum_i M_i^T g_i,   v_xi_s = J_l(xi_s)^T (sum_i g_i - sum_i M_i^T g_i).
All these Jacobians are smooth for rotation angles below 2 pi: zero-length exposures
(delta = 0), tiny ones and endpoints almost a half turn apart need no special branch beyond the
series branches of d2gs_np.geometry.

The three-knot path (``TrajectoryConfig.path = "three_knot"``): a third tangent xi_m, and

    T(u) = exp(c(u)) T̂,   c(u) = l_0(u) xi_s + l_1(u) xi_m + l_2(u) xi_e,
    l_0 = 2 (u - 1/2)(u - 1),  l_1 = -4 u (u - 1),  l_2 = 2 u (u - 1/2)              (``knot_weights``)

the quadratic in the tangent space of T̂ through the three knots at u = 0, 1/2, 1, so T(1/2) =
exp(xi_m) T̂ (for n = 1 too: the sharp camera is the middle knot). With xi_m = 0 and small
endpoints it is the geodesic to second order in |xi|; a free xi_m lets the path bend within the
exposure. Derivative: exp(c + dc) = exp(J_l(c) dc) exp(c), so the left perturbation of T(u_i) is
J_l(c_i) dc_i and, for tangent gradients g_i, v_xi_j = sum_i l_j(u_i) J_l(c_i)^T g_i.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.blur.config import _check_n
from d2gs_np.geometry.se3 import (
    check_rigid,
    se3_adjoint,
    se3_exp,
    se3_inverse,
    se3_left_jacobian,
    se3_log,
    se3_right_jacobian,
    se3_right_jacobian_inv,
)

__all__ = [
    "exposure_offsets",
    "knot_weights",
    "three_knot_poses",
    "three_knot_poses_fwd",
    "three_knot_poses_bwd",
    "subframe_times",
    "virtual_poses",
    "virtual_poses_fwd",
    "virtual_poses_bwd",
]


def exposure_offsets(n):
    """u_i (n,) float64: i / (n - 1) for n >= 2; [0.5] for n = 1 (the sharp camera)."""
    n = _check_n(n)
    if n == 1:
        return np.array([0.5])
    return np.arange(n, dtype=np.float64) / (n - 1)


def subframe_times(frame_time, tau, n):
    """t_i = frame_time + (u_i - 1/2) tau, (n,) float64."""
    return float(frame_time) + (exposure_offsets(n) - 0.5) * float(tau)


def _check_tangent(x, name, dtype=None):
    if not isinstance(x, np.ndarray) or x.dtype not in (np.float32, np.float64):
        got = x.dtype if isinstance(x, np.ndarray) else type(x).__name__
        raise TypeError(f"{name} must be a float32 or float64 numpy array; got {got}")
    if dtype is not None and x.dtype != dtype:
        raise TypeError(f"{name} must have dtype {dtype} like the other inputs; got {x.dtype}")
    if x.shape != (6,):
        raise ValueError(f"{name} must have shape (6,) ordered (rho, phi); got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf")


def virtual_poses_fwd(pose_est, xi_start, xi_end, n):
    """The n virtual cam_T_world poses of one exposure, and what the backward needs.

    pose_est: (4, 4) estimated mid-exposure cam_T_world T̂. xi_start, xi_end: (6,) left
    perturbations (rho, phi) of T̂ giving T_s, T_e. n: int >= 1.
    Returns (poses (n, 4, 4) of pose_est's dtype, saved). n = 1 returns T̂ itself (module
    docstring). Computed in float64.
    """
    n = _check_n(n)
    _check_pose_args(pose_est, xi_start, xi_end)
    return _virtual_poses_fwd(pose_est, xi_start, xi_end, n)


def _check_pose_args(pose_est, xi_start, xi_end):
    if not isinstance(pose_est, np.ndarray) or pose_est.dtype not in (np.float32, np.float64):
        raise TypeError(f"pose_est must be a float32 or float64 numpy array; got "
                        f"{getattr(pose_est, 'dtype', type(pose_est).__name__)}")
    if pose_est.shape != (4, 4):
        raise ValueError(f"pose_est must have shape (4, 4); got {pose_est.shape}")
    check_rigid(pose_est, "pose_est")
    _check_tangent(xi_start, "xi_start", pose_est.dtype)
    _check_tangent(xi_end, "xi_end", pose_est.dtype)


def _virtual_poses_fwd(pose_est, xi_start, xi_end, n):
    """``virtual_poses_fwd`` without validation (a rigid pose, finite tangents of its dtype)."""
    dtype = pose_est.dtype
    if n == 1:
        return pose_est[None].copy(), {"n": 1, "dtype": dtype}
    T_hat = pose_est.astype(np.float64)
    xs, xe = xi_start.astype(np.float64), xi_end.astype(np.float64)
    A, B = se3_exp(xs), se3_exp(xe)
    delta = se3_log(se3_inverse(A) @ B)
    u = exposure_offsets(n)
    L = A @ se3_exp(u[:, None] * delta)  # (n, 4, 4)
    poses = L @ T_hat
    saved = {"n": n, "dtype": dtype, "xi_start": xs, "xi_end": xe, "B": B, "delta": delta, "u": u, "L": L}
    return poses.astype(dtype), saved


def virtual_poses_bwd(saved, v_pose_tangents):
    """(v_xi_start (6,), v_xi_end (6,)) from left-perturbation gradients (n, 6) on the virtual poses.

    v_pose_tangents[i] is dLoss/d eps_i for T(u_i) -> exp(eps_i) T(u_i), e.g.
    ``matrix_grad_to_left_tangent(T_i, dL/dT_i)``. Derivation in the module docstring.
    """
    n, dtype = saved["n"], saved["dtype"]
    g = np.asarray(v_pose_tangents, dtype=np.float64)
    if g.shape != (n, 6):
        raise ValueError(f"v_pose_tangents must have shape ({n}, 6) like the virtual poses; got {g.shape}")
    if n == 1:
        return np.zeros(6, dtype=dtype), np.zeros(6, dtype=dtype)
    u, L, delta, B = saved["u"], saved["L"], saved["delta"], saved["B"]
    # sum_i M_i^T g_i = Ad_{B^-1}^T J_r^-1(delta)^T sum_i u_i J_r(u_i delta)^T Ad_{L_i}^T g_i
    J_r_u = se3_right_jacobian(u[:, None] * delta)  # (n, 6, 6)
    w = np.einsum("nji,nj->ni", se3_adjoint(L), g)  # Ad_{L_i}^T g_i
    w = np.einsum("nji,nj->ni", J_r_u, w) * u[:, None]
    s = w.sum(axis=0)
    s = se3_right_jacobian_inv(delta).T @ s
    v_eps_end = se3_adjoint(se3_inverse(B)).T @ s
    v_eps_start = g.sum(axis=0) - v_eps_end
    v_xi_start = se3_left_jacobian(saved["xi_start"]).T @ v_eps_start
    v_xi_end = se3_left_jacobian(saved["xi_end"]).T @ v_eps_end
    return v_xi_start.astype(dtype), v_xi_end.astype(dtype)


def virtual_poses(pose_est, xi_start, xi_end, n):
    """(n, 4, 4) virtual cam_T_world poses T(u_i) (see virtual_poses_fwd)."""
    return virtual_poses_fwd(pose_est, xi_start, xi_end, n)[0]



def knot_weights(u):
    """(len(u), 3) Lagrange weights (l_0, l_1, l_2) of the knots at u = 0, 1/2, 1 (module docstring)."""
    u = np.asarray(u, dtype=np.float64)
    return np.stack([2.0 * (u - 0.5) * (u - 1.0), -4.0 * u * (u - 1.0), 2.0 * u * (u - 0.5)], axis=-1)


def three_knot_poses_fwd(pose_est, xi_start, xi_mid, xi_end, n):
    """The n virtual cam_T_world poses of one exposure on the three-knot path (module docstring),
    and what the backward needs. Arguments as ``virtual_poses_fwd``, with xi_mid (6,) the middle
    knot. Returns (poses (n, 4, 4) of pose_est's dtype, saved); computed in float64."""
    n = _check_n(n)
    _check_pose_args(pose_est, xi_start, xi_end)
    _check_tangent(xi_mid, "xi_mid", pose_est.dtype)
    return _three_knot_poses_fwd(pose_est, xi_start, xi_mid, xi_end, n)


def _three_knot_poses_fwd(pose_est, xi_start, xi_mid, xi_end, n):
    """``three_knot_poses_fwd`` without validation."""
    dtype = pose_est.dtype
    W = knot_weights(exposure_offsets(n))  # (n, 3)
    knots = np.stack([xi_start, xi_mid, xi_end]).astype(np.float64)
    c = W @ knots  # (n, 6)
    poses = se3_exp(c) @ pose_est.astype(np.float64)
    return poses.astype(dtype), {"n": n, "dtype": dtype, "path": "three_knot", "W": W, "c": c}


def three_knot_poses_bwd(saved, v_pose_tangents):
    """(v_xi_start, v_xi_mid, v_xi_end) (6,) each from left-perturbation gradients (n, 6) on the
    virtual poses of ``three_knot_poses_fwd``."""
    n, dtype = saved["n"], saved["dtype"]
    g = np.asarray(v_pose_tangents, dtype=np.float64)
    if g.shape != (n, 6):
        raise ValueError(f"v_pose_tangents must have shape ({n}, 6) like the virtual poses; got {g.shape}")
    v_c = np.einsum("nji,nj->ni", se3_left_jacobian(saved["c"]), g)  # J_l(c_i)^T g_i
    v = saved["W"].T @ v_c  # (3, 6)
    return v[0].astype(dtype), v[1].astype(dtype), v[2].astype(dtype)


def three_knot_poses(pose_est, xi_start, xi_mid, xi_end, n):
    """(n, 4, 4) virtual cam_T_world poses on the three-knot path (see three_knot_poses_fwd)."""
    return three_knot_poses_fwd(pose_est, xi_start, xi_mid, xi_end, n)[0]
