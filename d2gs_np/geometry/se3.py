"""SE(3): exponential and logarithm maps, Jacobians, adjoint, geodesic interpolation.

Conventions
- Tangent vectors xi = (rho, phi) of shape (..., 6), TRANSLATION FIRST.
- ``se3_exp(xi) = [[exp(phi^), J_l(phi) rho], [0, 1]]``.
- Perturbations act on the LEFT: a pose T is perturbed as ``exp(delta) @ T``.
  The left Jacobian satisfies ``exp(xi + d) ~= exp(J_l(xi) d) exp(xi)``; the
  right one ``exp(xi + d) ~= exp(xi) exp(J_r(xi) d)``, ``J_r(xi) = J_l(-xi)``.
- Poses are 4x4 homogeneous matrices, vectorised over leading batch axes.
  Camera poses are named by their frames: ``cam_T_world`` maps world points to
  camera coordinates.

The 6x6 left Jacobian is [[J_l(phi), Q(rho, phi)], [0, J_l(phi)]] with Q from
Barfoot, "State Estimation for Robotics", eq. 7.86; its coefficients use Taylor
series below SERIES_ANGLE2 (see so3.py).
"""
from __future__ import annotations

import math

import numpy as np

from d2gs_np.constants import POSE_ROUNDING_TOL, RIGID_TOL
from d2gs_np.geometry import so3
from d2gs_np.geometry.so3 import _series, _split, float_dtype, hat

_N = 8
# (theta^2 + 2 cos theta - 2) / (2 theta^4) = sum_k (-1)^k theta^{2k} / (2k+4)!
_Q2_COEFFS = [(-1) ** k / math.factorial(2 * k + 4) for k in range(_N)]
# (2 theta - 3 sin theta + theta cos theta) / (2 theta^5) = sum_k (-1)^k (k+1) theta^{2k} / (2k+5)!
_Q3_COEFFS = [(-1) ** k * (k + 1) / math.factorial(2 * k + 5) for k in range(_N)]


def _coef_q2(theta2):
    small, t2, t = _split(theta2)
    return np.where(small, _series(theta2, _Q2_COEFFS), (t2 + 2.0 * np.cos(t) - 2.0) / (2.0 * t2 * t2))


def _coef_q3(theta2):
    small, t2, t = _split(theta2)
    direct = (2.0 * t - 3.0 * np.sin(t) + t * np.cos(t)) / (2.0 * t2 * t2 * t)
    return np.where(small, _series(theta2, _Q3_COEFFS), direct)


def _as_xi(xi, name="xi"):
    xi = np.asarray(xi, dtype=float_dtype(xi))
    if xi.shape[-1:] != (6,):
        raise ValueError(f"{name} must have shape (..., 6) ordered (rho, phi); got {xi.shape}")
    return xi


def _as_pose(T, name="T"):
    T = np.asarray(T, dtype=float_dtype(T))
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must have shape (..., 4, 4); got {T.shape}")
    return T


def se3_exp(xi):
    """(..., 6) tangent (rho, phi) -> (..., 4, 4) rigid transform."""
    xi = _as_xi(xi)
    rho, phi = xi[..., :3], xi[..., 3:]
    T = np.zeros(xi.shape[:-1] + (4, 4), dtype=xi.dtype)
    T[..., :3, :3] = so3.so3_exp(phi)
    T[..., :3, 3] = np.einsum("...ij,...j->...i", so3.left_jacobian(phi), rho)
    T[..., 3, 3] = 1.0
    return T


def se3_log(T):
    """(..., 4, 4) rigid transform -> (..., 6) tangent (rho, phi), |phi| <= pi."""
    T = _as_pose(T)
    phi = so3.so3_log(T[..., :3, :3])
    rho = np.einsum("...ij,...j->...i", so3.left_jacobian_inv(phi), T[..., :3, 3])
    return np.concatenate([rho, phi], axis=-1)


def se3_inverse(T):
    """Inverse of rigid transforms without a general matrix inverse."""
    T = _as_pose(T)
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def se3_compose(A, B):
    """A @ B for (batches of) rigid transforms."""
    return _as_pose(A, "A") @ _as_pose(B, "B")


