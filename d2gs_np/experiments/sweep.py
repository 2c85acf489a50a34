"""Experiments: named sweeps of independent training runs, run in parallel on Dask (docs/method.md §10).

An experiment is a list of variants; a sweep crosses it with scenes and seeds into cells. Each
cell is one run with its own folders (``OUT/scenes/<scene>_s<seed>_<kind>[_x<size>][_f<frames>]``,
``OUT/runs/<experiment>/<scene>_s<seed>_<variant>[_x<size>][_f<frames>]``): it makes its scene
(if not there), trains with the variant's config, evaluates, and writes ``RUN/metrics.json``.
A cell whose metrics exist is never recomputed (resume); its settings (budget, steps, base
config, and with a budget the thread count) are recorded in ``RUN/cell.json``, and a later sweep into the same folder with other
settings is refused with an error naming the cell, never answered with the old result. A cell
that raises is retried ``retries`` times and then reported as failed in the table and the
return value, never silently dropped.

Variants (``EXPERIMENTS``):
- ``baselines``: the full method; no blur model (n = 1, no pose refinement: the paper's
  GaussianFlow row); a two-stage baseline (``d2gs_np/evaluation/baselines.py``: each frame deconvolved
  with a kernel from the given poses, then trained without the blur model and without pose
  refinement, as the no-blur row); the sharp-input
  upper bound (sharp frames, true poses).
- ``progressive``: the paper's Table VI: no progressive resolution, linear, exponential, cosine.
- ``virtual-views``: n in {1, 2, 4, 8, 16}: quality against time.
- ``ablation``: the paper's Table V on the given poses: render only; + L_ts; + L_gs; + L_freq
  (each alone, at the method's weights); + the pose solver (the "+ L_reproj" row); all.
- ``suite``: what ``examples/suite.py`` runs (sharp / blurry with true poses, with and without
  the blur model / blurry with the given noisy poses); ``suite-ablation``: the ablation's
  regularisers with true poses (``examples/suite.py --variants render_only ...``).
- ``exposure-start``, ``exposure-path``, ``exposure-defaults`` (#39): where the exposure starts,
  its path, the defaults before and after; ``dynamic-depth`` (#40, #44): the dynamic seeds' depth
  by the rule against the scene's true depth (an oracle) and against a modelled video depth
  model's depth aligned to the static points, and that depth also as a loss (L_depth).
A variant is a name, config overrides (a nested dict merged into the config's JSON form, so a
variant is data and every key is checked by ``ExperimentConfig.from_dict``), scene overrides
(``SuiteConfig`` fields, e.g. exposure 0 or true poses) and an optional preprocessing of the
scene (``two_stage``).

Scheduling: ``scheduler=None`` runs the cells on Dask's local process pool (``jobs`` processes,
no set-up); ``scheduler="ADDRESS"`` submits them to a running ``dask.distributed`` scheduler
(``Client(ADDRESS)``), so a lab runs the same command on its cluster; a
``distributed.Client`` object may be passed too (tests use a ``LocalCluster``). Cells only
read and write their own folders under ``OUT``, which every worker must see (a shared file
system on a cluster).

Outputs: ``OUT/<name>.csv`` (a row per cell), ``OUT/<name>.md`` (the table, with the command),
``OUT/<name>_error_vs_time.png`` (held-out PSNR against training seconds, every cell).
"""
from __future__ import annotations

import copy
import csv
import json
import os
import shutil
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from d2gs_np.train.config import METHOD_REGULARISER_WEIGHTS

__all__ = ["Variant", "EXPERIMENTS", "run_cell", "run_experiment", "experiment_cells", "cell_folder"]


@dataclass(frozen=True)
class Variant:
    name: str
    config: dict = field(default_factory=dict)  # nested overrides of ExperimentConfig.to_dict()
    scene: dict = field(default_factory=dict)  # scene generator overrides (SuiteConfig / SyntheticConfig fields)
    two_stage: bool = False  # deconvolve the frames first (d2gs_np/evaluation/baselines.py), then train without blur

    @property
    def scene_kind(self) -> str:
        """The folder name part that identifies the scene this variant trains on."""
        parts = [f"{k}{v}" for k, v in sorted(self.scene.items())] or ["given"]
        return "_".join(parts).replace(".", "p") + ("_rl" if self.two_stage else "")


_REG = METHOD_REGULARISER_WEIGHTS  # the method's weights (docs/method.md §6)
_NO_REG = {k: 0.0 for k in _REG}
_TRUE_POSES = {"rot_noise_deg": 0.0, "trans_noise": 0.0}
_SHARP = {"exposure_fraction": 0.0, **_TRUE_POSES}

