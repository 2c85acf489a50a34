"""What a run models, decided once from the scene and the config (docs/method.md §9).

``decide_components`` leaves out what a scene does not need and says why in the run log: no
moving pixels, no dynamic set (and no deformation); sharp input, no blur model (n = 1 at the
given poses, no endpoint model); a learned exposure length only where it has an effect.

The optional parts of the method are loss terms (``train/terms.py``) and step plugins
(``train/plugins.py``); ``left_out`` lists those the run does not have, by what it has, so the
run log and ``metrics.json`` never claim a part that did not run (and a part that is added is
dropped from the list without touching this module's callers).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from d2gs_np.data.scene import Scene
from d2gs_np.pose.config import THEN_WITHOUT_SOLVER
from d2gs_np.train.config import ExperimentConfig

__all__ = ["Components", "decide_components", "decide_exposure_path", "resolved_config", "OPTIONAL_TERMS",
           "OPTIONAL_PLUGINS", "composition_notes"]

# Regularisers of docs/method.md §6, by loss-term name: left out unless a term of that name is in the loss.
OPTIONAL_TERMS = {"ts": "L_ts", "gs": "L_gs", "reproj": "L_reproj", "freq": "L_freq"}
# Regularisers this version implements (a LossConfig weight > 0 turns each on); the others are
# not part of this version yet.
IMPLEMENTED_TERMS = ("ts", "gs", "reproj", "freq")
# Optional step plugins, by plugin name -> the component they are (docs/method.md §5).
OPTIONAL_PLUGINS = {"pose_solver": "pose_refinement"}


@dataclass(frozen=True)
class Components:
    """What this run models; decided from the scene and the config (docs/method.md §9)."""

    dynamic: bool
    blur: bool
    learn_exposure: bool
    exposure_fraction: float  # used when not learned
    centred: bool = False  # the exposure stays centred on the reference pose (TrajectoryConfig.centre)
    # What refines the start poses when they are a kept bundle adjustment (PoseInitConfig.then):
    # "solver", "adam" or "hold"; "" when they are the given poses.
    adjusted_then: str = ""
    held_frames: tuple = ()  # frames that adjustment held at their given poses (too few observations)
    # per frame, how uncertain that adjustment left its rotation, over its prior's (AdjustedStart)
    rotation_uncertainty: tuple = ()
    # the exposure path "auto" chose (TrajectoryConfig.path, decide_exposure_path); "" when the
    # config names the path itself
    exposure_path: str = ""

    def __post_init__(self):
        # a checkpoint's JSON gives lists; tuples keep Components equal to the one it saved
        object.__setattr__(self, "held_frames", tuple(int(k) for k in self.held_frames))
        object.__setattr__(self, "rotation_uncertainty", tuple(float(u) for u in self.rotation_uncertainty))

    @property
    def poses_held(self) -> bool:
        """The start poses are held as exact: the scene's trusted ones, or a held adjustment."""
        return self.adjusted_then == "hold"

    @property
    def solver_left_out(self) -> bool:
        """The pose solver is left out because a kept adjustment is refined otherwise."""
        return self.adjusted_then in THEN_WITHOUT_SOLVER

    def left_out(self, terms=(), plugins=()) -> list:
        """Names of the parts of the method this run does not have: the sets and models the scene
        did not need, the optional plugins not among ``plugins`` and the regularisers not among
        ``terms`` (names of the run's plugins and loss terms)."""
        out = []
        if not self.dynamic:
            out += ["dynamic_set", "deformation"]
        if not self.blur:
            out += ["blur_model", "trajectory_model"]
        out += [part for name, part in OPTIONAL_PLUGINS.items() if name not in plugins]
        out += [f"loss_{name}" for name in OPTIONAL_TERMS if name not in terms]
        return out