def se3_adjoint(T):
    """Adjoint (..., 6, 6) for (rho, phi) ordering: [[R, t^ R], [0, R]], so T exp(d) T^-1 = exp(Ad d)."""
    T = _as_pose(T)
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6), dtype=T.dtype)
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = hat(t) @ R
    return out


def _q_matrix(xi):
    """Barfoot's Q(rho, phi), the top-right block of the SE(3) left Jacobian."""
    rho, phi = xi[..., :3], xi[..., 3:]
    theta2 = np.sum(phi * phi, axis=-1)
    rx, px = hat(rho), hat(phi)
    pxrx, rxpx = px @ rx, rx @ px
    pxrxpx = pxrx @ px
    c1 = so3.coef_c(theta2)[..., None, None]
    c2 = _coef_q2(theta2)[..., None, None]
    c3 = _coef_q3(theta2)[..., None, None]
    return (
        0.5 * rx
        + c1 * (pxrx + rxpx + pxrxpx)
        + c2 * (px @ pxrx + rxpx @ px - 3.0 * pxrxpx)
        + c3 * (pxrxpx @ px + px @ pxrxpx)
    )


def se3_left_jacobian(xi):
    """(..., 6) -> (..., 6, 6) left Jacobian of SE(3)."""
    xi = _as_xi(xi)
    Jl = so3.left_jacobian(xi[..., 3:])
    out = np.zeros(xi.shape[:-1] + (6, 6), dtype=xi.dtype)
    out[..., :3, :3] = Jl
    out[..., 3:, 3:] = Jl
    out[..., :3, 3:] = _q_matrix(xi)
    return out


def se3_left_jacobian_inv(xi):
    """Inverse of the SE(3) left Jacobian: [[Jl^-1, -Jl^-1 Q Jl^-1], [0, Jl^-1]]."""
    xi = _as_xi(xi)
    Jli = so3.left_jacobian_inv(xi[..., 3:])
    out = np.zeros(xi.shape[:-1] + (6, 6), dtype=xi.dtype)
    out[..., :3, :3] = Jli
    out[..., 3:, 3:] = Jli
    out[..., :3, 3:] = -Jli @ _q_matrix(xi) @ Jli
    return out


def se3_right_jacobian(xi):
    """J_r(xi) = J_l(-xi)."""
    return se3_left_jacobian(-_as_xi(xi))


def se3_right_jacobian_inv(xi):
    """J_r(xi)^{-1} = J_l(-xi)^{-1}."""
    return se3_left_jacobian_inv(-_as_xi(xi))


def se3_interpolate(pose_start, pose_end, u):
    """Geodesic T(u) = T_s exp(u log(T_s^{-1} T_e)) (docs/method.md §4, Eq. 9).

    pose_start, pose_end: (4, 4); u: scalar or (M,) -> (4, 4) or (M, 4, 4).
    u = 0 gives T_s, u = 1 gives T_e (up to rounding), u = 0.5 the geodesic midpoint.
    """
    Ts, Te = _as_pose(pose_start, "pose_start"), _as_pose(pose_end, "pose_end")
    u = np.asarray(u, dtype=Ts.dtype)
    delta = se3_log(se3_inverse(Ts) @ Te)
    return Ts @ se3_exp(u[..., None] * delta)


def matrix_grad_to_left_tangent(T, v_T):
    """Gradient w.r.t. a left perturbation delta of T (T -> exp(delta) T) from the entrywise 4x4 gradient.

    With dT = delta^ T: dL = <v_T, delta^ T> = <v_T T^T, delta^>, hence with M = v_T T^T,
    v_rho = M[:3, 3] and v_phi = (M21 - M12, M02 - M20, M10 - M01). Batched over leading axes.
    """
    T, v_T = _as_pose(T), _as_pose(v_T, "v_T")
    M = v_T @ np.swapaxes(T, -1, -2)
    v_rho = M[..., :3, 3]
    v_phi = np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)
    return np.concatenate([v_rho, v_phi], axis=-1)


