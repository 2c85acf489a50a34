"""L_var: the spread of the Gaussians' depths along each pixel's ray (docs/method.md §6).

A surface seen through a veil of faint Gaussians in front of it (or with layers behind it) renders
each training frame right and puts its expected depth off the surface, which moves it in a novel
view (#40). Mip-NeRF 360's distortion loss and 2DGS's depth distortion pull the weights of a ray
together; this is the same idea in the form a Gaussian splatter gets for the price of one more
render: the blending weights w_i of a pixel (sum a = alpha) give

    D = sum_i w_i z_i,   D2 = sum_i w_i z_i^2,   q = a D2 / D^2 - 1 = Var_w(z) / E_w(z)^2

with E_w, Var_w under the normalised weights w_i / a, z_i the camera depth of Gaussian i's centre.
q is the squared coefficient of variation of the depths along the ray: 0 for one layer, free of
the scene's units, >= 0 by Cauchy-Schwarz. L_var is its mean over the pixels whose alpha is at least
``alpha_min`` and whose D is above ``min_depth`` (and where the loss mask is on); fewer than one
such pixel: 0 and no gradient. D and D2 come from a render whose colours are the features
(z_i, z_i^2, 0) over a black background (``z_features_fwd``), so the splatter's own backward
carries the gradient to every Gaussian's mean, scale, rotation and opacity.

Derivatives: dq/da = D2 / D^2, dq/dD2 = a / D^2, dq/dD = -2 a D2 / D^3. Pure functions on plain
arrays, float64.
"""
from __future__ import annotations

import numpy as np

__all__ = ["depth_variance_fwd", "depth_variance_bwd", "z_features_fwd", "z_features_bwd"]


def _check_map(name, x, shape):
    x = np.asarray(x)
    if x.shape != shape:
        raise ValueError(f"{name} must have shape {shape}; got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf; every entry must be finite")
    return x.astype(np.float64, copy=False)


def depth_variance_fwd(depth, depth2, alpha, alpha_min=0.5, min_depth=1e-6, mask=None):
    """(L_var, saved) from the weighted depth sums D (h, w), D2 (h, w) and alpha (h, w); ``mask``
    (h, w) bool / 0-1 restricts the pixels (None: all)."""
    D = np.asarray(depth)
    if D.ndim != 2:
        raise ValueError(f"depth must be an (h, w) map; got shape {D.shape}")
    D = _check_map("depth", D, D.shape)
    D2 = _check_map("depth2", depth2, D.shape)
    a = _check_map("alpha", alpha, D.shape)
    valid = (a >= alpha_min) & (D > min_depth)
    if mask is not None:
        valid &= _check_map("mask", mask, D.shape) > 0
    n = int(valid.sum())
    if n == 0:
        return 0.0, None
    Dv, D2v, av = D[valid], D2[valid], a[valid]
    q = av * D2v / (Dv * Dv) - 1.0
    return float(q.mean()), (valid, Dv, D2v, av, n)


def depth_variance_bwd(saved, weight=1.0):
    """(v_depth, v_depth2, v_alpha), each (h, w), of weight x L_var; None when no pixel was valid."""
    if saved is None:
        return None
    valid, D, D2, a, n = saved
    c = weight / n
    out = [np.zeros(valid.shape) for _ in range(3)]
    out[0][valid] = -2.0 * c * a * D2 / D ** 3
    out[1][valid] = c * a / D ** 2
    out[2][valid] = c * D2 / D ** 2
    return tuple(out)


def z_features_fwd(means, cam_T_world):
    """Colours (N, 3) = (z, z^2, 0) of Gaussians at ``means`` (N, 3), z their depth in the camera
    ``cam_T_world`` (4, 4); and z (N,) for the backward."""
    T = np.asarray(cam_T_world, dtype=np.float64)
    z = np.asarray(means) @ T[2, :3] + T[2, 3]
    feats = np.zeros((len(z), 3), dtype=np.asarray(means).dtype)
    feats[:, 0], feats[:, 1] = z, z * z
    return feats, z


def z_features_bwd(v_features, z, cam_T_world):
    """v_means (N, 3) from the cotangents of the features (N, 3): dz / d mean = row 2 of R."""
    T = np.asarray(cam_T_world, dtype=np.float64)
    v_z = v_features[:, 0] + 2.0 * z * v_features[:, 1]
    return v_z[:, None] * T[2, :3][None, :]
