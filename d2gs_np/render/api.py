"""Public fast renderer: ``render_fwd`` / ``render_bwd`` (docs/conventions.md §10).

Numba, tile based like gsplat: projection (prange over Gaussians, project.py), tile
intersection lists sorted by (tile, float32 depth, Gaussian index) (binning.py), compositing with
prange over tiles (rasterize.py). Same contract and conventions as the float64 NumPy reference
``d2gs_np.reference.render_fwd/render_bwd``, which it matches to ~1e-10 relative in float64.

dtype: all float arrays float64, or all float32; a float32 call runs float32 kernels end to end
(every float constant is cast to the working dtype) and returns float32 outputs and gradients.

Backward determinism: gradients are bitwise identical run to run and for any thread count. The
per-Gaussian scatter of the compositing backward goes to a per-intersection buffer whose rows are
owned by one tile (one thread), then each Gaussian sums its own rows in a fixed order; the pose
and background gradients are fixed-order sums. No floating-point reduction depends on scheduling.

Choices the contract leaves open (documented here):
* Culled Gaussians (radii == 0) report means2d = conics = 0; ``depths`` is always camera z.
* Radii are ``min(ceil(3.33 sigma), 2**31 - 1)`` as int32 (the float value is used for culling
  and tiles, so only absurd footprints are affected by the int32 cap).
* ``saved`` keeps references to the input arrays (no copies): do not modify them in place
  between ``render_fwd`` and ``render_bwd``.
* Quaternions with norm < QUAT_NORM_MIN are rejected; opacities must lie in [0, 1]; K must
  have zero skew and positive focal lengths; scales must be >= 0 (same checks as the reference).
* Validation is done once, at the public boundary: ``_render_fwd`` / ``_render_bwd`` are the same
  functions without it, for a caller that validated its inputs itself (the trainer's step renders
  8 sub-frames per step of a model validated when it was built or loaded).
"""
from __future__ import annotations

import dataclasses
import numbers

import numpy as np

from d2gs_np import constants as C
from d2gs_np.render.config import RenderConfig
from d2gs_np.render.project import make_consts, project_bwd, project_fwd
from d2gs_np.render.binning import build_intersections
from d2gs_np.render.rasterize import rasterize_bwd, rasterize_fwd

_INT32_MAX = np.iinfo(np.int32).max


class RenderSaved:
    """State kept by :func:`render_fwd` for :func:`render_bwd` (opaque to callers).

    Attributes: inputs (dict of the input arrays), width, height, config, dtype, consts,
    proj (projection outputs), isect (intersection lists), raster (per-pixel T_final, last
    contributor, evaluation count, accumulated depth, in the rasteriser's dtype), rast (the
    rasteriser's float32 inputs with ``RenderConfig.raster_float32``, else None).
    """

    __slots__ = ("inputs", "width", "height", "config", "dtype", "consts", "proj", "isect", "raster", "rast")

    def __init__(self, inputs, width, height, config, dtype, consts, proj, isect, raster, rast=None):
        self.inputs = inputs
        self.width = width
        self.height = height
        self.config = config
        self.dtype = dtype
        self.consts = consts
        self.proj = proj
        self.isect = isect
        self.raster = raster
        # what the rasteriser ran on: (proj, colors, background, consts) in its dtype (float32
        # with RenderConfig.raster_float32), None when that is the render's own
        self.rast = rast

    @property
    def num_evaluations(self):
        """Number of (Gaussian, pixel) alpha evaluations of the forward pass (benchmarks)."""
        return int(self.raster["n_eval_tile"].sum())


# ---------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------

_FLOAT_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))


def _check_array(name, x, shape, dtype, fix_shape):
    """Type, dtype, shape and finiteness of one float array; returns it C-contiguous."""
    if not isinstance(x, np.ndarray):
        raise TypeError(f"{name} must be a numpy.ndarray of float64 or float32; got {type(x).__name__}. "
                        f"Fix: pass np.asarray({name}, dtype=np.float64)")
    if x.dtype not in _FLOAT_DTYPES:
        raise TypeError(f"{name} must have dtype float64 or float32; got {x.dtype}. "
                        f"Fix: cast with {name}.astype(np.float64)")
    if dtype is not None and x.dtype != dtype:
        raise TypeError(f"{name} has dtype {x.dtype} but means has dtype {dtype}; all float arrays must "
                        f"share one dtype. Fix: cast {name} with .astype(np.{dtype})")
    if x.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, x.shape)):
        raise ValueError(f"{name} must have shape {fix_shape}; got {tuple(x.shape)}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf values; all entries must be finite")
    return np.ascontiguousarray(x)


