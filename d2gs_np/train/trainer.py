"""The trainer: runs the steps of a run set up by ``train/setup.py``, and owns its log rows,
checkpoints and time budget.

One step (``Trainer.step``, then the plugins in ``Trainer.run``):
  sample     stage, frame and render scale (``train/stages.py``), the target at that scale
             (``train/schedule.py``, docs/method.md §7);
  forward    the model's render of the frame (``train/model.py``): with the blur model the mean
             of n renders along the exposure (docs/method.md §4), else one sharp render;
  losses     the loss terms (``train/terms.py``, docs/method.md §6), weighted and summed;
  backward   their cotangents back through the render to every parameter block;
  optimiser  Adam on the blocks the stage trains (``train/learning_rates.py``, docs/method.md §8);
  plugins    ``on_step(state) -> state`` on the training state (``train/state.py``), which
             carries the step's record (``StepRecord``) and screen-space gradients
             (``ScreenGrads``): held-out PSNR, densification statistics, pruning,
             densification, then any plugin passed in (``train/plugins.py``);
then a log row from the step's record, a checkpoint every ``checkpoint_every`` steps or
``checkpoint_seconds`` of wall clock, and a clean stop when the time budget is spent. A
checkpoint holds the model, Adam's state, per-row statistics, the schedule clock, every plugin's
``state_dict`` and the scene's record (``data.fingerprint``), so a resumed run continues bitwise
as if never interrupted, and only on the frames it was trained on. New parts plug in without
changing this loop: a regulariser is a loss term, a pose solver or a neighbour refresh a plugin,
an initialisation rule ``Model.from_scene``, a budget schedule a change of
``schedule.schedule_step``.

The run folder is written only once the set-up is done (``Trainer._open_run_folder``): a new
run's first act is its step-0 checkpoint, and only then are an earlier run's results in the
folder (``overwrite``) removed; so a failed or interrupted set-up leaves the folder as it was,
and at no moment does it hold neither the old result nor a checkpoint of the new run. Ctrl-C
during the steps finishes the step, writes a checkpoint and raises ``TrainingInterrupted``.
"""
from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from d2gs_np.data.scene import Scene
from d2gs_np.render.api import warm_up
from d2gs_np.scene import gaussians
from d2gs_np.scene.border import border_gaussians, static_renders
from d2gs_np.scene.gaussians import STATIC, num_static
from d2gs_np.scene.rigid import dynamic_positions, hold_rigid_residuals
from d2gs_np.train.background import background_rng, composite_bwd, composite_fwd
from d2gs_np.train.checkpoint import atomic_write_text, save_checkpoint
from d2gs_np.train.config import ExperimentConfig
from d2gs_np.train.learning_rates import centre_endpoint_grads, optimiser_step, position_row_factors
from d2gs_np.train.log import Stopwatch, psnr_from_mse
from d2gs_np.train.model import Model, frame_render_bwd, frame_render_fwd
from d2gs_np.train.plugins import plugin_states
from d2gs_np.train.pose_solver import HISTORY_FILE
from d2gs_np.train.run_folder import CHECKPOINT_NAME, CONFIG_NAME, FINAL_NAME, METRICS_NAME, REPORT_NAME
from d2gs_np.train.schedule import schedule_step, training_progress
from d2gs_np.train.setup import set_up_run
from d2gs_np.train.state import ScreenGrads, StepRecord
from d2gs_np.train.terms import TermInputs, terms_fwd_bwd

# Files of an earlier run that a new run in the same folder removes once its first checkpoint is
# written (checkpoint.npz, config.json and the log it rewrites).
REPLACED_RESULTS = (FINAL_NAME, METRICS_NAME, HISTORY_FILE, REPORT_NAME)
_BACKWARD_VIEWS_STREAM = 0xB1  # the seed stream of blur.backward_views' draws (apart from the frame order's)