EXPERIMENTS = {
    "baselines": (
        Variant("full"),
        Variant("noblur", config={"train": {"blur": "off"}, "pose_solver": {"mode": "off"}}),
        Variant("two_stage", config={"train": {"blur": "off"}, "pose_solver": {"mode": "off"}}, two_stage=True),
        Variant("sharp_bound", scene=_SHARP),
    ),
    "progressive": (
        Variant("none", config={"train": {"progressive": False}}),
        Variant("linear", config={"schedule": {"kind": "linear"}}),
        Variant("exponential", config={"schedule": {"kind": "exponential"}}),
        Variant("cosine", config={"schedule": {"kind": "cosine"}}),
    ),
    "virtual-views": tuple(
        Variant(f"n{n}", config={"train": {"blur": "off"}} if n == 1 else {"blur": {"num_virtual": n}})
        for n in (1, 2, 4, 8, 16)),
    # The paper's Table V on the given (noisy) poses: the photometric loss alone, each regulariser
    # added alone at the method's weight, the pose solver (the "+ L_reproj" row: refinement on
    # reprojection residuals), and everything.
    "ablation": (
        Variant("render_only", config={"loss": _NO_REG, "pose_solver": {"mode": "off"}}),
        Variant("+ts", config={"loss": {**_NO_REG, "lambda_ts": _REG["lambda_ts"]}, "pose_solver": {"mode": "off"}}),
        Variant("+gs", config={"loss": {**_NO_REG, "lambda_gs": _REG["lambda_gs"]}, "pose_solver": {"mode": "off"}}),
        Variant("+freq", config={"loss": {**_NO_REG, "lambda_freq": _REG["lambda_freq"]},
                                 "pose_solver": {"mode": "off"}}),
        Variant("+reproj", config={"loss": {**_NO_REG, "lambda_reproj": _REG["lambda_reproj"]},
                                   "pose_solver": {"mode": "on"}}),
        Variant("all", config={"loss": dict(_REG), "pose_solver": {"mode": "on"}}),
    ),
    # The same ablation with true poses (examples/suite.py): the regularisers without pose error;
    # trusted poses leave the pose solver out, so "+reproj" is L_reproj's depth term alone.
    "suite-ablation": (
        Variant("render_only", scene=_TRUE_POSES, config={"loss": _NO_REG}),
        Variant("+ts", scene=_TRUE_POSES, config={"loss": {**_NO_REG, "lambda_ts": _REG["lambda_ts"]}}),
        Variant("+gs", scene=_TRUE_POSES, config={"loss": {**_NO_REG, "lambda_gs": _REG["lambda_gs"]}}),
        Variant("+freq", scene=_TRUE_POSES, config={"loss": {**_NO_REG, "lambda_freq": _REG["lambda_freq"]}}),
        Variant("+reproj", scene=_TRUE_POSES, config={"loss": {**_NO_REG, "lambda_reproj": _REG["lambda_reproj"]}}),
        Variant("all", scene=_TRUE_POSES, config={"loss": dict(_REG)}),
    ),
    # Where the exposure starts and when it learns (issue #39, docs/results.md §5): the default start on
    # the velocity of the neighbouring given poses, the same from a 5-frame fit, and a start at the
    # given pose (a tiny spread, as the public deblurring codebases start), each with and without a
    # first fifth of the steps that fits the Gaussians alone; the no-blur baseline beside them.
    "exposure-start": (
        Variant("velocity"),
        Variant("velocity_h2", config={"trajectory": {"velocity_window": 2}}),
        Variant("velocity_gfirst", config={"train": {"camera_from_fraction": 0.2}}),
        Variant("given", config={"trajectory": {"init": "random"}}),
        Variant("given_gfirst", config={"trajectory": {"init": "random"}, "train": {"camera_from_fraction": 0.2}}),
        Variant("noblur", config={"train": {"blur": "off"}, "pose_solver": {"mode": "off"}}),
    ),
    # The exposure's path (issue #39, docs/method.md §4): the three-knot path from the velocity start
    # and from the given pose, on the given (noisy) and on true poses, the geodesic on true poses,
    # and the no-blur baseline of the same budget.
    "exposure-path": (
        Variant("knot_velocity", config={"trajectory": {"path": "three_knot"}}),
        Variant("knot_given", config={"trajectory": {"path": "three_knot", "init": "random"}}),
        Variant("noblur", config={"train": {"blur": "off"}, "pose_solver": {"mode": "off"}}),
        Variant("knot_true", scene=_TRUE_POSES, config={"trajectory": {"path": "three_knot"}}),
        Variant("geodesic_true", scene=_TRUE_POSES),
    ),
    # The defaults before and after issue #39's measurements, spelled out so the cells do not move
    # when the defaults do: the geodesic from the velocity start with the camera trained from the
    # first step, against the three-knot path after a fifth of the schedule on the Gaussians alone,
    # and the path each clip's bend chooses.
    "exposure-defaults": (
        Variant("geodesic", config={"trajectory": {"path": "geodesic"}, "train": {"camera_from_fraction": 0.0}}),
        Variant("three_knot_gfirst", config={"trajectory": {"path": "three_knot"},
                                             "train": {"camera_from_fraction": 0.2}}),
        Variant("noblur", config={"train": {"blur": "off"}, "pose_solver": {"mode": "off"}}),
        # the path chosen per clip by its measured bend (TrajectoryConfig.path = "auto")
        Variant("auto_path", config={"trajectory": {"path": "auto"}, "train": {"camera_from_fraction": 0.0}}),
    ),
    # Is the dynamic set's depth what tears movers in novel views (issues #40, #44, docs/method.md §8)?
    # The seeds at 0.8 x the frame's median static depth (the rule) against seeds at the scene's true
    # depth (an oracle: the suite's depth maps), the rest alike, with the given (noisy) poses.
    "dynamic-depth": (
        Variant("static_median", config={"init": {"dynamic_depth": "static_median"}}),
        Variant("oracle_depth", config={"init": {"dynamic_depth": "scene"}}),
        # a modelled video depth model's depth up to a scale (data/suite.py), aligned to the static points
        Variant("prior_depth", scene={"depth_prior": "video"}, config={"init": {"dynamic_depth": "prior"}}),
        # the same prior also as a loss on every frame's rendered depth (L_depth, docs/method.md §6):
        # every pixel pulled, or only beyond the prior's 10 % accuracy
        Variant("prior_loss", scene={"depth_prior": "video"},
                config={"init": {"dynamic_depth": "prior"},
                        "loss": {"lambda_depth_prior": 0.1, "depth_prior_tolerance": 0.0}}),
        Variant("prior_loss_tol", scene={"depth_prior": "video"},
                config={"init": {"dynamic_depth": "prior"},
                        "loss": {"lambda_depth_prior": 0.1, "depth_prior_tolerance": 0.1}}),
    ),
    # The dynamic set's growth capped by its moving pixels (docs/method.md §8, densification): no cap
    # of its own (the dynamic set takes what the total cap leaves) against one Gaussian per 17 moving
    # pixels, alone and with the depth prior's seeds and loss.
    "dynamic-cap": (
        Variant("uncapped", config={"densify": {"dynamic_pixels_per_gaussian": 0.0}}),
        Variant("dynamic_cap", config={"densify": {"dynamic_pixels_per_gaussian": 17.0}}),
        Variant("dynamic_cap_prior", scene={"depth_prior": "video"},
                config={"init": {"dynamic_depth": "prior"}, "densify": {"dynamic_pixels_per_gaussian": 17.0},
                        "loss": {"lambda_depth_prior": 0.1, "depth_prior_tolerance": 0.1}}),
    ),
    # Neighbouring exposures on one constant-velocity camera path (L_cont, docs/method.md §6; issue #39's
    # neighbour-continuity prior): off, at 0.01 per squared pixel of residual, and at a tenth of it.
    "exposure-continuity": (
        Variant("none", config={"loss": {"lambda_continuity": 0.0}}),
        Variant("continuity", config={"loss": {"lambda_continuity": 0.01}}),
        Variant("continuity_weak", config={"loss": {"lambda_continuity": 0.001}}),
    ),
    # The dynamic set's neighbour distances held over time as on rigid objects (L_iso, docs/method.md §6;
    # issue #44): off, at 0.01 and at 0.1.
    "dynamic-rigidity": (
        Variant("none", config={"loss": {"lambda_iso": 0.0}}),
        Variant("iso", config={"loss": {"lambda_iso": 0.01}}),
        Variant("iso_strong", config={"loss": {"lambda_iso": 0.1}}),
    ),
    # The static world's depth at the start (issue #40): the dense seeds and the fill at the plane sweep's
    # depth (the default) against the scene's true depth (an oracle, InitConfig.static_depth = "scene"),
    # with the movers' seeds at theirs too, with the true poses and with the given ones.
    "static-depth": (
        Variant("stereo_true", scene=_TRUE_POSES),
        Variant("oracle_true", scene=_TRUE_POSES, config={"init": {"static_depth": "scene", "dynamic_depth": "scene"}}),
        # and each tracked mover one body on a path chained from frame pairs at the true depth (issue #44)
        Variant("oracle_true_rigid_pairs", scene=_TRUE_POSES,
                config={"init": {"static_depth": "scene", "dynamic_depth": "scene"},
                        "motion_init": {"rigid": True, "rigid_residual": False, "rigid_fit": "pairs"}}),
        Variant("stereo"),
        Variant("oracle", config={"init": {"static_depth": "scene", "dynamic_depth": "scene"}}),
        # the realistic counterpart of the oracle: a modelled video depth prior (data/suite.py) aligned to
        # the static points, for every seed ("prior"), or only where the sweep disagrees with it by more
        # than 15 % ("stereo_prior"); the movers' seeds at the prior too
        Variant("prior_true", scene={**_TRUE_POSES, "depth_prior": "video"},
                config={"init": {"static_depth": "prior", "dynamic_depth": "prior"}}),
        Variant("stereo_prior_true", scene={**_TRUE_POSES, "depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior"}}),
        Variant("prior", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "prior", "dynamic_depth": "prior"}}),
        Variant("stereo_prior", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior"}}),
        # the static seeds alone from the prior, the movers' by the rule: which of the two costs big_mover's DVS
        Variant("stereo_prior_static", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "static_median"}}),
        # the interpolated seeds and the fill kept on the stereo's surface where it agrees with the prior
        Variant("stereo_prior_all", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "stereo_prior_scope": "all",
                                 "dynamic_depth": "prior"}}),
        # sharp input with true poses (issue #40's first line) given the same prior seeds
        Variant("stereo_prior_sharp", scene={**_SHARP, "depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior"}}),
        # the static seeds' priors fused over the frames first (InitConfig.depth_prior_fusion), with the
        # suite's prior error new in every frame and with half its variance shared by all frames
        Variant("stereo_prior_fused", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True}}),
        # and the movers' shape held to the priors' (L_dgrad on the moving pixels, issue #44: a mover's
        # patches drift apart along their rays inside L_depth's band)
        Variant("stereo_prior_fused_dgrad", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True},
                        "loss": {"lambda_depth_grad": 1.0}}),
        # and each tracked mover one rigid object (MotionInitConfig.rigid, scene/rigid.py, issue #44:
        # one shape, so one scale of it over the clip for the priors' frames to set together)
        Variant("stereo_prior_fused_rigid", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True},
                        "motion_init": {"rigid": True}}),
        # the same with the clusters' poses refined by PnP onto the tracked pixels
        Variant("stereo_prior_fused_rigid_pnp", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True},
                        "motion_init": {"rigid": True, "rigid_fit": "pnp"}}),
        # the same with each cluster one body (no residual motion of its Gaussians)
        Variant("stereo_prior_fused_rigid_body", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True},
                        "motion_init": {"rigid": True, "rigid_residual": False}}),
        # one body whose path is chained from frame pairs lifted at the aligned priors (rigid_fit "pairs")
        Variant("stereo_prior_fused_rigid_pairs", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True},
                        "motion_init": {"rigid": True, "rigid_residual": False, "rigid_fit": "pairs"}}),
        # and that path refined with the object's shape by the object bundle (rigid_fit "bundle")
        Variant("stereo_prior_fused_rigid_bundle", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True},
                        "motion_init": {"rigid": True, "rigid_residual": False, "rigid_fit": "bundle"}}),
        # the same with each point tracked 8 frames each way, not 5: more of a small mover's turn per track
        Variant("stereo_prior_fused_rigid_bundle_w8", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True},
                        "motion_init": {"rigid": True, "rigid_residual": False, "rigid_fit": "bundle",
                                        "bundle_window": 8}}),
        Variant("stereo_prior_true_fused_rigid_bundle", scene={**_TRUE_POSES, "depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True},
                        "motion_init": {"rigid": True, "rigid_residual": False, "rigid_fit": "bundle"}}),
        Variant("stereo_prior_fused_shared", scene={"depth_prior": "video", "prior_shared_error": 0.5},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True}}),
        Variant("stereo_prior_shared", scene={"depth_prior": "video", "prior_shared_error": 0.5},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior"}}),
        # the same priors as rows of the bundle adjustment before training too (PoseInitConfig.depth_prior_weight)
        Variant("stereo_prior_ba", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior"},
                        "pose_init": {"depth_prior_weight": 1.0}}),
        Variant("stereo_prior_fused_ba", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True},
                        "pose_init": {"depth_prior_weight": 1.0}}),
        # and the paper's opacity entropy L_gs against the translucent layers in front of a surface
        Variant("stereo_prior_fused_ba_gs", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior", "depth_prior_fusion": True},
                        "pose_init": {"depth_prior_weight": 1.0}, "loss": {"lambda_gs": _REG["lambda_gs"]}}),
        # the no-blur baseline (no blur model, no pose refinement) given the same prior seeds
        Variant("stereo_prior_noblur", scene={"depth_prior": "video"},
                config={"init": {"static_depth": "stereo_prior", "dynamic_depth": "prior"}, "train": {"blur": "off"},
                        "pose_solver": {"mode": "off"}}),
    ),
    # Opacity resets during densification (issue #40: faint layers in front of the static world,
    # docs/method.md §8): off; 3DGS's (to 0.01 every 500 schedule steps of the 2000, at 500 and 1000,
    # pruned at 0.005); splatfacto's, which BAD-Gaussians trains with (to 0.2, culled below 0.1 at
    # every prune); with the given (noisy) and the true poses.
    "opacity-reset": (
        Variant("none", config={"densify": {"opacity_reset_every": 0}}),
        Variant("reset", config={"densify": {"opacity_reset_every": 500}}),
        Variant("cull_reset", config={"densify": {"opacity_reset_every": 500, "opacity_reset_value": 0.2},
                                      "train": {"prune_opacity": 0.1}}),
        Variant("none_true", scene=_TRUE_POSES, config={"densify": {"opacity_reset_every": 0}}),
        Variant("cull_reset_true", scene=_TRUE_POSES,
                config={"densify": {"opacity_reset_every": 500, "opacity_reset_value": 0.2},
                        "train": {"prune_opacity": 0.1}}),
    ),
    # L_stereo, the plane sweep over the model's own renders as a depth prior (issue #40, docs/method.md
    # §6): made at a quarter and half of the schedule, its depth ratios ("stereo") or its depth itself
    # ("metric"); or the static set re-seeded from it once, at a quarter of the schedule ("reseed");
    # with the given (noisy) and the true poses.
    "render-stereo": (
        Variant("none", config={"loss": {"lambda_stereo": 0.0}}),
        Variant("stereo", config={"loss": {"lambda_stereo": 0.1}}),
        Variant("none_true", scene=_TRUE_POSES, config={"loss": {"lambda_stereo": 0.0}}),
        Variant("stereo_true", scene=_TRUE_POSES, config={"loss": {"lambda_stereo": 0.1}}),
        Variant("metric", config={"loss": {"lambda_stereo": 0.1, "stereo_space": "metric"}}),
        Variant("metric_true", scene=_TRUE_POSES, config={"loss": {"lambda_stereo": 0.1, "stereo_space": "metric"}}),
        Variant("reseed", config={"init": {"reseed_at": 0.25}}),
        Variant("reseed_true", scene=_TRUE_POSES, config={"init": {"reseed_at": 0.25}}),
    ),
    # A background drawn at random each step against the fixed black one, over which a model can
    # stay semi-transparent (issue #40, docs/method.md §10), with the given (noisy) and true poses.
    "background": (
        Variant("black"),
        Variant("random", config={"train": {"random_background": True}}),
        Variant("black_true", scene=_TRUE_POSES),
        Variant("random_true", scene=_TRUE_POSES, config={"train": {"random_background": True}}),
    ),
    # Position steps by depth (issue #44, docs/method.md §8): the same world-unit step for every
    # Gaussian against steps shortened for Gaussians nearer than the frame's median static depth,
    # with the given (noisy) and the true poses, and with a mover seeded and held at the depth prior.
    "position-depth": (
        Variant("world"),
        Variant("near", config={"train": {"lr": {"means_depth": "near"}}}),
        Variant("world_true", scene=_TRUE_POSES),
        Variant("near_true", scene=_TRUE_POSES, config={"train": {"lr": {"means_depth": "near"}}}),
        Variant("prior_world", scene={"depth_prior": "video"},
                config={"init": {"dynamic_depth": "prior"},
                        "loss": {"lambda_depth_prior": 0.1, "depth_prior_tolerance": 0.1}}),
        Variant("prior_near", scene={"depth_prior": "video"},
                config={"init": {"dynamic_depth": "prior"}, "train": {"lr": {"means_depth": "near"}},
                        "loss": {"lambda_depth_prior": 0.1, "depth_prior_tolerance": 0.1}}),
        # a rigid mover seen from one camera at a time keeps its images at any one scale about the
        # cameras (docs/method.md §8): held rigid over time (L_iso), one scale for the clip, which the
        # prior's every frame then sets, instead of a scale per frame
        Variant("prior_near_iso", scene={"depth_prior": "video"},
                config={"init": {"dynamic_depth": "prior"}, "train": {"lr": {"means_depth": "near"}},
                        "loss": {"lambda_depth_prior": 0.1, "depth_prior_tolerance": 0.1, "lambda_iso": 0.1}}),
        # and every frame's prior pulling the mover's pixels (tolerance 0 there), so their errors average
        Variant("prior_near_iso_tight", scene={"depth_prior": "video"},
                config={"init": {"dynamic_depth": "prior"}, "train": {"lr": {"means_depth": "near"}},
                        "loss": {"lambda_depth_prior": 0.1, "depth_prior_tolerance": 0.1,
                                 "depth_prior_tolerance_moving": 0.0, "lambda_iso": 0.1}}),
    ),
    # The spread of the Gaussians' depths along each ray held down (L_var, issue #40, docs/method.md §6):
    # off, at 0.1 and at 1 (at 1 its gradient on the static means is about the photometric loss's),
    # with the true and the given (noisy) poses.
    "depth-variance": (
        Variant("none_true", scene=_TRUE_POSES),
        Variant("var_true", scene=_TRUE_POSES, config={"loss": {"lambda_depth_var": 1.0}}),
        Variant("var_weak_true", scene=_TRUE_POSES, config={"loss": {"lambda_depth_var": 0.1}}),
        Variant("none"),
        Variant("var", config={"loss": {"lambda_depth_var": 1.0}}),
        Variant("var_weak", config={"loss": {"lambda_depth_var": 0.1}}),
    ),
    "suite": (
        Variant("sharp", scene=_SHARP),
        Variant("blur", scene=_TRUE_POSES),
        Variant("noblur", scene=_TRUE_POSES, config={"train": {"blur": "off"}}),
        Variant("noisy"),
        # the no-blur baseline of the noisy-pose run (same budget): what the full method must beat
        Variant("noisy_noblur", config={"train": {"blur": "off"}, "pose_solver": {"mode": "off"}}),
    ),
}


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def variant_config(variant: Variant, base=None, **train):
    """The ExperimentConfig of a variant: ``base`` (default config) with the variant's overrides and
    then ``train`` field overrides (budget, iters, seed, quiet). Unknown keys raise here."""
    from d2gs_np.train.config import ExperimentConfig

    d = (base or ExperimentConfig()).to_dict()
    d = _merge(d, variant.config)
    d = _merge(d, {"train": train})
    return ExperimentConfig.from_dict(d)


