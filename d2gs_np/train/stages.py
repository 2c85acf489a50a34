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
from d2gs_np.scene.gaussians import DYNAMIC, STATIC
from d2gs_np.trajectory import CAMERA, POSENET
from d2gs_np.train.config import ExperimentConfig, TrainConfig

__all__ = ["Stage", "make_stages", "StepPlan", "Planner", "sharpness", "frame_probabilities"]


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
        stages.append(Stage("deform", w, w + d, (f"{DYNAMIC}.",), False))
    stages.append(Stage("joint", w + d, n, (f"{STATIC}.", f"{DYNAMIC}.", f"{CAMERA}.", f"{POSENET}."), False))
    return [s for s in stages if s.stop > s.start]


def sharpness(image) -> float:
    """Mean squared gradient of an (H, W, 3) image's luminance (forward differences, both axes):
    a blurred copy of a view has less of it than a sharp one."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 2:
        raise ValueError(f"sharpness needs an (H, W, 3) image with H, W >= 2; got shape {img.shape}")
    y = img @ np.array([0.299, 0.587, 0.114])
    return float(0.5 * (np.mean(np.diff(y, axis=0) ** 2) + np.mean(np.diff(y, axis=1) ** 2)))


def frame_probabilities(images, share: float) -> np.ndarray:
    """Probability of drawing each frame (``TrainConfig.frame_sampling = "sharpness"``):
    (1 - share) / N + share * s_k / sum_j s_j with s_k = ``sharpness(images[k])``. share in
    [0, 1]; a set of flat images (every s_k = 0) is drawn uniformly."""
    s = np.array([sharpness(im) for im in images])
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"share must be in [0, 1]; got {share}")
    n = s.size
    if n == 0:
        raise ValueError("frame_probabilities needs at least one image")
    uniform = np.full(n, 1.0 / n)
    if s.sum() <= 0.0:
        return uniform
    p = (1.0 - share) * uniform + share * s / s.sum()
    return p / p.sum()


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
    ``make_stages`` (a list; replace it to change what a stage trains); frame_p: None (each frame
    once per epoch) or each frame's probability (``frame_probabilities``).
    """

    def __init__(self, config: ExperimentConfig, sizes, stages, frame_p=None):
        self.config = config
        self.num_frames = len(sizes)
        self.min_side = min(min(w, h) for w, h in sizes)
        self.stages = list(stages)
        if frame_p is not None:
            frame_p = np.asarray(frame_p, dtype=np.float64)
            if frame_p.shape != (self.num_frames,) or not np.all(frame_p >= 0) or not np.isclose(frame_p.sum(), 1.0):
                raise ValueError(f"frame_p must be {self.num_frames} probabilities >= 0 summing to 1; got {frame_p}")
        self.frame_p = frame_p

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
        """Seeded permutation per epoch (or, with ``frame_p``, N draws per epoch with those
        probabilities); depends only on (seed, step), so resuming reproduces it."""
        epoch, pos = divmod(step, self.num_frames)
        rng = np.random.default_rng((self.config.train.seed, epoch))
        if self.frame_p is None:
            return int(rng.permutation(self.num_frames)[pos])
        return int(rng.choice(self.num_frames, size=self.num_frames, p=self.frame_p)[pos])

    def plan(self, step: int, sched: int) -> StepPlan:
        lr_scale = sched / step if sched > step > 0 else 1.0
        return StepPlan(step, sched, self.stage_at(sched), self.frame_for_step(step), self.scale_at(sched), lr_scale)
