"""Densification (3DGS's adaptive density control): clone small and split large Gaussians whose
screen-space position gradient is large. docs/method.md §8 allows it "if measured to help".

Per Gaussian we accumulate the norm of dL/d(mean2d) in FULL-resolution pixels (the gradient at
render scale r is multiplied by r) over the steps where it was visible, and every ``every``
steps inside [start, stop) of training:
- mean norm > threshold and max scale <= percent_dense x extent: clone (a copy, same parameters);
- mean norm > threshold and larger: split into two, positions drawn from the Gaussian, scales
  divided by ``split_factor`` (the original is replaced);
new rows get zero Adam moments and statistics (``train.rows.resize_rows``) and dynamic rows keep
their deformation coefficients. The threshold is 3DGS's 2e-4 in NDC units, converted with
d(ndc) = 2 d(px) / W.

With ``absgrad`` the statistic is instead the norm of the per-axis sums of the absolute per-pixel
terms of dL/d(mean2d) (the renderer's ``means2d_abs``; gsplat's ``absgrad``, after AbsGS, Ye et
al. 2024): in fine texture a Gaussian too coarse for it is pulled different ways by its pixels,
and those pulls cancel in the plain gradient, so the plain rule leaves it alone. The absolute
sum is larger than the plain norm, so it has its own threshold, ``grad_threshold_abs_ndc``
(gsplat's advice for absgrad: 4x 3DGS's, 8e-4).

The statistics are per-row arrays in the training state's ``rows`` (``GRAD_SUM``,
``GRAD_COUNT``), accumulated after every step by the ``GradientStatistics`` plugin and used and
reset by the ``Densify`` plugin (``train/plugins.py``).
"""
from __future__ import annotations

import math

import numpy as np

from d2gs_np.geometry.quaternion import quat_to_rotmat
from d2gs_np.scene.gaussians import DYNAMIC, STATIC
from d2gs_np.train.config import DensifyConfig
from d2gs_np.train.rows import SETS, num_rows, resize_rows


GRAD_SUM = "densify/sum"  # per-row statistics (train/rows.py), checkpointed as densify/sum/<set>
GRAD_COUNT = "densify/count"


def gaussian_cap(config: DensifyConfig, pixels: int) -> int:
    """The most Gaussians densification may reach on a clip of ``pixels`` observed pixels (frames x
    height x width at full resolution): one per ``pixels_per_gaussian`` of them, at most
    ``max_gaussians``; ``max_gaussians`` alone when ``pixels_per_gaussian`` is 0 (the default:
    docs/method.md §8 has what the rule gained and lost)."""
    if config.pixels_per_gaussian <= 0:
        return int(config.max_gaussians)
    if pixels < 1:
        raise ValueError(f"gaussian_cap needs the clip's observed pixel count (>= 1); got {pixels}")
    return min(config.max_gaussians, max(1, math.ceil(pixels / config.pixels_per_gaussian)))


def dynamic_gaussian_cap(config: DensifyConfig, moving_pixels: int) -> int:
    """The most Gaussians densification may grow the dynamic set to on a clip whose motion masks mark
    ``moving_pixels`` pixels (over all frames, full resolution): one per
    ``dynamic_pixels_per_gaussian`` of them (17 by default), at least 1; 0 (no cap of its own: the
    dynamic set takes what the total cap leaves) when that is 0. A cap below the set's size stops
    its growth; it never removes rows."""
    if config.dynamic_pixels_per_gaussian <= 0:
        return 0
    if moving_pixels < 0:
        raise ValueError(f"dynamic_gaussian_cap needs the motion masks' pixel count (>= 0); got {moving_pixels}")
    return max(1, math.ceil(moving_pixels / config.dynamic_pixels_per_gaussian))


def init_grad_stats(params) -> dict:
    """Zero statistics for every row of both sets: {GRAD_SUM: {set: (N_set,)}, GRAD_COUNT: ...}."""
    return {name: {p: np.zeros(num_rows(params, p)) for p in SETS} for name in (GRAD_SUM, GRAD_COUNT)}


def add_grad_stats(rows, v_means2d_full, visible, num_static) -> dict:
    """Statistics after one step: ``v_means2d_full`` (M, 2) screen-space mean gradients in
    full-resolution pixels and ``visible`` (M,) 0/1 of the rendered rows (static first, then
    dynamic if it was rendered). Returns a new dict; other statistics in ``rows`` are kept."""
    norm = np.linalg.norm(v_means2d_full, axis=1) * visible
    s, c = dict(rows[GRAD_SUM]), dict(rows[GRAD_COUNT])
    s[STATIC] = s[STATIC] + norm[:num_static]
    c[STATIC] = c[STATIC] + visible[:num_static]
    if norm.shape[0] > num_static:
        s[DYNAMIC] = s[DYNAMIC] + norm[num_static:]
        c[DYNAMIC] = c[DYNAMIC] + visible[num_static:]
    return {**rows, GRAD_SUM: s, GRAD_COUNT: c}