def _scene_overrides(scene: str, variant: Variant, size: float) -> dict:
    from d2gs_np.data.suite import SUITE

    o = dict(variant.scene)
    if scene not in SUITE:  # regression presets name their fields differently
        if "trans_noise" in o:
            o["trans_noise_fraction"] = o.pop("trans_noise")
        if o.get("exposure_fraction") == 0.0:
            o["subframes"] = 1
    if size != 1.0:
        base_w, base_h = (240, 135)
        o.update(width=max(16, int(round(base_w * size))), height=max(16, int(round(base_h * size))))
    return o


def scene_folder(out, scene, variant: Variant, seed, size=1.0, frames=None) -> Path:
    """OUT/scenes/<scene>_s<seed>_<kind>[_x<size>][_f<frames>]: every setting that changes the
    scene is in its name, so sweeps at other sizes or frame counts in one OUT never share it."""
    name = f"{scene}_s{seed}_{variant.scene_kind}" + ("" if size == 1.0 else f"_x{size:g}")
    return Path(out) / "scenes" / (name + (f"_f{int(frames)}" if frames else ""))


def scene_done_marker(folder) -> Path:
    """The file that marks a scene folder as whole: the folder's name + ".done" (not
    ``with_suffix``, which would cut a size such as x0.6667 at its dot)."""
    folder = Path(folder)
    return folder.with_name(folder.name + ".done")