def backward_views_rng(seed: int, step: int) -> np.random.Generator:
    """The generator a training step draws its backward's views from (``blur.backward_views``):
    a function of (seed, step) only, so a resumed run draws what the uninterrupted one drew."""
    return np.random.default_rng((seed, step, _BACKWARD_VIEWS_STREAM))


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during the steps (``Trainer.run``): ``step`` steps are in the checkpoint ``path``
    (None: the run has none), the run goes on from there with ``resume``."""

    def __init__(self, message: str, step: int, path):
        super().__init__(message)
        self.step, self.path = step, path


@contextlib.contextmanager
def _interrupt_after_the_step():
    """A first SIGINT (Ctrl-C) sets the flag yielded (a list, non-empty once set), which the loop
    reads after each step; a second raises KeyboardInterrupt at once. Signal handlers live in the
    main thread only: elsewhere (a worker) nothing changes; nor where SIGINT is ignored (a
    background job)."""
    flag = []
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        yield flag
        return

    def handler(signum, frame):
        if flag:
            raise KeyboardInterrupt
        flag.append(signum)
        print("\n[d2gs] interrupted: a checkpoint is written after this step (Ctrl-C again to stop at once)",
              flush=True)

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)


@dataclass(frozen=True)
class RunResult:
    """What ``Trainer.run`` did: the steps the run has done, its training seconds (JIT warm-up
    and evaluation excluded) and the record of its last step (None when nothing was left to train)."""

    steps: int
    train_seconds: float
    last: Optional[StepRecord] = None


class Trainer:
    """Trains a model of ``scene`` with ``config`` into the folder ``run_dir``: the set-up
    (``train/setup.py``, ``set_up_run``) builds everything the run trains with, and the trainer
    keeps what it returns and only trains. A folder that is not empty needs ``resume`` (go on
    from its latest checkpoint, on the same scene and config) or ``overwrite`` (replace the run
    there; its files stay until the new run's first checkpoint). ``plugins``: step plugins run
    after the default ones, each a plugin or a builder of one from the run's ``RunContext``
    (``train/plugins.py``). Nothing is written into ``run_dir`` before ``run`` (or
    ``checkpoint``) is called."""

    def __init__(self, scene: Scene, config: ExperimentConfig, run_dir, plugins=(), resume: bool = False,
                 overwrite: bool = False):
        run = set_up_run(scene, config, run_dir, plugins, resume, overwrite)
        self.scene, self.config, self.frames = scene, config, scene.frames
        self.run_dir, self.extent = run.context.run_dir, run.context.extent
        self.log, self.terms, self.plugins = run.log, run.terms, run.plugins
        self.state, self.step_index, self.stopwatch = run.state, run.step, Stopwatch(run.seconds)
        self.position_extent, self.planner, self.adam_config = run.position_extent, run.planner, run.adam_config
        self.cache, self.scene_record = run.cache, run.scene_record
        self.camera_row_scales = run.camera_row_scales
        self._resumed_from = run.resumed_from
        self._opened = False  # whether the run has written into run_dir (_open_run_folder)
        # the latest checkpoint: its step and path (a resumed run's is the one it resumed)
        self._saved_step, self._saved_path = (run.step, run.resumed_from) if run.resumed_from else (None, None)
        self._last_save = time.perf_counter()

    # ------------------------------------------------------------------ views of the state
    @property
    def model(self) -> Model:
        return self.state.model

    @property
    def params(self) -> dict:
        return self.state.params

    @params.setter
    def params(self, params):
        self.state = self.state.with_params(params)

    @property
    def adam_state(self) -> dict:
        return self.state.adam

    @property
    def components(self):
        return self.state.model.components

    @property
    def stages(self) -> list:
        return self.planner.stages

    @stages.setter
    def stages(self, stages):
        self.planner.stages = list(stages)

    def num_gaussians(self) -> int:
        return self.state.model.num_gaussians()

    def left_out(self) -> list:
        return self.components.left_out([t.name for t in self.terms], [p.name for p in self.plugins])

    # ------------------------------------------------------------------ one step
    def step(self, step: int, sched: Optional[int] = None) -> StepRecord:
        """Sample, forward, losses, backward and optimiser of one step; returns the step's record
        (``StepRecord``) and leaves its screen-space gradients in ``state.screen_grads``. ``sched``
        is the step the schedules are read at (``schedule_step``: further along than ``step``
        when a time budget binds); default ``step``."""
        plan = self.planner.plan(step, step if sched is None else sched)
        state, k = self.state, plan.frame
        tgt = self.cache.get(k, plan.scale)
        record = StepRecord(step=step, frame=k, stage=plan.stage.name, scale=plan.scale, width=tgt.width,
                            height=tgt.height)
        # Moving pixels carry no loss while only the static set is rendered (warm-up stage).
        ignore = tgt.mask if (plan.stage.static_only and tgt.mask is not None) else None
        loss_mask = None if ignore is None else (~ignore).astype(state.params[f"{STATIC}.means"].dtype)
        if loss_mask is not None and not loss_mask.any():  # every pixel moving: nothing static to learn from
            self.state = state.replace(screen_grads=None)
            return record  # loss and train PSNR NaN, no views
        out, saved = frame_render_fwd(state.model, k, tgt.K, tgt.width, tgt.height, plan.stage.static_only)
        views = int(out["poses"].shape[0]) if "poses" in out else 1
        bg = None
        if self.config.train.random_background:  # the render moved over a background drawn for this step
            bg = background_rng(self.config.train.seed, step).random(3)
            out = dict(out, image=composite_fwd(out["image"], out["alpha"], bg, state.model.background))
        inputs = TermInputs(out, tgt.image, loss_mask, state.model, k, plan.stage, tgt.mask)
        loss, values, v_render, v_terms = terms_fwd_bwd(self.terms, inputs)
        if bg is not None and "image" in v_render:
            v_bg = composite_bwd(v_render["image"], bg, state.model.background)
            v_render["alpha"] = v_bg if v_render.get("alpha") is None else v_render["alpha"] + v_bg
        # The views a subset backward runs through (blur.backward_views) depend only on (seed, step),
        # so a resumed run draws the same ones.
        rng = backward_views_rng(self.config.train.seed, step)
        grads, v_means2d, v_means2d_abs = frame_render_bwd(saved, **{f"v_{n}": v for n, v in v_render.items()}, rng=rng)
        for n, g in v_terms.items():
            grads[n] = grads[n] + g if n in grads else g
        if self.components.centred:
            grads = centre_endpoint_grads(grads)
        if not self.config.motion_init.rigid_residual and gaussians.has_rigid(state.params):
            grads = hold_rigid_residuals(grads, state.params)
        lr = self.config.train.lr
        factors = None
        if lr.means_depth == "near":
            p = state.params
            world = (dynamic_positions(p, [state.model.times[k]], self.config.deform)[0]
                     if gaussians.has_rigid(p) else None)
            factors = position_row_factors(p, state.model.poses_ref[k], lr.means_depth_floor, world)
        params, adam_state = optimiser_step(grads, state.adam, state.params, self.adam_config, plan.stage.trainable,
                                            k, plan.lr_scale, self.camera_row_scales[k], factors)
        sq = (out["image"] - tgt.image) ** 2
        mse = float(np.mean(sq)) if ignore is None else float(np.mean(sq[~ignore]))
        screen = ScreenGrads(v_means2d=v_means2d, v_means2d_abs=v_means2d_abs, radii=out["radii"],
                             num_static=num_static(state.params))
        self.state = state.replace(model=state.model.replace(params=params), adam=adam_state, screen_grads=screen)
        return record.replace(views=views, loss=float(loss), train_psnr=psnr_from_mse(mse), losses=values)

    # ------------------------------------------------------------------ the loop
    def run(self) -> RunResult:
        """Train to the end of the schedule (or of the time budget); returns the steps done, the
        training seconds and the last step's record (``RunResult``). Ctrl-C:
        ``TrainingInterrupted`` after a checkpoint (module docstring)."""
        tc = self.config.train
        total = tc.iters
        if self._schedule_done(self.step_index, self.stopwatch.seconds()):
            # a resumed run that has nothing left to do: its folder stays as it is
            self.log.note(f"nothing to train: the run in {self.run_dir} is at step {self.step_index} of {total}")
            return RunResult(self.step_index, self.stopwatch.seconds())
        t_start = time.perf_counter()
        warm_up(self.config.render)
        for term in self.terms:  # loss terms with kernels of their own (L_freq)
            if hasattr(term, "warm_up"):
                term.warm_up()
        self.log.note(f"JIT warm-up (compile or cache load) took {time.perf_counter() - t_start:.1f}s, not counted "
                      "as training time")
        if self.step_index == 0:
            self.log.note("precision: parameters, projection and losses float64; steps rasterise in "
                          + ("float32 (render.raster_float32, docs/method.md §8)" if self.config.render.raster_float32
                             else "float64") + "; evaluation renders in float64")
            self.log.note(f"training {total} steps; stages: " + ", ".join(
                f"{s.name} [{s.start}, {s.stop})" for s in self.stages))
        with _interrupt_after_the_step() as interrupted:
            try:
                self._open_run_folder()
                record = self._loop(interrupted)
            except TrainingInterrupted:
                raise
            except KeyboardInterrupt:  # a second Ctrl-C, mid-step: the last checkpoint stands
                last = ("the run has no checkpoint yet" if self._saved_path is None else
                        f"the last checkpoint is step {self._saved_step} in {self._saved_path}")
                raise TrainingInterrupted(f"stopped at once during step {self.step_index}; {last}", self._saved_step,
                                          self._saved_path) from None
            wall = time.perf_counter() - t_start
            self.log.note(f"finished at step {self.step_index}: {self.stopwatch.seconds():.1f}s of training "
                          f"({wall:.1f}s wall including evaluation)")
            self.log.save()
        return RunResult(self.step_index, self.stopwatch.seconds(), record)

    def _loop(self, interrupted) -> StepRecord:
        """The steps from ``step_index`` to the end, then the final checkpoint (``run``); returns
        the last step's record. ``interrupted``: non-empty once Ctrl-C was pressed."""
        tc = self.config.train
        total, budget, stretch = tc.iters, tc.time_budget, tc.stretch_to_budget
        last_stage = None
        first = self.step_index
        # The clock ends a run only before its first step (a resumed run already out of time); after
        # that, the step whose own time spends the budget is marked last and ends the loop, so a
        # timed plugin that runs past the budget does not end the run behind its step's back.
        while not self._schedule_done(self.step_index, self.stopwatch.seconds() if self.step_index == first else None):
            step = self.step_index
            # The step the schedules are read at: the step itself, or further along when a time
            # budget binds, so a budgeted run finishes its schedule (schedule.training_progress);
            # past the schedule's end (stretch_to_budget) its final settings.
            sched = schedule_step(step, self.stopwatch.seconds(), total, budget)
            stage = self.planner.stage_at(sched)
            if stage.name != last_stage:
                self.log.note(f"stage {stage.name} from step {step}" + (f" (schedule step {sched})"
                                                                        if sched != step else ""))
                last_stage = stage.name
            self.stopwatch.start()
            record = self.step(step, sched)
            out_of_time = budget is not None and self.stopwatch.seconds() >= budget
            # Periodic plugins fire when the schedule step enters a new period (without a budget:
            # exactly at multiples of the period, as 3DGS).
            prev = self.state.last_sched if budget is not None else step - 1
            last = out_of_time or (step + 1 >= total and not (budget is not None and stretch))
            state = self.state.replace(step=step, sched=sched, prev_sched=prev, last_sched=sched, stage=stage,
                                       record=record, last=last,
                                       budget_fraction=None if budget is None else self.stopwatch.seconds() / budget)
            for plugin in self.plugins:
                state = self._on_step(plugin, state)
            self.stopwatch.pause()
            self.state, self.step_index = state, step + 1
            self._log_row(state)
            due = (tc.checkpoint_every and self.step_index % tc.checkpoint_every == 0) or \
                (tc.checkpoint_seconds and time.perf_counter() - self._last_save >= tc.checkpoint_seconds)
            if (due or interrupted) and not state.last:
                self.checkpoint()
            if interrupted and not state.last:
                raise TrainingInterrupted(f"checkpoint of step {self.step_index} written to {self._saved_path}",
                                          self.step_index, self._saved_path)
            if out_of_time:
                break
        if budget is not None and self.stopwatch.seconds() >= budget:
            self.log.note(f"time budget of {budget:.0f}s reached at step {self.step_index} (schedule step "
                          f"{self.state.sched} of {total}: schedule complete); stopping")
        self._extend_past_borders()
        self.checkpoint(final=True)
        return self.state.record

    def _extend_past_borders(self):
        """The finished model's static world continued past the frames' borders (``scene/border.py``),
        outside the training clock: no training view changes, so neither does anything trained."""
        cfg = self.config.border
        if cfg.margin <= 0:
            return
        t0 = time.perf_counter()
        model = self.state.model
        poses = model.mid_poses()
        images, alphas, depths = static_renders(model, poses)
        new, info = border_gaussians(images, alphas, depths, poses, model.Ks, cfg,
                                     existing=model.params[f"{STATIC}.means"], eps2d=model.config.render.eps2d)
        if new is not None:
            new = {k: v.astype(model.params[k].dtype, copy=False) for k, v in new.items()}
            self.state = self.state.resize_rows(STATIC, new=new)
        self.log.note(f"past the frames' borders: {info['added']} static Gaussians added of {info['candidates']} "
                      f"candidates" + (f" ({info['reason']})" if "reason" in info else "")
                      + f", {time.perf_counter() - t0:.1f}s outside the training clock")

    def _schedule_done(self, step, seconds) -> bool:
        """Whether the run has ended: its budget spent (``seconds``; None: not asked), or (unless
        stretched over a budget) its schedule's steps done."""
        tc = self.config.train
        if tc.time_budget is not None and seconds is not None and seconds >= tc.time_budget:
            return True
        return step >= tc.iters and not (tc.time_budget is not None and tc.stretch_to_budget)

    def _on_step(self, plugin, state):
        if plugin.timed:
            return plugin.on_step(state)
        self.stopwatch.pause()  # not training time (evaluation)
        try:
            return plugin.on_step(state)
        finally:
            self.stopwatch.start()

    def _log_row(self, state):
        tc, record = self.config.train, state.record
        if state.step % tc.log_every == 0 or state.last or record.heldout_psnr is not None:
            seconds = self.stopwatch.seconds()
            # how far the run is after this step: what a time budget has bought (1 when it is spent)
            progress = min(1.0, training_progress(state.step + 1, seconds, tc.iters, tc.time_budget))
            self.log.row(step=state.step, seconds=round(seconds, 4), stage=state.stage.name, loss=record.loss,
                         train_psnr=record.train_psnr, heldout_psnr=record.heldout_psnr,
                         scale=round(record.scale, 4), num_gaussians=self.num_gaussians(),
                         progress=round(progress, 4), views=record.views,
                         heldout_depth_absrel=record.heldout_depth_absrel,
                         **{f"loss_{t.name}": record.losses.get(t.name) for t in self.terms})
            self.log.progress(self.step_index, tc.iters, seconds, record.loss, record.train_psnr, state.stage.name,
                              fraction=progress)

    # ------------------------------------------------------------------ checkpoints
    def _open_run_folder(self):
        """The run's first writes into its folder, once setup is done (module docstring). A new
        run: its step-0 checkpoint, then an earlier run's results (``REPLACED_RESULTS``) go. A
        resumed one: the metrics and the final model of an earlier stop go (the model becomes
        checkpoint.npz when it is the one resumed), so nothing in the folder describes another
        state of the model than its checkpoint and log. Then config.json and the log."""
        if self._opened:
            return
        self._opened = True
        d = self.run_dir
        d.mkdir(parents=True, exist_ok=True)
        for name in (CHECKPOINT_NAME, FINAL_NAME, CONFIG_NAME, "log.json", HISTORY_FILE):
            for tmp in d.glob(f".{name}.*.tmp"):  # of an atomic write (train.checkpoint) a killed run left
                tmp.unlink(missing_ok=True)
        if self._resumed_from is not None:
            final = d / FINAL_NAME
            if final.exists():
                if final == self._resumed_from:
                    os.replace(final, d / CHECKPOINT_NAME)  # atomic; its contents are the resumed state
                    self._saved_path = d / CHECKPOINT_NAME
                else:
                    final.unlink()
            (d / METRICS_NAME).unlink(missing_ok=True)
            self._last_save = time.perf_counter()  # the wall-clock period counts from here
        else:
            # first the new checkpoint, then the old final.npz: a kill between the two leaves the old
            # final.npz, the latest checkpoint there, with its own config and log
            self._save(CHECKPOINT_NAME, final=False)
            for name in REPLACED_RESULTS:
                (d / name).unlink(missing_ok=True)
        atomic_write_text(d / CONFIG_NAME, self.config.to_json())
        self.log.truncate(self.step_index)
        self.log.save()

    def checkpoint(self, final: bool = False):
        """Write the state atomically to checkpoint.npz (``final``: final.npz), with the log."""
        self._open_run_folder()
        # the log first: a resume truncates it to the checkpoint it finds, so a kill between the two
        # writes loses no row of the steps that checkpoint holds
        self.log.save()
        self._save(FINAL_NAME if final else CHECKPOINT_NAME, final)

    def _save(self, name: str, final: bool):
        arrays, meta = self.state.to_checkpoint()
        plugin_arrays, meta["plugins"] = plugin_states(self.plugins)
        arrays.update(plugin_arrays)
        meta.update(step=self.step_index, seconds=self.stopwatch.seconds(), final=final, left_out=self.left_out(),
                    position_extent=self.position_extent,
                    scene_root=str(Path(self.scene.root).resolve()) if self.scene.root is not None else None,
                    scene_digest=self.scene_record["digest"])
        path = self.run_dir / name
        save_checkpoint(path, arrays, meta)
        self._saved_step, self._saved_path, self._last_save = self.step_index, path, time.perf_counter()
