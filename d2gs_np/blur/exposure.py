"""The exposure length tau of the blur model (docs/method.md §4), in normalised time: the clip
spans [0, 1] over N frames, so one frame interval is 1 / (N - 1).

- known from the scene: tau = exposure_fraction / (N - 1)  (``exposure_from_scene``);
- learned: block ``camera.exposure_logit`` (1,), tau = sigmoid(logit) / (N - 1), kept inside
  (0, 1) of the frame interval (``exposure_fwd``; ``exposure_bwd``:
  d tau / d logit = sigmoid (1 - sigmoid) / (N - 1)); initialised at fraction 1/2 (logit 0,
  ``init_exposure``), the middle of the range and a typical shutter of video (a 180-degree
  shutter), where the sigmoid is also steepest.

tau spreads the sub-frame times t_i = t_k + (u_i - 1/2) tau (d2gs_np.blur.virtual_poses); its
gradient comes from the blurred render's backward (d2gs_np.blur.render).
"""
from __future__ import annotations

import math

import numpy as np

from d2gs_np.base.checks import check_scalar, check_int

__all__ = [
    "EXPOSURE_BLOCK",
    "exposure_from_scene",
    "init_exposure",
    "exposure_fwd",
    "exposure_bwd",
]

EXPOSURE_BLOCK = "camera.exposure_logit"


def _check_num_frames(num_frames):
    return check_int(num_frames, "num_frames", 1)


def exposure_from_scene(exposure_fraction, num_frames):
    """tau = exposure_fraction / (N - 1) in normalised time (0 for a single frame).

    exposure_fraction: exposure time as a fraction of the frame interval, in [0, 1].
    """
    f = check_scalar(exposure_fraction, "exposure_fraction", 0.0)
    if f > 1.0:
        raise ValueError(f"exposure_fraction must be in [0, 1] (a fraction of the frame interval); got {f}")
    N = _check_num_frames(num_frames)
    return 0.0 if N == 1 else f / (N - 1)


def init_exposure(fraction=0.5, dtype=np.float64):
    """{"camera.exposure_logit": (1,)} with sigmoid(logit) = fraction in (0, 1) (default 1/2)."""
    f = check_scalar(fraction, "fraction")
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
    x = check_scalar(logit[0], EXPOSURE_BLOCK)
    N = _check_num_frames(num_frames)
    sig = 0.5 * (1.0 + math.tanh(0.5 * x))  # sigmoid without overflow
    scale = 0.0 if N == 1 else 1.0 / (N - 1)
    return sig * scale, {"sig": sig, "scale": scale, "dtype": logit.dtype}


def exposure_bwd(saved, v_tau):
    """{"camera.exposure_logit": (1,)} gradient from the scalar v_tau."""
    v_tau = check_scalar(v_tau, "v_tau")
    sig = saved["sig"]
    return {EXPOSURE_BLOCK: np.array([v_tau * saved["scale"] * sig * (1.0 - sig)], dtype=saved["dtype"])}

