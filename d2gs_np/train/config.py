"""Experiment configuration: frozen per-component dataclasses composed into one record.

``ExperimentConfig`` round-trips to JSON (``to_json``/``from_json``) by walking
the dataclass fields; no argparse reflection, no eval. Unknown keys are an error
naming the key and the known ones, so a typo in a config file fails before any
work is done.
"""
from __future__ import annotations

import dataclasses
import json
import numbers
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from d2gs_np.blur.config import BlurConfig, TrajectoryConfig
from d2gs_np.pose.config import CorrespondConfig, GaussNewtonConfig, PoseInitConfig
from d2gs_np.base.checks import ConfigWarning, check_bool, check_choice, check_int, check_number, name_items, warn
from d2gs_np.render.config import RenderConfig
from d2gs_np.scene.config import BorderConfig, DeformConfig, InitConfig, MotionInitConfig
from d2gs_np.train.schedule import ScheduleConfig

_AUTO = ("auto", "on", "off")
# Adam moves a parameter by about its learning rate each step; a rate above this (a position by the
# scene's size, a log-scale by an e-fold, a colour across its range) diverges (a ConfigWarning).
LR_PLAUSIBLE_MAX = 1.0


@dataclass(frozen=True)
class LossConfig:
    """Weights of the total loss (docs/method.md §6, Eq. 18): total = L_render + sum of weighted terms.

    A regulariser adds its weight here and its term to ``train.terms.loss_terms`` (entered when
    the weight is > 0); the training step does not change.
    """

    lambda_ssim: float = 0.2  # L_render = (1 - lambda_ssim) L1 + lambda_ssim (1 - SSIM)
    # Regularisers (docs/method.md §6); each enters the loss when its weight is > 0. L_ts, L_gs and
    # L_reproj default off (weight 0; the short-budget ablation of docs/method.md §6 decided it);
    # L_freq defaults on at the method's weight, on the static pixels only (docs/method.md §6 says
    # why). The method's weights are METHOD_REGULARISER_WEIGHTS below.
    lambda_ts: float = 0.0  # L_ts = ts_time_weight l_time + ts_spatial_weight l_spatial, times this
    ts_time_weight: float = 1.0  # lambda_t
    ts_spatial_weight: float = 1.0  # lambda_s
    ts_time_offset: float = 0.08  # epsilon of l_time: D(t) against D(t + epsilon), normalised time
    ts_neighbours: int = 8  # K nearest dynamic Gaussians (by base position) of l_spatial
    ts_knn_every: int = 250  # schedule steps between neighbour-list rebuilds (and after any resize)
    lambda_gs: float = 0.0  # opacity entropy L_gs
    lambda_freq: float = 0.002  # high-frequency loss L_freq (the method's weight)
    freq_cutoff: float = 0.1  # normalised radial frequency (1 = Nyquist) the L_freq high-pass keeps above
    freq_static_only: bool = True  # L_freq on the static pixels only (the frame's motion mask out), every stage
    # L_reproj on the rendered depth (train.terms.Reprojection): the pose solver's cycle residuals of
    # matched pixels (its matching settings, beta and robust scale: PoseSolverConfig) with the poses held
    lambda_reproj: float = 0.0
    # L_depth (train.terms.DepthPrior): the rendered depth against the scene's depth priors
    # (depth_prior_file_path), invariant to what their kind leaves unknown
    # (InitConfig.depth_prior_space). Not in the paper; off by default (why: docs/method.md §6)
    lambda_depth_prior: float = 0.0
    # a depth prior's log-ratio departures within this (relative) pull nothing: its own accuracy
    depth_prior_tolerance: float = 0.1
    # the same on the frame's moving pixels (its motion mask); None: depth_prior_tolerance. A mover's
    # depth is free up to a scale (docs/method.md §8), so its pixels may be held tighter than the static
    depth_prior_tolerance_moving: Optional[float] = None
    # L_dgrad (train.terms.DepthGradient): the rendered depth's log differences between neighbouring
    # pixels against the depth priors' (a mover's shape, its scale free). Not in the paper
    # (shape-of-motion's depth gradient loss); off by default. Region "moving" (the motion masks) or "all"
    lambda_depth_grad: float = 0.0
    depth_grad_region: str = "moving"
    # L_cont (train.terms.ExposureContinuity): neighbouring exposures on one constant-velocity camera
    # path, in squared pixels. Not in the paper (DyBluRF ties neighbouring exposures); off by default
    lambda_continuity: float = 0.0
    # L_iso (train.terms.Isometry): the dynamic set's neighbour distances at the step's time and
    # iso_time_offset later (earlier at the clip's end) alike, as on a rigid object. Not in the paper
    # (Dynamic 3D Gaussians' isometry); off by default. Its neighbours are L_ts's (ts_neighbours, ts_knn_every)
    lambda_iso: float = 0.0
    iso_time_offset: float = 0.25
    # L_stereo (train.terms.StereoPrior): L_depth's form against a plane sweep over the model's own
    # renders (train/render_stereo.py), made at these fractions of the schedule. Not in the paper; off
    lambda_stereo: float = 0.0
    stereo_tolerance: float = 0.05  # the sweep's own relative accuracy on sharp renders
    # "depth": the maps' depth ratios (each frame's scale free); "metric": the depth itself, a frame-wide
    # bias included (losses/depth_prior.py)
    stereo_space: str = "depth"
    stereo_at: tuple = (0.25, 0.5)
    stereo_depths: int = 64  # the sweep's hypotheses (InitConfig.stereo's other settings); renders are sharp
    # L_var (train.terms.DepthVariance): the spread of the Gaussians' depths along each ray (a veil in
    # front of a surface, layers behind it), from one more sharp render per step. Not in the paper
    # (Mip-NeRF 360's distortion, 2DGS's depth distortion in a splatter's form); off by default
    lambda_depth_var: float = 0.0

    def __post_init__(self):
        check_number(self.lambda_ssim, "LossConfig.lambda_ssim", 0.0, 1.0)
        for name in ("lambda_ts", "ts_time_weight", "ts_spatial_weight", "lambda_gs", "lambda_freq", "lambda_reproj",
                     "lambda_depth_prior", "lambda_continuity", "lambda_iso", "lambda_stereo", "lambda_depth_var",
                     "lambda_depth_grad"):
            check_number(getattr(self, name), f"LossConfig.{name}", 0.0, hint="0 = term off")
        check_number(self.depth_prior_tolerance, "LossConfig.depth_prior_tolerance", 0.0,
                     hint="the prior's relative accuracy, e.g. 0.1; 0 pulls every pixel")
        if self.depth_prior_tolerance_moving is not None:
            check_number(self.depth_prior_tolerance_moving, "LossConfig.depth_prior_tolerance_moving", 0.0,
                         hint="a relative accuracy on the moving pixels, e.g. 0.0; null: depth_prior_tolerance")
        check_number(self.ts_time_offset, "LossConfig.ts_time_offset", 0.0, lo_open=True,
                     hint="a time offset, the method's 0.08")
        check_number(self.iso_time_offset, "LossConfig.iso_time_offset", 0.0, 1.0, lo_open=True,
                     hint="a time offset in the clip's normalised time, e.g. 0.25")
        for name in ("ts_neighbours", "ts_knn_every"):
            check_int(getattr(self, name), f"LossConfig.{name}", 1)
        check_int(self.stereo_depths, "LossConfig.stereo_depths", 3, hint="a parabola needs three")
        check_choice(self.stereo_space, "LossConfig.stereo_space", ("depth", "metric"))
        check_choice(self.depth_grad_region, "LossConfig.depth_grad_region", ("moving", "all"))
        check_number(self.stereo_tolerance, "LossConfig.stereo_tolerance", 0.0,
                     hint="the sweep's relative accuracy, e.g. 0.05; 0 pulls every pixel")
        at = self.stereo_at
        if (not isinstance(at, tuple) or not at
                or not all(isinstance(a, numbers.Real) and not isinstance(a, bool) and 0.0 < a < 1.0 for a in at)):
            raise ValueError(f"LossConfig.stereo_at must be a non-empty tuple of schedule fractions in (0, 1), "
                             f"e.g. (0.25, 0.5); got {at!r}")
        check_bool(self.freq_static_only, "LossConfig.freq_static_only")
        check_number(self.freq_cutoff, "LossConfig.freq_cutoff", 0.0, 2.0 ** 0.5, lo_open=True, hi_open=True,
                     hint="normalised radial frequency up to sqrt 2, the method's 0.1")