def _check_int(name, x):
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, numbers.Integral):
        raise TypeError(f"{name} must be an int >= 1; got {type(x).__name__} {x!r}. Fix: pass int({name})")
    if x < 1:
        raise ValueError(f"{name} must be >= 1; got {x}")
    return int(x)


def _validate_inputs(means, quats, scales, opacities, colors, cam_T_world, K, width, height, background,
                     config):
    if config is None:
        config = RenderConfig()
    elif not isinstance(config, RenderConfig):
        raise TypeError(f"config must be a d2gs_np.render.RenderConfig or None; got {type(config).__name__}")
    means = _check_array("means", means, (None, 3), None, "(N, 3)")
    dtype = means.dtype
    n = means.shape[0]
    quats = _check_array("quats", quats, (n, 4), dtype, f"(N, 4) = ({n}, 4)")
    scales = _check_array("scales", scales, (n, 3), dtype, f"(N, 3) = ({n}, 3)")
    opacities = _check_array("opacities", opacities, (n,), dtype, f"(N,) = ({n},)")
    colors = _check_array("colors", colors, (n, 3), dtype, f"(N, 3) = ({n}, 3)")
    cam_T_world = _check_array("cam_T_world", cam_T_world, (4, 4), dtype, "(4, 4)")
    K = _check_array("K", K, (3, 3), dtype, "(3, 3)")
    background = _check_array("background", background, (3,), dtype, "(3,)")
    width = _check_int("width", width)
    height = _check_int("height", height)
    if n and (np.any(opacities < 0) or np.any(opacities > 1)):
        bad = opacities[(opacities < 0) | (opacities > 1)][0]
        raise ValueError(f"opacities must lie in [0, 1] (post-sigmoid); got a value {bad}. "
                         f"Fix: pass sigmoid(opacity_logits)")
    if n and np.any(scales < 0):
        i = tuple(int(k) for k in np.argwhere(scales < 0)[0])
        raise ValueError(f"scales are linear and must be >= 0; got scales[{i[0]}, {i[1]}] = {scales[i]}. "
                         f"Fix: pass exp(log_scales)")
    if n:
        qnorm = np.sqrt(np.sum(quats.astype(np.float64) ** 2, axis=1))
        if np.any(qnorm < C.QUAT_NORM_MIN):
            i = int(np.argmin(qnorm))
            raise ValueError(f"quats must have norm >= {C.QUAT_NORM_MIN} (they are normalised inside); "
                             f"row {i} has norm {qnorm[i]:.3g}")
    if K[0, 1] != 0:
        raise ValueError(f"K must have zero skew (K[0, 1] == 0); got K[0, 1] = {K[0, 1]}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"K must have positive focal lengths; got fx = {K[0, 0]}, fy = {K[1, 1]}")
    inputs = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                  cam_T_world=cam_T_world, K=K, background=background)
    return inputs, width, height, config, dtype


def _check_cotangent(name, x, shape, dtype, fix_shape):
    if x is None:
        return np.zeros(shape, dtype)
    x = _check_array(name, x, shape, None, fix_shape)
    if x.dtype != dtype:
        raise TypeError(f"{name} has dtype {x.dtype} but the render ran in {dtype}. "
                        f"Fix: cast with {name}.astype(np.{dtype})")
    return x


# ---------------------------------------------------------------------------------------------
# Forward / backward
# ---------------------------------------------------------------------------------------------


def render_fwd(means, quats, scales, opacities, colors, cam_T_world, K, width, height, background,
               config=None):
    """Render N Gaussians with the tile-based Numba splatter.

    Args:
        means: (N, 3) world positions.  quats: (N, 4) raw wxyz (normalised inside).
        scales: (N, 3) linear scales.  opacities: (N,) in [0, 1].  colors: (N, 3) RGB (any value).
        cam_T_world: (4, 4) world->camera, OpenCV axes (bottom row ignored).
        K: (3, 3) pinhole intrinsics with zero skew.  width, height: ints >= 1.
        background: (3,).  config: RenderConfig or None (defaults).
        All float arrays float64, or all float32. N = 0 is allowed.

    Returns:
        (out, saved). out: dict with "image" (H,W,3), "alpha" (H,W) = 1 - T_final, "depth" (H,W)
        = sum_i w_i z_i, "expected_depth" (H,W) = depth / max(alpha, 1e-10), "radii" (N,2) int32,
        "means2d" (N,2), "depths" (N,), "conics" (N,3), "num_intersections" int (tile-Gaussian
        pairs). saved: RenderSaved for render_bwd.
    """
    inputs, width, height, config, dtype = _validate_inputs(
        means, quats, scales, opacities, colors, cam_T_world, K, width, height, background, config)
    return _render(inputs, width, height, config, dtype)