def composition_notes(terms=(), plugins=()) -> list:
    """Run-log lines on the optional parts: which ran and which did not (``left_out``)."""
    notes = []
    if "pose_solver" not in plugins:
        notes.append("pose refinement (Gauss-Newton on reprojection residuals): not run (config pose_solver.mode, "
                     "trusted poses, a kept bundle adjustment refined otherwise (pose_init.then) or a run too "
                     "short; see the pose solver line above)")
    missing = [label for name, label in OPTIONAL_TERMS.items() if name not in terms]
    loss = " + ".join("L_render" if t == "photometric" else OPTIONAL_TERMS.get(t, t) for t in terms) or "L_render"
    off = [label for name, label in OPTIONAL_TERMS.items() if name not in terms and name in IMPLEMENTED_TERMS]
    absent = [label for label in missing if label not in off]
    if missing:
        why = ([f"{', '.join(off)}: off (weight 0 in the loss config, or not applicable)"] if off else []) + \
              ([f"{', '.join(absent)}: not applied (not part of this version)"] if absent else [])
        notes.append(f"regularisers {'; '.join(why)}; loss = {loss}")
    else:
        notes.append(f"loss = {loss}")
    return notes


def resolved_config(config: ExperimentConfig, components: Components) -> ExperimentConfig:
    """``config`` with the exposure path the run decided in place of "auto" (what the model and
    its checkpoints carry); ``config`` itself when it names the path."""
    if config.trajectory.path != "auto":
        return config
    path = components.exposure_path or "geodesic"
    return config.replace(trajectory=dataclasses.replace(config.trajectory, path=path))


def decide_exposure_path(scene: Scene, config: ExperimentConfig, blur: bool, start_poses=None, depth=None,
                         note: Optional[Callable] = None) -> str:
    """The exposure path of a run whose config says ``trajectory.path = "auto"`` (docs/method.md §4):
    "three_knot" where the start poses can be trusted to show the camera's path (``start_poses``, a
    kept bundle adjustment; or the given poses of a scene that flags them as exact) and the median
    frame's exposure bends by more than ``trajectory.bend_px`` full-resolution pixels
    (``blur.endpoints.exposure_bend_px``; translation at ``depth``, the adjustment's median point
    depth, else the scene's scale); else "geodesic". Given poses that are neither adjusted nor
    trusted are too noisy to show a bend (their pose error alone reads as one). Says why (``note``)."""
    from d2gs_np.blur.endpoints import exposure_bend_px

    say = note if note is not None else (lambda m: None)
    traj = config.trajectory
    if not blur:
        return ""
    if traj.kind != "direct":
        say("exposure path: geodesic (trajectory.path = auto; the three-knot path needs trajectory.kind = direct)")
        return "geodesic"
    trusted = bool(getattr(scene, "poses_trusted", None))
    if start_poses is None and not trusted:
        say("exposure path: geodesic (trajectory.path = auto; the given poses were not adjusted, and their error "
            "would read as a bend)")
        return "geodesic"
    poses = np.stack([f.cam_T_world for f in scene.frames]) if start_poses is None else np.asarray(start_poses)
    times = np.array([f.time for f in scene.frames], dtype=np.float64)
    if scene.num_frames < 3 or not scene.exposure_fraction:
        say("exposure path: geodesic (trajectory.path = auto; the bend needs 3 frames and a known exposure_fraction)")
        return "geodesic"
    depth = depth if depth else (scene.scene_scale or np.inf)
    bend = float(np.median(exposure_bend_px(poses, times, scene.exposure_fraction, scene.frames[0].K[0, 0], depth)))
    which = "adjusted" if start_poses is not None else "trusted"
    path = "three_knot" if bend > traj.bend_px else "geodesic"
    say(f"exposure path: {path.replace('_', '-')} (trajectory.path = auto; the median exposure bends "
        f"{bend:.2f} px on the {which} poses, {'over' if path == 'three_knot' else 'within'} trajectory.bend_px "
        f"= {traj.bend_px:g})")
    return path


