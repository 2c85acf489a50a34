"""The blurred render of one frame (docs/method.md §4, the paper's Eq. 5-6) and its backward.

The blurry frame is the mean of n sharp renders of the scene at the virtual poses T(u_i) and
sub-frame times t_i = t_k + (u_i - 1/2) tau of d2gs_np.blur.virtual_poses:

    B̂_k = (1/n) sum_i render(G(t_i), T(u_i))                                        (Eq. 6)

The backward runs each sub-frame's output cotangent (times 1/n) through the renderer and the
scene model; the renderer's pose gradients, as left tangents g_i, go to the exposure endpoints
(``virtual_poses_bwd``) and the sub-frame time gradients v_t_i to tau:
v_tau = sum_i v_t_i (u_i - 1/2).

- n = 1 is exactly the sharp render at the estimated pose T̂_k and time t_k, bit for bit (this
  is what "no blur model" means for the GaussianFlow baseline); xi_s, xi_e and tau get zero
  gradient.
- Every output (image, alpha, depth, expected_depth) is the plain mean over the n sub-frames. So
  the blurry "expected_depth" is the mean of the sub-frame expected depths, not the blurry depth
  divided by the blurry alpha; the sharp mid-pose depth docs/method.md §5 needs is rendered
  separately. "radii" is the element-wise max over sub-frames (a Gaussian is visible in the
  blurry frame when it is visible in any sub-frame).
- Every float argument must share the scene's dtype (float32 scenes get float32 virtual poses).
- The backward may run through some of the views only (``views``, drawn by
  d2gs_np.blur.views.backward_subset): an unbiased estimate of the gradient.
- The renderer and the scene model are arguments (default: the Numba renderer d2gs_np.render and
  d2gs_np.scene.render_inputs), so the NumPy reference or a port plugs in.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.base.checks import check_scalar
from d2gs_np.blur.config import BlurConfig
from d2gs_np.blur.virtual_poses import (_check_pose_args, _check_tangent, _three_knot_poses_fwd, _virtual_poses_fwd,
                                       exposure_offsets, three_knot_poses_bwd, virtual_poses_bwd)
from d2gs_np.geometry.se3 import matrix_grad_to_left_tangent
from d2gs_np.scene.gaussians import SCENE_PREFIXES, STATIC

__all__ = [
    "blur_render_fwd",
    "blur_render_bwd",
]

_RENDER_FIELDS = ("means", "quats", "scales", "opacities", "colors")
_OUTPUT_KEYS = ("image", "alpha", "depth", "expected_depth")


def _resolve_renderer(renderer):
    if renderer is None:
        from d2gs_np import render as renderer
    if isinstance(renderer, tuple):
        if len(renderer) != 2 or not all(callable(f) for f in renderer):
            raise TypeError("renderer must be a (render_fwd, render_bwd) pair of callables or a module")
        return renderer
    fwd, bwd = getattr(renderer, "render_fwd", None), getattr(renderer, "render_bwd", None)
    if not (callable(fwd) and callable(bwd)):
        raise TypeError(f"renderer must provide render_fwd and render_bwd; got {renderer!r}")
    return fwd, bwd


def _resolve_scene_model(scene_model):
    if scene_model is None:
        from d2gs_np.scene import render_inputs as scene_model
    fwd, bwd = getattr(scene_model, "render_inputs_fwd", None), getattr(scene_model, "render_inputs_bwd", None)
    if not (callable(fwd) and callable(bwd)):
        raise TypeError(f"scene_model must provide render_inputs_fwd and render_inputs_bwd; got {scene_model!r}")
    return fwd, bwd


def blur_render_fwd(params, frame_time, tau, pose_est, xi_start, xi_end, K, width, height, background,
                    blur_config, deform_config, render_config=None, renderer=None, scene_model=None, xi_mid=None):
    """Blurry render of one frame (Eq. 6), averaging n sharp sub-frame renders.

    params: dict of blocks; the scene blocks ("static.*", "dynamic.*") are used, other keys
        (e.g. "camera.*", "posenet.*") are ignored.
    frame_time: t_k, mid-exposure normalised time. tau: exposure length >= 0 in normalised time.
    pose_est: (4, 4) estimated cam_T_world T̂_k. xi_start, xi_end: (6,) endpoint perturbations.
    K (3, 3), width, height, background (3,): camera and background as for the renderer.
    blur_config: BlurConfig. deform_config: DeformConfig. render_config: RenderConfig or None.
    renderer: object with render_fwd/render_bwd (a module such as d2gs_np.reference) or a
        (render_fwd, render_bwd) pair; default d2gs_np.render (the Numba renderer).
    scene_model: object with render_inputs_fwd/render_inputs_bwd; default d2gs_np.scene.render_inputs.
    xi_mid: None (the geodesic path, Eq. 9) or (6,), the middle knot of the three-knot path
        (``blur.virtual_poses.three_knot_poses_fwd``; its gradient: ``blur_render_bwd``'s aux).
    Every float array must share the scene's dtype.

    Returns (out, saved): out has "image" (H, W, 3), "alpha", "depth", "expected_depth" (H, W)
    (means over sub-frames), "radii" (N, 2) int32 (max over sub-frames), "poses" (n, 4, 4) and
    "times" (n,) of the sub-frames.
    """
    if not isinstance(blur_config, BlurConfig):
        raise TypeError(f"blur_config must be a BlurConfig; got {type(blur_config).__name__}")
    if not isinstance(params, dict):
        raise TypeError(f"params must be a dict of arrays; got {type(params).__name__}")
    render_fwd, render_bwd = _resolve_renderer(renderer)
    render_inputs_fwd, render_inputs_bwd = _resolve_scene_model(scene_model)
    frame_time = check_scalar(frame_time, "frame_time")
    tau = check_scalar(tau, "tau", 0.0)
    scene_params = {k: v for k, v in params.items() if k.startswith(SCENE_PREFIXES)}
    if f"{STATIC}.means" not in scene_params:
        raise ValueError(f"params has no scene blocks ('{STATIC}.means', ...); build them with "
                         "d2gs_np.scene.gaussians.init_params")
    dtype = scene_params[f"{STATIC}.means"].dtype
    for name, arr in (("pose_est", pose_est), ("xi_start", xi_start), ("xi_end", xi_end), ("K", K),
                      ("background", background)) + ((("xi_mid", xi_mid),) if xi_mid is not None else ()):
        if not isinstance(arr, np.ndarray) or arr.dtype != dtype:
            got = arr.dtype if isinstance(arr, np.ndarray) else type(arr).__name__
            raise TypeError(f"{name} must be a numpy array of the scene dtype {dtype}; got {got} "
                            f"(cast it with .astype(np.{np.dtype(dtype).name}))")

    n = blur_config.num_virtual
    _check_pose_args(pose_est, xi_start, xi_end)
    if xi_mid is not None:
        _check_tangent(xi_mid, "xi_mid", dtype)
    return _blur_render_fwd(scene_params, frame_time, tau, pose_est, xi_start, xi_end, K, width, height, background,
                            n, deform_config, render_config, (render_fwd, render_bwd), (render_inputs_fwd, render_inputs_bwd),
                            xi_mid)


def _blur_render_fwd(scene_params, frame_time, tau, pose_est, xi_start, xi_end, K, width, height, background, n,
                     deform_config, render_config, renderer, scene_model, xi_mid=None):
    """``blur_render_fwd`` after validation: ``scene_params`` holds only the scene blocks,
    ``frame_time`` and ``tau`` are floats, ``renderer`` and ``scene_model`` are (fwd, bwd) pairs.

    The trainer's step calls it directly with the unvalidated fast paths
    (``render.api._render_fwd``, ``scene.render_inputs._render_inputs_fwd`` and their backwards) on a model it
    validated once; ``blur_render_bwd`` then uses those backwards too.
    """
    render_fwd, render_bwd = renderer
    render_inputs_fwd, render_inputs_bwd = scene_model
    dtype = scene_params[f"{STATIC}.means"].dtype
    if xi_mid is None:
        poses, pose_saved = _virtual_poses_fwd(pose_est, xi_start, xi_end, n)
    else:
        poses, pose_saved = _three_knot_poses_fwd(pose_est, xi_start, xi_mid, xi_end, n)
    u = exposure_offsets(n)
    times = frame_time + (u - 0.5) * tau
    sums, radii, subs = None, None, []
    for i in range(n):
        inputs, eval_saved = render_inputs_fwd(scene_params, float(times[i]), deform_config)
        out_i, render_saved = render_fwd(**inputs, cam_T_world=poses[i], K=K, width=width, height=height,
                                         background=background, config=render_config)
        subs.append((eval_saved, render_saved))
        if sums is None:
            sums = {key: np.array(out_i[key], copy=True) for key in _OUTPUT_KEYS}
            radii = np.array(out_i["radii"], copy=True)
        else:
            for key in _OUTPUT_KEYS:
                sums[key] += out_i[key]
            np.maximum(radii, out_i["radii"], out=radii)
    out = {key: sums[key] / dtype.type(n) if n > 1 else sums[key] for key in _OUTPUT_KEYS}
    out.update(radii=radii, poses=poses, times=times)
    saved = {"n": n, "u": u, "poses": poses, "pose_saved": pose_saved, "subs": subs,
             "render_bwd": render_bwd, "render_inputs_bwd": render_inputs_bwd, "dtype": dtype,
             "scene_keys": list(scene_params), "shape": sums["alpha"].shape}
    return out, saved


def blur_render_bwd(saved, v_image, v_alpha=None, v_depth=None, v_expected_depth=None, return_aux=False,
                    views=None):
    """Backward of blur_render_fwd.

    v_image (H, W, 3); v_alpha, v_depth, v_expected_depth (H, W) or None (zero).
    Returns (v_params, v_xi_start (6,), v_xi_end (6,), v_tau float): v_params is keyed like the
    scene blocks of the forward's params (every block, dense). v_tau = sum_i v_t_i (u_i - 1/2)
    (0 for n = 1). With return_aux=True a fifth element is returned: dict(v_means2d (k, N, 2),
    the renderer's screen-space mean gradients of each sub-frame the backward ran through (for
    densification), v_means2d_abs (k, N, 2), their sums of absolute per-pixel terms (the
    renderer's ``means2d_abs``), and v_pose_tangents (n, 6), the left-perturbation gradients of the virtual
    poses (zero for the views it skipped), and v_xi_mid (6,), the middle knot's gradient on the
    three-knot path (None on the geodesic)).
    views: None (every view: the exact gradient) or (indices, weights) from
        ``d2gs_np.blur.views.backward_subset``: the backward runs only through those sub-frames,
        view i_j's output cotangent scaled by w_j instead of 1 / n (an unbiased estimate of the
        exact gradient).
    """
    n, u, dtype = saved["n"], saved["u"], saved["dtype"]
    H, W = saved["shape"]
    cot = {}
    for name, v, shape in (("v_image", v_image, (H, W, 3)), ("v_alpha", v_alpha, (H, W)),
                           ("v_depth", v_depth, (H, W)), ("v_expected_depth", v_expected_depth, (H, W))):
        if v is None:
            cot[name] = None
            continue
        if not isinstance(v, np.ndarray) or v.dtype != dtype:
            got = v.dtype if isinstance(v, np.ndarray) else type(v).__name__
            raise TypeError(f"{name} must be a numpy array of the scene dtype {dtype}; got {got}")
        if v.shape != shape:
            raise ValueError(f"{name} must have shape {shape}; got {v.shape}")
        cot[name] = v / dtype.type(n) if (n > 1 and views is None) else v
    if cot["v_image"] is None:
        raise ValueError("v_image must be given (pass zeros for a loss without the image)")
    if views is None:
        index, weight = range(n), None
    else:
        index, weight = _check_views(views, n)
    render_bwd, render_inputs_bwd = saved["render_bwd"], saved["render_inputs_bwd"]
    v_params = None
    v_tau = 0.0
    g_pose = np.zeros((n, 6))
    v_means2d, v_means2d_abs = [], []
    for j, i in enumerate(index):
        eval_saved, render_saved = saved["subs"][i]
        c = cot if weight is None else {name: (None if v is None else v * dtype.type(weight[j]))
                                        for name, v in cot.items()}
        grads = render_bwd(render_saved, c["v_image"], c["v_alpha"], c["v_depth"], c["v_expected_depth"])
        v_p, v_t = render_inputs_bwd(eval_saved, {f: grads[f] for f in _RENDER_FIELDS})
        if v_params is None:
            v_params = v_p
        else:
            for k in v_params:
                v_params[k] += v_p[k]
        v_tau += float(v_t) * (u[i] - 0.5)
        g_pose[i] = matrix_grad_to_left_tangent(saved["poses"][i].astype(np.float64),
                                                np.asarray(grads["cam_T_world"], np.float64))
        if return_aux:
            v_means2d.append(grads["means2d"])
            v_means2d_abs.append(grads["means2d_abs"])
    v_xi_mid = None
    if saved["pose_saved"].get("path") == "three_knot":
        v_xi_start, v_xi_mid, v_xi_end = three_knot_poses_bwd(saved["pose_saved"], g_pose)
    else:
        v_xi_start, v_xi_end = virtual_poses_bwd(saved["pose_saved"], g_pose)
    if n == 1:
        v_tau = 0.0
    if return_aux:
        aux = {"v_means2d": np.stack(v_means2d), "v_means2d_abs": np.stack(v_means2d_abs), "v_pose_tangents": g_pose,
               "v_xi_mid": v_xi_mid}
        return v_params, v_xi_start, v_xi_end, v_tau, aux
    return v_params, v_xi_start, v_xi_end, v_tau


def _check_views(views, n):
    try:
        index, weight = views
    except (TypeError, ValueError):
        raise ValueError("views must be None or an (indices, weights) pair from backward_subset") from None
    index = np.asarray(index)
    weight = np.asarray(weight, dtype=np.float64)
    if (index.ndim != 1 or index.size == 0 or weight.shape != index.shape or not np.issubdtype(index.dtype, np.integer)
            or index.min() < 0 or index.max() >= n or np.unique(index).size != index.size
            or not np.all(np.isfinite(weight))):
        raise ValueError(f"views must be (indices, weights): distinct int indices in [0, {n}) and finite weights of "
                         f"the same length; got {index!r}, {weight!r} (use backward_subset)")
    return [int(i) for i in index], weight