def _render_fwd(means, quats, scales, opacities, colors, cam_T_world, K, width, height, background, config):
    """``render_fwd`` without validation: the private fast path of a caller that validated its
    inputs once (the trainer's step, through ``d2gs_np.blur.render`` and ``d2gs_np.scene.render_inputs``).

    The caller guarantees what ``render_fwd`` checks: C-contiguous float arrays of one dtype and
    the documented shapes, finite values, opacities in [0, 1], scales >= 0, quaternion norms
    >= QUAT_NORM_MIN, K without skew, ints width, height >= 1, and a RenderConfig. Same outputs
    to the last bit.
    """
    inputs = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                  cam_T_world=cam_T_world, K=K, background=background)
    return _render(inputs, width, height, config, means.dtype)


# the projection outputs the binning and the compositing read
_RASTER_PROJ = ("means2d", "conics", "opac_eff", "depths", "radii_f", "cov2d")


def _raster_inputs(proj, colors, config, width, height, dtype):
    """(proj, colors, background, consts) cast to float32 for the rasteriser with
    ``RenderConfig.raster_float32`` on float64 inputs; None when the rasteriser runs on the
    render's own arrays. A render whose values do not all fit float32 (a 2D covariance or conic
    beyond 3.4e38, from absurd scales) keeps float64: the cast never turns a finite render into
    inf or NaN."""
    if not (config.raster_float32 and dtype == np.float64):
        return None
    f32 = np.float32
    with np.errstate(over="ignore"):
        rproj = {k: np.ascontiguousarray(proj[k], f32) for k in _RASTER_PROJ}
        rcolors = np.ascontiguousarray(colors, f32)
    if not all(np.isfinite(a).all() for a in (*rproj.values(), rcolors)):
        return None
    # background zero: the float64 background is added to the float32 colour sum afterwards
    return rproj, rcolors, np.zeros(3, f32), make_consts(config, width, height, f32)


def _render(inputs, width, height, config, dtype):
    ts = int(config.tile_size)
    consts = make_consts(config, width, height, dtype)
    proj = project_fwd(inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"],
                       inputs["cam_T_world"], inputs["K"], consts, config.antialiased)
    rast = _raster_inputs(proj, inputs["colors"], config, width, height, dtype)
    rproj, rcolors, rbackground, rconsts = rast or (proj, inputs["colors"], inputs["background"], consts)
    isect = build_intersections(rproj, rconsts, width, height, ts)
    raster = rasterize_fwd(rproj, rcolors, rbackground, rconsts, isect, width, height, ts)
    image, depth, T_final = raster["image"], raster["depth"], raster["T_final"]
    if rast is not None:
        depth, T_final = depth.astype(dtype), T_final.astype(dtype)
        image = image.astype(dtype) + T_final[..., None] * inputs["background"]
    alpha = 1 - T_final
    expected_depth = depth / np.maximum(alpha, dtype.type(C.EXPECTED_DEPTH_ALPHA_MIN))
    radii = np.minimum(proj["radii_f"], _INT32_MAX).astype(np.int32)
    out = dict(image=image, alpha=alpha, depth=depth, expected_depth=expected_depth,
               radii=radii, means2d=proj["means2d"], depths=proj["depths"], conics=proj["conics"],
               num_intersections=isect["n_box_isect"])
    saved = RenderSaved(inputs, width, height, config, dtype, consts, proj, isect, raster, rast)
    return out, saved


def render_bwd(saved, v_image, v_alpha=None, v_depth=None, v_expected_depth=None):
    """Gradients of L = <v_image, image> + <v_alpha, alpha> + <v_depth, depth>
    + <v_expected_depth, expected_depth> (docs/conventions.md §10).

    Args:
        saved: the RenderSaved of render_fwd.  v_image: (H,W,3).  v_alpha, v_depth,
        v_expected_depth: (H,W) or None (zero). Same dtype as the render.

    Returns dict: "means" (N,3), "quats" (N,4) (raw quats), "scales" (N,3), "opacities" (N,),
    "colors" (N,3), "cam_T_world" (4,4) (bottom row zero), "background" (3,), "means2d" (N,2).
    Deterministic: bitwise identical for any thread count (see the module docstring).
    """
    if not isinstance(saved, RenderSaved):
        raise TypeError(f"saved must be the RenderSaved returned by d2gs_np.render.render_fwd; "
                        f"got {type(saved).__name__}")
    H, W, dtype = saved.height, saved.width, saved.dtype
    v_image = _check_cotangent("v_image", v_image, (H, W, 3), dtype, f"(H, W, 3) = ({H}, {W}, 3)")
    v_alpha = _check_cotangent("v_alpha", v_alpha, (H, W), dtype, f"(H, W) = ({H}, {W})")
    v_depth = _check_cotangent("v_depth", v_depth, (H, W), dtype, f"(H, W) = ({H}, {W})")
    v_ed = _check_cotangent("v_expected_depth", v_expected_depth, (H, W), dtype, f"(H, W) = ({H}, {W})")
    return _render_grads(saved, v_image, v_alpha, v_depth, v_ed)


