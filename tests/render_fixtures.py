"""Shared helpers for the renderer tests (reference and fast path).

Scenes are plain dicts whose keys are the argument names of ``render_fwd``, so a scene renders
with ``render_fwd(**scene, config=cfg)``.

Discontinuities. The rendered outputs are only piecewise smooth in the inputs (docs/conventions.md
§8): a (Gaussian, pixel) evaluation switches on or off when its alpha crosses 1/255, the
compositing stops when ``T * (1 - alpha)`` crosses 1e-4, the gradient through the 0.999 clamp
switches off when ``o * exp(-sigma)`` crosses 0.999, a Gaussian is culled at the near plane,
the front-to-back order changes when two depths cross, and the Jacobian's x/z, y/z clamp has a
kink. ``threshold_margins`` reports, for each of these, the smallest *relative* distance of any
evaluation to its threshold; finite-difference tests use scenes whose margin is large compared
with the relative change a step of size h can cause (``safe_random_scene``).
"""
from __future__ import annotations

import numpy as np


# The scene builders and threshold margins live in the package, shared with the reference-check
# kit (d2gs_np/refcheck/scenes.py); re-exported here under their old names.
from d2gs_np.refcheck.scenes import (  # noqa: E402,F401
    _hat,
    _so3_exp,
    camera_scene,
    cast_scene,
    copy_scene,
    random_rotation,
    random_scene,
    safe_random_scene,
    threshold_margin,
    threshold_margins,
)

# ---------------------------------------------------------------------------------------------
# Losses and finite differences
# ---------------------------------------------------------------------------------------------

OUTPUT_KEYS = ("image", "alpha", "depth", "expected_depth")


def random_cotangents(rng, width, height, dtype=np.float64):
    """Random loss weights: dict(v_image (H,W,3), v_alpha, v_depth, v_expected_depth (H,W))."""
    return dict(
        v_image=rng.normal(size=(height, width, 3)).astype(dtype),
        v_alpha=rng.normal(size=(height, width)).astype(dtype),
        v_depth=rng.normal(size=(height, width)).astype(dtype),
        v_expected_depth=rng.normal(size=(height, width)).astype(dtype),
    )


def weighted_loss(out, cot):
    """L = sum(v_image*image) + sum(v_alpha*alpha) + sum(v_depth*depth) + sum(v_ed*expected_depth).

    Its gradient is ``render_bwd(saved, **cot)``. Summed in float64.
    """
    total = 0.0
    for key in OUTPUT_KEYS:
        total += float(np.sum(np.asarray(out[key], np.float64) * np.asarray(cot["v_" + key], np.float64)))
    return total


def central_fd(f, x, h):
    """Central finite-difference gradient of the scalar function ``f`` at array ``x``.

    Returns an array shaped like ``x``: entry k is (f(x + h e_k) - f(x - h e_k)) / (2h). ``x`` is
    not modified.
    """
    x = np.asarray(x)
    grad = np.zeros(x.shape, dtype=np.float64)
    for k in np.ndindex(*x.shape):
        xp = x.copy()
        xm = x.copy()
        xp[k] += h
        xm[k] -= h
        grad[k] = (f(xp) - f(xm)) / (2.0 * h)
    return grad


def wavy_depth(shape, seed=0, lo=1.5, hi=6.0):
    """A smooth (h, w) depth map spanning about [lo, hi] with a little noise: the depth losses' test input."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    return lo + (hi - lo) * (0.5 + 0.4 * np.sin(xx / 2.3 + seed) * np.cos(yy / 3.1)) + 0.05 * rng.standard_normal(shape)


def with_holes(prior, alpha, seed=1):
    """Copies of a depth prior and an alpha map with NaN in a tenth of the prior's pixels and alpha
    0.3 (below the depth losses' 0.5) in another tenth: pixels the depth losses must ignore."""
    rng = np.random.default_rng(seed)
    prior, alpha = prior.copy(), alpha.copy()
    prior[rng.random(prior.shape) < 0.1] = np.nan
    alpha[rng.random(alpha.shape) < 0.1] = 0.3
    return prior, alpha


def central_fd_scalar(g, h):
    """(g(h) - g(-h)) / (2h) for a scalar function g of a scalar step."""
    return (g(h) - g(-h)) / (2.0 * h)


# ---------------------------------------------------------------------------------------------
# Pose perturbations on SE(3)
# ---------------------------------------------------------------------------------------------


def left_perturb(T, i, h):
    """exp(h e_i) @ T: a left perturbation of the 4x4 pose T along tangent axis i of (rho, phi)."""
    xi = np.zeros(6)
    xi[i] = h
    return _se3_exp(xi) @ np.asarray(T, dtype=np.float64)


def left_tangent_from_matrix_grad(T, G):
    """Tangent gradient (6,) (rho, phi) of a left perturbation from the 4x4 entrywise gradient G.

    For T(delta) = exp(delta^) T: M = G @ T.T; v_rho = M[:3, 3];
    v_phi = (M[2,1]-M[1,2], M[0,2]-M[2,0], M[1,0]-M[0,1]) (docs/conventions.md §8).
    """
    M = np.asarray(G, np.float64) @ np.asarray(T, np.float64).T
    return np.array([M[0, 3], M[1, 3], M[2, 3], M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])


def _se3_exp_local(xi):
    """exp of xi = (rho, phi) in se(3) -> (4, 4), local fallback."""
    xi = np.asarray(xi, dtype=np.float64)
    rho, phi = xi[:3], xi[3:]
    theta = np.linalg.norm(phi)
    W = _hat(phi)
    if theta < 1e-8:
        V = np.eye(3) + 0.5 * W + W @ W / 6.0
    else:
        V = np.eye(3) + (1.0 - np.cos(theta)) / theta**2 * W + (theta - np.sin(theta)) / theta**3 * W @ W
    T = np.eye(4)
    T[:3, :3] = _so3_exp(phi)
    T[:3, 3] = V @ rho
    return T


def _se3_exp(xi):
    try:  # the library's version once it exists
        from d2gs_np.geometry.se3 import se3_exp
    except ImportError:
        return _se3_exp_local(xi)
    return np.asarray(se3_exp(np.asarray(xi, dtype=np.float64)))
