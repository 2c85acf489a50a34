"""Configurations of the scene model and of its initialisation: frozen dataclasses, validated on construction.

``DeformConfig`` sizes the deformation model (scene/deformation.py), ``InitConfig`` and the
``StereoConfig`` it nests set up the initial point clouds (scene/initialize.py, scene/stereo.py),
``MotionInitConfig`` the initial motion of the dynamic set (scene/motion_init.py). Plain data:
importing this module loads none of the code that uses it (no OpenCV, Numba or CasADi).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

import numpy as np

from d2gs_np.pose.config import FeatureConfig

__all__ = ["DeformConfig", "InitConfig", "StereoConfig", "MotionInitConfig", "WARPS"]

# how a seed's pixel can follow its object's track (``MotionInitConfig.warp``)
WARPS = ("centroid", "similarity", "homography", "flow")


@dataclass(frozen=True)
class DeformConfig:
    """Size of the deformation model.

    degree: P, highest power of t in the polynomial part (P = 0: no polynomial part).
    order: L, number of Fourier harmonics (L = 0: no Fourier part).
    omega: base angular frequency w of the Fourier part, in radians per unit of normalised time
        (2 pi = one period over the clip).
    """

    degree: int = 2
    order: int = 2
    omega: float = 2.0 * math.pi

    def __post_init__(self):
        for name in ("degree", "order"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:
                raise ValueError(f"DeformConfig.{name} must be an integer >= 0; got {value!r}")
        if isinstance(self.omega, bool) or not isinstance(self.omega, numbers.Real):
            raise ValueError(f"DeformConfig.omega must be a real number; got {self.omega!r}")
        if not (math.isfinite(self.omega) and self.omega > 0.0):
            raise ValueError(f"DeformConfig.omega must be finite and > 0; got {self.omega!r}")

    @property
    def num_coefs(self) -> int:
        """K = P + 2L, the length of the coefficient axis."""
        return int(self.degree) + 2 * int(self.order)


@dataclass(frozen=True)
class StereoConfig:
    """Settings of ``plane_sweep_depth`` (scene/stereo.py). ``enabled = False`` keeps the older interpolated dense seeds."""

    enabled: bool = True
    num_depths: int = 128
    window: int = 5  # odd, pixels
    min_sources: int = 2
    min_texture: float = 0.02  # grey-level standard deviation over the window (images in [0, 1])
    max_cost_ratio: float = 0.8  # best cost / best cost away from the minimum
    depth_margin: float = 0.5  # the sweep covers [(1 - m) near, (1 + m) far] of the given range
    # the distinctness check compares with hypotheses this many source pixels away (0: two hypotheses
    # away, the default; 1 fills cube_sign's stereo but cost novel views in 600 s runs: docs/method.md §8)
    distinct_px: float = 0.0

    def __post_init__(self):
        for name in ("num_depths", "window", "min_sources"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
                raise ValueError(f"StereoConfig.{name} must be an int >= 1; got {v!r}")
        if self.num_depths < 3:
            raise ValueError(f"StereoConfig.num_depths must be >= 3 (a parabola needs three); got {self.num_depths}")
        if self.window % 2 == 0:
            raise ValueError(f"StereoConfig.window must be odd; got {self.window}")
        if not 0.0 <= self.min_texture < float("inf"):
            raise ValueError(f"StereoConfig.min_texture must be >= 0; got {self.min_texture}")
        if not 0.0 < self.max_cost_ratio <= 1.0:
            raise ValueError(f"StereoConfig.max_cost_ratio must be in (0, 1]; got {self.max_cost_ratio}")
        if not (isinstance(self.distinct_px, numbers.Real) and 0.0 <= self.distinct_px < float("inf")):
            raise ValueError(f"StereoConfig.distinct_px must be a finite number >= 0; got {self.distinct_px!r}")
        if not 0.0 <= self.depth_margin < 1.0:
            raise ValueError(f"StereoConfig.depth_margin must be in [0, 1); got {self.depth_margin}")


@dataclass(frozen=True)
class InitConfig:
    """Settings of the initial point clouds. Validated on construction."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    # pair frame k with k + s for each s (clamped to N - 1). Wide baselines: with independent
    # per-frame pose noise, consecutive frames triangulate poorly (docs/results.md §9)
    frame_skips: tuple = (2, 4, 8)
    max_static_points: int = 20000  # triangulated points kept (seeded random subset beyond)
    random_fill_points: int = 2000  # extra static points at random depths in the view frusta
    # Dense seeding (step 3 of scene/initialize.py's docstring): a pixel grid of stride dense_stride on
    # static pixels of dense_frames evenly spaced keyframes, lifted at the depth interpolated
    # from the triangulated points. 0 frames: off.
    dense_frames: int = 4
    dense_stride: int = 3
    dense_outlier_rel: float = 0.15  # drop a sparse depth that differs this much from its neighbours' median
    stereo: StereoConfig = field(default_factory=StereoConfig)  # the dense seeds' depths (scene/stereo.py)
    # random fill at the depth interpolated from the triangulated and dense points seen in its frame
    # (uniform in [near, far] where they give none); False: uniform everywhere, which puts a fog of
    # Gaussians between the camera and the walls that training does not clear (docs/results.md §9).
    fill_on_surface: bool = True
    # Largest initial scale, in pixels of the point's source frame (scale <= max_scale_px * z / fx
    # there; 0 = no cap). 3DGS's neighbour-distance scale makes a lone point near the camera a
    # blob tens of pixels wide that veils everything behind it (docs/results.md §9).
    max_scale_px: float = 3.0
    dynamic_points: int = 2000  # points seeded inside the motion masks
    max_reprojection_error_px: float = 2.0  # max over both views
    min_parallax_deg: float = 2.0  # min angle between the two viewing rays of a triangulated point
    fill_depth_percentiles: tuple = (5.0, 95.0)  # of triangulated depths -> fill depth range
    fill_depth_margin: float = 0.2  # near = (1 - m) p_lo, far = (1 + m) p_hi
    fallback_depth_range: tuple = (0.25, 2.0)  # x scene_scale, when nothing was triangulated
    # Robust depth range (scene/initialize.py's docstring, step 4): the percentiles are clipped to the median depth
    # times exp(+-k sigma), sigma = 1.4826 MAD of the log depths (k = depth_range_mad; 0: no clip).
    # Against two-view mismatches that stretch the sweep far below the true depths (cube_sign with
    # noisy poses, docs/results.md §9).
    depth_range_mad: float = 0.0  # 0: the plain percentiles (default; 3 with distinct_px = 1: docs/method.md §8)
    dynamic_depth_factor: float = 0.8  # dynamic depth = factor x frame's median static depth
    dynamic_depth_jitter: float = 0.05  # relative half-width of the uniform depth jitter

    def __post_init__(self):
        if not isinstance(self.features, FeatureConfig):
            raise TypeError(f"InitConfig.features must be a FeatureConfig; got {type(self.features).__name__}")
        if not (isinstance(self.max_scale_px, numbers.Real) and 0.0 <= self.max_scale_px < float("inf")):
            raise ValueError(f"InitConfig.max_scale_px must be a finite number >= 0 (0 = no cap); got "
                             f"{self.max_scale_px!r}")
        if not isinstance(self.fill_on_surface, bool):
            raise ValueError(f"InitConfig.fill_on_surface must be true or false; got {self.fill_on_surface!r}")
        if not isinstance(self.stereo, StereoConfig):
            raise TypeError(f"InitConfig.stereo must be a StereoConfig; got {type(self.stereo).__name__}")
        skips = self.frame_skips
        if (not isinstance(skips, tuple) or len(skips) == 0
                or not all(isinstance(s, numbers.Integral) and not isinstance(s, bool) and s >= 1 for s in skips)):
            raise ValueError(f"InitConfig.frame_skips must be a non-empty tuple of ints >= 1; got {skips!r}")
        if not (isinstance(self.depth_range_mad, numbers.Real) and 0.0 <= self.depth_range_mad < float("inf")):
            raise ValueError(f"InitConfig.depth_range_mad must be a finite number >= 0 (0 = no clip); got "
                             f"{self.depth_range_mad!r}")
        for name in ("max_static_points", "random_fill_points", "dynamic_points", "dense_frames"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 0:
                raise ValueError(f"InitConfig.{name} must be an int >= 0; got {v!r}")
        for name in ("max_reprojection_error_px", "min_parallax_deg", "fill_depth_margin",
                     "dynamic_depth_factor", "dynamic_depth_jitter"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not np.isfinite(v):
                raise TypeError(f"InitConfig.{name} must be a finite real number; got {v!r}")
        if isinstance(self.dense_stride, bool) or not isinstance(self.dense_stride, numbers.Integral) \
                or self.dense_stride < 1:
            raise ValueError(f"InitConfig.dense_stride must be an int >= 1; got {self.dense_stride!r}")
        if not (isinstance(self.dense_outlier_rel, numbers.Real) and 0.0 < self.dense_outlier_rel):
            raise ValueError(f"InitConfig.dense_outlier_rel must be > 0; got {self.dense_outlier_rel!r}")
        if self.max_reprojection_error_px <= 0:
            raise ValueError(f"InitConfig.max_reprojection_error_px must be > 0; got {self.max_reprojection_error_px}")
        if not 0.0 <= self.min_parallax_deg < 90.0:
            raise ValueError(f"InitConfig.min_parallax_deg must be in [0, 90); got {self.min_parallax_deg}")
        lo, hi = _pair(self.fill_depth_percentiles, "fill_depth_percentiles")
        if not 0.0 <= lo <= hi <= 100.0:
            raise ValueError(f"InitConfig.fill_depth_percentiles must satisfy 0 <= lo <= hi <= 100; got {(lo, hi)}")
        if not 0.0 <= self.fill_depth_margin < 1.0:
            raise ValueError(f"InitConfig.fill_depth_margin must be in [0, 1); got {self.fill_depth_margin}")
        lo, hi = _pair(self.fallback_depth_range, "fallback_depth_range")
        if not 0.0 < lo < hi:
            raise ValueError(f"InitConfig.fallback_depth_range must satisfy 0 < near < far; got {(lo, hi)}")
        if not 0.0 < self.dynamic_depth_factor <= 1.0:
            raise ValueError(f"InitConfig.dynamic_depth_factor must be in (0, 1]; got {self.dynamic_depth_factor}")
        if not 0.0 <= self.dynamic_depth_jitter < 1.0:
            raise ValueError(f"InitConfig.dynamic_depth_jitter must be in [0, 1); got {self.dynamic_depth_jitter}")


def _pair(v, name):
    if not isinstance(v, tuple) or len(v) != 2 or not all(isinstance(x, numbers.Real) for x in v):
        raise ValueError(f"InitConfig.{name} must be a tuple of two numbers; got {v!r}")
    return float(v[0]), float(v[1])


@dataclass(frozen=True)
class MotionInitConfig:
    """Settings of ``initialize_deformation``; steps are those of scene/motion_init.py's docstring."""

    enabled: bool = True
    min_area_fraction: float = 5e-4  # components below this share of the image are noise
    max_jump_fraction: float = 0.25  # centroid jump gate between consecutive frames, x image diagonal
    ridge: float = 1e-4  # Tikhonov weight on the coefficients relative to the number of frames (step 5)
    rotation: bool = True  # follow each track's in-image rotation (step 3); False: translation only
    min_rotation_inliers: int = 6  # fewer RANSAC inliers between two frames: no rotation measured
    # how a seed's pixel follows its track (steps 3-4): "flow" (similarity refined by optical flow),
    # "similarity" or "homography" (the chained warps alone), "centroid" (the component's centroid
    # plus the similarity's turn and scale about it; ``rotation`` applies to this rule only)
    warp: str = "flow"

    def __post_init__(self):
        if not 0.0 <= self.min_area_fraction < 1.0:
            raise ValueError(f"MotionInitConfig.min_area_fraction must be in [0, 1); got {self.min_area_fraction}")
        if self.max_jump_fraction <= 0.0:
            raise ValueError(f"MotionInitConfig.max_jump_fraction must be > 0; got {self.max_jump_fraction}")
        if not self.ridge > 0.0:  # tracks shorter than 1 + K frames need it to be well posed
            raise ValueError(f"MotionInitConfig.ridge must be > 0; got {self.ridge}")
        if self.warp not in WARPS:
            raise ValueError(f"MotionInitConfig.warp must be one of {WARPS}; got {self.warp!r}")
        if self.min_rotation_inliers < 3:  # a similarity has 4 degrees of freedom: 2 points + 1 check
            raise ValueError(f"MotionInitConfig.min_rotation_inliers must be >= 3; got {self.min_rotation_inliers}")