def _make_scene(out, scene, variant, seed, size, frames) -> Path:
    from d2gs_np.evaluation.baselines import deblur_scene
    from d2gs_np.data.suite import SUITE, write_suite_scene
    from d2gs_np.data.synthetic import write_synthetic_scene

    folder = scene_folder(out, scene, variant, seed, size, frames)
    done = scene_done_marker(folder)
    if done.exists():
        return folder
    o = _scene_overrides(scene, variant, size)
    if frames:
        o["num_frames"] = frames
    # Cells that share a scene may start together (threads of one worker, or workers on a shared
    # file system): each writes its own copy under a private name and publishes it by one atomic
    # rename, so a cell never reads a folder another is still writing (a sweep test saw a cell
    # fail that way). The first rename wins; a later writer finds the folder there and discards
    # its copy, which is the same scene (same generator, seed and settings).
    tag = f".tmp-{os.getpid()}-{threading.get_ident()}"
    tmp = folder.with_name(folder.name + tag)
    raw = folder.with_name(folder.name + "_raw" + tag) if variant.two_stage else tmp
    for d in {tmp, raw}:
        shutil.rmtree(d, ignore_errors=True)
    try:
        if scene in SUITE:
            write_suite_scene(raw, scene, seed, overwrite=True, **o)
        else:
            write_synthetic_scene(raw, scene, seed, overwrite=True, **o)
        if variant.two_stage:
            rep = deblur_scene(raw, tmp, overwrite=True)
            (tmp / "deblur_report.json").write_text(json.dumps(rep, indent=1) + "\n")
        try:
            os.rename(tmp, folder)
        except OSError:
            if not folder.is_dir():  # not "another writer published it first"
                raise
    finally:
        for d in {tmp, raw}:
            shutil.rmtree(d, ignore_errors=True)
    done.write_text("ok\n")
    return folder


