"""Settings of the pose package, validated on construction: plain frozen dataclasses.

Each solver module imports its config from here, and so does the experiment config
(``train/config.py``): reading a config loads neither OpenCV, CasADi nor Numba (only NumPy and
the constants), so a config file can be checked, diffed or written without the solvers.
"""
from __future__ import annotations

import numbers
from dataclasses import dataclass, field

from d2gs_np.base.checks import check_choice, check_int, check_number

__all__ = [
    "DETECTORS",
    "ROBUST_LOSSES",
    "BUNDLE_SOLVERS",
    "FeatureConfig",
    "CorrespondConfig",
    "TrackConfig",
    "PoseInitConfig",
    "GaussNewtonConfig",
    "PoseFitConfig",
]

# Feature detectors: SIFT is the default (docs/method.md §5); ORB and AKAZE give binary
# descriptors, matched by Hamming distance.
DETECTORS = ("sift", "orb", "akaze")
# The 8-point/7-point solvers inside FM_RANSAC need at least 8 correspondences.
_MIN_RANSAC_MATCHES = 8
# The pose solver's robust losses on its data residuals (pose/lm.py ``robust_cost``).
ROBUST_LOSSES = ("none", "huber", "cauchy")
# The bundle adjustment's solvers (pose/bundle.py ``bundle_adjust(solver=...)``).
BUNDLE_SOLVERS = ("scipy", "schur")
_MODES = ("auto", "on", "off")  # PoseInitConfig.mode
ADJUSTED_POSES_THEN = ("solver", "adam", "hold")  # PoseInitConfig.then
THEN_WITHOUT_SOLVER = ("adam", "hold")  # the values of PoseInitConfig.then that leave the pose solver out
ADAM_ROW_RULES = ("constant", "uncertainty")  # PoseInitConfig.adam_rows


@dataclass(frozen=True)
class FeatureConfig:
    """Settings of detection, matching and geometric verification (``pose/features.py``). Validated on construction."""

    ratio: float = 0.75  # Lowe ratio: keep a match if d1 < ratio * d2
    ransac_threshold_px: float = 1.0  # max distance (px) to the epipolar line for a RANSAC inlier
    ransac_confidence: float = 0.999
    ransac_max_iters: int = 2000
    mask_dilation_px: int = 4  # radius (px) by which motion masks grow before excluding pixels
    max_features: int = 0  # keep the best n keypoints per image (cv2 nfeatures); 0 = all
    contrast_threshold: float = 0.02  # SIFT DoG contrast threshold; OpenCV's default 0.04 finds
    # too few keypoints on small blurry frames (blur lowers DoG contrast)
    edge_threshold: float = 10.0  # SIFT edge-response threshold (OpenCV default)
    sigma: float = 1.6  # SIFT base blur (OpenCV default)
    octave_layers: int = 3  # SIFT layers per octave (Lowe's and OpenCV's default)
    min_matches: int = 8  # fewer ratio-test matches than this (>= 8) -> no matches are returned
    seed: int = 0  # OpenCV RNG seed for RANSAC
    detector: str = "sift"  # "sift" (float descriptors, L2), "orb" or "akaze" (binary, Hamming)
    max_displacement_px: float = 0.0  # > 0: a keypoint is matched only to keypoints within this
    # distance (px), before the ratio test (guided matching between nearby video frames); 0 = anywhere

    def __post_init__(self):
        check_choice(self.detector, "FeatureConfig.detector", DETECTORS)
        check_number(self.ratio, "FeatureConfig.ratio", 0.0, 1.0, lo_open=True)
        for name in ("ransac_threshold_px", "contrast_threshold", "edge_threshold", "sigma"):
            check_number(getattr(self, name), f"FeatureConfig.{name}", 0.0, lo_open=True)
        check_number(self.ransac_confidence, "FeatureConfig.ransac_confidence", 0.0, 1.0, lo_open=True, hi_open=True)
        check_number(self.max_displacement_px, "FeatureConfig.max_displacement_px", 0.0, hint="0 = no limit")
        for name in ("octave_layers", "ransac_max_iters"):
            check_int(getattr(self, name), f"FeatureConfig.{name}", 1)
        for name in ("mask_dilation_px", "max_features", "seed"):
            check_int(getattr(self, name), f"FeatureConfig.{name}", 0)
        check_int(self.min_matches, "FeatureConfig.min_matches", _MIN_RANSAC_MATCHES, hint="RANSAC on F needs 8 points")


