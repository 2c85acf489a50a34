"""A run's set-up, everything before its first step, in one function (``set_up_run``), in order:

1. checks      the run folder (``run_folder.check_run_folder``: a folder that is not empty needs
               ``resume`` or ``overwrite``) and the scene (``validate_scene_for_training``); to
               resume, the latest checkpoint's config and scene (``check_resume``);
2. log         the run log (``train/log.py``), which every decision below goes to, and the run's
               ``RunContext`` (``train/plugins.py``): what a plugin may use of the run;
3. components  what the run models (``train/components.py``, docs/method.md §9): decided from
               the scene, the config and, for a fresh run, its start poses: the given poses'
               bundle adjustment (``pose.given.initial_poses``), which ``pose_init.then`` says
               what refines; or the resumed run's;
4. terms and plugins  the loss terms (``train/terms.py``), then the step plugins in their order:
               the default ones (``default_plugins``), the loss terms' (``term.plugins``), those
               passed in (a plugin as it is, or a builder, a class or function of the context);
5. model       a fresh run: the initial model from the start poses (``Model.from_scene``),
               each plugin's ``on_init``, Adam's state; a resumed run: the checkpoint's model,
               Adam state, statistics, step, time and each plugin's state;
6. schedule    the stages and the step planner (``train/stages.py``), the learning rate of every
               block (``train/learning_rates.py``), the cache of targets (``train/schedule.py``).

It returns a ``RunSetup``, plain fields the trainer (``train/trainer.py``) trains with. Nothing
is written into the run folder here (the trainer's first write is its step-0 checkpoint), so a
set-up that fails or is interrupted leaves the folder as it was.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from d2gs_np.data import fingerprint
from d2gs_np.data.scene import Scene
from d2gs_np.optim import adam
from d2gs_np.pose.given import adjusted_start
from d2gs_np.scene.gaussians import STATIC
from d2gs_np.train.checkpoint import load_checkpoint
from d2gs_np.train.components import Components, composition_notes, decide_components, resolved_config
from d2gs_np.train.config import ExperimentConfig
from d2gs_np.train.learning_rates import camera_row_scales, learning_rates, position_extent, scene_extent
from d2gs_np.train.log import RunLog
from d2gs_np.train.model import Model
from d2gs_np.train.render_stereo import Reseed
from d2gs_np.train.plugins import (Densify, GradientStatistics, HeldOutPSNR, OpacityReset, Prune, RunContext,
                                   load_plugin_states)
from d2gs_np.train.pose_solver import PoseSolver, use_pose_solver
from d2gs_np.train.run_folder import check_run_folder, check_scene_of_run, latest_checkpoint
from d2gs_np.train.schedule import TargetCache
from d2gs_np.train.stages import Planner, make_stages
from d2gs_np.train.state import TrainState
from d2gs_np.train.terms import loss_terms

__all__ = ["RunSetup", "set_up_run", "validate_scene_for_training", "check_resume", "default_plugins"]


@dataclass(frozen=True)
class RunSetup:
    """What ``set_up_run`` built: everything a run trains with, before its first step."""

    context: RunContext  # scene, config, run folder, note (the log's), camera extent
    log: RunLog  # the run log, with every decision of the set-up in its notes; nothing written yet
    scene_record: dict  # data.fingerprint.scene_record of the scene (kept in every checkpoint)
    terms: list  # the loss terms, photometric first
    plugins: list  # the step plugins, in the order they run
    state: TrainState  # the initial (or resumed) model, Adam state and per-row statistics
    step: int  # the first step to train: 0, or the resumed checkpoint's
    seconds: float  # training time so far: 0, or the resumed checkpoint's
    position_extent: float  # the length the position learning rates are scaled by
    planner: Planner  # stage, frame and render scale of each step
    adam_config: adam.AdamConfig  # the learning rate of every parameter block
    cache: TargetCache  # the training targets at each render scale
    camera_row_scales: np.ndarray  # (N,) factor on each frame's endpoint rate (camera_row_scales)
    resumed_from: Optional[Path] = None  # the checkpoint resumed; None for a fresh run


def set_up_run(scene: Scene, config: ExperimentConfig, run_dir, plugins=(), resume: bool = False,
               overwrite: bool = False) -> RunSetup:
    """The set-up of a run of ``config`` on ``scene`` in ``run_dir`` (module docstring). A folder
    that is not empty needs ``resume`` (go on from its latest checkpoint, on the same scene and
    config) or ``overwrite`` (replace the run there, from the trainer's first checkpoint on).
    ``plugins``: step plugins to run after the default ones, each a plugin or a builder of one
    (a class or function of the ``RunContext``)."""
    run_dir = Path(run_dir)
    # 1. checks, before any work
    check_run_folder(run_dir, resume, overwrite)
    validate_scene_for_training(scene)
    validate_scene_for_dynamic(scene, config)
    scene_record = fingerprint.scene_record(scene)
    resumed_from = saved = None
    resume_notes = []
    if resume:
        resumed_from = latest_checkpoint(run_dir)
        saved = load_checkpoint(resumed_from)  # (arrays, meta), read once
        # an "auto" exposure path resumes as the run decided it (the checkpoint's config names it)
        config = resolved_config(config, Components(**saved[1]["components"]))
        resume_notes = check_resume(saved[1], config, scene, resumed_from, scene_record)

    # 2. the log and the run context
    log = RunLog(run_dir, quiet=config.train.quiet, resume=resume)
    # the input's warnings (printed when issued: docs/dataset_format.md §5), kept in the run log
    for line in [f"warning: {m}" for m in scene.warnings + config.train.lr.implausible()] + resume_notes:
        log.note(line)
    extent = scene_extent(np.stack([f.cam_T_world for f in scene.frames]).astype(np.float64), scene.scene_scale)
    context = RunContext(scene=scene, config=config, run_dir=run_dir, note=log.note, extent=extent)

    # 3. what the run models; a fresh run's start poses first, since holding them decides some of it
    if resume:
        components = Components(**saved[1]["components"])
    else:
        start = adjusted_start(scene, config, log.note)
        start_poses = start.poses
        components = decide_components(scene, config, log.note, adjusted=start_poses is not None,
                                       held_frames=start.held_frames, rotation_uncertainty=start.rotation_uncertainty,
                                       start_poses=start_poses, depth=start.depth)
        # from here on the config names the exposure path the run decided (the model carries it)
        config = resolved_config(config, components)
        context = dataclasses.replace(context, config=config)

    # 4. loss terms (the log has a column per term) and step plugins, in order
    terms = loss_terms(config.loss, components, log.note, scene=scene, run_dir=run_dir,
                       pose_solver=config.pose_solver, prior_space=config.init.depth_prior_space,
                       init=config.init, iters=config.train.iters)
    log.add_columns([f"loss_{t.name}" for t in terms])
    plugins = (default_plugins(context, components.adjusted_then)
               + [p for t in terms for p in getattr(t, "plugins", ())]
               + [_built(p, context) for p in plugins])

    # 5. the model: initial, or the checkpoint's
    if resume:
        arrays, meta = saved
        params = {k[len("params/"):]: v for k, v in arrays.items() if k.startswith("params/")}
        state = TrainState.from_checkpoint(arrays, meta, _plugin_rows(plugins, params))
        state = state.replace(model=state.model.replace(config=config))
        load_plugin_states(plugins, arrays, meta.get("plugins", {}))
        pos_extent = float(meta.get("position_extent", extent))
        step, seconds = int(meta["step"]), float(meta["seconds"])
        log.note(f"resumed from {resumed_from} at step {step} ({meta['seconds']:.1f}s of training)")
    else:
        for line in composition_notes([t.name for t in terms], [p.name for p in plugins]):
            log.note(line)
        model = Model.from_scene(scene, config, components, log.note, poses=start_poses, anchor_points=start.points)
        for p in plugins:
            p.on_init(model)
        state = TrainState(model, adam.adam_init(model.params), _plugin_rows(plugins, model.params))
        # the position rates' length, from the initial points (kept in the checkpoints for a resume)
        pos_extent = position_extent(config.train.lr, extent, model.poses_est, model.params[f"{STATIC}.means"])
        if config.train.lr.means_unit == "scene":
            log.note(f"position learning rates in units of the scene's size {pos_extent:.3g} "
                     f"(camera extent {extent:.3g}; train.lr.means_unit)")
        step, seconds = 0, 0.0

    # 6. the schedule: stages, planner, learning rates, targets
    components = state.model.components
    planner = Planner(config, [(f.width, f.height) for f in scene.frames],
                      make_stages(config.train, components.dynamic))
    rates = learning_rates(state.params, config.train.lr, pos_extent, config.train.iters, len(scene.frames),
                           centred=components.centred)
    row_scales = camera_row_scales(components, config.train.lr, len(scene.frames), config.pose_init.adam_rows)
    if components.adjusted_then == "adam":
        held = (f", the {len(components.held_frames)} it held at the given pose at the full rate"
                if components.held_frames else "")
        if config.pose_init.adam_rows == "uncertainty" and components.rotation_uncertainty:
            moved = np.delete(row_scales, list(components.held_frames))
            log.note(f"exposure endpoints: each frame the adjustment moved learns at its rotation's uncertainty over "
                     f"the prior's x the camera rate, {moved.min():.3g} to {moved.max():.3g} (median "
                     f"{np.median(moved):.3g}; at least train.lr.camera_adjusted_scale; pose_init.adam_rows)" + held)
        else:
            log.note(f"exposure endpoints: the frames the adjustment moved learn at "
                     f"{config.train.lr.camera_adjusted_scale:g} x the camera rate (train.lr.camera_adjusted_scale)"
                     + held)
    cache = TargetCache.from_scene(scene, mask_threshold=config.schedule.mask_threshold)
    return RunSetup(context=context, log=log, scene_record=scene_record, terms=terms, plugins=plugins, state=state,
                    step=step, seconds=seconds, position_extent=pos_extent, planner=planner, adam_config=rates,
                    cache=cache, camera_row_scales=row_scales, resumed_from=resumed_from)


def validate_scene_for_training(scene: Scene):
    if scene.num_frames < 2:
        raise ValueError(f"training needs at least 2 frames; the scene has {scene.num_frames}")
    for i, f in enumerate(scene.frames):
        if f.image is None:
            raise ValueError(f"frame {i} ({f.file_path}) has no image loaded; load the scene with load_images=True")
        if f.image.shape != (f.height, f.width, 3):
            raise ValueError(f"frame {i} ({f.file_path}) image has shape {f.image.shape}; expected {(f.height, f.width, 3)}")
        if not np.all(np.isfinite(f.image)):
            raise ValueError(f"frame {i} ({f.file_path}) image contains NaN or inf")
    # every image one flat colour (a single flat frame: load_scene warns)
    if all(np.all(f.image == f.image[0, 0]) for f in scene.frames):
        colour = ", ".join(f"{v:.3g}" for v in scene.frames[0].image[0, 0])
        raise ValueError(f"every training image is one flat colour (frame 0: RGB {colour}): there is nothing to "
                         "reconstruct, and a render of the flat colour would score an infinite PSNR; check that the "
                         "images were exported (file_path of each frame)")


def validate_scene_for_dynamic(scene: Scene, config: ExperimentConfig):
    """Unless ``config.train.dynamic`` is off, refuse what the dynamic set cannot learn from, before any
    work (docs/dataset_format.md §5): motion masks on only some frames, or moving pixels in frames that
    all share one time."""
    from d2gs_np.base.checks import name_items

    if config.train.dynamic == "off":
        return
    lacking = scene.frames_without_masks
    if lacking:
        raise ValueError(
            f"{len(lacking)} of the {scene.num_frames} training frames {'has' if len(lacking) == 1 else 'have'} "
            "no motion mask ("
            f"{name_items([f'frame {i} ({scene.frames[i].file_path})' for i in lacking])}) while the others have one, "
            "and the dynamic set needs a mask on every frame: add mask_path to those frames (an all-zero mask where "
            "nothing moves), or train without the dynamic set (--dynamic off)")
    times = {f.time for f in scene.frames}
    if len(times) == 1 and scene.has_moving_pixels:
        raise ValueError(
            f"all {scene.num_frames} training frames have time {scene.frames[0].time:g}, but the motion masks mark "
            "moving pixels and the deformation model needs each frame's time: give frame k of N the time k / (N - 1) "
            "in transforms.json, or train without the dynamic set (--dynamic off)")


def check_resume(meta: dict, config: ExperimentConfig, scene: Scene, path, scene_record=None) -> list:
    """Refuse to resume the checkpoint ``path`` (its ``meta``) with another config or scene;
    returns notes (``run_folder.check_scene_of_run``). ``scene_record``: the scene's
    ``fingerprint.scene_record`` if already computed."""
    saved_cfg = ExperimentConfig.from_dict(meta["config"])
    # A resumed run continues the saved experiment: only the run length, housekeeping and output may change.
    free = {"iters", "time_budget", "stretch_to_budget", "quiet", "checkpoint_every", "checkpoint_seconds"}
    changed = [f"train.{k}" for k, v in config.train.__dict__.items()
               if k not in free and getattr(saved_cfg.train, k) != v]
    changed += [k for k in saved_cfg.__dict__ if k != "train" and getattr(saved_cfg, k) != getattr(config, k)]
    if changed:
        raise ValueError(f"--resume with a config that differs from the saved run in {changed}; resume with the "
                         f"run's own config (RUN/config.json), changing only {sorted(free)}")
    return check_scene_of_run(meta, scene, Path(path).parent, "--resume",
                              "resume with the run's scene, or start a new run (another --out, or --overwrite "
                              "to replace this one)", scene_record)


def default_plugins(context: RunContext, adjusted_then: str = "") -> list:
    """The plugins a run has by its config, in order (``train/plugins.py``); the pose solver last,
    when ``use_pose_solver`` says so (its correspondence cache goes to the run folder); what
    refines a kept bundle adjustment (``adjusted_then``, ``Components.adjusted_then``) decides too."""
    scene, config = context.scene, context.config
    tc = config.train
    plugins = []
    if tc.eval_every:
        plugins.append(HeldOutPSNR(scene, tc.eval_every, tc.eval_frames))
    if config.densify.enabled:
        plugins.append(GradientStatistics(config.densify.absgrad))
    if tc.prune_every:
        plugins.append(Prune(config, context.extent, [f.mask for f in scene.frames]))
    if config.densify.enabled:
        pixels = sum(f.width * f.height for f in scene.frames)
        moving = sum(int(np.count_nonzero(f.mask)) for f in scene.frames if f.mask is not None)
        plugins.append(Densify(config, context.extent, max(f.width for f in scene.frames), pixels,
                                context.note, moving_pixels=moving))
        if config.densify.opacity_reset_every:
            plugins.append(OpacityReset(config, context.note))
    if config.init.reseed_at > 0 and scene.num_frames > 1:
        plugins.append(Reseed(scene, config, context.note))
    if use_pose_solver(scene, config, context.note, adjusted_then):
        plugins.append(PoseSolver(scene, config, context.run_dir, context.note))
    return plugins


def _built(plugin, context: RunContext):
    """``plugin`` as it is, or, for a builder (a class, or a function without ``on_step``), the
    plugin it builds from ``context``."""
    return plugin(context) if isinstance(plugin, type) or not hasattr(plugin, "on_step") else plugin


def _plugin_rows(plugins, params) -> dict:
    """The per-row statistics the plugins keep (``Plugin.rows``), zero for ``params``."""
    rows = {}
    for p in plugins:
        rows.update(p.rows(params))
    return rows