def decide_components(scene: Scene, config: ExperimentConfig, note: Optional[Callable] = None,
                      adjusted: bool = False, held_frames=(), rotation_uncertainty=(), start_poses=None,
                      depth=None) -> Components:
    """Apply docs/method.md §9: leave out what the scene does not need, and say why (``note``).
    ``adjusted``: the run starts from a kept bundle adjustment, refined as ``pose_init.then``
    says; held ("hold"), its exposure is centred as a trusted scene's is. ``held_frames``,
    ``rotation_uncertainty``, ``start_poses`` (N, 4, 4), ``depth``: that adjustment's
    (``pose.given.AdjustedStart``); the last two decide an "auto" exposure path
    (``decide_exposure_path``)."""
    adjusted_then = config.pose_init.then if adjusted else ""
    poses_held = adjusted_then == "hold"
    tc = config.train
    say = note if note is not None else (lambda m: None)
    if tc.dynamic == "off":
        dynamic = False
        say("dynamic set: off (config train.dynamic = off)")
    elif not scene.has_masks:
        dynamic = tc.dynamic == "on"
        if dynamic:
            raise ValueError("train.dynamic = on needs motion masks, but the scene has none; add masks/ or use auto")
        say("dynamic set: left out (the scene has no motion masks)")
    elif not scene.has_moving_pixels:
        dynamic = False
        say("dynamic set: left out (the motion masks contain no moving pixels), and with it the deformation model")
    else:
        dynamic = True
        say("dynamic set: on (motion masks mark moving pixels)")

    ef = scene.exposure_fraction
    if tc.blur == "off":
        blur, learn = False, False
        say("blur model: off (config train.blur = off); n = 1 sharp camera at the given poses")
    elif tc.blur == "auto" and ef is not None and ef == 0.0:
        blur, learn = False, False
        say("blur model: left out (scene exposure_fraction = 0: sharp input); n = 1, no endpoint model")
    elif config.blur.num_virtual == 1:
        blur, learn = False, False
        say("blur model: left out (blur.num_virtual = 1)")
    else:
        blur = True
        if tc.learn_exposure == "on" or (tc.learn_exposure == "auto" and ef is None):
            if not dynamic:
                # tau only moves the sub-frame times, which only the dynamic set sees.
                learn = False
                say("blur model: on; exposure length not learned (no dynamic set, so tau has no effect)")
            else:
                learn = True
                why = "config train.learn_exposure = on" if tc.learn_exposure == "on" else \
                    "the scene gives no exposure_fraction"
                say(f"blur model: on, n = {config.blur.num_virtual}, exposure length learned ({why})")
        else:
            learn = False
            if ef is None:
                raise ValueError("train.learn_exposure = off but the scene has no exposure_fraction; use auto or on")
            say(f"blur model: on, n = {config.blur.num_virtual} virtual views, exposure_fraction = {ef} from the scene")
        if config.blur.n_schedule == "scale":
            say(f"virtual views follow the render scale r: 1 + ceil(r (n - 1)) of n = {config.blur.num_virtual} "
                "(blur.n_schedule = scale)")
        elif config.blur.n_schedule == "length":
            say(f"virtual views follow each frame's blur length: 1 + ceil(L / {config.blur.view_spacing_px:g} px), "
                f"2 to n = {config.blur.num_virtual} (blur.n_schedule = length)")
        if config.blur.backward_views > 0:
            say(f"backward through {config.blur.backward_views} of each step's virtual views, drawn one per run of "
                "neighbours and weighted by the run (blur.backward_views; the forward averages every view)")
        say(f"trajectory model: {config.trajectory.kind}")
    centred = False
    if blur:
        traj = config.trajectory
        trusted = bool(getattr(scene, "poses_trusted", None))
        centred = traj.centre == "on" or (traj.centre == "auto" and (trusted or poses_held) and traj.kind == "direct")
        if centred:
            why = "config trajectory.centre = on" if traj.centre == "on" else \
                "the scene flags its poses as exact" if trusted else "the adjusted poses are held: pose_init.then = hold"
            which = "adjusted" if poses_held else "given"
            say(f"exposure endpoints: centred on the {which} poses, only their spread learned ({why})")
        else:
            say("exposure endpoints: both free (start and end learned; the mid pose moves with them)")
    path = ""
    if config.trajectory.path == "auto":
        path = decide_exposure_path(scene, config, blur, start_poses if adjusted else None, depth, say)
    return Components(dynamic=dynamic, blur=blur, learn_exposure=learn, exposure_fraction=float(ef or 0.0),
                      centred=centred, adjusted_then=adjusted_then,
                      held_frames=held_frames if adjusted else (),
                      rotation_uncertainty=rotation_uncertainty if adjusted else (), exposure_path=path)
