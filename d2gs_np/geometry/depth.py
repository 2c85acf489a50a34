"""Rendered depth against the true depth: the per-pixel terms of AbsRel and delta < 1.25.

Here, below the training layer, so that the trainer's held-out log (``train/plugins.py``) and the
evaluation (``evaluation/metrics.depth_errors``, ``evaluation/runs.py``) score depth alike.
"""
from __future__ import annotations

import numpy as np

__all__ = ["depth_error_terms"]


def depth_error_terms(pred, true, mask=None):
    """Per-pixel terms of the depth metrics (Eigen et al. 2014), for pooling over views.

    pred, true: (H, W) depths (camera z). Scored pixels: ``true`` finite and > 0 (and ``mask``, a
    bool (H, W), True, if given). A prediction that is not finite and positive (nothing rendered
    there) scores as depth 0: relative error 1, outside every delta threshold. Returns (rel (P,) =
    |pred - true| / true, ratio (P,) = max(pred / true, true / pred), +inf for depth 0), over the
    P scored pixels.
    """
    p, t = np.asarray(pred, dtype=np.float64), np.asarray(true, dtype=np.float64)
    if p.ndim != 2 or p.shape != t.shape:
        raise ValueError(f"pred and true must be (H, W) depth maps of one shape; got {p.shape} and {t.shape}")
    keep = np.isfinite(t) & (t > 0)
    if mask is not None:
        m = np.asarray(mask)
        if m.dtype != np.bool_ or m.shape != t.shape:
            raise ValueError(f"mask must be a bool array of shape {t.shape}; got {m.dtype} {m.shape}")
        keep &= m
    p, t = p[keep], t[keep]
    p = np.where(np.isfinite(p) & (p > 0), p, 0.0)
    safe = np.where(p > 0, p, 1.0)
    ratio = np.where(p > 0, np.maximum(p / t, t / safe), np.inf)
    return np.abs(p - t) / t, ratio
