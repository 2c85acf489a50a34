"""Progressive-resolution schedule (docs/method.md §7, the paper's Eq. 16) and downsampled targets.

Training renders frame k at render scale r <= 1: the image size is
``geometry.camera.scaled_size(W, H, r)``, the intrinsics are scaled to that size
(``geometry.camera.scale_intrinsics``) and the blurry target (and its motion mask) is
downsampled to the same size by area averaging. The scale rises from r0 (default 0.2) to 1 over
the first ``T = ramp_fraction * total_steps`` steps (default: half of training) and stays at 1
afterwards. Eq. 16 as printed decreases; the text means an increase, which is what is done here.

Kinds of ramp, with s = step / T in [0, 1] (all give r(0) = r0, r(T) = 1 and are non-decreasing):

- ``"cosine"``      r = r0 + (1 - r0) (1 - cos(pi s)) / 2          (the paper's; slow-fast-slow)
- ``"linear"``      r = r0 + (1 - r0) s
- ``"exponential"`` r = r0^(1 - s)   (geometric: equal *ratios* per step; slow start)
- ``"inverse_sqrt"`` r = 1 / sqrt(1/r0^2 - (1/r0^2 - 1) s)
      i.e. the area per rendered pixel, 1/r^2, falls linearly from 1/r0^2 to 1, so r is an
      inverse square root of a linear function of the step. This is the slowest start of the
      four (r(T/2) = 0.277 for r0 = 0.2, against 0.447 exponential and 0.6 cosine / linear):
      most of the ramp runs at low, cheap resolutions and the last part sharpens quickly.
      (The transformer "inverse square root" learning-rate rule decays without ever reaching a
      fixed end; it cannot hit r(T) = 1 exactly, hence this definition.)
"""
from __future__ import annotations

import math
import numbers
from collections import OrderedDict
from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np

from d2gs_np.base.checks import check_choice, check_int, check_number
from d2gs_np.geometry.camera import check_intrinsics, scale_intrinsics, scaled_size

__all__ = [
    "SCHEDULE_KINDS",
    "ScheduleConfig",
    "training_progress",
    "schedule_step",
    "render_scale",
    "downsample_area",
    "downsample_mask",
    "Target",
    "TargetCache",
]

SCHEDULE_KINDS = ("cosine", "linear", "exponential", "inverse_sqrt")


def _check_schedule_args(r0, kind, ramp_fraction, where):
    check_number(r0, f"{where}r0", 0.0, 1.0, lo_open=True)
    check_choice(kind, f"{where}kind", SCHEDULE_KINDS)
    check_number(ramp_fraction, f"{where}ramp_fraction", 0.0, 1.0)


@dataclass(frozen=True)
class ScheduleConfig:
    """Progressive-resolution settings (docs/method.md §7).

    r0: render scale at step 0, in (0, 1].
    kind: one of SCHEDULE_KINDS ("cosine" is the paper's).
    ramp_fraction: the scale reaches 1 after ramp_fraction * total_steps steps, in [0, 1]
        (0: full resolution from the start).
    mask_threshold: a low-resolution pixel is marked moving when the area fraction of moving
        full-resolution pixels it covers is > mask_threshold, in [0, 1). The default 0 marks it
        moving as soon as any moving pixel falls inside it (a conservative dilation: static-only
        uses of the mask, such as static correspondences, never see a moving pixel).
    """

    r0: float = 0.2
    kind: str = "cosine"
    ramp_fraction: float = 0.5
    mask_threshold: float = 0.0

    def __post_init__(self):
        _check_schedule_args(self.r0, self.kind, self.ramp_fraction, "ScheduleConfig.")
        check_number(self.mask_threshold, "ScheduleConfig.mask_threshold", 0.0, 1.0, hi_open=True)

    def scale(self, step, total_steps):
        """render_scale(step, total_steps) with this config's r0, kind and ramp_fraction."""
        return render_scale(step, total_steps, r0=self.r0, kind=self.kind, ramp_fraction=self.ramp_fraction)


