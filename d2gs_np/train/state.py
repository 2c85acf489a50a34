"""The training state step plugins receive and return: ``on_step(state) -> state``.

Persistent part (checkpointed, so a resumed run is exact):
- ``model``: the ``train.model.Model`` (parameters and camera state);
- ``adam``: the Adam state of the parameter blocks (``optim/adam.py``);
- ``rows``: per-row statistics kept in step with the Gaussians (``train/rows.py``);
- ``last_sched``: the schedule step of the latest step (periodic plugins fire when the schedule
  step enters a new period, ``entered_period``).

The step's part, set by the loop before the plugins run: ``step``, ``sched`` (the step the
schedules were read at), ``prev_sched`` (the one the periods compare against), ``stage``,
``last`` (the run's last step: iterations done or time budget spent), ``budget_fraction`` (seconds
of training after this step over the time budget; None without one), and the step's two
channels, each a record with named fields:
- ``record`` (``StepRecord``): what the step did (frame, render scale and size, loss, each loss
  term's value, train PSNR); plugins add theirs with ``record.replace`` (``heldout_psnr``,
  ``pose_solver``); the log row is written from it;
- ``screen_grads`` (``ScreenGrads``): what the step's backward exposes, the screen-space mean
  gradients and which Gaussians were visible (densification's statistics read them); None for a
  step without loss.

The state is immutable: a plugin returns ``state.replace(...)`` (or ``state.resize_rows(...)``)
and never edits arrays in place.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from d2gs_np.train import rows as rows_mod
from d2gs_np.train.model import Model
from d2gs_np.train.stages import Stage

__all__ = ["TrainState", "StepRecord", "ScreenGrads", "entered_period"]

ADAM_KEY = "adam/"


@dataclass(frozen=True)
class StepRecord:
    """What one step did (``Trainer.step``); its log row is written from it."""

    step: int
    frame: int  # the frame trained on
    stage: str  # the stage's name (train/stages.py)
    scale: float  # the render scale
    width: int  # render size, pixels
    height: int
    views: int = 0  # virtual views rendered: n with the blur model, else 1; 0 for a step without loss
    loss: float = float("nan")  # the weighted sum of the terms; NaN for a step without loss (no pixel carried any)
    train_psnr: float = float("nan")  # of the render against its target, on the pixels that carry loss
    losses: dict = field(default_factory=dict)  # term name -> its unweighted value (log column loss_<name>)
    heldout_psnr: Optional[float] = None  # plugins.HeldOutPSNR on its steps (None also without sharp frames)
    heldout_depth_absrel: Optional[float] = None  # the same renders' depth AbsRel (None without true depth)
    pose_solver: Optional[dict] = None  # pose_solver.PoseSolver on its steps: the summary of its call

    def replace(self, **changes) -> "StepRecord":
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True, eq=False)
class ScreenGrads:
    """What a step's backward exposes to the plugins, for the M rendered Gaussians (static rows
    first): densification's statistics (``plugins.GradientStatistics``) read it."""

    v_means2d: np.ndarray  # (M, 2) screen-space gradient of each mean, full-resolution pixels, summed over sub-frames
    v_means2d_abs: np.ndarray  # (M, 2) the same as sums of absolute per-pixel terms (DensifyConfig.absgrad)
    radii: np.ndarray  # (M, 2) the render's radii (max over sub-frames); 0: not visible
    num_static: int  # rows [0, num_static) are the static set's, the others the dynamic set's


@dataclass(frozen=True, eq=False)
class TrainState:
    model: Model
    adam: dict
    rows: dict = field(default_factory=dict)
    last_sched: int = -1
    step: int = -1
    sched: int = -1
    prev_sched: int = -1
    stage: Optional[Stage] = None
    record: Optional[StepRecord] = None
    screen_grads: Optional[ScreenGrads] = None
    last: bool = False
    budget_fraction: Optional[float] = None

    @property
    def params(self) -> dict:
        return self.model.params

    def replace(self, **changes) -> "TrainState":
        return dataclasses.replace(self, **changes)

    def with_params(self, params) -> "TrainState":
        return self.replace(model=self.model.replace(params=params))

    def resize_rows(self, prefix, keep=None, new=None) -> "TrainState":
        """``train.rows.resize_rows`` on this state's parameters, Adam state and statistics."""
        params, adam_state, rows = rows_mod.resize_rows(self.params, self.adam, self.rows, prefix, keep, new)
        return self.replace(model=self.model.replace(params=params), adam=adam_state, rows=rows)

    # ------------------------------------------------------------------ checkpoint
    def to_checkpoint(self):
        """(arrays, meta) of the persistent part: the model's, Adam's as ``adam/<slot>/<block>``
        (``adam/<slot>`` for a scalar slot), the statistics as ``<name>/<set>``."""
        arrays, meta = self.model.to_checkpoint()
        for slot, blocks in self.adam.items():
            if isinstance(blocks, dict):
                for n, v in blocks.items():
                    arrays[f"{ADAM_KEY}{slot}/{n}"] = v
            else:
                arrays[f"{ADAM_KEY}{slot}"] = np.asarray(blocks)
        for name, per in self.rows.items():
            for prefix, v in per.items():
                arrays[f"{name}/{prefix}"] = v
        meta["last_sched"] = int(self.last_sched)
        return arrays, meta

    @classmethod
    def from_checkpoint(cls, arrays, meta, rows: dict) -> "TrainState":
        """Inverse of ``to_checkpoint``. ``rows``: the statistics the run keeps, initialised (zero)
        for the checkpoint's parameters; each one present in the checkpoint is restored."""
        model = Model.from_checkpoint(arrays, meta)
        adam_state = {}
        for k, v in arrays.items():
            if k.startswith(ADAM_KEY):
                parts = k.split("/", 2)
                if len(parts) == 3:
                    adam_state.setdefault(parts[1], {})[parts[2]] = v
                else:
                    adam_state[parts[1]] = v.item() if v.ndim == 0 else v
        rows = {name: {p: arrays.get(f"{name}/{p}", v) for p, v in per.items()} for name, per in rows.items()}
        last = int(meta.get("last_sched", int(meta["step"]) - 1))
        return cls(model=model, adam=adam_state, rows=rows, last_sched=last)


def entered_period(state: TrainState, every: int) -> bool:
    """True when the schedule step entered a new period of ``every`` steps with this step
    (without a time budget: at multiples of ``every``, as 3DGS), never at schedule step 0."""
    return bool(every) and state.sched > 0 and state.sched // every > state.prev_sched // every