@dataclass(frozen=True)
class CorrespondConfig:
    """Which frame pairs are matched and how (``pose/correspond.py``; ``features``: detector, ratio, RANSAC)."""

    # Detection tuned for small blurry frames, where OpenCV's SIFT defaults leave most pairs with too
    # few verified matches (docs/results.md §12).
    features: FeatureConfig = field(default_factory=lambda: FeatureConfig(
        contrast_threshold=0.002, sigma=1.0, ratio=0.85, ransac_threshold_px=1.5))
    gaps: tuple = (1, 2)  # pairs (k, k + g): consecutive frames and frames two apart
    min_pair_matches: int = 12  # a pair with fewer verified matches is skipped (and reported)
    # Guided matching: a keypoint of frame k is matched only within max_flow_fraction x width x gap
    # pixels of itself in frame k + gap (0 = anywhere). RANSAC on F cannot reject a wrong match
    # along an epipolar line, and a sideways-moving camera has horizontal epipolar lines: on
    # repeating texture many F-verified matches were tens of pixels off (docs/results.md §12).
    max_flow_fraction: float = 0.06

    def __post_init__(self):
        if not isinstance(self.features, FeatureConfig):
            raise TypeError(f"CorrespondConfig.features must be a FeatureConfig; got {type(self.features).__name__}")
        gaps = tuple(self.gaps) if isinstance(self.gaps, (tuple, list)) else None
        if not gaps or not all(isinstance(g, numbers.Integral) and not isinstance(g, bool) and g >= 1 for g in gaps) \
                or len(set(gaps)) != len(gaps):
            raise ValueError(f"CorrespondConfig.gaps must be distinct ints >= 1, e.g. (1, 2); got {self.gaps!r}")
        object.__setattr__(self, "gaps", gaps)
        check_number(self.max_flow_fraction, "CorrespondConfig.max_flow_fraction", 0.0, 1.0, hint="0 = no window")
        check_int(self.min_pair_matches, "CorrespondConfig.min_pair_matches", 1)


@dataclass(frozen=True)
class TrackConfig:
    """Settings of the KLT tracker (``pose/tracks.py``). Validated on construction."""

    # points per frame: 240x135 suite frames have 500-600 Shi-Tomasi corners at quality 0.005
    max_corners: int = 600
    quality: float = 0.005  # Shi-Tomasi quality (share of the best corner's score): low, blur lowers corner scores
    min_distance_px: int = 5  # corners (new and active) at least this far apart
    window_px: int = 15  # Lucas-Kanade window; 15 px: a few px of blur fits inside
    # points that fail (step 1) with window_px are tracked again with this window (0: no retry):
    # frames streaked by a fast turning shake need the wider window; only the failures get it
    # because it is worse for the rest (docs/results.md §12)
    retry_window_px: int = 21
    levels: int = 3  # pyramid levels (3: displacements of ~30 px between neighbouring frames)
    fb_px: float = 0.5  # forward-backward error above which a track ends
    ransac_px: float = 1.0  # distance to the epipolar line (F between neighbouring frames) for an inlier
    mask_dilation_px: int = 4  # as FeatureConfig.mask_dilation_px: keep off the border of a mover

    def __post_init__(self):
        for name in ("max_corners", "min_distance_px"):
            check_int(getattr(self, name), f"TrackConfig.{name}", 1)
        check_int(self.window_px, "TrackConfig.window_px", 3)
        for name in ("levels", "mask_dilation_px", "retry_window_px"):
            check_int(getattr(self, name), f"TrackConfig.{name}", 0)
        if 0 < self.retry_window_px < 3:
            raise ValueError(f"TrackConfig.retry_window_px must be 0 (no retry) or >= 3; got {self.retry_window_px}")
        check_number(self.quality, "TrackConfig.quality", 0.0, 1.0, lo_open=True, hi_open=True)
        for name in ("fb_px", "ransac_px"):
            check_number(getattr(self, name), f"TrackConfig.{name}", 0.0, lo_open=True)


