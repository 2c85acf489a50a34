"""Reference Gaussian splatting renderer: plain NumPy forward and hand-derived backward.

``render_fwd`` / ``render_bwd`` implement the renderer contract (docs/conventions.md §10) with the
conventions of docs/conventions.md §1-8 (gsplat 1.5.3's reference renderer). This is the obvious version
that the Numba fast path (``d2gs_np.render``) is tested against: projection of all Gaussians at
once (``project.py``), then a dense front-to-back loop over the Gaussians, each evaluated on all
pixels (``rasterize.py``). Meant for tiny scenes (memory O(N H W)).

Choices the contract leaves open, fixed here:
- Culling uses the clamped determinant (``det = max(det, 1e-10) > 0``), as gsplat's
  ``_fully_fused_projection`` does; with eps2d > 0 this never culls.
- "means2d" and "conics" are 0 for culled Gaussians (radii == 0); "depths" is the camera z of
  every Gaussian, culled or not.
- Front-to-back order: stable argsort of camera z cast to float32, over the non-culled Gaussians.
- "num_intersections" counts the (Gaussian, pixel) evaluations made before each pixel stopped
  (not tile-Gaussian pairs).
- Gradient of expected_depth: D / max(alpha, 1e-10) passes gradient to alpha when
  alpha >= 1e-10 (torch's clamp_min convention), none below.
- At the Jacobian clamp's boundaries (x/z exactly at a limit) the gradient is that of the
  unclamped side (torch's clamp convention).
- cam_T_world need not be rigid: the renderer uses its top 3x4 block as given (so the entrywise
  gradient can be checked by finite differences); its bottom row is ignored.
- Scales must be >= 0 and opacities in [0, 1] (ValueError otherwise); quaternions need a norm
  above QUAT_NORM_MIN.
"""
from __future__ import annotations

import numbers

import numpy as np

from d2gs_np import constants as C
from d2gs_np.reference.project import project_bwd, project_fwd
from d2gs_np.reference.rasterize import rasterize_bwd, rasterize_fwd
from d2gs_np.render.config import RenderConfig

_FLOAT_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))


def _as_float(name, x, shape, dtype=None):
    """Validate a float array: dtype float32/float64 (== dtype if given), shape, all finite.

    ``shape`` uses None for a free dimension.
    """
    arr = np.asarray(x)
    if arr.dtype not in _FLOAT_DTYPES:
        raise TypeError(f"{name} must be a float64 (or float32) array; got dtype {arr.dtype}. "
                        f"Convert it with np.asarray({name}, dtype=np.float64)")
    if dtype is not None and arr.dtype != dtype:
        raise TypeError(f"{name} has dtype {arr.dtype} but means has dtype {dtype}; pass every float "
                        f"array in one dtype (all float64, or all float32)")
    expected = "(" + ", ".join("N" if d is None else str(d) for d in shape) + ")"
    if arr.ndim != len(shape) or any(d is not None and d != e for d, e in zip(shape, arr.shape)):
        raise ValueError(f"{name} must have shape {expected}; got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf at index {tuple(np.argwhere(~np.isfinite(arr))[0])}; "
                         f"every entry must be finite")
    return arr


def _as_size(name, x):
    if isinstance(x, bool) or not isinstance(x, numbers.Integral):
        raise TypeError(f"{name} must be an int; got {type(x).__name__} {x!r}")
    if x < 1:
        raise ValueError(f"{name} must be >= 1; got {x}")
    return int(x)


def _validate(means, quats, scales, opacities, colors, cam_T_world, K, width, height, background, config):
    means = _as_float("means", means, (None, 3))
    dtype = means.dtype
    n = means.shape[0]
    quats = _as_float("quats", quats, (n, 4), dtype)
    scales = _as_float("scales", scales, (n, 3), dtype)
    opacities = _as_float("opacities", opacities, (n,), dtype)
    colors = _as_float("colors", colors, (n, 3), dtype)
    cam_T_world = _as_float("cam_T_world", cam_T_world, (4, 4), dtype)
    K = _as_float("K", K, (3, 3), dtype)
    background = _as_float("background", background, (3,), dtype)
    width = _as_size("width", width)
    height = _as_size("height", height)
    if config is None:
        config = RenderConfig()
    elif not isinstance(config, RenderConfig):
        raise TypeError(f"config must be a d2gs_np.render.config.RenderConfig or None; got {type(config).__name__}")

    if K[0, 1] != 0:
        raise ValueError(f"K must have zero skew (K[0, 1] == 0); got K[0, 1] = {K[0, 1]}. "
                         f"The renderer's Jacobian ignores skew (docs/conventions.md §2)")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"K must have positive focal lengths; got fx = {K[0, 0]}, fy = {K[1, 1]}")
    if n:
        qn = np.linalg.norm(quats, axis=1)
        if np.any(qn < C.QUAT_NORM_MIN):
            i = int(np.argmin(qn))
            raise ValueError(f"quats must have non-zero norm (>= {C.QUAT_NORM_MIN}); quats[{i}] has norm {qn[i]}")
        if np.any(scales < 0):
            i = tuple(np.argwhere(scales < 0)[0])
            raise ValueError(f"scales are linear and must be >= 0; got scales{list(i)} = {scales[i]}. "
                             f"Pass exp(log_scales)")
        if np.any((opacities < 0) | (opacities > 1)):
            i = int(np.argwhere((opacities < 0) | (opacities > 1))[0, 0])
            raise ValueError(f"opacities must lie in [0, 1] (post-sigmoid); got opacities[{i}] = {opacities[i]}. "
                             f"Pass sigmoid(opacity_logits)")
    return means, quats, scales, opacities, colors, cam_T_world, K, width, height, background, config