def check_rigid(T, name="T", tol=RIGID_TOL):
    """Raise ValueError naming ``name`` unless T is a finite (..., 4, 4) rigid transform."""
    T = np.asarray(T)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must have shape (..., 4, 4); got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name} contains NaN or inf; poses must be finite")
    R = T[..., :3, :3].astype(np.float64)
    err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(initial=0.0)
    det = np.linalg.det(R)
    if err > tol or np.any(np.abs(det - 1.0) > tol):
        raise ValueError(
            f"{name} is not rigid: max |R^T R - I| = {err:.3g}, det(R) in "
            f"[{np.min(det):.6g}, {np.max(det):.6g}] (tolerance {tol:g}); pass a rotation+translation "
            "(re-orthonormalise with d2gs_np.geometry.so3.so3_orthonormalize if it has drifted)"
        )
    bottom = T[..., 3, :].astype(np.float64)
    if np.abs(bottom - np.array([0.0, 0.0, 0.0, 1.0])).max(initial=0.0) > tol:
        raise ValueError(f"{name} must have bottom row (0, 0, 0, 1); got {bottom.reshape(-1, 4)[0]}")


def rigid_deviation(T):
    """(..., 4, 4) -> (...,) how far each T is from rigid: the largest of max |R^T R - I|, max |R R^T - I|
    (the inverse's R^T R: the loader inverts its poses), |det R - 1| and the bottom row's distance from
    (0, 0, 0, 1) (max abs entry)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    ortho = np.maximum(np.abs(Rt @ R - np.eye(3)).max(axis=(-2, -1)), np.abs(R @ Rt - np.eye(3)).max(axis=(-2, -1)))
    det = np.abs(np.linalg.det(R) - 1.0)
    bottom = np.abs(T[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=-1)
    return np.maximum(np.maximum(ortho, det), bottom)


def nearest_rigid(T, name="T", tol=POSE_ROUNDING_TOL):
    """A pose that is rigid up to rounding (e.g. a JSON export at 6 decimals) -> (T', deviation).

    T: (..., 4, 4) finite. deviation: (...,) ``rigid_deviation(T)``. Poses within RIGID_TOL come back
    unchanged (bitwise); those within ``tol`` get the nearest rotation (``so3.so3_orthonormalize``,
    the polar factor) and the bottom row (0, 0, 0, 1), the translation kept. Beyond ``tol``:
    ValueError naming ``name`` and what the matrix is instead (a reflection, a scale or shear).
    ``check_rigid`` stays the strict test for poses the code computes itself.
    """
    T = np.asarray(T)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must have shape (..., 4, 4); got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name} contains NaN or inf; poses must be finite")
    T = T.astype(np.float64)
    dev = rigid_deviation(T)
    R = T[..., :3, :3]
    det = np.linalg.det(R)
    if np.any(det <= 0.0):
        raise ValueError(
            f"{name} is not rigid: det(R) = {np.min(det):.6g} <= 0, a reflection (a left-handed frame) or a "
            "singular matrix, not a rotation; flip the sign of one axis to make the frame right-handed")
    if np.any(dev > tol):
        sv = np.linalg.svd(R, compute_uv=False)
        bottom = T[..., 3, :].reshape(-1, 4)[int(np.argmax(dev.reshape(-1)))]
        what = (f"bottom row {bottom.tolist()} instead of (0, 0, 0, 1)" if np.abs(bottom - [0, 0, 0, 1]).max() > tol
                else f"the singular values of R are in [{sv.min():.6g}, {sv.max():.6g}] instead of 1: a scale or shear")
        raise ValueError(
            f"{name} is not rigid: {what} (deviation {dev.max():.3g}, beyond the {tol:g} that rounding to 4 or "
            "more decimals stays within); pass a rotation+translation")
    out = T.copy()
    fix = dev > RIGID_TOL
    if np.any(fix):
        out[fix, :3, :3] = so3.so3_orthonormalize(R[fix])
        out[fix, 3, :] = (0.0, 0.0, 0.0, 1.0)
    return out, dev
