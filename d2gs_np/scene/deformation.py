"""Dual-Domain Deformation Model (DDDM) of the dynamic Gaussians (docs/method.md §2).

Each dynamic Gaussian's position, rotation and colour follow

    A(t) = A0 + D(t),   D(t) = sum_{n=1..P} a_n t^n + sum_{l=1..L} (f_sin,l sin(l w t) + f_cos,l cos(l w t))

(the n = 0 polynomial term would duplicate A0 and is left out; the sin / cos labels are the
intended ones, not Eq. 4's swapped ones). Scale and opacity do not deform.

Conventions
- ``t`` is normalised time (the clip spans [0, 1]); ``t`` is *not* restricted to [0, 1] because
  sub-frame times of the blur model and the ``t + eps`` of the temporal loss step outside it.
- The coefficient axis (length K = P + 2L) of every coefficient block is ordered
  ``[a_1 .. a_P, f_sin_1 .. f_sin_L, f_cos_1 .. f_cos_L]``, so that D(t) = b(t) @ coef with the
  basis ``b(t) = [t, t^2, .., t^P, sin(w t), .., sin(L w t), cos(w t), .., cos(L w t)]``
  (``deform_basis``).
- Rotation: the residual is added to the *raw* (not necessarily unit) base quaternion, wxyz,
  and the sum is L2-normalised: q(t) = r / |r|, r = q0 + D_q(t). Outputs are unit quaternions;
  the backward includes the normalisation Jacobian (I - q q^T) / |r|. Zero coefficients give
  means and colours bitwise equal to the base and q0 / |q0|.
- Degenerate rotation: where |r| < QUAT_NORM_MIN (no direction can be recovered) the output is
  the identity quaternion (1, 0, 0, 0) and the gradient through that Gaussian's quaternion is
  zero. This keeps the forward finite and unit; it is a measure-zero event in training.
- Vectorised NumPy over Gaussians (N is thousands, K is small); the per-Gaussian loop version is
  ``d2gs_np.reference.deformation.deform``. Arrays keep their dtype (float64 or float32, all
  arguments the same); the basis is evaluated in float64 and cast to that dtype.
"""
from __future__ import annotations


import numpy as np

from d2gs_np.constants import QUAT_NORM_MIN
from d2gs_np.base.checks import check_scalar
from d2gs_np.scene.config import DeformConfig

__all__ = ["deform_basis", "deform_fwd", "deform_bwd"]


def _check_time(t, name="t"):
    return check_scalar(t, name, hint="a scalar time")


def deform_basis(t, config: DeformConfig):
    """Basis b(t) and its time derivative db/dt, both float64 arrays of shape (K,).

    b = [t, t^2, .., t^P, sin(w t), .., sin(L w t), cos(w t), .., cos(L w t)], so that the
    deformation of a coefficient block ``coef (N, K, D)`` is ``b @ coef`` (N, D).
    """
    if not isinstance(config, DeformConfig):
        raise TypeError(f"config must be a DeformConfig; got {type(config).__name__}")
    t = _check_time(t)
    P, L, w = int(config.degree), int(config.order), float(config.omega)
    n = np.arange(1, P + 1, dtype=np.float64)
    lw = w * np.arange(1, L + 1, dtype=np.float64)
    b = np.concatenate([t**n, np.sin(lw * t), np.cos(lw * t)])
    db_dt = np.concatenate([n * t ** (n - 1.0), lw * np.cos(lw * t), -lw * np.sin(lw * t)])
    return b, db_dt


def _check_block(name, x, shape, dtype=None):
    """Validate one array argument; ``shape`` uses None for free axes."""
    if not isinstance(x, np.ndarray):
        raise TypeError(f"{name} must be a numpy array; got {type(x).__name__}")
    if x.dtype not in (np.float64, np.float32):
        raise TypeError(f"{name} must be float64 or float32; got {x.dtype}")
    if dtype is not None and x.dtype != dtype:
        raise TypeError(
            f"{name} has dtype {x.dtype} but the other arguments are {dtype}; cast all arrays to one dtype"
        )
    expected = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
    if x.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, x.shape)):
        raise ValueError(f"{name} must have shape {expected}; got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf; every entry must be finite")