def cell_folder(out, experiment, scene, variant: Variant, seed, size=1.0, frames=None) -> Path:
    """OUT/runs/<experiment>/<scene>_s<seed>_<variant>[_x<size>][_f<frames>]: variants of other
    experiments may share a name (``noblur``), and sweeps at other sizes or frame counts may share
    an OUT, so all of these are in the path."""
    name = f"{scene}_s{seed}_{variant.name}" + ("" if size == 1.0 else f"_x{size:g}")
    return Path(out) / "runs" / str(experiment) / (name + (f"_f{int(frames)}" if frames else ""))


def cell_settings(experiment, scene, variant: Variant, seed, budget, iters, size, frames, config_path,
                  threads=1) -> dict:
    """What decides a cell's result besides its folder (``RUN/cell.json``). The thread count only
    with a time budget: results do not depend on it, but the steps a budget buys do."""
    base = None
    if config_path is not None:
        base = json.loads(Path(config_path).read_text())
    return {"experiment": experiment, "scene": scene, "seed": int(seed), "variant": variant.name,
            "variant_config": variant.config, "variant_scene": variant.scene, "two_stage": variant.two_stage,
            "budget": budget, "iters": iters, "size": size, "frames": frames, "base_config": base,
            "threads": None if budget is None else int(threads)}


