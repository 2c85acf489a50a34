"""Run log: error against wall-clock time, and the decisions the pipeline made.

Every row records the step, the seconds of training so far (JIT warm-up and
evaluation excluded, see ``Stopwatch``), the loss and train PSNR, and, on
evaluation steps, held-out PSNR; also the render scale, the number of Gaussians,
the progress of the run after the row's step (``schedule.training_progress``: with a
time budget it runs ahead of ``step / iters`` and reaches 1 when the budget is spent) and the number of
virtual views the step rendered (1 without the blur model). Rows are appended to ``RUN/log.csv`` as they
come (so a crash keeps them) and the whole history is rewritten atomically to
``RUN/log.json`` at checkpoints.
"""
from __future__ import annotations

import csv
import json
import math
import sys
import time
from pathlib import Path

from d2gs_np.train.checkpoint import atomic_write_text

LOG_FIELDS = ("step", "seconds", "stage", "loss", "train_psnr", "heldout_psnr", "scale", "num_gaussians", "progress",
              "views", "heldout_depth_absrel")


class Stopwatch:
    """Accumulates training time only; ``pause()`` around evaluation and checkpointing."""

    def __init__(self, elapsed: float = 0.0):
        self.elapsed = float(elapsed)
        self._t0 = None

    def start(self):
        if self._t0 is None:
            self._t0 = time.perf_counter()

    def pause(self):
        if self._t0 is not None:
            self.elapsed += time.perf_counter() - self._t0
            self._t0 = None

    def seconds(self) -> float:
        return self.elapsed + (time.perf_counter() - self._t0 if self._t0 is not None else 0.0)


class RunLog:
    """The run's log; ``extra_fields`` are columns after LOG_FIELDS (``add_columns``: the set-up
    adds one per loss term, ``loss_<name>``, the term's unweighted value)."""

    def __init__(self, run_dir, quiet: bool = False, resume: bool = False, extra_fields=()):
        self.run_dir = Path(run_dir)
        self.fields = tuple(LOG_FIELDS)
        self.rows: list = []
        self.notes: list = []  # (seconds, message): what was left out and why, stage changes, ...
        self.quiet = quiet
        self._csv_path = self.run_dir / "log.csv"
        # Nothing is written until the first row or ``truncate`` (the trainer's first write into
        # the run folder): a setup that fails leaves an earlier run's log as it was.
        self._started = False
        self.add_columns(extra_fields)
        if resume and (self.run_dir / "log.json").exists():
            data = json.loads((self.run_dir / "log.json").read_text())
            self.rows, self.notes = data.get("rows", []), data.get("notes", [])

    def add_columns(self, names):
        """Columns after the present ones (those already there are skipped); before the first row."""
        if self._started:
            raise RuntimeError("RunLog.add_columns after the log was started: add the columns before the first row")
        self.fields += tuple(n for n in names if n not in self.fields)

    def note(self, message: str):
        """A decision or event in words (also printed)."""
        self.notes.append(message)
        if not self.quiet:
            print(f"[d2gs] {message}", flush=True)

    def row(self, **values):
        row = {k: values.get(k) for k in self.fields}
        if not self._started:
            self.truncate(row["step"])
        self.rows.append(row)
        with open(self._csv_path, "a", newline="") as f:
            csv.writer(f).writerow(["" if row[k] is None else row[k] for k in self.fields])

    def progress(self, step: int, total: int, seconds: float, loss: float, psnr: float, stage: str,
                 fraction=None):
        """The progress bar; ``fraction`` is the schedule's progress in [0, 1] (default step/total),
        from which the time left is estimated."""
        if self.quiet:
            return
        width = 24
        frac = min(1.0, step / max(total, 1) if fraction is None else fraction)
        done = int(width * frac)
        bar = "#" * done + "-" * (width - done)
        rate = step / seconds if seconds > 0 else float("nan")
        left = seconds * (1.0 - frac) / frac if frac > 0 else float("nan")
        msg = (f"\r[{bar}] {step}/{total} {stage:>8s} loss {loss:.4f} psnr {psnr:5.2f} dB "
               f"{seconds:6.1f}s ({rate:.1f} it/s, ~{left:.0f}s left)")
        sys.stdout.write(msg)
        sys.stdout.flush()
        if step >= total or frac >= 1.0:
            sys.stdout.write("\n")

    def truncate(self, step: int):
        """Forget rows at or after ``step`` (a resumed run redoes them) and rewrite log.csv to match
        (with ``step`` 0: a new log.csv of the header alone)."""
        self.rows = [r for r in self.rows if r["step"] is not None and r["step"] < step]
        self._started = True
        self.run_dir.mkdir(parents=True, exist_ok=True)
        with open(self._csv_path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(self.fields)
            for row in self.rows:
                w.writerow(["" if row.get(k) is None else row[k] for k in self.fields])

    def save(self):
        rows = [{k: _finite_or_none(v) for k, v in r.items()} for r in self.rows]  # strict JSON: no NaN/inf
        atomic_write_text(self.run_dir / "log.json",
                          json.dumps({"rows": rows, "notes": self.notes}, indent=1, allow_nan=False))


def _finite_or_none(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def psnr_from_mse(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)