def render_fwd(means, quats, scales, opacities, colors, cam_T_world, K, width, height, background,
               config=None):
    """Render N Gaussians seen by a pinhole camera.

    means (N,3) world positions; quats (N,4) raw wxyz (normalised inside); scales (N,3) linear;
    opacities (N,) in [0,1]; colors (N,3) RGB, not clamped; cam_T_world (4,4) world->camera,
    OpenCV axes (bottom row ignored); K (3,3) pinhole with K[0,1] == 0; width, height ints >= 1;
    background (3,); config: RenderConfig or None (defaults).
    All float arrays float64, or all float32 (then every output stays float32).

    Returns (out, saved). out: "image" (H,W,3) = C + T_final background; "alpha" (H,W) =
    1 - T_final; "depth" (H,W) = sum_i w_i z_i; "expected_depth" (H,W) = depth / max(alpha, 1e-10);
    "radii" (N,2) int32 (0 if culled); "means2d" (N,2) (u, v); "depths" (N,) camera z;
    "conics" (N,3) (a, b, c); "num_intersections" int (evaluated (Gaussian, pixel) pairs).
    saved: a dict for ``render_bwd`` (keys "proj", "raster", "order", "config", ... ; read by
    tests/render_fixtures.py, otherwise opaque).
    """
    (means, quats, scales, opacities, colors, cam_T_world, K, width, height, background,
     config) = _validate(means, quats, scales, opacities, colors, cam_T_world, K, width, height,
                         background, config)
    dtype = means.dtype

    proj, proj_saved = project_fwd(means, quats, scales, opacities, cam_T_world, K, width, height, config)

    # Front to back by camera z cast to float32; ties by Gaussian index (stable sort).
    vis_idx = np.flatnonzero(proj["visible"])
    order = vis_idx[np.argsort(proj["depths"][vis_idx].astype(np.float32), kind="stable")]

    ras, ras_saved = rasterize_fwd(proj["means2d"], proj["conics"], colors, proj["opacities"],
                                   proj["depths"], order, width, height, background)
    out = {
        "image": ras["image"],
        "alpha": ras["alpha"],
        "depth": ras["depth"],
        "expected_depth": ras["expected_depth"],
        "radii": proj["radii"],
        "means2d": proj["means2d"],
        "depths": proj["depths"],
        "conics": proj["conics"],
        "num_intersections": ras["num_intersections"],
    }
    for key, val in out.items():  # internal invariant: float32 in, float32 out
        if isinstance(val, np.ndarray) and key != "radii":
            assert val.dtype == dtype, (key, val.dtype)
    saved = {
        "config": config,
        "dtype": dtype,
        "width": width,
        "height": height,
        "n": means.shape[0],
        "order": ras_saved["order"],
        "proj": proj_saved,
        "raster": ras_saved,
    }
    return out, saved


def _as_cotangent(name, x, shape, dtype):
    if x is None:
        return np.zeros(shape, dtype=dtype)
    arr = np.asarray(x)
    if arr.dtype != dtype:
        raise TypeError(f"{name} must have the render's dtype {dtype}; got {arr.dtype}")
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}; got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; cotangents must be finite")
    return arr


def render_bwd(saved, v_image, v_alpha=None, v_depth=None, v_expected_depth=None):
    """Gradients of a scalar loss given its cotangents w.r.t. the outputs of ``render_fwd``.

    v_image (H,W,3); v_alpha, v_depth, v_expected_depth (H,W) or None (= zero), in the render's
    dtype. Returns dict: "means" (N,3), "quats" (N,4) (w.r.t. the raw quats: orthogonal to q),
    "scales" (N,3), "opacities" (N,), "colors" (N,3), "cam_T_world" (4,4) entrywise with the
    bottom row zero, "background" (3,), "means2d" (N,2) dL/d(projected mean), "means2d_abs" (N,2) the
    per-axis sums over pixels of |each pixel's term of it| (gsplat's absgrad).
    The discrete choices (culling, order, 1/255 skip, 1e-4 stop) are held fixed; no gradient
    through the 0.999 clamp once o exp(-sigma) > 0.999, nor through the det clamp.
    """
    if not isinstance(saved, dict) or "raster" not in saved:
        raise TypeError("saved must be the second value returned by d2gs_np.reference.render_fwd")
    dtype, H, W = saved["dtype"], saved["height"], saved["width"]
    v_image = _as_cotangent("v_image", v_image, (H, W, 3), dtype)
    v_alpha = _as_cotangent("v_alpha", v_alpha, (H, W), dtype)
    v_depth = _as_cotangent("v_depth", v_depth, (H, W), dtype)
    v_expected_depth = _as_cotangent("v_expected_depth", v_expected_depth, (H, W), dtype)

    g_ras = rasterize_bwd(saved["raster"], v_image, v_alpha, v_depth, v_expected_depth)
    g_proj = project_bwd(saved["proj"], g_ras["means2d"], g_ras["conics"], g_ras["opacities"], g_ras["depths"])
    grads = {
        "means": g_proj["means"],
        "quats": g_proj["quats"],
        "scales": g_proj["scales"],
        "opacities": g_proj["opacities"],
        "colors": g_ras["colors"],
        "cam_T_world": g_proj["cam_T_world"],
        "background": g_ras["background"],
        "means2d": g_ras["means2d"],
        "means2d_abs": g_ras["means2d_abs"],
    }
    for key, val in grads.items():  # internal invariant: float32 in, float32 out
        assert val.dtype == dtype, (key, val.dtype)
    return grads