def run_cell(out, scene, variant: Variant, seed, budget=None, iters=None, size=1.0, threads=1, config_path=None,
             frames=None, experiment="cells") -> dict:
    """Make the scene, train, evaluate one cell (module docstring); returns its record. Runs in a
    worker; imports inside so a worker process starts light."""
    import numba

    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    from d2gs_np.data.io import load_scene
    from d2gs_np.evaluation.runs import evaluate_run
    from d2gs_np.train.config import ExperimentConfig
    from d2gs_np.train.trainer import Trainer

    run_dir = cell_folder(out, experiment, scene, variant, seed, size, frames)
    metrics_path = run_dir / "metrics.json"
    settings = json.loads(json.dumps(cell_settings(experiment, scene, variant, seed, budget, iters, size, frames,
                                                   config_path, threads)))
    settings_path = run_dir / "cell.json"
    if settings_path.exists():
        before = json.loads(settings_path.read_text())
        if before != settings:
            diff = sorted(k for k in set(before) | set(settings) if before.get(k) != settings.get(k))
            raise ValueError(f"cell {run_dir} was run with other settings ({', '.join(diff)}: "
                             f"{[before.get(k) for k in diff]} then, {[settings.get(k) for k in diff]} now); "
                             "give the sweep a new --out, or delete that cell's folder to rerun it")
    if not metrics_path.exists():
        base = ExperimentConfig.load(config_path) if config_path else None
        train = {"quiet": True, "seed": int(seed), "time_budget": budget}
        if iters:
            train["iters"] = int(iters)
        cfg = variant_config(variant, base, **train)  # config errors before any scene is made
        sdir = _make_scene(out, scene, variant, seed, size, frames)
        run_dir.mkdir(parents=True, exist_ok=True)
        tmp = settings_path.with_name("cell.json.tmp")
        tmp.write_text(json.dumps(settings, indent=1) + "\n")
        tmp.replace(settings_path)
        t0 = time.perf_counter()
        Trainer(load_scene(sdir), cfg, run_dir, overwrite=True).run()  # a retried cell starts over
        wall = time.perf_counter() - t0
        result = evaluate_run(run_dir)
        result["wall_seconds"] = wall
        tmp = metrics_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(result, indent=1, allow_nan=False, default=lambda x: None) + "\n")
        tmp.replace(metrics_path)  # a finished cell is marked done atomically
    return {"scene": scene, "variant": variant.name, "seed": int(seed), "run": str(run_dir), "status": "ok",
            **flatten(json.loads(metrics_path.read_text()))}


