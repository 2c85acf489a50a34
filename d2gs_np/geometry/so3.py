"""SO(3): exponential and logarithm maps, Jacobians, re-orthonormalisation.

Conventions
- Rotation vectors phi (..., 3), rotation matrices R (..., 3, 3); every
  function is vectorised over leading batch axes.
- ``so3_exp(phi) = exp(hat(phi))``; ``so3_log`` returns theta in [0, pi].
- Perturbations act on the LEFT: ``exp(phi + d) ~= exp(J_l(phi) d) exp(phi)``
  and ``exp(phi + d) ~= exp(phi) exp(J_r(phi) d)`` with ``J_r(phi) = J_l(-phi)``.

Numerics
- Coefficient functions of theta are evaluated from Taylor series when
  theta^2 < SERIES_ANGLE2 and from closed forms otherwise (the "two-step where":
  the closed form sees a safe dummy angle where the series is used).
- so3_log uses theta = atan2(|s|, c) with s = vee(R - R^T)/2 = sin(theta) a and
  c = (tr R - 1)/2, which is accurate at all angles (arccos is not near 0 and pi);
  near pi (c < LOG_SYMMETRIC_BRANCH_COS) the axis comes from the symmetric part.
"""
from __future__ import annotations

import math

import numpy as np

from d2gs_np.constants import LOG_SYMMETRIC_BRANCH_COS, SERIES_ANGLE2

_NUM_SERIES_TERMS = 8  # truncation of every series below is < 1e-19 for theta^2 < 0.25


def _series(theta2, coeffs):
    """Evaluate sum_k coeffs[k] * theta2**k by Horner's rule."""
    out = np.full_like(theta2, coeffs[-1])
    for c in coeffs[-2::-1]:
        out = out * theta2 + c
    return out


# Taylor coefficients in theta^2 (derivations in the docstrings of the users).
_A_COEFFS = [(-1) ** k / math.factorial(2 * k + 1) for k in range(_NUM_SERIES_TERMS)]  # sin t / t
_B_COEFFS = [(-1) ** k / math.factorial(2 * k + 2) for k in range(_NUM_SERIES_TERMS)]  # (1-cos t)/t^2
_C_COEFFS = [(-1) ** k / math.factorial(2 * k + 3) for k in range(_NUM_SERIES_TERMS)]  # (t-sin t)/t^3
# (1 - (t/2) cot(t/2)) / t^2 = sum_k |B_{2k+2}| t^{2k} / (2k+2)!  (Bernoulli numbers)
_BERNOULLI_ABS = [1 / 6, 1 / 30, 1 / 42, 1 / 30, 5 / 66, 691 / 2730, 7 / 6, 3617 / 510]
_D_COEFFS = [_BERNOULLI_ABS[k] / math.factorial(2 * k + 2) for k in range(_NUM_SERIES_TERMS)]


def _split(theta2):
    small = theta2 < SERIES_ANGLE2
    safe2 = np.where(small, 1.0, theta2)  # dummy angle keeps the closed forms finite
    return small, safe2, np.sqrt(safe2)


def coef_a(theta2):
    """sin(theta) / theta."""
    small, t2, t = _split(theta2)
    return np.where(small, _series(theta2, _A_COEFFS), np.sin(t) / t)


def coef_b(theta2):
    """(1 - cos(theta)) / theta^2, via the half angle to avoid cancellation."""
    small, t2, t = _split(theta2)
    h = np.sin(0.5 * t) / t
    return np.where(small, _series(theta2, _B_COEFFS), 2.0 * h * h)


def coef_c(theta2):
    """(theta - sin(theta)) / theta^3."""
    small, t2, t = _split(theta2)
    return np.where(small, _series(theta2, _C_COEFFS), (t - np.sin(t)) / (t2 * t))


def coef_d(theta2):
    """(1 - (theta/2) cot(theta/2)) / theta^2, the phi^2 coefficient of J_l^{-1}."""
    small, t2, t = _split(theta2)
    half = 0.5 * t
    direct = (1.0 - half * np.cos(half) / np.sin(half)) / t2
    return np.where(small, _series(theta2, _D_COEFFS), direct)


def hat(phi):
    """(..., 3) -> (..., 3, 3) skew-symmetric matrix with hat(a) @ b = a x b."""
    phi = np.asarray(phi)
    if phi.shape[-1:] != (3,):
        raise ValueError(f"hat expects vectors of shape (..., 3); got {phi.shape}")
    out = np.zeros(phi.shape + (3,), dtype=float_dtype(phi))
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    out[..., 0, 1] = -z
    out[..., 0, 2] = y
    out[..., 1, 0] = z
    out[..., 1, 2] = -x
    out[..., 2, 0] = -y
    out[..., 2, 1] = x
    return out


