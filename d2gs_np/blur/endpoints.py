"""Camera trajectory model: the exposure start / end poses of every frame (docs/method.md §4).

Frame k has an estimated mid-exposure pose ``T̂_k`` (cam_T_world, 4x4) and the exposure
endpoints are its LEFT perturbations ``T_s,k = exp(xi_s,k) T̂_k``, ``T_e,k = exp(xi_e,k) T̂_k``
with xi = (rho, phi) in se(3), translation first (d2gs_np.geometry.se3). This module produces the
endpoint tangents (xi_s, xi_e) of a batch of frames from trainable blocks; d2gs_np.blur.virtual_poses
turns them into virtual poses and d2gs_np.blur.render into a blurry render. Two parametrisations
(``TrajectoryConfig.kind``, d2gs_np.blur.config):

``direct``  blocks ``camera.xi_start`` (N, 6) and ``camera.xi_end`` (N, 6), one row per frame.

``posenet`` (Eq. 8) a tiny MLP F(log T̂_k, t_k) -> (xi_s,k, xi_e,k):
    x = (z - mean) / std,   z = [se3_log(T̂_k) (6), t_k] (7,)
    h_0 = act(x W_0 + b_0),  h_1 = act(h_0 W_1 + b_1),  ...  y = h_last W_L + b_L  (12,)
    xi_s = y[:6], xi_e = y[6:]
  blocks ``posenet.W0`` (7, H), ``posenet.b0`` (H,), ``posenet.W1`` (H, H), ``posenet.b1`` (H,),
  ``posenet.W2`` (H, 12), ``posenet.b2`` (12,) for the default 2 hidden layers of H = 64
  (weights stored (fan_in, fan_out), rows are the batch). Choices the paper leaves open (docs/method.md §4):
  - Inputs are standardised per component with the mean and standard deviation over all N
    frames passed in ``poses_est`` / ``times`` (a fixed affine map, since the estimates are fixed);
    a component whose spread is below POSENET_INPUT_STD_MIN is only centred.
  - Activation ``tanh`` by default (smooth, bounded, zero-centred; ``softplus`` available).
  - Hidden layers: LeCun-normal weights (std 1/sqrt(fan_in)), zero biases. Output layer: weights
    with std ``output_init_scale / sqrt(H)`` (so each output starts within ~output_init_scale of
    its bias) and the bias ``[-s d, +s d]`` with d one random unit 6-vector: the network starts
    next to the direct model's initialisation (a tiny symmetric spread around T̂).
  - log T̂_k jumps where the rotation angle of T̂_k crosses pi (the log is discontinuous there);
    the network sees that jump as an input discontinuity. Poses near a rotation of pi in world
    coordinates are rare for camera trajectories; re-centre the world frame if they occur.

Why the initial spread is not zero (both kinds). With xi_s = xi_e the blurry render is a sharp
render and, for a static scene, the loss is even in the spread d = xi_e - xi_s: swapping the
endpoints reverses the order of the virtual poses on a grid of u symmetric about 1/2, which
leaves their mean unchanged. Its gradient in d is therefore exactly zero at d = 0: zero spread
is a critical point (a saddle once the target is blurrier than the sharp render), and a
gradient method started there never grows any blur. A tiny random spread (s ~ 1e-4, far below
any pose error that matters) breaks the symmetry, so the spread receives a gradient; the mid
pose exp(-s d) -> exp(+s d) still has its geodesic midpoint exactly at T̂_k.

Public API: ``init_trajectory``, ``endpoints_fwd``, ``endpoints_bwd``, ``trajectory_block_names``
(the settings: ``TrajectoryConfig`` in d2gs_np.blur.config).
"""
from __future__ import annotations

import numpy as np

from d2gs_np.base.checks import check_int
from d2gs_np.blur.config import TrajectoryConfig
from d2gs_np.constants import POSENET_INPUT_STD_MIN
from d2gs_np.geometry.se3 import check_rigid, se3_inverse, se3_log

__all__ = [
    "CAMERA",
    "POSENET",
    "XI_START",
    "XI_END",
    "XI_MID",
    "trajectory_block_names",
    "mid_knots",
    "check_trajectory",
    "init_trajectory",
    "exposure_bend",
    "exposure_bend_px",
    "tangent_px",
    "endpoints_fwd",
    "endpoints_bwd",
    "posenet_inputs",
]

