"""Opacity entropy L_gs (docs/method.md §6, Eq. 14): pushes each Gaussian to be opaque or gone.

    L_gs = mean over Gaussians of  -o log(clamp(o, OPACITY_ENTROPY_MIN, 1)),   o = sigmoid(logit)

-o log o is 0 at o = 0 and o = 1 and largest (1/e) at o = 1/e, so its gradient moves a
half-transparent Gaussian (a floater) towards one of the two ends; pruning then removes the
transparent ones. The clamp keeps log(o) finite as o -> 0: below the clamp the term is
-o log(OPACITY_ENTROPY_MIN), linear in o, and its gradient through the logit,
-log(OPACITY_ENTROPY_MIN) o (1 - o), goes to 0 with o. At o = 1 (a logit of +inf in float64 for
logits above ~37) the value and gradient are 0. ``1 - o`` is evaluated as ``sigmoid(-logit)`` so
it keeps its precision where o is close to 1.

The backward is through the logit: d/dlogit = dh/do * o (1 - o), dh/do = -(log o + 1) above the
clamp and -log(OPACITY_ENTROPY_MIN) below it.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.constants import OPACITY_ENTROPY_MIN
from d2gs_np.scene.gaussians import sigmoid

__all__ = ["entropy_fwd", "entropy_bwd"]


def entropy_fwd(opacity_logits):
    """Mean opacity entropy of the Gaussians with these logits.

    opacity_logits: (N,) float64 or float32 array, finite (N = 0 gives 0).
    Returns (value, a Python float, saved).
    """
    if not isinstance(opacity_logits, np.ndarray):
        raise TypeError(f"opacity_logits must be a numpy array; got {type(opacity_logits).__name__}")
    if opacity_logits.dtype not in (np.float64, np.float32):
        raise TypeError(f"opacity_logits must be float64 or float32; got {opacity_logits.dtype}")
    if opacity_logits.ndim != 1:
        raise ValueError(f"opacity_logits must have shape (N,); got {opacity_logits.shape}")
    if not np.all(np.isfinite(opacity_logits)):
        raise ValueError("opacity_logits contains NaN or inf; every logit must be finite")
    return _entropy_fwd(opacity_logits)


def _entropy_fwd(opacity_logits):
    n = opacity_logits.shape[0]
    z = opacity_logits.astype(np.float64, copy=False)
    o = sigmoid(z)
    one_minus_o = sigmoid(-z)
    log_o = np.log(np.maximum(o, OPACITY_ENTROPY_MIN))
    value = float(-np.sum(o * log_o) / n) if n else 0.0
    saved = dict(o=o, one_minus_o=one_minus_o, log_o=log_o, clamped=o < OPACITY_ENTROPY_MIN,
                 dtype=opacity_logits.dtype, n=n)
    return value, saved


def entropy_bwd(saved, v_value=1.0):
    """Gradient of ``v_value * entropy_fwd(logits)[0]`` w.r.t. the logits, (N,) of their dtype."""
    n = saved["n"]
    if n == 0:
        return np.zeros(0, dtype=saved["dtype"])
    dh_do = np.where(saved["clamped"], -saved["log_o"], -(saved["log_o"] + 1.0))
    v = (v_value / n) * dh_do * (saved["o"] * saved["one_minus_o"])
    return v.astype(saved["dtype"], copy=False)