def vee(W):
    """(..., 3, 3) -> (..., 3): inverse of hat, using the antisymmetric part of W."""
    W = np.asarray(W)
    if W.shape[-2:] != (3, 3):
        raise ValueError(f"vee expects matrices of shape (..., 3, 3); got {W.shape}")
    return 0.5 * np.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], axis=-1
    )


def float_dtype(x):
    """float32 stays float32; everything else computes in float64."""
    return np.float32 if np.asarray(x).dtype == np.float32 else np.float64


def _as_vec3(phi, name):
    phi = np.asarray(phi, dtype=float_dtype(phi))
    if phi.shape[-1:] != (3,):
        raise ValueError(f"{name} must have shape (..., 3); got {phi.shape}")
    return phi


def so3_exp(phi):
    """Rodrigues: (..., 3) rotation vectors -> (..., 3, 3) rotation matrices."""
    phi = _as_vec3(phi, "phi")
    theta2 = np.sum(phi * phi, axis=-1)
    K = hat(phi)
    K2 = K @ K
    a = coef_a(theta2)[..., None, None]
    b = coef_b(theta2)[..., None, None]
    return np.eye(3, dtype=phi.dtype) + a * K + b * K2


def so3_log(R):
    """(..., 3, 3) rotations -> (..., 3) rotation vectors with |phi| in [0, pi].

    At theta = pi exactly both +pi a and -pi a are logarithms; the sign is
    chosen to agree with the (tiny) skew part when it is non-zero, else the
    largest axis component is made positive.
    """
    R = np.asarray(R, dtype=float_dtype(R))
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3); got {R.shape}")
    s = vee(R)  # sin(theta) * axis
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    sin_t = np.linalg.norm(s, axis=-1)
    theta = np.arctan2(sin_t, c)

    # Generic branch: phi = theta / sin(theta) * s. The factor is 1/coef_a(theta^2).
    generic = s / coef_a(theta * theta)[..., None]

    # Near-pi branch: (R + R^T)/2 - c I = (1 - c) a a^T; pick the best-conditioned column.
    sym = 0.5 * (R + np.swapaxes(R, -1, -2))
    one_minus_c = np.maximum(1.0 - c, 1.0)  # only used where c < -0.5, so 1 - c > 1.5
    aat = (sym - c[..., None, None] * np.eye(3, dtype=R.dtype)) / one_minus_c[..., None, None]
    diag = np.diagonal(aat, axis1=-2, axis2=-1)
    k = np.argmax(diag, axis=-1)
    col = np.take_along_axis(aat, k[..., None, None], axis=-1)[..., 0]
    axis = col / np.sqrt(np.maximum(np.take_along_axis(diag, k[..., None], axis=-1), 1e-300))
    # Orient the axis along the skew part; when that vanishes (theta = pi) keep +a_k.
    dot = np.sum(axis * s, axis=-1)
    axis = np.where((dot < 0.0)[..., None], -axis, axis)
    near_pi = theta[..., None] * axis

    use_sym = (c < LOG_SYMMETRIC_BRANCH_COS)[..., None]
    return np.where(use_sym, near_pi, generic)


def left_jacobian(phi):
    """J_l(phi) = I + B hat(phi) + C hat(phi)^2, (..., 3) -> (..., 3, 3)."""
    phi = _as_vec3(phi, "phi")
    theta2 = np.sum(phi * phi, axis=-1)
    K = hat(phi)
    return np.eye(3, dtype=phi.dtype) + coef_b(theta2)[..., None, None] * K + coef_c(theta2)[..., None, None] * (K @ K)


def left_jacobian_inv(phi):
    """J_l(phi)^{-1} = I - hat(phi)/2 + D hat(phi)^2, valid for |phi| < 2 pi."""
    phi = _as_vec3(phi, "phi")
    theta2 = np.sum(phi * phi, axis=-1)
    K = hat(phi)
    return np.eye(3, dtype=phi.dtype) - 0.5 * K + coef_d(theta2)[..., None, None] * (K @ K)


def right_jacobian(phi):
    """J_r(phi) = J_l(-phi) = J_l(phi)^T."""
    return left_jacobian(-_as_vec3(phi, "phi"))


def right_jacobian_inv(phi):
    """J_r(phi)^{-1} = J_l(-phi)^{-1}."""
    return left_jacobian_inv(-_as_vec3(phi, "phi"))


def so3_orthonormalize(R):
    """Nearest rotation (Frobenius) to a drifted (..., 3, 3) matrix, by SVD with det fixed to +1."""
    R = np.asarray(R)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3); got {R.shape}")
    U, _, Vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0.0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt
