"""Blur formation model (docs/method.md §4, the paper's Eq. 5-9).

Frame k has an estimated mid-exposure pose T̂_k (cam_T_world) and time t_k. The camera moves
during the exposure from T_s = exp(xi_s) T̂_k to T_e = exp(xi_e) T̂_k (LEFT perturbations,
xi = (rho, phi), translation first, as in d2gs_np.geometry.se3). The blurry frame is the mean
of n sharp renders at virtual poses on the geodesic and at sub-frame times:

    T(u_i) = T_s exp(u_i log(T_s^-1 T_e)),   u_i = i / (n - 1),  i = 0 .. n-1       (Eq. 9)
    t_i    = t_k + (u_i - 1/2) tau                                                  (objects move)
    B̂_k    = (1/n) sum_i render(G(t_i), T(u_i))                                     (Eq. 6)

Choices made here (the paper leaves them open or states them loosely; docs/method.md §4):

- n = 1 is a sharp camera at the ESTIMATED pose T̂_k and time t_k: xi_s, xi_e are ignored (their
  gradients are zero) and so is tau. It is exactly the sharp render at T̂_k, bit for bit (this
  is what "no blur model" means for the GaussianFlow baseline). Note that it is *not* T(1/2),
  the geodesic midpoint of the endpoints, which differs from T̂_k once the endpoints have moved
  asymmetrically.
- The virtual poses are evaluated as T(u) = exp(xi_s) exp(u delta) T̂ with
  delta = log(exp(-xi_s) exp(xi_e)). This is Eq. 9 exactly, because
  T_s^-1 T_e = T̂^-1 exp(-xi_s) exp(xi_e) T̂ and conjugation commutes with log (it preserves the
  rotation angle), but it never forms T̂^-1 T̂ and so with xi_s = xi_e = 0 every virtual pose is
  T̂ to the last bit. The geodesic is the one of the rotation log with angle <= pi; at exactly
  pi (a half turn between start and end, never a real exposure) it is ambiguous.
- Every output (image, alpha, depth, expected_depth) is the plain mean over the n sub-frames. So
  the blurry "expected_depth" is the mean of the sub-frame expected depths, not the blurry depth
  divided by the blurry alpha; the sharp mid-pose depth docs/method.md §5 needs is rendered
  separately. "radii" is the element-wise max over sub-frames (a Gaussian is visible in the
  blurry frame when it is visible in any sub-frame).
- Pose arithmetic is done in float64 and cast to the scene dtype for rendering (float32 scenes
  get float32 virtual poses; every float argument must share the scene's dtype).

Exposure length tau, in normalised time (the clip spans [0, 1] over N frames, so one frame
interval is 1 / (N - 1)):
- known from the scene: tau = exposure_fraction / (N - 1)  (``exposure_from_scene``);
- learned: block ``camera.exposure_logit`` (1,), tau = sigmoid(logit) / (N - 1), kept inside
  (0, 1) of the frame interval (``exposure_fwd`` / ``exposure_bwd``); initialised at fraction
  1/2 (logit 0, ``init_exposure``), the middle of the range and a typical shutter of video
  (a 180-degree shutter), where the sigmoid is also steepest.

Endpoint derivative (hand derived, checked against finite differences in tests/blur/test_render.py).
Write A = exp(xi_s), B = exp(xi_e), delta = log(A^-1 B), L(u) = A exp(u delta), so T(u) = L(u) T̂
and a left perturbation of L(u) is the same left perturbation of T(u). Left-perturb A by eps_s
and B by eps_e:
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
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from d2gs_np.geometry.camera import project_points
from d2gs_np.geometry.se3 import (
    check_rigid,
    matrix_grad_to_left_tangent,
    se3_adjoint,
    se3_exp,
    se3_inverse,
    se3_left_jacobian,
    se3_log,
    se3_right_jacobian,
    se3_right_jacobian_inv,
)
from d2gs_np.scene.gaussians import DYNAMIC, STATIC

__all__ = [
    "BlurConfig",
    "N_SCHEDULES",
    "views_at_scale",
    "views_for_length",
    "blur_length_px",
    "EXPOSURE_BLOCK",
    "exposure_offsets",
    "subframe_times",
    "virtual_poses",
    "virtual_poses_fwd",
    "virtual_poses_bwd",
    "blur_render_fwd",
    "blur_render_bwd",
    "backward_subset",
    "exposure_from_scene",
    "init_exposure",
    "exposure_fwd",
    "exposure_bwd",
]

EXPOSURE_BLOCK = "camera.exposure_logit"
_SCENE_PREFIXES = (f"{STATIC}.", f"{DYNAMIC}.")
_RENDER_FIELDS = ("means", "quats", "scales", "opacities", "colors")
_OUTPUT_KEYS = ("image", "alpha", "depth", "expected_depth")


N_SCHEDULES = ("fixed", "scale", "length")


@dataclass(frozen=True)
class BlurConfig:
    """Blur formation settings.

    num_virtual: n, number of virtual sub-frames averaged per blurry frame (>= 1; 1 = sharp
        camera at the estimated pose, see the module docstring). Default 8 (docs/method.md §4).
    n_schedule: how many of them a training render at render scale r uses
        (``views_at_scale``): "fixed", n at every scale; "scale", fewer while the progressive
        schedule renders small images, so the virtual views stay as far apart in pixels as n
        views are at full resolution (the blur's length in pixels scales with r); "length", per
        frame and step from the blur's current length in render pixels (``blur_length_px`` of
        the current endpoints and scene, ``views_for_length``): just enough views to keep
        neighbouring views at most ``view_spacing_px`` render pixels apart, at most n. It
        follows the render scale too, and gives a short blur few views. The default: on the
        five suite scenes (blurry input, true poses, 600 s, one thread, two runs at a time) it
        made 1.10-1.70x the steps of "fixed" and deblurred as well or better on every scene
        (+0.05 to +1.02 dB; docs/method.md §4).
    view_spacing_px: the largest gap, in render pixels, between neighbouring virtual views of
        the "length" schedule (> 0).
    backward_views: m, how many of a step's virtual views its backward runs through (0: all).
        The forward always renders and averages every view, so the loss is exact; with
        0 < m < n views the gradient is the unbiased stratified estimate of
        ``backward_subset``: the views are cut into m runs of neighbours, one view of each run
        is drawn at random and carries its run's share of the weight. The backward costs about
        twice the forward, so the backward of m = 2 of n = 8 views costs a quarter of the
        exact one. Views of one exposure see the scene from poses a few pixels apart, so their
        gradients are nearly the same and the estimate's noise is small. Default 2: on the
        five suite scenes (blurry input, true poses, 600 s) it made 1.20-1.37x the steps of the
        exact backward and deblurred better on every scene (+0.16 to +0.62 dB); m = 1 lost
        0.47 dB against m = 2 on cube_sign (docs/method.md §4).
    """

    num_virtual: int = 8
    n_schedule: str = "length"
    view_spacing_px: float = 1.0
    backward_views: int = 2

    def __post_init__(self):
        n = self.num_virtual
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
            raise ValueError(f"BlurConfig.num_virtual must be an int >= 1; got {n!r}")
        if self.n_schedule not in N_SCHEDULES:
            raise ValueError(f"BlurConfig.n_schedule must be one of {N_SCHEDULES}; got {self.n_schedule!r}")
        d = self.view_spacing_px
        if isinstance(d, bool) or not isinstance(d, numbers.Real) or not (0.0 < d < float("inf")):
            raise ValueError(f"BlurConfig.view_spacing_px must be a finite number of pixels > 0; got {d!r}")
        _check_backward_views(self.backward_views, "BlurConfig.backward_views")


def views_at_scale(n, scale, schedule="fixed"):
    """Number of virtual views a render at scale r in (0, 1] uses (``BlurConfig.n_schedule``).

    "fixed": n. "scale": 1 + ceil(r (n - 1)), at least 2 and at most n: the n views of a blur
    L full-resolution pixels long are L / (n - 1) pixels apart; at scale r the blur is r L pixels
    long, and 1 + ceil(r (n - 1)) views keep the spacing at or below L / (n - 1). n = 1 (no blur
    model) stays 1. Example, n = 8: r = 0.2 -> 3, r = 0.5 -> 5, r = 1 -> 8.
    """
    n = _check_n(n)
    if isinstance(scale, bool) or not isinstance(scale, numbers.Real) or not (0.0 < scale <= 1.0):
        raise ValueError(f"scale must be a real number in (0, 1]; got {scale!r}")
    if schedule not in N_SCHEDULES:
        raise ValueError(f"n schedule must be one of {N_SCHEDULES}; got {schedule!r}")
    if schedule == "length":
        raise ValueError("the 'length' n schedule depends on the frame's blur, not only the scale: use "
                         "views_for_length(n, blur_length_px(...), spacing)")
    if schedule == "fixed" or n <= 2:
        return n
    # the tiny slack keeps exact scales (r (n - 1) an integer up to rounding) from taking one view too many
    return int(min(n, max(2, 1 + math.ceil(scale * (n - 1) - 1e-9))))


def views_for_length(n, length_px, spacing_px=1.0):
    """Virtual views of the "length" n schedule: 1 + ceil(L / d), at least 2 and at most n, for a
    blur L render pixels long and a largest gap d between neighbouring views (n views of a blur L
    long are L / (n - 1) apart). n <= 2 stays n. A zero-length blur gets 2 views (the model's
    smallest n > 1; with identical endpoints both are the same render).
    Example, d = 1: L = 0 -> 2, L = 2.5 -> 4, L = 20 -> n."""
    n = _check_n(n)
    L = _check_real(length_px, "length_px", low=0.0)
    d = _check_real(spacing_px, "spacing_px")
    if d <= 0.0:
        raise ValueError(f"spacing_px must be > 0; got {d}")
    if n <= 2:
        return n
    return int(min(n, max(2, 1 + math.ceil(L / d - 1e-9))))


def blur_length_px(means_start, means_end, pose_start, pose_end, K, width, height, quantile=0.99):
    """Length in pixels of a frame's blur: the ``quantile`` of the image-space distance between
    each point projected at the exposure start (``means_start`` (N, 3) world points through
    ``pose_start``, a (4, 4) cam_T_world) and at its end (``means_end`` through ``pose_end``),
    over the points in front of both cameras (z > 1e-6) whose start projection falls inside the
    width x height image of intrinsics K. A high quantile rather than the maximum, so one stray
    point near the camera does not decide the length. 0.0 when no point qualifies.

    Pass the same array twice for a static scene; the dynamic set's points at the start and end
    sub-frame times for a moving one."""
    ms = np.asarray(means_start, dtype=np.float64)
    me = np.asarray(means_end, dtype=np.float64)
    if ms.ndim != 2 or ms.shape[1] != 3 or me.shape != ms.shape:
        raise ValueError(f"means_start and means_end must both be (N, 3); got {ms.shape} and {me.shape}")
    if not 0.0 < quantile <= 1.0:
        raise ValueError(f"quantile must be in (0, 1]; got {quantile}")
    if ms.shape[0] == 0:
        return 0.0
    ps, zs = project_points(ms, pose_start, np.asarray(K, dtype=np.float64))
    pe, ze = project_points(me, pose_end, np.asarray(K, dtype=np.float64))
    inside = ((zs > 1e-6) & (ze > 1e-6) & (ps[:, 0] >= 0) & (ps[:, 0] < width) & (ps[:, 1] >= 0)
              & (ps[:, 1] < height))
    if not inside.any():
        return 0.0
    d = np.linalg.norm(pe[inside] - ps[inside], axis=1)
    d = d[np.isfinite(d)]
    return float(np.quantile(d, quantile)) if d.size else 0.0


# ---------------------------------------------------------------------------------------------
# Virtual poses and sub-frame times
# ---------------------------------------------------------------------------------------------


def _check_backward_views(m, what):
    if isinstance(m, bool) or not isinstance(m, numbers.Integral) or m < 0:
        raise ValueError(f"{what} must be an int >= 0 (0: every view); got {m!r}")


def _check_n(n):
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
        raise ValueError(f"n (number of virtual poses) must be an int >= 1; got {n!r}")
    return int(n)


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


# ---------------------------------------------------------------------------------------------
# Blurry render
# ---------------------------------------------------------------------------------------------


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


def _check_real(x, name, low=None):
    if isinstance(x, np.ndarray) and x.shape == ():
        x = x[()]
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, numbers.Real):
        raise TypeError(f"{name} must be a real scalar; got {type(x).__name__}")
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite; got {x}")
    if low is not None and x < low:
        raise ValueError(f"{name} must be >= {low}; got {x}")
    return x


def blur_render_fwd(params, frame_time, tau, pose_est, xi_start, xi_end, K, width, height, background,
                    blur_config, deform_config, render_config=None, renderer=None, scene_model=None):
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
    frame_time = _check_real(frame_time, "frame_time")
    tau = _check_real(tau, "tau", low=0.0)
    scene_params = {k: v for k, v in params.items() if k.startswith(_SCENE_PREFIXES)}
    if f"{STATIC}.means" not in scene_params:
        raise ValueError(f"params has no scene blocks ('{STATIC}.means', ...); build them with "
                         "d2gs_np.scene.gaussians.init_params")
    dtype = scene_params[f"{STATIC}.means"].dtype
    for name, arr in (("pose_est", pose_est), ("xi_start", xi_start), ("xi_end", xi_end), ("K", K),
                      ("background", background)):
        if not isinstance(arr, np.ndarray) or arr.dtype != dtype:
            got = arr.dtype if isinstance(arr, np.ndarray) else type(arr).__name__
            raise TypeError(f"{name} must be a numpy array of the scene dtype {dtype}; got {got} "
                            f"(cast it with .astype(np.{np.dtype(dtype).name}))")

    n = blur_config.num_virtual
    _check_pose_args(pose_est, xi_start, xi_end)
    return _blur_render_fwd(scene_params, frame_time, tau, pose_est, xi_start, xi_end, K, width, height, background,
                            n, deform_config, render_config, (render_fwd, render_bwd), (render_inputs_fwd, render_inputs_bwd))


def _blur_render_fwd(scene_params, frame_time, tau, pose_est, xi_start, xi_end, K, width, height, background, n,
                     deform_config, render_config, renderer, scene_model):
    """``blur_render_fwd`` after validation: ``scene_params`` holds only the scene blocks,
    ``frame_time`` and ``tau`` are floats, ``renderer`` and ``scene_model`` are (fwd, bwd) pairs.

    The trainer's step calls it directly with the unvalidated fast paths
    (``render.api._render_fwd``, ``scene.model._render_inputs_fwd`` and their backwards) on a model it
    validated once; ``blur_render_bwd`` then uses those backwards too.
    """
    render_fwd, render_bwd = renderer
    render_inputs_fwd, render_inputs_bwd = scene_model
    dtype = scene_params[f"{STATIC}.means"].dtype
    poses, pose_saved = _virtual_poses_fwd(pose_est, xi_start, xi_end, n)
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


def backward_subset(n, m, rng):
    """Views (indices, weights) for a backward through m of n virtual views (``BlurConfig.backward_views``).

    The n views are cut into m runs of consecutive views, as equal as they can be (sizes
    differ by at most one); one view is drawn uniformly from each run and weighted by
    |run| / n. Each view is drawn with probability 1 / |run|, so the expectation of
    sum_j w_j g_{i_j} is sum_i g_i / n, the exact gradient of the mean: the estimate is
    unbiased, and the runs make it cover the whole exposure (start and end halves for m = 2).
    m = 0 or m >= n: every view, weight 1 / n (the exact backward). rng: numpy Generator.
    Returns (indices (k,) int64 increasing, weights (k,) float64 summing to 1).
    """
    n = _check_n(n)
    _check_backward_views(m, "m (views in the backward)")
    if m == 0 or m >= n:
        return np.arange(n, dtype=np.int64), np.full(n, 1.0 / n)
    edges = (np.arange(m + 1) * n) // m  # run j is [edges[j], edges[j + 1]), sizes floor or ceil of n / m
    sizes = np.diff(edges)
    idx = edges[:-1] + rng.integers(0, sizes)
    return idx.astype(np.int64), sizes / float(n)


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
    poses (zero for the views it skipped)).
    views: None (every view: the exact gradient) or (indices, weights) from ``backward_subset``:
        the backward runs only through those sub-frames, view i_j's output cotangent scaled by
        w_j instead of 1 / n (an unbiased estimate of the exact gradient).
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
    v_xi_start, v_xi_end = virtual_poses_bwd(saved["pose_saved"], g_pose)
    if n == 1:
        v_tau = 0.0
    if return_aux:
        aux = {"v_means2d": np.stack(v_means2d), "v_means2d_abs": np.stack(v_means2d_abs), "v_pose_tangents": g_pose}
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


# ---------------------------------------------------------------------------------------------
# Exposure length
# ---------------------------------------------------------------------------------------------


def _check_num_frames(num_frames):
    if isinstance(num_frames, bool) or not isinstance(num_frames, numbers.Integral) or num_frames < 1:
        raise ValueError(f"num_frames must be an int >= 1; got {num_frames!r}")
    return int(num_frames)


def exposure_from_scene(exposure_fraction, num_frames):
    """tau = exposure_fraction / (N - 1) in normalised time (0 for a single frame).

    exposure_fraction: exposure time as a fraction of the frame interval, in [0, 1].
    """
    f = _check_real(exposure_fraction, "exposure_fraction", low=0.0)
    if f > 1.0:
        raise ValueError(f"exposure_fraction must be in [0, 1] (a fraction of the frame interval); got {f}")
    N = _check_num_frames(num_frames)
    return 0.0 if N == 1 else f / (N - 1)


def init_exposure(fraction=0.5, dtype=np.float64):
    """{"camera.exposure_logit": (1,)} with sigmoid(logit) = fraction in (0, 1) (default 1/2)."""
    f = _check_real(fraction, "fraction")
    if not 0.0 < f < 1.0:
        raise ValueError(f"fraction must be in (0, 1) (the sigmoid cannot reach 0 or 1); got {f}")
    return {EXPOSURE_BLOCK: np.array([math.log(f) - math.log1p(-f)], dtype=dtype)}


def exposure_fwd(params, num_frames):
    """tau = sigmoid(params["camera.exposure_logit"][0]) / (N - 1) (0 when N = 1); (tau, saved)."""
    if EXPOSURE_BLOCK not in params:
        raise ValueError(f"params lacks {EXPOSURE_BLOCK!r}; create it with init_exposure()")
    logit = params[EXPOSURE_BLOCK]
    if not isinstance(logit, np.ndarray) or logit.shape != (1,):
        raise ValueError(f"{EXPOSURE_BLOCK} must be an array of shape (1,); got {getattr(logit, 'shape', logit)}")
    x = _check_real(logit[0], EXPOSURE_BLOCK)
    N = _check_num_frames(num_frames)
    sig = 0.5 * (1.0 + math.tanh(0.5 * x))  # sigmoid without overflow
    scale = 0.0 if N == 1 else 1.0 / (N - 1)
    return sig * scale, {"sig": sig, "scale": scale, "dtype": logit.dtype}


def exposure_bwd(saved, v_tau):
    """{"camera.exposure_logit": (1,)} gradient from the scalar v_tau."""
    v_tau = _check_real(v_tau, "v_tau")
    sig = saved["sig"]
    return {EXPOSURE_BLOCK: np.array([v_tau * saved["scale"] * sig * (1.0 - sig)], dtype=saved["dtype"])}