@dataclass(frozen=True)
class PoseInitConfig:
    """Bundle adjustment of the given poses before training (``pose/given.py``).

    mode: "auto" runs it when the pose solver runs (poses not trusted); "on" / "off" force it.
    then: what refines a kept adjustment's poses during training. "adam" (default): Adam alone on
        the exposure endpoints, no pose solver, the frames the adjustment moved at
        ``LearningRates.camera_adjusted_scale`` x the camera rate; "solver": Adam at the camera
        rate and the pose solver's calls (``pose_solver``);
        "hold": nothing, the poses held as exact ones are (the exposure centred on them, only its
        spread learned). A run whose adjustment is not kept (too few points, a bad fit) refines
        the given poses with both either way. Why: docs/method.md §5, the solver after a kept
        adjustment.
    adam_rows: the rate factor of each moved frame's rows under then = "adam". "uncertainty"
        (default): the adjustment's own uncertainty of that frame's rotation relative to the others
        (``pose.bundle.relative_rotation_std``) over ``prior_rot_deg``, clipped to
        [``camera_adjusted_scale``, 1]: a frame the tracks pinned down learns slowly, one they left
        near the prior's uncertainty at nearly the full rate; "constant": ``camera_adjusted_scale``.
        Why: docs/method.md §5, the solver after a kept adjustment.
    """

    mode: str = "auto"
    then: str = "adam"
    adam_rows: str = "uncertainty"
    # The tracker without its retry window (TrackConfig.retry_window_px): the retry keeps
    # more tracks through streaked frames, which the importer needs to connect a video, but they
    # are less precise, and this adjustment starts from poses that already connect the frames:
    # without the retry the adjusted ATE is lower on most suite scenes (docs/results.md §12). The
    # pose solver's track check uses the same tracks.
    tracks: TrackConfig = field(default_factory=lambda: TrackConfig(retry_window_px=0))
    min_views: int = 3  # a track needs this many frames to be triangulated
    min_parallax_deg: float = 1.0  # how far its rays open (triangulate_tracks)
    min_points: int = 50  # fewer triangulated tracks: the given poses are kept
    # Fewer than min_points: the tracks are triangulated again with these looser gates, and the
    # adjustment runs if that gives fallback_min_points (0: no second try). Why: a short or
    # streaked clip else keeps its given poses, which training refines less well than it refines
    # this adjustment's; only as a second try, since where the first gates find enough points
    # their tracks are the better ones (docs/results.md §4, the demo setting).
    fallback_min_views: int = 2
    fallback_parallax_deg: float = 0.5
    fallback_min_points: int = 20
    # A frame with fewer observations (of triangulated tracks; counted again after the outliers are
    # dropped) is held at its given pose: the prior alone did not hold a streaked frame that a few
    # observations turned by degrees (docs/results.md §12). 10 observations are 20 equations for a
    # pose's 6 unknowns.
    min_frame_observations: int = 10
    outlier_px: float = 3.0  # observations further than this from their projection are dropped (round 2)
    robust_px: float = 1.0  # soft-L1 scale of the adjustment
    # "schur": Levenberg-Marquardt with the points eliminated (pose.bundle._schur_lm); "scipy":
    # SciPy's trust region (least_squares, LSMR). Same cost, same unknowns, same prior.
    solver: str = "schur"
    max_nfev: int = 60  # residual evaluations per round (either solver: one per trial step)
    # The prior on the given poses (``pose.bundle.pose_prior_fwd``): it holds the gauge (the
    # world frame and scale of the given poses) and the slow drift the tracks do not determine
    # (a scene whose tracks are short). sigma_t = prior_trans_rel x the median depth of the points.
    prior_rot_deg: float = 1.0
    prior_trans_rel: float = 0.02
    # The camera centres held on a smooth path (``pose.bundle.path_smoothness_fwd``): their second
    # difference between neighbouring frames at sigma = smooth_trans_rel x the median depth of the
    # points per frame squared; 0: off. Why: docs/method.md §5, the path's smoothness.
    smooth_trans_rel: float = 0.0
    # The frames' depth priors (one scale for the clip: InitConfig.depth_prior_space = "depth") as
    # rows of a third round, weight x (log z - log a - log prior) per observation beside its pixels,
    # the clip scale a fitted to the second round's points and held, the result scaled back to that
    # round's path; 0: off. Why: the poses' slow rotation drift moves every point's disparity alike,
    # which the tracks cannot tell from depth and the prior's shape can (docs/method.md §5).
    depth_prior_weight: float = 0.0
    max_rms_px: float = 1.5  # an adjustment with a larger residual (inliers) is not kept
    max_change_deg: float = 5.0  # nor one that turns a camera by more than this from the given pose
    max_change_rel: float = 0.1  # nor one that moves a centre by more than this x the median point depth

    def __post_init__(self):
        check_choice(self.mode, "PoseInitConfig.mode", _MODES)
        check_choice(self.then, "PoseInitConfig.then", ADJUSTED_POSES_THEN)
        check_choice(self.adam_rows, "PoseInitConfig.adam_rows", ADAM_ROW_RULES)
        check_choice(self.solver, "PoseInitConfig.solver", BUNDLE_SOLVERS)
        if not isinstance(self.tracks, TrackConfig):
            raise TypeError(f"PoseInitConfig.tracks must be a TrackConfig; got {type(self.tracks).__name__}")
        check_int(self.min_views, "PoseInitConfig.min_views", 2)
        check_int(self.fallback_min_views, "PoseInitConfig.fallback_min_views", 2)
        for name in ("max_nfev", "min_points", "min_frame_observations"):
            check_int(getattr(self, name), f"PoseInitConfig.{name}", 1)
        check_int(self.fallback_min_points, "PoseInitConfig.fallback_min_points", 0)
        for name in ("min_parallax_deg", "fallback_parallax_deg", "outlier_px", "robust_px", "max_rms_px", "max_change_deg", "max_change_rel",
                     "prior_rot_deg", "prior_trans_rel"):
            check_number(getattr(self, name), f"PoseInitConfig.{name}", 0.0, lo_open=True)
        check_number(self.smooth_trans_rel, "PoseInitConfig.smooth_trans_rel", 0.0)
        check_number(self.depth_prior_weight, "PoseInitConfig.depth_prior_weight", 0.0)


