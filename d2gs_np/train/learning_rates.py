"""Learning rates per parameter block, and the optimiser step of training that applies them (Adam).

Learning-rate policy (3DGS's, docs/method.md §8), decided per block from its name:

- positions (``*.means``) and position coefficients (``dynamic.deform_means``): exponential
  decay over the run, scaled by a length (``position_extent``: the scene's size by default, or
  the camera extent as in 3DGS; a scene twice as large moves its Gaussians twice as far per step);
- other deformation coefficients, scales, rotations, opacities, colours: constants of
  ``LearningRates``;
- camera endpoints (``camera.xi_*``) and PoseNet weights: exponential decay; the per-frame
  endpoint rows are visited once per epoch, so they decay over the visits a row gets. A centred
  exposure (trusted poses, ``Components.centred``) trains only its spread h, xi_end = h =
  -xi_start, at ``camera_spread`` (``centre_endpoint_grads``); the rows of frames a kept bundle
  adjustment moved, when Adam alone refines them (``PoseInitConfig.then = "adam"``), at
  ``camera_adjusted_scale`` times the camera rate (``camera_row_scales``);
- the exposure logit: a constant.

A block no rule covers is an error naming the block and where to add its rate.

The stage decides which blocks a step trains (``train/stages.py``). Per-frame blocks (one row per
frame: the direct endpoints) get row-sparse Adam: only the rows of the step's frame are updated,
moments included, so other frames' endpoints do not drift on stale momentum.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from d2gs_np.blur.exposure import EXPOSURE_BLOCK
from d2gs_np.optim import adam
from d2gs_np.blur.endpoints import CAMERA, POSENET, XI_END, XI_MID, XI_START
from d2gs_np.scene.gaussians import CLUSTER, DYNAMIC, STATIC
from d2gs_np.train.config import NON_RATE_FIELDS, LearningRates

__all__ = ["PER_FRAME_BLOCKS", "POSITION_BLOCKS", "position_row_factors", "scene_extent", "size_extent", "position_extent", "block_learning_rate",
           "learning_rates", "camera_row_scales", "centre_endpoint_grads", "optimiser_step"]

PER_FRAME_BLOCKS = (XI_START, XI_END, XI_MID)  # one row per frame: row-sparse Adam
_RATE_FIELDS = {f.name for f in dataclasses.fields(LearningRates)} - set(NON_RATE_FIELDS)
# The blocks whose rows are Gaussian positions (or their deformation's position coefficients).
POSITION_BLOCKS = (f"{STATIC}.means", f"{DYNAMIC}.means", f"{DYNAMIC}.deform_means")


def scene_extent(poses, scene_scale=None) -> float:
    """1.1 x the radius of the camera centres around their mean (3DGS's 'cameras_extent'), which
    scales the position learning rates and the size rules of pruning and densification. A camera
    that does not move (tripod) has no such radius: then the scene's scene_scale is used, else 1."""
    centres = np.array([-T[:3, :3].T @ T[:3, 3] for T in poses])
    r = float(np.max(np.linalg.norm(centres - centres.mean(0), axis=1))) * 1.1
    if r > 1e-9 * max(1.0, float(np.max(np.abs(centres)))):
        return r
    return float(scene_scale) if scene_scale else 1.0


def size_extent(poses, points, camera_extent) -> float:
    """The scene's size for pruning's oversized rule: the larger of the camera extent and 1.1 x the
    90th percentile distance of the initial points from the camera centres' mean.

    3DGS measures its size rules in units of the camera extent, which for a camera that circles the
    scene is the scene's size; a hand-held camera looking forward moves little against the depth it
    sees, so in that unit the oversized rule pruned every seed over two pixels. The point cloud says
    how large the scene is, whichever way the camera moves. Densification keeps the camera extent
    for its clone/split boundary, which fitted fine detail better (docs/results.md §10)."""
    if points is None or len(points) == 0:
        return float(camera_extent)
    centres = np.array([-T[:3, :3].T @ T[:3, 3] for T in poses])
    d = np.linalg.norm(np.asarray(points, dtype=np.float64) - centres.mean(0), axis=1)
    return max(float(camera_extent), 1.1 * float(np.percentile(d, 90)))


def block_learning_rate(name: str, lr: LearningRates, extent: float, iters: int, num_frames: int,
                        centred: bool = False):
    """The learning rate (a number or an ``adam`` schedule) of block ``name`` (module docstring);
    ``extent``: the length the position rates are scaled by (``lr.means_unit``: the camera extent
    or the scene's size, ``position_extent``); ``centred``: the endpoints are a centred exposure
    (only the spread is trained)."""
    kind = name.split(".", 1)[1] if "." in name else name
    if name.startswith((f"{CAMERA}.xi", f"{POSENET}.")):
        # Per-frame rows are visited once per epoch: decay over the visits a row gets.
        visits = iters // num_frames + 1 if name.startswith(f"{CAMERA}.xi") else iters
        if centred and name.startswith(f"{CAMERA}.xi"):
            return adam.exponential_decay(lr.camera_spread, lr.camera_spread_final, visits)
        return adam.exponential_decay(lr.camera, lr.camera_final, visits)
    if name == EXPOSURE_BLOCK:
        return lr.exposure
    if kind == "means":
        return adam.exponential_decay(lr.means * extent, lr.means_final * extent, iters)
    if kind == "deform_means":
        return adam.exponential_decay(lr.deform * extent, lr.means_final * extent, iters)
    if kind.startswith("deform_"):
        return _constant_or_decay(lr.deform_other, lr.final_ratio, iters)
    if kind in _RATE_FIELDS:
        return _constant_or_decay(getattr(lr, kind), lr.final_ratio, iters)
    raise ValueError(f"no learning rate for block {name!r}: add a field {kind!r} to LearningRates "
                     "(train/config.py), or a rule for the block to block_learning_rate (train/learning_rates.py)")


def _constant_or_decay(rate: float, final_ratio: float, iters: int):
    """A block's constant ``rate``, or its log-linear decay to ``final_ratio x rate`` over ``iters``."""
    if final_ratio == 1.0 or rate == 0.0:
        return rate
    return adam.exponential_decay(rate, rate * final_ratio, iters)


def position_extent(lr: LearningRates, camera_extent: float, poses, points) -> float:
    """The length the position rates are scaled by: the camera extent (``lr.means_unit =
    "camera"``, 3DGS) or the scene's size (``"scene"``: ``size_extent`` of the initial points)."""
    if lr.means_unit == "scene":
        return size_extent(poses, points, camera_extent)
    return float(camera_extent)


def learning_rates(block_names, lr: LearningRates, extent: float, iters: int, num_frames: int,
                   centred: bool = False) -> adam.AdamConfig:
    """AdamConfig with the rate of every block in ``block_names`` but the untrained cluster ids."""
    return adam.AdamConfig(lrs={n: block_learning_rate(n, lr, extent, iters, num_frames, centred)
                                for n in block_names if n != CLUSTER})


def camera_row_scales(components, lr: LearningRates, num_frames: int, rule: str = "constant") -> np.ndarray:
    """(num_frames,) factor on the rate of each frame's endpoint rows when Adam alone refines a kept
    bundle adjustment (``Components.adjusted_then == "adam"``), 1 elsewhere (module docstring).
    The frames it held at their given poses: 1. Those it moved: ``lr.camera_adjusted_scale``
    (``rule`` "constant", ``PoseInitConfig.adam_rows``), or ("uncertainty") the frame's
    ``Components.rotation_uncertainty`` clipped to [``lr.camera_adjusted_scale``, 1]."""
    scale = np.ones(num_frames)
    if components.adjusted_then == "adam":
        u = components.rotation_uncertainty
        if rule == "uncertainty" and len(u) == num_frames:
            scale[:] = np.clip(np.asarray(u, dtype=np.float64), lr.camera_adjusted_scale, 1.0)
        else:
            scale[:] = lr.camera_adjusted_scale
        scale[list(components.held_frames)] = 1.0
    return scale


def centre_endpoint_grads(grads):
    """Gradients of a centred exposure: with xi_end = h and xi_start = -h, dL/dh = g_end - g_start,
    given to xi_end, and its negation to xi_start. From antisymmetric endpoints and moments
    (``init_trajectory``'s starts are), Adam's updates then stay exact negations of each other
    (its moment updates are odd in the gradient, v even), so xi_start = -xi_end holds to the last
    bit and the exposure's geodesic midpoint stays the reference pose. On the three-knot path the
    middle knot's gradient is zeroed instead (its T(1/2) is the reference pose) and the endpoints
    keep theirs. Other blocks unchanged."""
    if XI_MID in grads:
        # the three-knot path: its middle knot, the deblurred view, stays at the trusted pose, and
        # the endpoints are free, so the path may bend through it
        return {**grads, XI_MID: np.zeros_like(grads[XI_MID])}
    if XI_START not in grads or XI_END not in grads:
        return grads
    g = grads[XI_END] - grads[XI_START]
    return {**grads, XI_END: g, XI_START: -g}


def position_row_factors(params, cam_T_world, floor: float, dynamic_means=None) -> dict:
    """Per-Gaussian factors on the position steps (``LearningRates.means_depth = "near"``): for
    each block of ``POSITION_BLOCKS`` in ``params``, (N,) factors clip(z / z_med, floor, 1), z each
    Gaussian's (base) depth in the camera ``cam_T_world`` (4, 4) and z_med the median depth of the
    static Gaussians in front of it. A step of length s moves a Gaussian at depth z by about
    f s / z pixels: the factor gives a near Gaussian the pixel step of one at the median depth;
    those at or beyond it, and behind the camera (z <= 0: floor), as a world-unit rule would.
    No static Gaussian in front: all factors 1. ``dynamic_means`` (Nd, 3): the dynamic set's world
    positions where its base means are not (rigid clusters: ``scene.rigid.dynamic_positions``)."""
    R, t = np.asarray(cam_T_world[:3, :3], np.float64), np.asarray(cam_T_world[:3, 3], np.float64)
    depth = {p: np.asarray(params[f"{p}.means"] if p == STATIC or dynamic_means is None else dynamic_means,
                           np.float64) @ R[2] + t[2]
             for p in (STATIC, DYNAMIC) if f"{p}.means" in params}
    zs = depth.get(STATIC, np.zeros(0))
    zs = zs[zs > 0]
    z_med = float(np.median(zs)) if zs.size else None
    out = {}
    for name in POSITION_BLOCKS:
        if name in params:
            z = depth[name.split(".", 1)[0]]
            out[name] = np.ones(len(z)) if z_med is None else np.clip(z / z_med, floor, 1.0)
    return out


def optimiser_step(grads, adam_state, params, config: adam.AdamConfig, trainable, frame: int, lr_scale=1.0,
                   row_scale=1.0, position_factors=None):
    """One Adam step on the blocks whose names start with one of ``trainable`` (the stage's);
    per-frame blocks only in row ``frame``, at ``row_scale`` times their rate (the frame's
    ``camera_row_scales``); blocks in ``position_factors`` (name -> (N,) factors,
    ``position_row_factors``) with each row's step times its factor, as if that row's rate were
    (moments unchanged). Returns (params, adam_state), new dicts."""
    grads = {n: g for n, g in grads.items() if n.startswith(trainable) and n in params}
    sparse = {n: grads.pop(n) for n in list(grads) if n in PER_FRAME_BLOCKS}
    old = params
    params, adam_state = adam.adam_update(grads, adam_state, params, config, lr_step_scale=lr_scale)
    if position_factors:
        params = dict(params)
        for n, f in position_factors.items():
            if n in grads:
                f = np.asarray(f, dtype=old[n].dtype).reshape((-1,) + (1,) * (old[n].ndim - 1))
                params[n] = old[n] + f * (params[n] - old[n])
    if sparse:
        params, adam_state = adam.adam_update_rows(sparse, {n: [frame] for n in sparse}, adam_state, params, config,
                                                   lr_step_scale=lr_scale, lr_factor=row_scale)
    return params, adam_state
