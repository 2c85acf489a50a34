"""What each training step does: its stage, its frame and its render scale (docs/method.md §7-8).

Stages (docs/method.md §8): ``warmup`` trains the static set and the camera model on static
pixels only (dynamic Gaussians are not rendered, masked pixels carry no loss); ``deform`` trains
the dynamic set and its deformation; ``joint`` trains everything. Stages a scene does not need
are left out (no dynamic set: no ``deform`` stage).

Frames are visited in a seeded permutation per epoch that depends only on (seed, step), so a
resumed run visits the same frames. The render scale follows the progressive schedule
(docs/method.md §7, ``train/schedule.py``). Stage and scale are read at the *schedule step*,
which a time budget moves ahead of the step (``schedule.schedule_step``); so is the learning-rate
decay, through ``lr_scale``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from d2gs_np.losses.ssim import SSIM_WINDOW
from d2gs_np.scene.gaussians import DYNAMIC, RIGID, STATIC
from d2gs_np.blur.endpoints import CAMERA, POSENET
from d2gs_np.train.config import ExperimentConfig, TrainConfig

__all__ = ["Stage", "make_stages", "StepPlan", "Planner"]


@dataclass(frozen=True)
class Stage:
    name: str
    start: int  # first step (inclusive)
    stop: int  # last step (exclusive)
    trainable: tuple  # block-name prefixes trained in this stage
    static_only: bool  # render only the static set and ignore masked (moving) pixels


def make_stages(train: TrainConfig, dynamic: bool) -> list:
    """The stages of a run of ``train.iters`` steps (no ``deform`` stage without a dynamic set)."""
    n = train.iters
    w = int(round(train.warmup_fraction * n))
    d = int(round(train.deform_fraction * n)) if dynamic else 0
    xi = f"{CAMERA}.xi"  # both endpoint blocks (XI_START, XI_END), not the exposure
    stages = []
    if w > 0:
        # camera.exposure_logit is not trained here: only the static set is rendered, and tau
        # only moves the dynamic set's sub-frame times, so its gradient is exactly zero.
        stages.append(Stage("warmup", 0, w, (f"{STATIC}.", xi, f"{POSENET}."), True))
    if d > 0:
        stages.append(Stage("deform", w, w + d, (f"{DYNAMIC}.", f"{RIGID}."), False))
    stages.append(Stage("joint", w + d, n, (f"{STATIC}.", f"{DYNAMIC}.", f"{RIGID}.", f"{CAMERA}.", f"{POSENET}."),
                        False))
    c = int(round(train.camera_from_fraction * n))
    if c > 0:
        stages = _camera_from(stages, c)
    return [s for s in stages if s.stop > s.start]


def _camera_from(stages, c):
    """The stages with the camera blocks left out of the steps before ``c``: a stage that spans
    ``c`` is cut in two, its first part named ``<name>-gaussians``."""
    out = []
    for s in stages:
        without = tuple(p for p in s.trainable if not p.startswith((f"{CAMERA}.", f"{POSENET}.")))
        if s.stop <= c:
            out.append(Stage(s.name, s.start, s.stop, without, s.static_only))
        elif s.start < c:
            out.append(Stage(f"{s.name}-gaussians", s.start, c, without, s.static_only))
            out.append(Stage(s.name, c, s.stop, s.trainable, s.static_only))
        else:
            out.append(s)
    return out


class StepPlan(NamedTuple):
    step: int
    sched: int  # the step the schedules are read at
    stage: Stage
    frame: int
    scale: float  # render scale of the progressive schedule
    lr_scale: float  # learning-rate decays are read at count x lr_scale (optim.adam)


class Planner:
    """Stage, frame and scale of every step of one run.

    config: the experiment config; sizes: (width, height) of each training frame; stages: from
    ``make_stages`` (a list; replace it to change what a stage trains).
    """

    def __init__(self, config: ExperimentConfig, sizes, stages):
        self.config = config
        self.num_frames = len(sizes)
        self.min_side = min(min(w, h) for w, h in sizes)
        self.stages = list(stages)

    def stage_at(self, sched: int) -> Stage:
        for s in self.stages:
            if s.start <= sched < s.stop:
                return s
        return self.stages[-1]

    def scale_at(self, sched: int) -> float:
        """Render scale of the progressive schedule, raised if needed so that the smallest image
        side keeps at least one SSIM window (11 px)."""
        if not self.config.train.progressive:
            return 1.0
        r = self.config.schedule.scale(sched, self.config.train.iters)
        if self.config.loss.lambda_ssim > 0:
            r = max(r, min(1.0, SSIM_WINDOW / self.min_side))
        return r

    def frame_for_step(self, step: int) -> int:
        """Seeded permutation per epoch; depends only on (seed, step), so resuming reproduces it."""
        epoch, pos = divmod(step, self.num_frames)
        perm = np.random.default_rng((self.config.train.seed, epoch)).permutation(self.num_frames)
        return int(perm[pos])

    def plan(self, step: int, sched: int) -> StepPlan:
        lr_scale = sched / step if sched > step > 0 else 1.0
        return StepPlan(step, sched, self.stage_at(sched), self.frame_for_step(step), self.scale_at(sched), lr_scale)