CAMERA = "camera"  # block-name prefix of the per-frame camera blocks (and blur.exposure.EXPOSURE_BLOCK)
POSENET = "posenet"  # block-name prefix of the PoseNet weights
XI_START = f"{CAMERA}.xi_start"  # (N, 6) direct model: one row per frame
XI_END = f"{CAMERA}.xi_end"
XI_MID = f"{CAMERA}.xi_mid"  # (N, 6) the middle knot of the three-knot path (TrajectoryConfig.path)
_NUM_INPUTS = 7  # log T̂ (6) and t (1)
_NUM_OUTPUTS = 12  # xi_s (6) and xi_e (6)


def trajectory_block_names(config):
    """Names of the parameter blocks of this trajectory model, in a fixed order."""
    _check_config(config)
    if config.kind == "direct":
        return [XI_START, XI_END] + ([XI_MID] if config.path == "three_knot" else [])
    names = []
    for layer in range(config.hidden_layers + 1):
        names += [f"{POSENET}.W{layer}", f"{POSENET}.b{layer}"]
    return names


def _check_config(config):
    if not isinstance(config, TrajectoryConfig):
        raise TypeError(f"config must be a TrajectoryConfig; got {type(config).__name__}")


def _float_dtype(x):
    return np.float32 if np.asarray(x).dtype == np.float32 else np.float64


def _check_poses_times(poses_est, times):
    poses_est = np.asarray(poses_est)
    if poses_est.ndim != 3 or poses_est.shape[1:] != (4, 4):
        raise ValueError(f"poses_est must have shape (N, 4, 4); got {poses_est.shape}")
    check_rigid(poses_est, "poses_est")
    times = np.asarray(times)
    if times.shape != (poses_est.shape[0],):
        raise ValueError(f"times must have shape ({poses_est.shape[0]},) like poses_est; got {times.shape}")
    if not np.all(np.isfinite(times)):
        raise ValueError("times contains NaN or inf")
    return poses_est, times