@dataclass(frozen=True)
class GaussNewtonConfig:
    """Settings of the pose solver (``pose/gauss_newton.py``; its robust loss and damping: ``pose/lm.py``)."""

    max_iters: int = 40  # the tight pose prior needs them to converge (docs/results.md §11)
    # Weight of the relative depth residual (the paper's 100 reduced to 10) and a Cauchy loss at
    # 1 px: the choice against the paper's beta with a Huber loss is in docs/results.md §11.
    beta: float = 10.0
    robust: str = "cauchy"  # "none", "huber" or "cauchy" (IRLS)
    robust_scale: float = 1.0  # d of the robust loss, in residual units (pixels)
    spread_sigma: float = 1e-3  # prior: a change of the endpoint spread b - a by this costs 1/2
    damping_init: float = 1e-3  # initial Levenberg-Marquardt lambda (relative to diag(H))
    damping_up: float = 10.0  # lambda x this after a rejected step
    damping_down: float = 0.3  # lambda x this after an accepted step
    ftol: float = 1e-6  # stop when an accepted step lowers the cost by less than this fraction
    xtol: float = 1e-10  # stop when |dx| < xtol (|x| + xtol)

    def __post_init__(self):
        for name in ("beta", "robust_scale", "spread_sigma", "damping_init", "ftol", "xtol"):
            check_number(getattr(self, name), f"GaussNewtonConfig.{name}", 0.0, lo_open=True)
        check_number(self.damping_up, "GaussNewtonConfig.damping_up", 1.0, lo_open=True)
        check_number(self.damping_down, "GaussNewtonConfig.damping_down", 0.0, 1.0, lo_open=True, hi_open=True)
        check_int(self.max_iters, "GaussNewtonConfig.max_iters", 0)
        check_choice(self.robust, "GaussNewtonConfig.robust", ROBUST_LOSSES)


@dataclass(frozen=True)
class PoseFitConfig:
    """Settings of the single-pose fit (``pose/fit.py``): Adam steps in the tangent at the current pose."""

    steps: int = 100
    lr: float = 1e-3  # radians per step for rotation; times the median depth for translation
    betas: tuple = (0.9, 0.999)
    eps: float = 1e-12

    def __post_init__(self):
        check_int(self.steps, "PoseFitConfig.steps", 0)
        check_number(self.lr, "PoseFitConfig.lr", 0.0, lo_open=True)
