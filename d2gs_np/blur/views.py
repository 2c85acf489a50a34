"""How many virtual views a blurry render uses, and which of them its backward runs through
(docs/method.md §4; ``BlurConfig.n_schedule``, ``BlurConfig.backward_views``).

n views of a blur L pixels long sit L / (n - 1) pixels apart. A render at scale r uses

    "fixed"    n
    "scale"    1 + ceil(r (n - 1)),  at least 2, at most n   (the blur is r L render pixels long)
    "length"   1 + ceil(L / d),      at least 2, at most n   (L: the blur's current length in render
                                                              pixels, d: BlurConfig.view_spacing_px)

views; n = 1 (no blur model) and n = 2 stay n. L is a high quantile of the image-space
displacement of the scene's points between the exposure's start and end (``blur_length_px``);
``frame_views`` applies the schedule to one frame of a model.

The backward through m of the n views (``backward_subset``) cuts the views into m runs of
neighbours, draws view i_j uniformly from run j and weights it w_j = |run_j| / n. View i_j is
drawn with probability 1 / |run_j|, so E[sum_j w_j g_{i_j}] = sum_i g_i / n: the estimate is
unbiased for the gradient of the mean of the n views.
"""
from __future__ import annotations

import math

import numpy as np

from d2gs_np.base.checks import check_scalar, check_choice, check_number
from d2gs_np.blur.config import N_SCHEDULES, _check_backward_views, _check_n
from d2gs_np.geometry.camera import project_points
from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.scene.rigid import dynamic_positions
from d2gs_np.scene.gaussians import DYNAMIC, STATIC

__all__ = [
    "views_at_scale",
    "views_for_length",
    "blur_length_px",
    "frame_views",
    "backward_subset",
]


def views_at_scale(n, scale, schedule="fixed"):
    """Number of virtual views a render at scale r in (0, 1] uses (``BlurConfig.n_schedule``).

    "fixed": n. "scale": 1 + ceil(r (n - 1)), at least 2 and at most n: the n views of a blur
    L full-resolution pixels long are L / (n - 1) pixels apart; at scale r the blur is r L pixels
    long, and 1 + ceil(r (n - 1)) views keep the spacing at or below L / (n - 1). n = 1 (no blur
    model) stays 1. Example, n = 8: r = 0.2 -> 3, r = 0.5 -> 5, r = 1 -> 8.
    """
    n = _check_n(n)
    check_number(scale, "scale", 0.0, 1.0, lo_open=True)
    check_choice(schedule, "n schedule", N_SCHEDULES)
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
    L = check_scalar(length_px, "length_px", 0.0)
    d = check_scalar(spacing_px, "spacing_px")
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


def frame_views(scene_params, frame_time, tau, pose_est, xi_start, xi_end, K, width, height, full_width,
                blur_config, deform_config) -> int:
    """Virtual views of one frame's blurry render at width x height (``blur_config.n_schedule``):
    n ("fixed"), by render scale width / full_width ("scale") or by the blur's current length in
    render pixels ("length": the static means through the endpoint poses exp(xi_start) T̂ and
    exp(xi_end) T̂, and the dynamic set's deformed means at the first and last sub-frame times
    frame_time -/+ tau / 2; the longer of the two blurs).

    scene_params: the scene blocks ("static.*", "dynamic.*"). frame_time, tau: the frame's
    mid-exposure time and exposure length. pose_est: (4, 4) cam_T_world T̂ the endpoints perturb;
    xi_start, xi_end: (6,). K: (3, 3) intrinsics at width x height; full_width: the frame's
    full-resolution width. blur_config: BlurConfig; deform_config: DeformConfig. Trusts its
    inputs (the training step calls it on a validated model).
    """
    bc = blur_config
    if bc.n_schedule != "length":
        return views_at_scale(bc.num_virtual, min(1.0, width / full_width), bc.n_schedule)
    T = np.asarray(pose_est, dtype=np.float64)
    Ts, Te = se3_exp(np.asarray(xi_start, np.float64)) @ T, se3_exp(np.asarray(xi_end, np.float64)) @ T
    m = scene_params[f"{STATIC}.means"]
    length = blur_length_px(m, m, Ts, Te, K, width, height)
    if f"{DYNAMIC}.means" in scene_params and scene_params[f"{DYNAMIC}.means"].shape[0] > 0:
        t = float(frame_time)
        ends = dynamic_positions(scene_params, (t - 0.5 * tau, t + 0.5 * tau), deform_config)
        length = max(length, blur_length_px(ends[0], ends[1], Ts, Te, K, width, height))
    return views_for_length(bc.num_virtual, length, bc.view_spacing_px)


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