def _unit_vectors(rng, n):
    d = rng.standard_normal((n, 6))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def velocity_endpoints(poses_est, times, exposure_fraction, window=1):
    """Endpoint tangents (xi_start, xi_end) (N, 6) of an exposure centred on each estimated pose,
    moving with the camera's velocity estimated from the neighbouring estimates.

    Velocity v_k (left-perturbation tangent per unit time), from the frames within ``window`` of k:
    window 1: v_k = log(T_{k+1} T_{k-1}^{-1}) / (t_{k+1} - t_{k-1}), one-sided at the ends;
    window h >= 2: the linear coefficient of a least-squares quadratic in (t_j - t_k) through the
    tangents log(T_j T_k^{-1}), j = k-h..k+h clipped to the frames (a line where only two frames
    remain). Both are exact for a constant velocity. The exposure lasts tau = exposure_fraction x
    the local frame interval, so xi_start = -v tau / 2 and xi_end = +v tau / 2
    (T(t) ~ exp((t - t_k) v) T_k).
    """
    check_int(window, "velocity_endpoints: window", 1, hint="frames on each side")
    N = poses_est.shape[0]
    P = np.asarray(poses_est, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    lo = np.clip(np.arange(N) - 1, 0, N - 1)
    hi = np.clip(np.arange(N) + 1, 0, N - 1)
    dt = t[hi] - t[lo]
    if window == 1:
        rel = np.einsum("nij,njk->nik", P[hi], se3_inverse(P[lo]))
        v = se3_log(rel) / np.where(dt > 0, dt, 1.0)[:, None]
        v[dt <= 0] = 0.0
    else:
        v = np.zeros((N, 6))
        inv = se3_inverse(P)
        for k in range(N):
            j = np.arange(max(0, k - window), min(N, k + window + 1))
            d = t[j] - t[k]
            if j.size < 2 or not np.ptp(d) > 0:
                continue
            y = se3_log(np.einsum("nij,jk->nik", P[j], inv[k]))
            A = np.vander(d, min(3, j.size), increasing=True)
            v[k] = np.linalg.lstsq(A, y, rcond=None)[0][1]
    interval = dt / np.maximum(hi - lo, 1)  # local frame interval
    half = 0.5 * float(exposure_fraction) * interval[:, None]
    return -v * half, v * half


def exposure_bend(poses_est, times, exposure_fraction):
    """How far each frame's exposure bends (N, 6): the tangent from the chord's midpoint to the
    path's at mid-exposure, with the path the quadratic c(d) = a d + b d^2 in T̂_k's tangent space
    through the neighbouring poses (d = t_j - t_k, c(-d_-) = log(T_{k-1} T_k^{-1}),
    c(d_+) = log(T_{k+1} T_k^{-1})). Over an exposure of tau = exposure_fraction x the local
    frame interval the chord's midpoint lies b tau^2 / 4 from c(0) = 0 (a sagitta); equal
    intervals give exposure_fraction^2 / 8 x the second difference. The end frames take their
    neighbour's b. Zero for fewer than 3 frames (no second difference) and for a straight,
    constant-velocity path."""
    P = np.asarray(poses_est, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    N = P.shape[0]
    if N < 3:
        return np.zeros((N, 6))
    k = np.arange(1, N - 1)
    inv = se3_inverse(P[k])
    x_lo = se3_log(np.einsum("nij,njk->nik", P[k - 1], inv))
    x_hi = se3_log(np.einsum("nij,njk->nik", P[k + 1], inv))
    d_lo, d_hi = t[k] - t[k - 1], t[k + 1] - t[k]
    if not (np.all(d_lo > 0) and np.all(d_hi > 0)):
        raise ValueError("exposure_bend: times must increase strictly from frame to frame")
    b = (x_hi / d_hi[:, None] + x_lo / d_lo[:, None]) / (d_lo + d_hi)[:, None]
    b = np.concatenate([b[:1], b, b[-1:]])
    interval = np.concatenate([d_lo[:1], 0.5 * (d_lo + d_hi), d_hi[-1:]])
    tau = float(exposure_fraction) * interval
    return b * (tau ** 2 / 4.0)[:, None]


def tangent_px(xi, focal, depth=np.inf):
    """How far a camera motion xi (..., 6) moves the image, in pixels: its rotation turns the view
    by focal x angle, its translation shifts a point at ``depth`` by focal x length / depth (the
    two added, an upper bound)."""
    xi = np.asarray(xi, dtype=np.float64)
    return float(focal) * (np.linalg.norm(xi[..., 3:], axis=-1) + np.linalg.norm(xi[..., :3], axis=-1) / float(depth))


def exposure_bend_px(poses_est, times, exposure_fraction, focal, depth=np.inf):
    """``exposure_bend`` in pixels (N,) (``tangent_px``)."""
    return tangent_px(exposure_bend(poses_est, times, exposure_fraction), focal, depth)


def init_trajectory(config, poses_est, times, rng, exposure_fraction=None):
    """Initial trajectory blocks.

    config: TrajectoryConfig. poses_est: (N, 4, 4) estimated cam_T_world. times: (N,).
    exposure_fraction: used by the "velocity" start of the direct model (None: 0.5, the learned
    exposure's initial value).
    rng: np.random.Generator (directions of the initial spread, PoseNet weights).
    Returns a dict of C-contiguous blocks (names: trajectory_block_names(config)), of the dtype
    of poses_est (float32 stays float32, else float64).
    """
    _check_config(config)
    poses_est, times = _check_poses_times(poses_est, times)
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a np.random.Generator; got {type(rng).__name__}")
    dtype = _float_dtype(poses_est)
    N = poses_est.shape[0]
    s = float(config.init_spread)
    if config.kind == "direct":
        d = _unit_vectors(rng, N)
        xs, xe = -s * d, s * d
        if config.init == "velocity" and N > 1:
            vs, ve = velocity_endpoints(poses_est, times, 0.5 if exposure_fraction is None else exposure_fraction,
                                        window=config.velocity_window)
            # Keep the tiny random spread where the camera did not move (a saddle otherwise).
            moving = np.linalg.norm(ve - vs, axis=1) > 2 * s
            xs[moving], xe[moving] = vs[moving], ve[moving]
        blocks = {XI_START: np.ascontiguousarray(xs, dtype=dtype), XI_END: np.ascontiguousarray(xe, dtype=dtype)}
        if config.path == "three_knot":
            blocks[XI_MID] = np.zeros((N, 6), dtype=dtype)  # the path starts as the line through T̂
        return blocks
    H, L = config.hidden_width, config.hidden_layers
    params = {}
    fan_in = _NUM_INPUTS
    for layer in range(L):
        params[f"{POSENET}.W{layer}"] = rng.standard_normal((fan_in, H)) / np.sqrt(fan_in)
        params[f"{POSENET}.b{layer}"] = np.zeros(H)
        fan_in = H
    params[f"{POSENET}.W{L}"] = rng.standard_normal((H, _NUM_OUTPUTS)) * (config.output_init_scale / np.sqrt(H))
    d = _unit_vectors(rng, 1)[0]
    params[f"{POSENET}.b{L}"] = np.concatenate([-s * d, s * d])
    return {k: np.ascontiguousarray(v, dtype=dtype) for k, v in params.items()}


def posenet_inputs(poses_est, times):
    """Standardised PoseNet inputs of all frames: (N, 7) = ((log T̂_k, t_k) - mean) / std.

    Mean and std are over the N frames; a std below POSENET_INPUT_STD_MIN is replaced by 1.
    Computed in float64.
    """
    return _posenet_inputs(*_check_poses_times(poses_est, times))


def _posenet_inputs(poses_est, times):
    z = np.concatenate([se3_log(poses_est.astype(np.float64)), times.astype(np.float64)[:, None]], axis=1)
    mean = z.mean(axis=0)
    std = z.std(axis=0)
    std = np.where(std < POSENET_INPUT_STD_MIN, 1.0, std)
    return (z - mean) / std


def _check_frame_indices(frame_indices, N):
    idx = np.asarray(frame_indices)
    if idx.ndim == 0:
        idx = idx[None]
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
        raise TypeError(f"frame_indices must be an int or a 1-D integer array; got {idx.dtype} {idx.shape}")
    if idx.size and (idx.min() < 0 or idx.max() >= N):
        raise ValueError(f"frame_indices must be in [0, {N}); got min {idx.min()}, max {idx.max()}")
    return idx.astype(np.int64)


def _check_params(params, config, N):
    names = trajectory_block_names(config)
    missing = [k for k in names if k not in params]
    if missing:
        raise ValueError(f"params lacks the {config.kind} trajectory blocks {missing}; create them with init_trajectory")
    dtype = np.asarray(params[names[0]]).dtype
    if dtype not in (np.float32, np.float64):
        raise TypeError(f"{names[0]} must be float32 or float64; got {dtype}")
    for k in names:
        a = params[k]
        if not isinstance(a, np.ndarray) or a.dtype != dtype:
            raise TypeError(f"{k} must be a numpy array of dtype {dtype} like {names[0]}; got "
                            f"{getattr(a, 'dtype', type(a).__name__)}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{k} contains NaN or inf")
    if config.kind == "direct":
        for k in names:
            if params[k].shape != (N, 6):
                raise ValueError(f"{k} must have shape ({N}, 6) (one row per frame of poses_est); got {params[k].shape}")
    else:
        H, L = config.hidden_width, config.hidden_layers
        fan_in = _NUM_INPUTS
        for layer in range(L + 1):
            fan_out = _NUM_OUTPUTS if layer == L else H
            for k, shape in ((f"{POSENET}.W{layer}", (fan_in, fan_out)), (f"{POSENET}.b{layer}", (fan_out,))):
                if params[k].shape != shape:
                    raise ValueError(f"{k} must have shape {shape} for {config}; got {params[k].shape}")
            fan_in = fan_out
    return dtype


def check_trajectory(params, config, poses_est, times):
    """Raise a clear error unless ``params`` holds finite blocks of this trajectory model for the
    N frames of ``poses_est`` (rigid, (N, 4, 4)) and ``times`` (finite, (N,)). What
    ``endpoints_fwd`` checks on every call, for a caller that checks once (``train.model``)."""
    _check_config(config)
    poses_est, times = _check_poses_times(poses_est, times)
    _check_params(params, config, poses_est.shape[0])


def _act(a, kind):
    if kind == "tanh":
        h = np.tanh(a)
        return h, 1.0 - h * h
    h = np.logaddexp(0.0, a)  # softplus, stable for large |a|
    return h, 0.5 * (1.0 + np.tanh(0.5 * a))  # its derivative, sigmoid(a), without overflow


def endpoints_fwd(params, config, frame_indices, poses_est, times):
    """Endpoint tangents of a batch of frames.

    params: dict holding the blocks of ``trajectory_block_names(config)`` (other keys ignored).
    frame_indices: (B,) ints (or one int) into the N frames.
    poses_est: (N, 4, 4) estimated cam_T_world of ALL frames; times: (N,) of all frames
        (PoseNet standardises its inputs over these).
    Returns ((xi_start (B, 6), xi_end (B, 6)), saved); dtype of the blocks.
    """
    _check_config(config)
    poses_est, times = _check_poses_times(poses_est, times)
    N = poses_est.shape[0]
    _check_params(params, config, N)
    return _endpoints_fwd(params, config, _check_frame_indices(frame_indices, N), poses_est, times)


def _endpoints_fwd(params, config, idx, poses_est, times):
    """``endpoints_fwd`` without validation: blocks of ``trajectory_block_names(config)`` shaped
    for the N frames, finite; ``idx`` a 1-D int64 array in [0, N); rigid poses, finite times.
    The trainer's step calls it on a model validated once (``check_rigid`` of every pose per
    step is what this saves)."""
    N = poses_est.shape[0]
    dtype = params[trajectory_block_names(config)[0]].dtype
    if config.kind == "direct":
        xs = params[XI_START][idx]
        xe = params[XI_END][idx]
        return (xs, xe), {"config": config, "idx": idx, "N": N, "dtype": dtype}
    x = _posenet_inputs(poses_est, times)[idx].astype(dtype)
    L = config.hidden_layers
    acts, derivs = [x], []
    h = x
    for layer in range(L):
        a = h @ params[f"{POSENET}.W{layer}"] + params[f"{POSENET}.b{layer}"]
        h, dh = _act(a, config.activation)
        acts.append(h)
        derivs.append(dh)
    y = h @ params[f"{POSENET}.W{L}"] + params[f"{POSENET}.b{L}"]
    saved = {"config": config, "idx": idx, "N": N, "dtype": dtype, "acts": acts, "derivs": derivs,
             "weights": [params[f"{POSENET}.W{layer}"] for layer in range(L + 1)]}
    return (np.ascontiguousarray(y[:, :6]), np.ascontiguousarray(y[:, 6:])), saved


def mid_knots(params, config, idx):
    """The middle knots xi_mid (B, 6) of frames ``idx`` (a 1-D int64 array) on the three-knot path,
    else None (the geodesic path has none). Unvalidated, like ``_endpoints_fwd``."""
    return params[XI_MID][idx] if config.kind == "direct" and config.path == "three_knot" else None


def endpoints_bwd(saved, v_xi_start, v_xi_end, v_xi_mid=None):
    """Gradient of a loss w.r.t. the trajectory blocks, from v_xi_start, v_xi_end (B, 6) (and
    v_xi_mid (B, 6) on the three-knot path; None: zero).

    Returns a dict keyed like trajectory_block_names(config); direct rows of frames outside the
    batch are zero (a frame repeated in the batch accumulates).
    """
    config, idx, dtype = saved["config"], saved["idx"], saved["dtype"]
    B = idx.shape[0]
    v_xs = np.asarray(v_xi_start, dtype=dtype)
    v_xe = np.asarray(v_xi_end, dtype=dtype)
    for name, v in (("v_xi_start", v_xs), ("v_xi_end", v_xe)):
        if v.shape != (B, 6):
            raise ValueError(f"{name} must have shape ({B}, 6) like the forward's output; got {v.shape}")
    if config.kind == "direct":
        N = saved["N"]
        g_s = np.zeros((N, 6), dtype=dtype)
        g_e = np.zeros((N, 6), dtype=dtype)
        np.add.at(g_s, idx, v_xs)
        np.add.at(g_e, idx, v_xe)
        out = {XI_START: g_s, XI_END: g_e}
        if config.path == "three_knot":
            g_m = np.zeros((N, 6), dtype=dtype)
            if v_xi_mid is not None:
                v_xm = np.asarray(v_xi_mid, dtype=dtype)
                if v_xm.shape != (B, 6):
                    raise ValueError(f"v_xi_mid must have shape ({B}, 6) like the forward's output; got {v_xm.shape}")
                np.add.at(g_m, idx, v_xm)
            out[XI_MID] = g_m
        return out
    L = config.hidden_layers
    acts, derivs, weights = saved["acts"], saved["derivs"], saved["weights"]
    grads = {}
    v_a = np.concatenate([v_xs, v_xe], axis=1)  # dL/d(pre-activation) of the output layer = v_y
    for layer in range(L, -1, -1):
        # forward: a_layer = acts[layer] @ W_layer + b_layer
        grads[f"{POSENET}.W{layer}"] = acts[layer].T @ v_a
        grads[f"{POSENET}.b{layer}"] = v_a.sum(axis=0)
        if layer > 0:
            v_h = v_a @ weights[layer].T
            v_a = v_h * derivs[layer - 1]  # acts[layer] = act(a_{layer-1})
    return {k: np.ascontiguousarray(grads[k], dtype=dtype) for k in trajectory_block_names(config)}