def _cell_with_retries(retries, *args, **kwargs):
    last = None
    for attempt in range(retries + 1):
        try:
            rec = run_cell(*args, **kwargs)
            rec["attempts"] = attempt + 1
            return rec
        except Exception:  # reported below with its traceback; a cell never disappears
            last = traceback.format_exc()
    scene, variant, seed = args[1], args[2], args[3]
    return {"scene": scene, "variant": variant.name, "seed": int(seed), "status": "failed", "attempts": retries + 1,
            "error": last.strip().splitlines()[-1], "traceback": last}


def flatten(m: dict) -> dict:
    def g(*keys):
        d = m
        for k in keys:
            if not isinstance(d, dict) or k not in d:
                return None
            d = d[k]
        return d
    return {
        "dvs_psnr": g("dvs", "psnr"), "dvs_ssim": g("dvs", "ssim"), "input_psnr": g("input_blur", "psnr"),
        "input_ssim": g("input_blur", "ssim"), "nvs_psnr": g("nvs", "psnr"), "nvs_ssim": g("nvs", "ssim"),
        "dvs_flip": g("dvs", "flip"), "input_flip": g("input_blur", "flip"), "nvs_flip": g("nvs", "flip"),
        "dvs_moving_psnr": g("dvs", "moving_psnr"), "input_moving_psnr": g("input_blur", "moving_psnr"),
        "dvs_static_psnr": g("dvs", "static_psnr"), "input_static_psnr": g("input_blur", "static_psnr"),
        "nvs_moving_psnr": g("nvs", "moving_psnr"), "nvs_rig_psnr": g("nvs_rig", "psnr"),
        "nvs_rig_moving_psnr": g("nvs_rig", "moving_psnr"), "nvs_seen_psnr": g("nvs", "seen_psnr"),
        "dvs_depth_absrel_static": g("dvs", "depth", "absrel_static"),
        "nvs_depth_absrel_static": g("nvs", "depth", "absrel_static"),
        "ate": g("trajectory", "ate"), "ate_initial": g("trajectory", "initial", "ate"),
        "ate_bundle": g("trajectory", "bundle_adjusted", "ate"),
        "num_gaussians": g("num_gaussians"), "steps": g("steps"), "train_seconds": g("train_seconds"),
        "wall_seconds": g("wall_seconds"),
    }


def experiment_cells(name: str, scenes, seeds, variants=None):
    """(scene, Variant, seed) cells of an experiment, optionally restricted to named variants."""
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {name!r}; choose from {sorted(EXPERIMENTS)}")
    vs = EXPERIMENTS[name]
    if variants:
        known = [v.name for v in vs]
        bad = sorted(set(variants) - set(known))
        if bad:
            raise ValueError(f"experiment {name!r} has no variant(s) {bad}; its variants are {known}")
        vs = tuple(v for v in vs if v.name in variants)
    return [(s, v, int(seed)) for s in scenes for seed in seeds for v in vs]


def _check_scenes(scenes):
    from d2gs_np.data.suite import SUITE
    from d2gs_np.data.synthetic import PRESETS

    bad = sorted(set(scenes) - set(SUITE) - set(PRESETS))
    if bad or not scenes:
        raise ValueError(f"unknown scene(s) {bad or scenes}; choose suite scenes {sorted(SUITE)} or regression "
                         f"presets {sorted(PRESETS)}")