# The method's regulariser weights (docs/method.md §6, Eq. 18), for turning the terms on
# (``LossConfig(**METHOD_REGULARISER_WEIGHTS)``; examples/suite.py's ablation variants use them).
METHOD_REGULARISER_WEIGHTS = {"lambda_ts": 1.0, "lambda_gs": 0.01, "lambda_freq": 0.002, "lambda_reproj": 0.001}


# LearningRates fields that are settings, not rates (no rate checks, not in the block rules).
NON_RATE_FIELDS = ("means_unit", "final_ratio", "means_depth", "means_depth_floor")


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates per block kind (3DGS's, the positions' scaled to the scene's size)."""

    # Positions: times the length of ``means_unit``; decays exponentially to means_final. 2x 3DGS's
    # 1.6e-4 in the scene's units (the choice: docs/results.md §7).
    means: float = 3.2e-4
    means_final: float = 3.2e-6
    # Twice 3DGS's 5e-3 (the choice: docs/results.md §7).
    log_scales: float = 1e-2
    quats: float = 1e-3
    opacity_logits: float = 5e-2
    colors: float = 2.5e-3 * 4  # no SH: plain RGB learns faster than 3DGS's SH DC term
    deform: float = 3.2e-4  # deformation coefficients of means (times the means_unit length); others use deform_other
    deform_other: float = 1e-3
    camera: float = 1e-3  # trajectory endpoints xi_start / xi_end and PoseNet weights; decays to camera_final
    camera_final: float = 1e-5
    # The spread of a centred exposure (trusted poses, TrajectoryConfig.centre): a tenth of the
    # camera rate, so Adam does not walk it away from the true exposure's (docs/results.md §7).
    camera_spread: float = 1e-4
    camera_spread_final: float = 1e-6
    # The camera rate's factor for the endpoint rows of frames a kept bundle adjustment moved, when
    # Adam alone refines them (PoseInitConfig.then = "adam"); frames it held at their given poses
    # keep the full rate. Poses the adjustment brought close need small steps: at the full rate
    # their jitter blurs the scene fitted to them (docs/results.md §4).
    camera_adjusted_scale: float = 0.1
    exposure: float = 1e-2
    # The constant-rate Gaussian blocks (log_scales, quats, opacity_logits, colors, deform_other)
    # decay log-linearly to final_ratio x their rate over the run; 1 keeps them constant, as 3DGS
    # does (why: docs/results.md §7).
    final_ratio: float = 1.0
    # The length that scales the position rates (means, deform): "camera", 3DGS's camera extent
    # (train.learning_rates.scene_extent), or "scene", the scene's size (train.learning_rates.size_extent: the
    # larger of that and 1.1 x the 90th percentile distance of the initial points from the cameras'
    # mean). A hand-held camera moves little against the depth it sees, so camera units make the
    # position steps too small for a CPU budget (docs/results.md §7).
    means_unit: str = "scene"
    # How a position step depends on the Gaussian's depth: "world", the same length for every
    # Gaussian (3DGS); "near", a Gaussian nearer than the step frame's median static depth takes
    # it shortened by its depth over that median (at least means_depth_floor), so its step in
    # pixels is the median's, not up to 1 / depth times it (train.learning_rates.position_row_factors).
    means_depth: str = "world"
    means_depth_floor: float = 0.1

    def __post_init__(self):
        check_choice(self.means_unit, "LearningRates.means_unit", ("camera", "scene"))
        check_choice(self.means_depth, "LearningRates.means_depth", ("world", "near"))
        check_number(self.means_depth_floor, "LearningRates.means_depth_floor", 0.0, 1.0, lo_open=True,
                     hint="the shortest factor on a near Gaussian's position step, e.g. 0.1")
        check_number(self.final_ratio, "LearningRates.final_ratio", 0.0, 1.0, lo_open=True, hint="1: constant rates")
        for f in dataclasses.fields(self):
            if f.name not in NON_RATE_FIELDS:
                check_number(getattr(self, f.name), f"LearningRates.{f.name}", 0.0, hint="0 freezes the block")
        for message in self.implausible():
            warn(message, ConfigWarning, stacklevel=3)

    def implausible(self) -> list:
        """Warnings (one line each) on rates that are possible but implausible: above LR_PLAUSIBLE_MAX."""
        high = [f"LearningRates.{f.name} = {getattr(self, f.name):g}" for f in dataclasses.fields(self)
                if f.name not in NON_RATE_FIELDS and getattr(self, f.name) > LR_PLAUSIBLE_MAX]
        if not high:
            return []
        return [f"{name_items(high)} above {LR_PLAUSIBLE_MAX:g}: Adam moves a parameter by about its learning rate "
                "each step (a position in units of the scene's size, a log-scale by an e-fold, a colour across its "
                "range), so training diverges; the defaults are at most 5e-2"]


@dataclass(frozen=True)
class TrainConfig:
    iters: int = 2000
    # Stage split (docs/method.md §8): camera/static warm-up, deformation, joint; fractions of iters.
    warmup_fraction: float = 0.1
    deform_fraction: float = 0.1
    # The camera model (exposure endpoints, PoseNet) is not trained before this fraction of iters:
    # 0 trains it from the first step; > 0 fits the Gaussians at the start poses first, as the public
    # deblurring codebases do (docs/method.md §8).
    camera_from_fraction: float = 0.0
    seed: int = 0
    background: tuple = (0.0, 0.0, 0.0)
    # True: each step's render is moved over a background drawn at random for that step, so
    # transparency costs loss and the model turns opaque where the images are (train/background.py);
    # evaluation renders over ``background``. Off by default (why: docs/results.md §4).
    random_background: bool = False
    lr: LearningRates = field(default_factory=LearningRates)
    # Components: "auto" lets the scene decide (docs/method.md §9); "on"/"off" force.
    dynamic: str = "auto"
    blur: str = "auto"
    learn_exposure: str = "auto"  # learned tau when the scene gives no exposure_fraction
    progressive: bool = True
    # Housekeeping
    log_every: int = 10
    eval_every: int = 250
    checkpoint_every: int = 500
    # also a checkpoint when this many seconds of wall clock have passed since the last (0 = never):
    # a slow step (seconds with the blur model) would otherwise put many minutes at risk
    checkpoint_seconds: float = 300.0
    prune_every: int = 250
    prune_opacity: float = 0.005
    time_budget: Optional[float] = None  # seconds of training; stops cleanly when exceeded
    # With a time budget: True ends the run when the budget ends; a run that finishes its schedule of
    # iters steps early trains on at the schedule's end (final rates, full resolution) until then.
    # False also ends it at iters steps. docs/method.md §7.
    stretch_to_budget: bool = True
    eval_frames: int = 4  # held-out PSNR on this many frames (sharp GT if present, else blurry)
    quiet: bool = False

    def __post_init__(self):
        check_int(self.iters, "TrainConfig.iters", 1)
        if not (0 <= self.warmup_fraction and 0 <= self.deform_fraction and self.warmup_fraction + self.deform_fraction <= 1):
            raise ValueError(
                f"TrainConfig stage fractions must be >= 0 and sum to <= 1; got warmup_fraction="
                f"{self.warmup_fraction}, deform_fraction={self.deform_fraction}")
        check_number(self.camera_from_fraction, "TrainConfig.camera_from_fraction", 0.0, 1.0,
                     hint="a fraction of iters; 0 trains the camera from the start")
        for name in ("dynamic", "blur", "learn_exposure"):
            check_choice(getattr(self, name), f"TrainConfig.{name}", _AUTO)
        if isinstance(self.background, (str, bytes)) or not hasattr(self.background, "__len__") \
                or len(self.background) != 3:
            raise ValueError(f"TrainConfig.background must have 3 values (R, G, B in [0, 1]); got {self.background!r}")
        for i, v in enumerate(self.background):
            check_number(v, f"TrainConfig.background[{i}]", 0.0, 1.0, hint="an RGB colour: 0 black, 1 white")
        for name in ("log_every", "eval_frames"):
            check_int(getattr(self, name), f"TrainConfig.{name}", 1)
        for name in ("eval_every", "checkpoint_every", "prune_every"):
            check_int(getattr(self, name), f"TrainConfig.{name}", 0, hint="0 = never")
        check_int(self.seed, "TrainConfig.seed", 0, hint="a NumPy seed")
        for name in ("progressive", "quiet", "stretch_to_budget", "random_background"):
            check_bool(getattr(self, name), f"TrainConfig.{name}")
        check_number(self.prune_opacity, "TrainConfig.prune_opacity", 0.0, 1.0, hi_open=True)
        if self.time_budget is not None:
            check_number(self.time_budget, "TrainConfig.time_budget", 0.0, lo_open=True, hint="seconds")
        check_number(self.checkpoint_seconds, "TrainConfig.checkpoint_seconds", 0.0,
                     hint="seconds; 0 = no wall-clock checkpoints")


@dataclass(frozen=True)
class PoseSolverConfig:
    """Pose refinement between Adam steps (docs/method.md §5; the "pose_solver" step plugin,
    ``train/pose_solver.py``). ``mode``: "auto" runs it unless the scene flags its poses as exact
    (``poses_trusted``) or the run is too short for it to fire (iters <= every); "on" / "off" force.
    ``accept``: "converged" writes a call's poses only when the solver converged (relative cost
    decrease or step below tolerance, not stopped by ``max_iters`` or the damping limit) with a
    full-rank normal matrix (every free frame observed); "always" writes every call's result.
    "converged" because an unconverged call is the one that can move the poses away from the
    truth (the calls measured: docs/results.md §11)."""

    mode: str = "auto"
    every: int = 150  # schedule steps between solver calls (R; the paper's 500 is for GPU-length runs)
    render_scale: float = 1.0  # depth maps rendered at this fraction of the frame size
    correspond: CorrespondConfig = field(default_factory=CorrespondConfig)
    gauss_newton: GaussNewtonConfig = field(default_factory=GaussNewtonConfig)
    accept: str = "converged"
    # The pose prior of pose/gauss_newton.py: every call holds the mid poses near the GIVEN poses
    # (sigma_r = prior_rot_deg, sigma_t = prior_trans_rel x the median rendered depth of the
    # matches); 0 turns that part off. The data's residuals are not independent (the scene is
    # fitted to the poses they test), so the prior is set tighter than the poses' true error, which
    # alone lets the calls drift (docs/results.md §11). hold_scale: after each
    # call the refined camera centres are rescaled about frame 0's so the trajectory keeps the size
    # it had before the call (the scale is a gauge the rendered depths fix only softly, and biased).
    # Both keep the calls from shrinking and turning the trajectory (docs/results.md §11).
    # Real (not schedule) steps a call needs since the previous call, or since the start: the
    # depths a call reads come from the scene Adam fitted since. The cadence ``every`` runs on the
    # schedule's clock, which a loaded machine stretches; the default is one period's real steps on
    # an idle machine (docs/results.md §11).
    min_steps: int = 40
    prior_rot_deg: float = 0.3
    prior_trans_rel: float = 0.006
    hold_scale: bool = True
    # The independent check of a solve (train/pose_solver.py): KLT point tracks through the frames,
    # triangulated with the current and with the proposed mid poses (pose_init.
    # track_reprojection_rms); a solve whose poses explain the tracks worse, by more than
    # track_tolerance (relative rise of the rms), is not written. The solver's residuals read
    # rendered depths of a scene fitted to the poses they test; the tracks depend on none
    # (docs/results.md §11).
    track_check: bool = True
    track_tolerance: float = 0.1

    def __post_init__(self):
        for name in ("prior_rot_deg", "prior_trans_rel"):
            check_number(getattr(self, name), f"PoseSolverConfig.{name}", 0.0, hint="0 = no prior")
        if (self.prior_rot_deg == 0.0) != (self.prior_trans_rel == 0.0):
            raise ValueError("PoseSolverConfig.prior_rot_deg and prior_trans_rel must both be > 0 (the pose prior) "
                             f"or both 0 (no prior); got {self.prior_rot_deg}, {self.prior_trans_rel}")
        check_int(self.min_steps, "PoseSolverConfig.min_steps", 0, hint="real steps between calls")
        check_bool(self.track_check, "PoseSolverConfig.track_check")
        check_number(self.track_tolerance, "PoseSolverConfig.track_tolerance", 0.0, hint="a relative rise")
        check_bool(self.hold_scale, "PoseSolverConfig.hold_scale")
        check_choice(self.mode, "PoseSolverConfig.mode", _AUTO)
        check_choice(self.accept, "PoseSolverConfig.accept", ("converged", "always"))
        check_int(self.every, "PoseSolverConfig.every", 1, hint="schedule steps")
        check_number(self.render_scale, "PoseSolverConfig.render_scale", 0.0, 1.0, lo_open=True)


@dataclass(frozen=True)
class DensifyConfig:
    """Densification: clone / split where the screen-space gradient is large (train/densify.py's
    module docstring)."""

    # On by default: fine texture needs more Gaussians than the seeds give (docs/results.md §10).
    enabled: bool = True
    start_fraction: float = 0.1
    stop_fraction: float = 0.6
    every: int = 100
    grad_threshold_ndc: float = 2e-4  # 3DGS default
    percent_dense: float = 0.01  # clone below this share of the scene extent, split above
    split_factor: float = 1.6
    max_gaussians: int = 40000
    # > 0: the cap follows the clip, one Gaussian per this many observed pixels (frames x height x
    # width), at most max_gaussians (densify.gaussian_cap); 0, the default: max_gaussians alone
    # (why: docs/method.md §8).
    pixels_per_gaussian: float = 0.0
    # > 0: the dynamic set grows to at most one Gaussian per this many moving pixels (the motion
    # masks' pixels over all frames, full resolution; densify.dynamic_gaussian_cap); 0: the dynamic
    # set takes what the total cap leaves (why 17: docs/method.md §8).
    dynamic_pixels_per_gaussian: float = 17.0
    absgrad: bool = False  # densify on the absolute-sum statistic (module docstring)
    grad_threshold_abs_ndc: float = 8e-4  # its threshold (gsplat's advice for absgrad)
    # > 0: every this many schedule steps inside [start, stop) every opacity is lowered to at most
    # opacity_reset_value and its Adam moments zeroed (3DGS's opacity reset, every 3000 of its
    # 30 000 steps): what the loss does not raise again is pruned. 0, the default: off
    # (docs/method.md §8, densification).
    opacity_reset_every: int = 0
    opacity_reset_value: float = 0.01  # 3DGS's

    def __post_init__(self):
        for name in ("start_fraction", "stop_fraction"):
            check_number(getattr(self, name), f"DensifyConfig.{name}", 0.0, 1.0)
        if not self.start_fraction <= self.stop_fraction:
            raise ValueError(f"DensifyConfig needs 0 <= start_fraction <= stop_fraction <= 1; got "
                             f"{self.start_fraction}, {self.stop_fraction}")
        for name in ("every", "max_gaussians"):
            check_int(getattr(self, name), f"DensifyConfig.{name}", 1)
        for name in ("grad_threshold_ndc", "grad_threshold_abs_ndc", "percent_dense"):
            check_number(getattr(self, name), f"DensifyConfig.{name}", 0.0, lo_open=True)
        check_number(self.pixels_per_gaussian, "DensifyConfig.pixels_per_gaussian", 0.0,
                     hint="observed pixels per Gaussian, or 0 for the fixed max_gaussians")
        check_number(self.dynamic_pixels_per_gaussian, "DensifyConfig.dynamic_pixels_per_gaussian", 0.0,
                     hint="moving pixels per dynamic Gaussian, or 0 for no cap of the dynamic set's own")
        check_number(self.split_factor, "DensifyConfig.split_factor", 1.0, lo_open=True)
        check_bool(self.enabled, "DensifyConfig.enabled")
        check_bool(self.absgrad, "DensifyConfig.absgrad")
        check_int(self.opacity_reset_every, "DensifyConfig.opacity_reset_every", 0, hint="schedule steps, 0 = off")
        check_number(self.opacity_reset_value, "DensifyConfig.opacity_reset_value", 0.0, 1.0, lo_open=True,
                     hi_open=True)


@dataclass(frozen=True)
class PruneConfig:
    """Pruning rules (train/prune.py's module docstring). 0 switches a size or share rule off."""

    max_scale_fraction: float = 0.1  # x scene extent; 3DGS's big-points rule
    max_outside_share: float = 0.5  # of the frames where a dynamic centre is in view
    mask_dilation_px: int = 3  # masks are grown this much before the escaped test (blur, init slack)
    # Prune also past the schedule's end, while a budgeted run trains on (TrainConfig.stretch_to_budget),
    # until 90 % of the budget. Off by default (why: docs/method.md §10, the veils).
    past_schedule: bool = False

    def __post_init__(self):
        check_bool(self.past_schedule, "PruneConfig.past_schedule")
        check_number(self.max_scale_fraction, "PruneConfig.max_scale_fraction", 0.0, hint="0 = off")
        check_number(self.max_outside_share, "PruneConfig.max_outside_share", 0.0, 1.0, hint="0 = off")
        check_int(self.mask_dilation_px, "PruneConfig.mask_dilation_px", 0)


@dataclass(frozen=True)
class ExperimentConfig:
    train: TrainConfig = field(default_factory=TrainConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    # training steps rasterise in float32 (RenderConfig.raster_float32; docs/method.md §8) for speed
    # (docs/results.md §7); evaluation and Model.render stay float64
    render: RenderConfig = field(default_factory=lambda: RenderConfig(raster_float32=True))
    deform: DeformConfig = field(default_factory=DeformConfig)
    blur: BlurConfig = field(default_factory=BlurConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    init: InitConfig = field(default_factory=InitConfig)
    motion_init: MotionInitConfig = field(default_factory=MotionInitConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    prune: PruneConfig = field(default_factory=PruneConfig)
    pose_solver: PoseSolverConfig = field(default_factory=PoseSolverConfig)
    pose_init: PoseInitConfig = field(default_factory=PoseInitConfig)
    # the static world continued past the frames' borders, added to the finished model
    border: BorderConfig = field(default_factory=BorderConfig)

    def __post_init__(self):
        m, d = self.motion_init, self.init.dynamic_depth
        if m.rigid and m.rigid_fit in ("pairs", "bundle") and d not in ("prior", "scene", "auto"):
            raise ValueError(f"motion_init.rigid_fit = {m.rigid_fit!r} lifts each pair's correspondences at the "
                             f"dynamic seeds' depth maps, which init.dynamic_depth = {d!r} has none of: set "
                             "init.dynamic_depth to 'prior' (depth priors), 'scene' (true depth) or 'auto', or "
                             "rigid_fit to 'kabsch'")

    def to_dict(self) -> dict:
        return _to_plain(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, d: dict) -> "ExperimentConfig":
        return _from_plain(cls, d, "config")

    @classmethod
    def from_json(cls, text: str) -> "ExperimentConfig":
        return cls.from_dict(json.loads(text))

    @classmethod
    def load(cls, path) -> "ExperimentConfig":
        path = Path(path)
        if path.is_dir():
            hint = f" (e.g. {path / 'config.json'})" if (path / "config.json").is_file() else ""
            raise ValueError(f"config file {path} is a folder; pass the config JSON file{hint}")
        if not path.exists():
            raise FileNotFoundError(f"config file {path} does not exist")
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"config file {path} is not valid JSON: {e}") from e
        return cls.from_dict(data)

    def replace(self, **sections) -> "ExperimentConfig":
        return dataclasses.replace(self, **sections)


def _to_plain(obj):
    if dataclasses.is_dataclass(obj):
        return {f.name: _to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [_to_plain(v) for v in obj]
    if isinstance(obj, dict):
        return {k: _to_plain(v) for k, v in obj.items()}
    return obj


def _from_plain(cls, data, where, base=None):
    """``cls`` from a JSON object; keys left out take ``base``'s values (the enclosing config's
    default for a section), else the class defaults."""
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be a JSON object; got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {sorted(unknown)}; known keys are {sorted(names)}")
    kwargs = {}
    for name, value in data.items():
        tp = hints[name]
        if dataclasses.is_dataclass(tp):
            kwargs[name] = _from_plain(tp, value, f"{where}.{name}", _field_default(cls, name))
        elif isinstance(value, list):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    try:
        return cls(**kwargs) if base is None else dataclasses.replace(base, **kwargs)
    except TypeError as e:
        raise ValueError(f"{where}: {e}") from e


def _field_default(cls, name):
    """The default value of field ``name`` of dataclass ``cls`` (None if it has none)."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None if f.default is dataclasses.MISSING else f.default
