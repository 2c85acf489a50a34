"""The training state step plugins receive and return: ``on_step(state) -> state``.

Persistent part (checkpointed, so a resumed run is exact):
- ``model``: the ``train.model.Model`` (parameters and camera state);
- ``adam``: the Adam state of the parameter blocks (``optim/adam.py``);
- ``rows``: per-row statistics kept in step with the Gaussians (``train/rows.py``);
- ``last_sched``: the schedule step of the latest step (periodic plugins fire when the schedule
  step enters a new period, ``entered_period``).

The step's part, set by the loop before the plugins run: ``step``, ``sched`` (the step the
schedules were read at), ``prev_sched`` (the one the periods compare against), ``stage``,
``record`` (the step's record: loss, loss terms, train PSNR, ...; plugins add to it, e.g.
``heldout_psnr``), ``aux`` (what the step's backward exposes: the screen-space mean gradients
``v_means2d`` and ``v_means2d_abs`` (M, 2) in full-resolution pixels, ``radii``, ``num_static``; empty for a step
without loss) and ``last`` (the run's last step: iterations done or time budget spent).

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

__all__ = ["TrainState", "entered_period"]

ADAM_KEY = "adam/"


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
    record: dict = field(default_factory=dict)
    aux: dict = field(default_factory=dict)
    last: bool = False

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