def mean_grad(rows, prefix):
    """Mean screen-space gradient norm of each row of a set over the steps it was visible."""
    return rows[GRAD_SUM][prefix] / np.maximum(rows[GRAD_COUNT][prefix], 1.0)


def reset_opacity(params, adam_state, value):
    """3DGS's opacity reset: every opacity lowered to at most ``value`` (in (0, 1)), the Adam moments
    of the opacity blocks zeroed and their step counts kept (as 3DGS replaces the optimiser's tensor).
    Returns (params, adam_state, number lowered); the inputs are not modified."""
    if not 0.0 < value < 1.0:
        raise ValueError(f"reset_opacity: value must lie in (0, 1); got {value}")
    ceiling = math.log(value) - math.log1p(-value)  # logit(value)
    params, adam_state = dict(params), {slot: dict(blocks) for slot, blocks in adam_state.items()}
    lowered = 0
    for prefix in SETS:
        name = f"{prefix}.opacity_logits"
        if name not in params:
            continue
        x = params[name]
        lowered += int(np.count_nonzero(x > ceiling))
        params[name] = np.minimum(x, np.asarray(ceiling, dtype=x.dtype))
        for slot in ("m", "v"):
            if name in adam_state.get(slot, {}):
                adam_state[slot][name] = np.zeros_like(adam_state[slot][name])
    return params, adam_state, lowered


def densify(params, adam_state, rows, config: DensifyConfig, extent, width, rng, dynamic_cap: int = 0):
    """Clone / split (see the module docstring), through ``train.rows.resize_rows`` so the Adam
    state and every per-row statistic follow; then the gradient statistics restart from zero.
    Returns (params, adam_state, rows, info) with info = {"cloned": int, "split": int} (totals)
    and, per set, {"<set>_cloned": int, "<set>_split": int}.

    When the candidates exceed what ``max_gaussians`` leaves, the static set takes the room first
    (its highest gradients), the dynamic set what is left: the moving pixels are not short of
    Gaussians, so a joint ranking would only move rows to the dynamic set (docs/results.md §10).
    ``dynamic_cap`` > 0 (``dynamic_gaussian_cap``) bounds the dynamic set's own growth as well."""
    threshold = (config.grad_threshold_abs_ndc if config.absgrad else config.grad_threshold_ndc) * 2.0 / float(width)
    info = {"cloned": 0, "split": 0}
    info.update({f"{p}_{kind}": 0 for p in SETS for kind in ("cloned", "split")})
    total = sum(num_rows(params, p) for p in SETS)
    for prefix in SETS:
        n = num_rows(params, prefix)
        if n == 0:
            continue
        budget = config.max_gaussians - total
        if prefix == DYNAMIC and dynamic_cap > 0:
            budget = min(budget, dynamic_cap - n)
        if budget <= 0:
            continue
        grad = mean_grad(rows, prefix)
        scales = np.exp(params[f"{prefix}.log_scales"])
        big = scales.max(axis=1) > config.percent_dense * extent
        hot = grad > threshold
        clone_idx = np.flatnonzero(hot & ~big)
        split_idx = np.flatnonzero(hot & big)
        # Highest gradients first when over budget (a split adds one net row, a clone one).
        order = np.concatenate([clone_idx, split_idx])
        if order.size > budget:
            keep = order[np.argsort(-grad[order])[:budget]]
            clone_idx = np.intersect1d(clone_idx, keep)
            split_idx = np.intersect1d(split_idx, keep)
        fields = [k[len(prefix) + 1:] for k in params if k.startswith(prefix + ".")]
        new = {f"{prefix}.{f}": params[f"{prefix}.{f}"][np.concatenate([clone_idx, split_idx, split_idx])].copy()
               for f in fields}
        if split_idx.size:
            # Two children per split Gaussian, sampled from it, smaller by split_factor.
            s = scales[split_idx]
            R = quat_to_rotmat(params[f"{prefix}.quats"][split_idx])
            m = len(clone_idx)
            for c in range(2):
                sl = slice(m + c * len(split_idx), m + (c + 1) * len(split_idx))
                offset = np.einsum("nij,nj->ni", R, rng.normal(size=s.shape) * s)
                new[f"{prefix}.means"][sl] += offset
                new[f"{prefix}.log_scales"][sl] -= np.log(config.split_factor)
        # New rows appended, the split originals removed.
        keep = np.ones(n + len(clone_idx) + 2 * len(split_idx), dtype=bool)
        keep[split_idx] = False
        params, adam_state, rows = resize_rows(params, adam_state, rows, prefix, keep=keep, new=new)
        info["cloned"] += int(len(clone_idx))
        info["split"] += int(len(split_idx))
        info[f"{prefix}_cloned"], info[f"{prefix}_split"] = int(len(clone_idx)), int(len(split_idx))
        total += len(clone_idx) + len(split_idx)
    return params, adam_state, {**rows, **init_grad_stats(params)}, info