def _render_bwd(saved, v_image, v_alpha=None, v_depth=None, v_expected_depth=None):
    """``render_bwd`` without validation (the fast path beside ``_render_fwd``): the cotangents are
    C-contiguous, finite arrays of the render's dtype and shape, or None (zero)."""
    shape, dtype = (saved.height, saved.width), saved.dtype
    zero = lambda x: np.zeros(shape, dtype) if x is None else x  # noqa: E731  (as _check_cotangent)
    return _render_grads(saved, v_image, zero(v_alpha), zero(v_depth), zero(v_expected_depth))


def _render_grads(saved, v_image, v_alpha, v_depth, v_ed):
    dtype = saved.dtype
    inp, proj, raster, cfg = saved.inputs, saved.proj, saved.raster, saved.config
    T_final = raster["T_final"].astype(dtype, copy=False)  # float32 with RenderConfig.raster_float32
    depth = raster["depth"].astype(dtype, copy=False)
    bg = inp["background"]

    # expected_depth = depth / max(alpha, eps); alpha = 1 - T_final; image = C + T_final bg
    alpha = 1 - T_final
    eps = dtype.type(C.EXPECTED_DEPTH_ALPHA_MIN)
    active = alpha > eps
    denom = np.maximum(alpha, eps)
    v_depth_tot = v_depth + v_ed / denom
    v_alpha_tot = v_alpha - np.where(active, v_ed * depth / (denom * denom), 0)
    v_T = v_image[..., 0] * bg[0] + v_image[..., 1] * bg[1] + v_image[..., 2] * bg[2] - v_alpha_tot
    v_background = np.array([np.sum(T_final * v_image[..., c]) for c in range(3)], dtype=dtype)

    ts = int(cfg.tile_size)
    # the compositing backward in the rasteriser's dtype (float32 with RenderConfig.raster_float32)
    rproj, rcolors, _, rconsts = saved.rast or (proj, inp["colors"], None, saved.consts)
    rdtype = rconsts.dtype
    g = rasterize_bwd(rproj, rcolors, rconsts, saved.isect, raster, ts, np.ascontiguousarray(v_image, rdtype),
                      np.ascontiguousarray(v_depth_tot, rdtype), np.ascontiguousarray(v_T, rdtype))
    if saved.rast is not None:
        g = {k: v.astype(dtype) for k, v in g.items()}
    v_means, v_quats, v_scales, v_opacities, v_view = project_bwd(
        inp["means"], inp["quats"], inp["scales"], inp["opacities"], inp["cam_T_world"], inp["K"],
        saved.consts, cfg.antialiased, proj["radii_f"], g["v_means2d"], g["v_depths"], g["v_conics"],
        g["v_opac_eff"])
    return dict(means=v_means, quats=v_quats, scales=v_scales, opacities=v_opacities, colors=g["v_colors"],
                cam_T_world=v_view, background=v_background, means2d=g["v_means2d"], means2d_abs=g["v_means2d_abs"])


def warm_up(config=None):
    """Compile (or load from the Numba cache) the kernels of ``render_fwd`` and ``render_bwd`` for
    float64 inputs on one tiny Gaussian, so that timing what follows measures work, not JIT: with
    ``config.raster_float32`` both the float32 rasteriser and the float64 one (evaluation)."""
    one = np.ones((1, 3))
    configs = [config]
    if config is not None and config.raster_float32:
        configs.append(dataclasses.replace(config, raster_float32=False))
    for cfg in configs:
        out, saved = render_fwd(np.array([[0.0, 0.0, 2.0]]), np.array([[1.0, 0.0, 0.0, 0.0]]), 0.1 * one,
                                np.array([0.5]), 0.5 * one, np.eye(4),
                                np.array([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]), 8, 8, np.zeros(3), cfg)
        render_bwd(saved, np.ones_like(out["image"]))
