"""Smooth camera paths of the synthetic worlds (data/synthetic.py, data/suite.py): sums of sines.

A sway or a shake is a block (n, 3, 3) of n sine terms per axis, rows (amplitude, cycles per
clip, phase) (``random_sines``); its value at normalised times t (``eval_sines``) is C-infinity
in t, so a camera built from such blocks moves smoothly inside every exposure.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.geometry.camera import look_at, make_intrinsics
from d2gs_np.geometry.so3 import so3_exp

__all__ = ["random_sines", "eval_sines", "as_times", "shaken_look_at", "fov_intrinsics"]


def random_sines(rng, amps, freqs, freq_jitter=0.15):
    """(n, 3, 3) sum-of-sines block: amplitude (n, 3), cycles per clip (n, 3), random phase."""
    amps = np.broadcast_to(np.asarray(amps, dtype=np.float64), (len(freqs), 3))
    f = np.asarray(freqs, dtype=np.float64)[:, None] * (1.0 + freq_jitter * rng.uniform(-1, 1, (len(freqs), 3)))
    p = rng.uniform(0.0, 2.0 * np.pi, (len(freqs), 3))
    return np.stack([amps, f, p], axis=1)


def eval_sines(block, t):
    """block (n, 3, 3), t (M,) -> (M, 3)."""
    a, f, p = block[:, 0], block[:, 1], block[:, 2]
    return np.einsum("nd,mnd->md", a, np.sin(2.0 * np.pi * f[None] * t[:, None, None] + p[None]))


def as_times(t, name="t"):
    """Time(s) t as a float64 array (a scalar or (M,)), checked finite."""
    arr = np.asarray(t, dtype=np.float64)
    if arr.ndim > 1:
        raise ValueError(f"{name} must be a scalar or a 1-D array of times; got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


def shaken_look_at(eye, target, rot_shake):
    """(M, 4, 4) cam_T_world looking from eye (M, 3) at target (M, 3), y up, then turned about the
    camera centre by so3_exp(rot_shake) (M, 3): a hand's rotational shake."""
    R_shake = so3_exp(rot_shake)
    poses = np.empty((len(eye), 4, 4))
    for m in range(len(eye)):
        T = look_at(eye[m], target[m], up=(0.0, 1.0, 0.0))
        poses[m] = T
        poses[m, :3, :3] = R_shake[m] @ T[:3, :3]
        poses[m, :3, 3] = R_shake[m] @ T[:3, 3]
    return poses


def fov_intrinsics(width, height, fov_x_deg):
    """(3, 3) K: square pixels, horizontal field of view ``fov_x_deg``, principal point at the image centre."""
    f = 0.5 * width / np.tan(0.5 * np.deg2rad(fov_x_deg))
    return make_intrinsics(f, f, 0.5 * width, 0.5 * height)