def render_scale(step, total_steps, r0=0.2, kind="cosine", ramp_fraction=0.5):
    """Render scale r(step) in [r0, 1] (see the module docstring for the four kinds).

    step: int >= 0 (steps past total_steps are allowed and give 1).
    total_steps: int >= 1. The ramp length is T = ramp_fraction * total_steps (a float);
    T = 0 gives r = 1 for every step.
    """
    for name, value, low in (("step", step, 0), ("total_steps", total_steps, 1)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise TypeError(f"{name} must be an int; got {type(value).__name__}")
        if value < low:
            raise ValueError(f"{name} must be >= {low}; got {value}")
    _check_schedule_args(r0, kind, ramp_fraction, "")
    ramp = float(ramp_fraction) * int(total_steps)
    if ramp <= 0.0 or step >= ramp:
        return 1.0
    s = step / ramp
    r0 = float(r0)
    if kind == "cosine":
        r = r0 + (1.0 - r0) * 0.5 * (1.0 - math.cos(math.pi * s))
    elif kind == "linear":
        r = r0 + (1.0 - r0) * s
    elif kind == "exponential":
        r = r0 ** (1.0 - s)
    else:  # inverse_sqrt
        a = 1.0 / (r0 * r0)
        r = 1.0 / math.sqrt(a - (a - 1.0) * s)
    return min(1.0, max(r0, r))


def training_progress(step, seconds, total_steps, time_budget=None):
    """How far a run is, in [0, 1]: ``step / total_steps``, or with a time budget (seconds of
    training) the larger of that and ``seconds / time_budget``, whichever ends the schedule first.

    Every schedule of a run (progressive resolution, stages, learning-rate decays, densification
    and pruning windows) reads this progress, so a run stopped by its budget has finished its
    schedule, and a run without one behaves exactly as before (progress = step / total_steps).
    A run that finishes its schedule inside its budget trains on at the schedule's end until the
    budget is spent (``TrainConfig.stretch_to_budget``, the trainer's loop).
    """
    if total_steps < 1:
        raise ValueError(f"total_steps must be >= 1; got {total_steps}")
    p = step / total_steps
    if time_budget is not None:
        if not time_budget > 0:
            raise ValueError(f"time_budget must be > 0 seconds; got {time_budget}")
        p = max(p, seconds / time_budget)
    return min(max(p, 0.0), 1.0)


def schedule_step(step, seconds, total_steps, time_budget=None):
    """The step the schedules are read at: ``step`` without a budget (exactly), else
    ``max(step, floor(progress x total_steps))``."""
    if time_budget is None:
        return int(step)
    return max(int(step), int(math.floor(training_progress(step, seconds, total_steps, time_budget) * total_steps)))


def _check_size(width, height):
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise TypeError(f"{name} must be an int; got {type(value).__name__}")
        if value < 1:
            raise ValueError(f"{name} must be >= 1; got {value}")


def _area_weights(n_in, n_out):
    """(n_out, n_in) matrix of area-averaging weights along one axis (rows sum to 1).

    Output pixel j covers the input interval [j f, (j + 1) f), f = n_in / n_out; its weight on
    input pixel i is the length of [i, i + 1) inside that interval, divided by f.
    """
    f = n_in / n_out
    lo = np.arange(n_out)[:, None] * f
    hi = lo + f
    i = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(hi, i + 1.0) - np.maximum(lo, i), 0.0, None)
    return overlap / overlap.sum(axis=1, keepdims=True)


def downsample_area(image, width, height):
    """Area-averaged resize of ``image`` (H, W, C) or (H, W) to (height, width, ...).

    The semantics of cv2.INTER_AREA for shrinking: each output pixel is the mean of the input
    area it covers, input pixels cut by its border weighted by the covered fraction. Computed
    here exactly, as two separable weight matrices in float64 (cv2's own implementation uses
    float32 weights, ~1e-8 relative error for factor 3), so an integer factor gives the exact
    block mean. Only downsampling (width <= W, height <= H); the same size returns a copy.
    float32 input returns float32 (computed in float64), anything else float64.
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must have shape (H, W) or (H, W, C); got {image.shape}")
    _check_size(width, height)
    H, W = image.shape[:2]
    if width > W or height > H:
        raise ValueError(
            f"downsample_area only shrinks images: asked for {width}x{height} from {W}x{H}; "
            "pass width <= W and height <= H")
    dtype = np.float32 if image.dtype == np.float32 else np.float64
    if (width, height) == (W, H):
        return np.array(image, dtype=dtype, copy=True)
    x = image.astype(np.float64)
    if H % height == 0 and W % width == 0:  # integer factors: plain block mean
        fy, fx = H // height, W // width
        out = x.reshape((height, fy, width, fx) + x.shape[2:]).mean(axis=(1, 3))
    else:
        out = np.tensordot(_area_weights(H, height), x, axes=(1, 0))  # (height, W, ...)
        out = np.moveaxis(np.tensordot(_area_weights(W, width), out, axes=(1, 1)), 0, 1)
    return np.ascontiguousarray(out, dtype=dtype)


def downsample_mask(mask, width, height, threshold=0.0):
    """Boolean (height, width) motion mask from a (H, W) mask: area fraction > threshold.

    With threshold 0 a low-resolution pixel is moving when any full-resolution pixel inside it is
    moving (the area average of a 0/1 image is exactly 0 where no moving pixel contributes).
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask must have shape (H, W); got {mask.shape}")
    if not (0.0 <= threshold < 1.0):
        raise ValueError(f"threshold must be in [0, 1); got {threshold}")
    frac = downsample_area((mask > 0).astype(np.float64), width, height)
    return frac > threshold


class Target(NamedTuple):
    """A training target at one size: image (h, w, 3), mask (h, w) bool or None, K (3, 3)."""

    image: np.ndarray
    mask: Optional[np.ndarray]
    K: np.ndarray
    width: int
    height: int