def default_threads(jobs: int, cores: Optional[int] = None) -> int:
    """Numba threads per cell that spend this machine's cores: ``cores // jobs``, at least 1. With a
    time budget the steps a cell buys follow its threads, so one cell at a time should not leave
    cores idle (docs/results.md §4 measures it)."""
    cores = (os.cpu_count() or 1) if cores is None else int(cores)
    return max(1, cores // max(1, int(jobs)))


def run_experiment(name: str, out, scenes, seeds=(0,), budget: Optional[float] = None, iters: Optional[int] = None,
                   size: float = 1.0, jobs: int = 1, threads: Optional[int] = None, scheduler=None,
                   retries: int = 1, config_path=None, variants=None, frames=None, command: str = "") -> list:
    """Run an experiment's cells (module docstring); returns the records (failed cells included,
    ``status == "failed"``) and writes the table, CSV and plot. ``threads`` per cell defaults to
    ``default_threads(jobs)`` (this machine's cores; give it for a remote ``scheduler``'s workers)."""
    _check_scenes(scenes)
    if threads is None:
        threads = default_threads(jobs)
    if budget is None and not iters:
        raise ValueError("give a time budget (seconds per cell) or a number of steps per cell")
    if budget is not None and not budget > 0:
        raise ValueError(f"budget must be > 0 seconds; got {budget}")
    if jobs < 1 or threads < 1 or retries < 0 or size <= 0:
        raise ValueError(f"jobs and threads must be >= 1, retries >= 0, size > 0; got {jobs}, {threads}, {retries}, "
                         f"{size}")
    if config_path is not None and not Path(config_path).exists():
        raise FileNotFoundError(f"config file {config_path} does not exist")
    cells = experiment_cells(name, scenes, seeds, variants)
    base = None
    if config_path is not None:
        from d2gs_np.train.config import ExperimentConfig
        base = ExperimentConfig.load(config_path)
    for _, v, _ in cells:  # every variant's config is valid before any cell starts
        variant_config(v, base)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    kw = dict(budget=budget, iters=iters, size=size, threads=threads, config_path=config_path, frames=frames,
              experiment=name)
    records = _run_cells(cells, str(out), retries, kw, jobs, scheduler)
    order = {(s, v.name, sd): i for i, (s, v, sd) in enumerate(cells)}
    records.sort(key=lambda r: order[(r["scene"], r["variant"], r["seed"])])
    write_outputs(name, out, records, command)
    return records


def compute_local(tasks, jobs):
    """Dask delayed ``tasks`` on the local process pool, ``jobs`` at once. One task per dispatch
    (``chunksize=1``): Dask's default batches up to 6 ready tasks into one worker's job, which on
    a sweep of minutes-long cells left a worker idle while the other ran a batch in turn."""
    import dask

    return list(dask.compute(*tasks, scheduler="processes", num_workers=jobs, chunksize=1))


def _run_cells(cells, out, retries, kw, jobs, scheduler):
    import dask

    tasks = [dask.delayed(_cell_with_retries, pure=False)(retries, out, s, v, sd, **kw) for s, v, sd in cells]
    if scheduler is None:
        return compute_local(tasks, jobs)
    from distributed import Client

    client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
    try:
        return list(dask.compute(*tasks, scheduler=client))
    finally:
        if client is not scheduler:
            client.close()


def _fmt(x, spec=".2f"):
    return "" if x is None else format(x, spec)


def table(records) -> str:
    lines = ["| scene | seed | variant | status | input dB | DVS PSNR dB | DVS SSIM | DVS FLIP | moving px: input -> DVS dB | "
             "static px: input -> DVS dB | NVS PSNR dB | NVS SSIM | NVS beside its frame dB | NVS seen px dB | "
             "static depth AbsRel DVS / NVS | ATE initial -> trained | Gaussians | steps | train s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        status = r["status"] if r["status"] == "ok" else f"FAILED: {r.get('error', '')}"
        lines.append(
            f"| {r['scene']} | {r['seed']} | {r['variant']} | {status} | {_fmt(r.get('input_psnr'))} | "
            f"{_fmt(r.get('dvs_psnr'))} | {_fmt(r.get('dvs_ssim'), '.3f')} | {_fmt(r.get('dvs_flip'), '.4f')} | "
            f"{_fmt(r.get('input_moving_psnr'))} -> {_fmt(r.get('dvs_moving_psnr'))} | "
            f"{_fmt(r.get('input_static_psnr'))} -> {_fmt(r.get('dvs_static_psnr'))} | "
            f"{_fmt(r.get('nvs_psnr'))} | "
            f"{_fmt(r.get('nvs_ssim'), '.3f')} | {_fmt(r.get('nvs_rig_psnr'))} | {_fmt(r.get('nvs_seen_psnr'))} | "
            f"{_fmt(r.get('dvs_depth_absrel_static'), '.3f')} / {_fmt(r.get('nvs_depth_absrel_static'), '.3f')} | "
            f"{_fmt(r.get('ate_initial'), '.4f')} -> {_fmt(r.get('ate'), '.4f')} | {_fmt(r.get('num_gaussians'), 'd')} | "
            f"{_fmt(r.get('steps'), 'd')} | {_fmt(r.get('train_seconds'), '.0f')} |")
    return "\n".join(lines)


def write_outputs(name, out, records, command=""):
    out = Path(out)
    fields = ["scene", "seed", "variant", "status", "attempts", "input_psnr", "dvs_psnr", "dvs_ssim", "nvs_psnr",
              "nvs_ssim", "nvs_moving_psnr", "nvs_rig_psnr", "nvs_rig_moving_psnr", "nvs_seen_psnr",
              "dvs_depth_absrel_static", "nvs_depth_absrel_static", "input_flip", "dvs_flip",
              "nvs_flip", "ate_initial", "ate_bundle", "ate", "num_gaussians", "steps", "train_seconds",
              "wall_seconds", "run", "error"]
    with open(out / f"{name}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(records)
    md = table(records)
    (out / f"{name}.md").write_text((f"`{command}`\n\n" if command else "") + md + "\n")
    ok = [r for r in records if r["status"] == "ok"]
    if ok:
        from d2gs_np.reporting.plots import heldout_curve, plot_curves_by_scene

        plot_curves_by_scene([(r["scene"], r["variant"], r["seed"], *heldout_curve(r["run"]), r.get("input_psnr"))
                              for r in ok], out / f"{name}_error_vs_time.png",
                             title=f"{name}: held-out PSNR against training seconds")
    return md