def deform_fwd(base_means, base_quats, base_colors, coef_means, coef_quats, coef_colors, t, config):
    """Deformed attributes of the dynamic Gaussians at time ``t``.

    base_means (N, 3), base_quats (N, 4) raw wxyz, base_colors (N, 3): A0 of each attribute.
    coef_means (N, K, 3), coef_quats (N, K, 4), coef_colors (N, K, 3): coefficients, K = P + 2L,
        ordered [a_1..a_P, f_sin_1..f_sin_L, f_cos_1..f_cos_L].
    t: real scalar, normalised time.
    config: DeformConfig.

    Returns ((means (N, 3), quats (N, 4) unit wxyz, colors (N, 3)), saved), arrays of the input
    dtype. See the module docstring for the conventions.
    """
    if not isinstance(config, DeformConfig):
        raise TypeError(f"config must be a DeformConfig; got {type(config).__name__}")
    if not isinstance(base_means, np.ndarray):
        raise TypeError(f"base_means must be a numpy array; got {type(base_means).__name__}")
    _check_block("base_means", base_means, (None, 3))
    dtype = base_means.dtype
    N, K = base_means.shape[0], config.num_coefs
    _check_block("base_quats", base_quats, (N, 4), dtype)
    _check_block("base_colors", base_colors, (N, 3), dtype)
    _check_block("coef_means", coef_means, (N, K, 3), dtype)
    _check_block("coef_quats", coef_quats, (N, K, 4), dtype)
    _check_block("coef_colors", coef_colors, (N, K, 3), dtype)
    return _deform_fwd(base_means, base_quats, base_colors, coef_means, coef_quats, coef_colors, t, config)


def _deform_fwd(base_means, base_quats, base_colors, coef_means, coef_quats, coef_colors, t, config):
    """``deform_fwd`` without validating the blocks (the caller did: ``scene.render_inputs.render_inputs_fwd``
    checks the whole parameter dict once, the trainer's step trusts a validated model)."""
    dtype = base_means.dtype
    b64, db64 = deform_basis(t, config)
    b = b64.astype(dtype)
    # D(t) = b(t) @ coef: (K,) @ (N, K, D) -> (N, D)
    means = base_means + b @ coef_means
    colors = base_colors + b @ coef_colors
    r = base_quats + b @ coef_quats  # raw rotated quaternion before normalisation
    norm = np.sqrt(np.sum(r * r, axis=1))
    degenerate = norm < QUAT_NORM_MIN
    safe_norm = np.where(degenerate, 1.0, norm).astype(dtype)  # two-step where: no 0 division
    quats = r / safe_norm[:, None]
    if np.any(degenerate):
        quats[degenerate] = np.array([1.0, 0.0, 0.0, 0.0], dtype=dtype)

    saved = dict(
        b=b,
        db_dt=db64.astype(dtype),
        quats=quats,
        safe_norm=safe_norm,
        degenerate=degenerate,
        coef_means=coef_means,
        coef_quats=coef_quats,
        coef_colors=coef_colors,
    )
    return (means, quats, colors), saved


def deform_bwd(saved, v_means, v_quats, v_colors):
    """Vector-Jacobian product of ``deform_fwd``.

    v_means (N, 3), v_quats (N, 4), v_colors (N, 3): cotangents of the outputs (None = zero).

    Returns dict(base_means (N, 3), base_quats (N, 4), base_colors (N, 3), coef_means (N, K, 3),
    coef_quats (N, K, 4), coef_colors (N, K, 3), t (scalar of the input dtype)).
    """
    quats = saved["quats"]
    dtype = quats.dtype
    N = quats.shape[0]
    for name, v, D in (("v_means", v_means, 3), ("v_quats", v_quats, 4), ("v_colors", v_colors, 3)):
        if v is not None:
            _check_block(name, v, (N, D), dtype)
    return _deform_bwd(saved, v_means, v_quats, v_colors)


def _deform_bwd(saved, v_means, v_quats, v_colors):
    """``deform_bwd`` without validating the cotangents (finite, of the forward's dtype and shape,
    or None for zero)."""
    b, db_dt, quats = saved["b"], saved["db_dt"], saved["quats"]
    dtype = quats.dtype
    N = quats.shape[0]
    v_means, v_quats, v_colors = (np.zeros((N, D), dtype=dtype) if v is None else v
                                  for v, D in ((v_means, 3), (v_quats, 4), (v_colors, 3)))

    # q = r / |r|  =>  v_r = (v_q - q (q . v_q)) / |r|; zero where the output was the identity fallback
    v_r = (v_quats - quats * np.sum(quats * v_quats, axis=1, keepdims=True)) / saved["safe_norm"][:, None]
    if np.any(saved["degenerate"]):
        v_r[saved["degenerate"]] = 0.0

    # A = A0 + b @ coef  =>  v_A0 = v_A, v_coef[n, k, :] = b[k] v_A[n, :]
    # dA/dt = db_dt @ coef  =>  v_t = sum(v_A * (db_dt @ coef))
    v_t = (
        np.sum(v_means * (db_dt @ saved["coef_means"]))
        + np.sum(v_r * (db_dt @ saved["coef_quats"]))
        + np.sum(v_colors * (db_dt @ saved["coef_colors"]))
    )
    return dict(
        base_means=v_means.copy(),
        base_quats=v_r,
        base_colors=v_colors.copy(),
        coef_means=b[None, :, None] * v_means[:, None, :],
        coef_quats=b[None, :, None] * v_r[:, None, :],
        coef_colors=b[None, :, None] * v_colors[:, None, :],
        t=dtype.type(v_t),
    )
