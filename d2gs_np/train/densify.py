"""Densification (3DGS's adaptive density control): clone small and split large Gaussians whose
screen-space position gradient is large. docs/method.md §8 allows it "if measured to help".

Per Gaussian we accumulate the norm of dL/d(mean2d) in FULL-resolution pixels (the gradient at
render scale r is multiplied by r) over the steps where it was visible, and every ``every``
steps inside [start, stop) of training:
- mean norm > threshold and max scale <= percent_dense x extent: clone (a copy, same parameters);
- mean norm > threshold and larger: split into two, positions drawn from the Gaussian, scales
  divided by ``split_factor`` (the original is replaced);
new rows get zero Adam moments (``adam_extend``) and dynamic rows keep their deformation
coefficients. The threshold is 3DGS's 2e-4 in NDC units, converted with d(ndc) = 2 d(px) / W.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from d2gs_np.geometry.quaternion import quat_to_rotmat
from d2gs_np.optim import adam
from d2gs_np.scene import gaussians


@dataclass(frozen=True)
class DensifyConfig:
    # On by default, measured: sharp preset (24 frames 240x135, 2000 steps) DVS 31.3 dB without,
    # 39.3 dB with (158 s -> 277 s of training); blurry demo scene 19.34 -> 19.99 dB.
    enabled: bool = True
    start_fraction: float = 0.1
    stop_fraction: float = 0.6
    every: int = 100
    grad_threshold_ndc: float = 2e-4  # 3DGS default
    percent_dense: float = 0.01  # clone below this share of the scene extent, split above
    split_factor: float = 1.6
    max_gaussians: int = 40000

    def __post_init__(self):
        if not 0.0 <= self.start_fraction <= self.stop_fraction <= 1.0:
            raise ValueError(f"DensifyConfig needs 0 <= start_fraction <= stop_fraction <= 1; got "
                             f"{self.start_fraction}, {self.stop_fraction}")
        if self.every < 1 or self.max_gaussians < 1:
            raise ValueError("DensifyConfig.every and max_gaussians must be >= 1")
        if self.grad_threshold_ndc <= 0 or self.percent_dense <= 0 or self.split_factor <= 1:
            raise ValueError("DensifyConfig: grad_threshold_ndc and percent_dense must be > 0, split_factor > 1")


class GradientStats:
    """Accumulated screen-space gradient norms per set ("static", "dynamic")."""

    def __init__(self, params):
        self.sum = {p: np.zeros(self._n(params, p)) for p in ("static", "dynamic")}
        self.count = {p: np.zeros(self._n(params, p)) for p in ("static", "dynamic")}

    @staticmethod
    def _n(params, prefix):
        return params[f"{prefix}.means"].shape[0] if f"{prefix}.means" in params else 0

    def add(self, v_means2d_full, visible, num_static):
        """v_means2d_full (M, 2) for the rendered rows (static first, then dynamic if rendered)."""
        norm = np.linalg.norm(v_means2d_full, axis=1) * visible
        self.sum["static"] += norm[:num_static]
        self.count["static"] += visible[:num_static]
        if norm.shape[0] > num_static:
            self.sum["dynamic"] += norm[num_static:]
            self.count["dynamic"] += visible[num_static:]

    def select(self, prefix, keep):
        self.sum[prefix] = self.sum[prefix][keep]
        self.count[prefix] = self.count[prefix][keep]

    def mean(self, prefix):
        return self.sum[prefix] / np.maximum(self.count[prefix], 1.0)


def densify(params, adam_state, stats: GradientStats, config: DensifyConfig, extent, width, rng):
    """Clone / split (see the module docstring). Returns (params, adam_state, stats, info)."""
    threshold = config.grad_threshold_ndc * 2.0 / float(width)
    info = {"cloned": 0, "split": 0}
    total = sum(GradientStats._n(params, p) for p in ("static", "dynamic"))
    for prefix in ("static", "dynamic"):
        n = GradientStats._n(params, prefix)
        if n == 0:
            continue
        budget = config.max_gaussians - total
        if budget <= 0:
            break
        grad = stats.mean(prefix)
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
                rows = slice(m + c * len(split_idx), m + (c + 1) * len(split_idx))
                offset = np.einsum("nij,nj->ni", R, rng.normal(size=s.shape) * s)
                new[f"{prefix}.means"][rows] += offset
                new[f"{prefix}.log_scales"][rows] -= np.log(config.split_factor)
        params = gaussians.append_gaussians(params, new)
        adam_state = adam.adam_extend(adam_state, prefix, len(clone_idx) + 2 * len(split_idx))
        # Remove the split originals.
        keep = np.ones(n + len(clone_idx) + 2 * len(split_idx), dtype=bool)
        keep[split_idx] = False
        keep_s = keep if prefix == "static" else np.ones(GradientStats._n(params, "static"), bool)
        keep_d = keep if prefix == "dynamic" else (
            np.ones(GradientStats._n(params, "dynamic"), bool) if gaussians.has_dynamic(params) else None)
        params = gaussians.prune(params, keep_s, keep_d)
        adam_state = adam.adam_select(adam_state, prefix, keep)
        info["cloned"] += int(len(clone_idx))
        info["split"] += int(len(split_idx))
        total += len(clone_idx) + len(split_idx)
    return params, adam_state, GradientStats(params), info
