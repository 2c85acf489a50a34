"""Configurations of the scene model and of its initialisation: frozen dataclasses, validated on construction.

``DeformConfig`` sizes the deformation model (scene/deformation.py), ``InitConfig`` and the
``StereoConfig`` it nests set up the initial point clouds (scene/initialize.py, scene/stereo.py),
``MotionInitConfig`` the initial motion of the dynamic set (scene/motion_init.py), ``BorderConfig`` the
static world continued past the frames' borders at the end of training (scene/border.py). Plain data:
importing this module loads none of the code that uses it (no OpenCV, Numba or CasADi).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

from d2gs_np.base.checks import check_bool, check_choice, check_int, check_number
from d2gs_np.pose.config import FeatureConfig

__all__ = ["DeformConfig", "InitConfig", "StereoConfig", "MotionInitConfig", "BorderConfig", "WARPS"]

# how a seed's pixel can follow its object's track (``MotionInitConfig.warp``)
WARPS = ("centroid", "similarity", "homography", "flow")
RIGID_FITS = ("kabsch", "pnp", "pairs", "bundle")
DYNAMIC_DEPTHS = ("static_median", "scene", "prior", "auto")  # InitConfig.dynamic_depth
STATIC_DEPTHS = ("stereo", "scene", "prior", "stereo_prior", "auto")  # InitConfig.static_depth
STEREO_PRIOR_SCOPES = ("measured", "all")  # InitConfig.stereo_prior_scope
PRIOR_SPACES = ("depth", "disparity")  # InitConfig.depth_prior_space


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
            check_int(getattr(self, name), f"DeformConfig.{name}", 0)
        check_number(self.omega, "DeformConfig.omega", 0.0, lo_open=True)

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
    # away, the default; why not 1: docs/method.md §8)
    distinct_px: float = 0.0

    def __post_init__(self):
        check_int(self.num_depths, "StereoConfig.num_depths", 3, hint="a parabola needs three")
        for name in ("window", "min_sources"):
            check_int(getattr(self, name), f"StereoConfig.{name}", 1)
        if self.window % 2 == 0:
            raise ValueError(f"StereoConfig.window must be odd; got {self.window}")
        check_number(self.min_texture, "StereoConfig.min_texture", 0.0)
        check_number(self.max_cost_ratio, "StereoConfig.max_cost_ratio", 0.0, 1.0, lo_open=True)
        check_number(self.distinct_px, "StereoConfig.distinct_px", 0.0)
        check_number(self.depth_margin, "StereoConfig.depth_margin", 0.0, 1.0, hi_open=True)


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
    # Fewer triangulated points than this whose median depth lies outside the fallback range are
    # dropped, as if none were triangulated (``few_points_disagree``): with noisy poses and a
    # short clip, a handful of two-view points can all sit at a fraction of the true depth
    # (docs/method.md §8, the demo setting), and their percentiles are not a range.
    min_range_points: int = 20
    # Robust depth range (scene/initialize.py's docstring, step 4): the percentiles are clipped to the median depth
    # times exp(+-k sigma), sigma = 1.4826 MAD of the log depths (k = depth_range_mad; 0: no clip).
    # Against two-view mismatches that stretch the sweep far below the true depths (noisy poses;
    # docs/results.md §9).
    depth_range_mad: float = 0.0  # 0: the plain percentiles (default; 3 with distinct_px = 1: docs/method.md §8)
    dynamic_depth_factor: float = 0.8  # dynamic depth = factor x frame's median static depth
    dynamic_depth_jitter: float = 0.05  # relative half-width of the uniform depth jitter
    # Where a dynamic seed's depth comes from: "static_median" (the rule above) or "scene": the
    # scene's depth maps (depth_file_path) at the seed's pixel, for data with measured depth. On
    # synthetic scenes those are the truth: a run with "scene" is then an oracle (docs/method.md §8).
    # "prior": the scene's depth priors (depth_prior_file_path, e.g. a monocular network's), each
    # frame's aligned by a scale and shift to the static points seen in it (align_depth_prior).
    # "auto": "prior" when the scene has depth priors, else "static_median" (said in the run log).
    dynamic_depth: str = "static_median"
    # Where the dense seeds and the fill of the static set take their depth: "stereo" (the plane
    # sweep, interpolated where it keeps nothing) or "scene": the scene's depth maps at each seed's
    # pixel (measured depth; on a synthetic scene the truth: an oracle, docs/method.md §8); "prior":
    # the scene's depth priors aligned as the dynamic seeds' are; "stereo_prior": the sweep where it
    # agrees with the aligned prior within stereo_prior_tolerance (relative), the prior elsewhere;
    # "auto": "stereo_prior" when the scene has depth priors, else "stereo" (said in the run log).
    static_depth: str = "stereo"
    stereo_prior_tolerance: float = 0.15
    # Which seeds' own depths "stereo_prior" checks against the prior: "measured", the sweep's own
    # pixels only (the interpolated seeds and the fill take the prior); "all", also the depths
    # interpolated between trusted stereo pixels and the fill's on the surface the seeds describe.
    stereo_prior_scope: str = "measured"
    # > 0: a sweep pixel that disagrees with the prior keeps its own depth still where its matching
    # cost is at most this fraction of the cost at the prior's depth (the images prefer it); 0: off
    stereo_prior_cost_ratio: float = 0.0
    # Once, at this fraction of the schedule, the static set replaced by seeds from a plane sweep over
    # the model's own sharp renders (train/render_stereo.py, Reseed); 0: never (docs/method.md §8)
    reseed_at: float = 0.0
    # What a prior holds (scene/depth_prior.py): "depth", a depth up to one scale for the clip
    # (video depth models such as the paper's Align3R), or "disparity", inverse depth up to a scale
    # and a shift per frame (single-image networks).
    depth_prior_space: str = "depth"
    # The static seeds' priors ("prior", "stereo_prior") fused over the frames before use: each static
    # pixel's depth the geometric mean of what the frames that see its point give it, readings off by
    # more than the gate (|log ratio|) left out (scene/depth_prior.py fuse_depth_maps; docs/method.md §8)
    depth_prior_fusion: bool = False
    depth_prior_fusion_gate: float = 0.3
    depth_prior_min_points: int = 20  # fewer usable static points: the frame's (clip's) seeds keep the static-median rule

    def __post_init__(self):
        if not isinstance(self.features, FeatureConfig):
            raise TypeError(f"InitConfig.features must be a FeatureConfig; got {type(self.features).__name__}")
        check_number(self.max_scale_px, "InitConfig.max_scale_px", 0.0, hint="0 = no cap")
        check_bool(self.fill_on_surface, "InitConfig.fill_on_surface")
        if not isinstance(self.stereo, StereoConfig):
            raise TypeError(f"InitConfig.stereo must be a StereoConfig; got {type(self.stereo).__name__}")
        skips = self.frame_skips
        if (not isinstance(skips, tuple) or len(skips) == 0
                or not all(isinstance(s, numbers.Integral) and not isinstance(s, bool) and s >= 1 for s in skips)):
            raise ValueError(f"InitConfig.frame_skips must be a non-empty tuple of ints >= 1; got {skips!r}")
        check_number(self.depth_range_mad, "InitConfig.depth_range_mad", 0.0, hint="0 = no clip")
        for name in ("max_static_points", "random_fill_points", "dynamic_points", "dense_frames", "min_range_points"):
            check_int(getattr(self, name), f"InitConfig.{name}", 0)
        check_int(self.dense_stride, "InitConfig.dense_stride", 1)
        check_number(self.dense_outlier_rel, "InitConfig.dense_outlier_rel", 0.0, lo_open=True)
        check_number(self.max_reprojection_error_px, "InitConfig.max_reprojection_error_px", 0.0, lo_open=True)
        check_number(self.min_parallax_deg, "InitConfig.min_parallax_deg", 0.0, 90.0, hi_open=True)
        lo, hi = _pair(self.fill_depth_percentiles, "fill_depth_percentiles")
        if not 0.0 <= lo <= hi <= 100.0:
            raise ValueError(f"InitConfig.fill_depth_percentiles must satisfy 0 <= lo <= hi <= 100; got {(lo, hi)}")
        check_number(self.fill_depth_margin, "InitConfig.fill_depth_margin", 0.0, 1.0, hi_open=True)
        lo, hi = _pair(self.fallback_depth_range, "fallback_depth_range")
        if not 0.0 < lo < hi:
            raise ValueError(f"InitConfig.fallback_depth_range must satisfy 0 < near < far; got {(lo, hi)}")
        check_number(self.dynamic_depth_factor, "InitConfig.dynamic_depth_factor", 0.0, 1.0, lo_open=True)
        check_number(self.dynamic_depth_jitter, "InitConfig.dynamic_depth_jitter", 0.0, 1.0, hi_open=True)
        check_choice(self.dynamic_depth, "InitConfig.dynamic_depth", DYNAMIC_DEPTHS)
        check_choice(self.static_depth, "InitConfig.static_depth", STATIC_DEPTHS)
        check_number(self.reseed_at, "InitConfig.reseed_at", 0.0, 1.0, hi_open=True, hint="0 = never")
        check_choice(self.depth_prior_space, "InitConfig.depth_prior_space", PRIOR_SPACES)
        check_number(self.stereo_prior_tolerance, "InitConfig.stereo_prior_tolerance", 0.0,
                     hint="a relative difference, e.g. 0.15")
        check_choice(self.stereo_prior_scope, "InitConfig.stereo_prior_scope", STEREO_PRIOR_SCOPES)
        check_number(self.stereo_prior_cost_ratio, "InitConfig.stereo_prior_cost_ratio", 0.0, 1.0,
                     hint="a cost ratio in (0, 1], e.g. 0.8; 0 = off")
        check_bool(self.depth_prior_fusion, "InitConfig.depth_prior_fusion")
        check_number(self.depth_prior_fusion_gate, "InitConfig.depth_prior_fusion_gate", 0.0, lo_open=True,
                     hint="a |log ratio|, e.g. 0.3")
        check_int(self.depth_prior_min_points, "InitConfig.depth_prior_min_points", 3,
                  hint="a scale and shift need at least 3 points to be checked")


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
    # each track with three or more seeds becomes one rigid object (``scene/rigid.py``): a pose path
    # fitted to its seeds' targets, the seeds' own deformation a residual starting at zero (issue #44)
    rigid: bool = False
    # with ``rigid``: False holds the clustered Gaussians' own position and rotation residuals at zero
    # (their gradients dropped), so each cluster moves as one body; True trains them as the rest
    rigid_residual: bool = True
    # with ``rigid``: how each cluster's pose at a frame is fitted, "kabsch" (to its seeds' lifted 3D
    # targets) or "pnp" (then the shape projected onto their tracked pixels; worse in training:
    # docs/results.md §4, "Rigid movers: one pose path per tracked mover (session 52; built, opt-in)"),
    # or "pairs" (chained from each consecutive pair's rigid motion, the pair's correspondences
    # lifted at the seeds' depth maps: a turn out of the image plane too; needs init.dynamic_depth
    # "prior" or "scene"), or "bundle" (those chained poses refined with the object's shape by a bundle
    # adjustment over short flow tracks inside it, the depth maps a weak term: scene/object_bundle.py)
    rigid_fit: str = "kabsch"
    # with rigid_fit "bundle": frames each point is tracked forwards and backwards; the depth maps'
    # relative error (standard deviation of the log depth); the pose path's turn per frame allowed to
    # change by about this many degrees from frame to frame (0: no smoothness term)
    bundle_window: int = 5
    bundle_depth_sigma: float = 0.1
    bundle_accel_deg: float = 3.0

    def __post_init__(self):
        for name in ("enabled", "rotation", "rigid", "rigid_residual"):
            check_bool(getattr(self, name), f"MotionInitConfig.{name}")
        check_number(self.min_area_fraction, "MotionInitConfig.min_area_fraction", 0.0, 1.0, hi_open=True)
        check_number(self.max_jump_fraction, "MotionInitConfig.max_jump_fraction", 0.0, lo_open=True)
        # tracks shorter than 1 + K frames need the ridge to be well posed
        check_number(self.ridge, "MotionInitConfig.ridge", 0.0, lo_open=True)
        check_choice(self.warp, "MotionInitConfig.warp", WARPS)
        check_choice(self.rigid_fit, "MotionInitConfig.rigid_fit", RIGID_FITS)
        check_int(self.bundle_window, "MotionInitConfig.bundle_window", 1)
        check_number(self.bundle_depth_sigma, "MotionInitConfig.bundle_depth_sigma", 0.0, lo_open=True)
        check_number(self.bundle_accel_deg, "MotionInitConfig.bundle_accel_deg", 0.0)
        # a similarity has 4 degrees of freedom: 2 points + 1 check
        check_int(self.min_rotation_inliers, "MotionInitConfig.min_rotation_inliers", 3)


@dataclass(frozen=True)
class BorderConfig:
    """The static world continued past the training frames' borders (``scene/border.py``), added to
    the finished model (``Trainer``): opaque copies of each frame's border pixels, outward."""

    # how far past each border, as a share of the image's larger side (0 = off): as far as a novel
    # view beside the path may look past a frame's edge (docs/method.md §2)
    margin: float = 0.12
    step_px: float = 3.0  # spacing of the copies along and across the border, pixels
    gap: int = 2  # the first copy lies gap * step_px px past the border (its footprint off the image)
    sigma: float = 0.6  # each copy's isotropic sigma, in units of step_px at its depth
    min_alpha: float = 0.5  # border pixels whose static alpha is lower are not copied
    opacity: float = 0.98
    # the copies' depth continues the surface's slope, measured this many pixels inside the border
    # (0: the border pixel's depth, fronto-parallel), within a factor max_depth_ratio of it
    slope_px: int = 6
    max_depth_ratio: float = 2.0
    colour_sigma_px: float = 3.0  # the copies take the border's colour blurred by a Gaussian of this sigma

    def __post_init__(self):
        check_number(self.margin, "BorderConfig.margin", 0.0, 1.0, hint="0 = off")
        check_number(self.step_px, "BorderConfig.step_px", 0.0, lo_open=True)
        check_int(self.gap, "BorderConfig.gap", 1)
        check_number(self.sigma, "BorderConfig.sigma", 0.0, lo_open=True)
        check_number(self.min_alpha, "BorderConfig.min_alpha", 0.0, 1.0)
        check_number(self.opacity, "BorderConfig.opacity", 0.0, 1.0, lo_open=True, hi_open=True)
        check_int(self.slope_px, "BorderConfig.slope_px", 0)
        check_number(self.max_depth_ratio, "BorderConfig.max_depth_ratio", 1.0)
        check_number(self.colour_sigma_px, "BorderConfig.colour_sigma_px", 0.0, hint="0 = the border pixel's own")