class TargetCache:
    """Per-(frame, size) cache of downsampled targets, masks and scaled intrinsics.

    images: sequence of N arrays (H_k, W_k, 3) (full-resolution blurry frames).
    masks: None, or a sequence of N arrays (H_k, W_k) (bool or 0/1; True = moving) or None each.
    intrinsics: one (3, 3) matrix for all frames, or a sequence of N of them.
    mask_threshold: see ScheduleConfig.mask_threshold.
    max_entries: least-recently-used entries beyond this are dropped (a continuous schedule
        visits many sizes; each entry holds a copy of a target image).

    ``get(frame_index, scale)`` returns a ``Target`` at ``scaled_size(W_k, H_k, scale)``; the
    second call with the same frame and size returns the *same* object. The intrinsics are
    scaled per axis by (w / W_k, h / H_k) so pixel edges map to edges (scale_intrinsics). At
    scale 1 the full-resolution image itself is returned (no copy).
    """

    def __init__(self, images, masks=None, intrinsics=None, mask_threshold=0.0, max_entries=256):
        self._images = list(images)
        n = len(self._images)
        for k, img in enumerate(self._images):
            if not isinstance(img, np.ndarray) or img.ndim != 3:
                raise ValueError(f"images[{k}] must be an array of shape (H, W, C); got "
                                 f"{getattr(img, 'shape', type(img).__name__)}")
        if masks is None:
            masks = [None] * n
        self._masks = list(masks)
        if len(self._masks) != n:
            raise ValueError(f"masks must have one entry per image ({n}); got {len(self._masks)}")
        for k, (img, m) in enumerate(zip(self._images, self._masks)):
            if m is not None and np.shape(m) != img.shape[:2]:
                raise ValueError(f"masks[{k}] must have shape {img.shape[:2]} like images[{k}]; "
                                 f"got {np.shape(m)}")
        if intrinsics is None:
            raise ValueError("intrinsics must be given: one (3, 3) K or a sequence of N of them")
        Ks = np.asarray(intrinsics, dtype=np.float64)
        if Ks.shape == (3, 3):
            Ks = np.broadcast_to(Ks, (n, 3, 3))
        if Ks.shape != (n, 3, 3):
            raise ValueError(f"intrinsics must have shape (3, 3) or ({n}, 3, 3); got {Ks.shape}")
        for k in range(n):
            check_intrinsics(Ks[k], name=f"intrinsics[{k}]")
        self._Ks = Ks
        if not (0.0 <= mask_threshold < 1.0):
            raise ValueError(f"mask_threshold must be in [0, 1); got {mask_threshold}")
        self._mask_threshold = float(mask_threshold)
        check_int(max_entries, "max_entries", 1)
        self._max_entries = int(max_entries)
        self._cache = OrderedDict()

    @classmethod
    def from_scene(cls, scene, mask_threshold=0.0, max_entries=256):
        """A cache over the training frames of a ``d2gs_np.data.scene.Scene`` (images loaded)."""
        frames = scene.frames
        for k, f in enumerate(frames):
            if f.image is None:
                raise ValueError(f"scene.frames[{k}].image is not loaded; load the scene with its images")
        return cls([f.image for f in frames], [f.mask for f in frames], [f.K for f in frames],
                   mask_threshold=mask_threshold, max_entries=max_entries)

    def __len__(self):
        return len(self._cache)

    @property
    def num_frames(self):
        return len(self._images)

    def size(self, frame_index, scale):
        """(w, h) of frame ``frame_index`` at render scale ``scale``."""
        H, W = self._images[self._check_index(frame_index)].shape[:2]
        return scaled_size(W, H, scale)

    def _check_index(self, frame_index):
        if isinstance(frame_index, bool) or not isinstance(frame_index, numbers.Integral):
            raise TypeError(f"frame_index must be an int; got {type(frame_index).__name__}")
        if not 0 <= frame_index < len(self._images):
            raise ValueError(f"frame_index must be in [0, {len(self._images)}); got {frame_index}")
        return int(frame_index)

    def get(self, frame_index, scale):
        """The Target of frame ``frame_index`` at render scale ``scale`` in (0, 1]."""
        k = self._check_index(frame_index)
        check_number(scale, "scale", 0.0, 1.0, lo_open=True)
        img = self._images[k]
        H, W = img.shape[:2]
        w, h = scaled_size(W, H, scale)
        key = (k, w, h)
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        mask = self._masks[k]
        if (w, h) == (W, H):
            image = img
            mask = None if mask is None else np.asarray(mask) > 0
            K = self._Ks[k].copy()
        else:
            image = downsample_area(img, w, h)
            mask = None if mask is None else downsample_mask(mask, w, h, self._mask_threshold)
            K = scale_intrinsics(self._Ks[k], w / W, h / H)
        target = Target(image=image, mask=mask, K=K, width=w, height=h)
        self._cache[key] = target
        while len(self._cache) > self._max_entries:
            self._cache.popitem(last=False)
        return target
