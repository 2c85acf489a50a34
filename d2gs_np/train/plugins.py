"""Step plugins: what runs after the optimiser step, in order, on the training state; and the
run context they are built with.

A plugin has a ``name``, ``on_step(state) -> state`` (``train/state.py``), and, when it keeps
anything between steps, ``state_dict()`` / ``load_state_dict(d)``: the trainer checkpoints it
(``plugin_states``: arrays under ``plugins/<name>/<key>``, other values as JSON), so a resumed
run is exact even when the plugin changes the model. ``rows(params)`` declares per-row
statistics it keeps in ``state.rows`` (zero at the start); any change in the number of Gaussians
goes through ``state.resize_rows`` so parameters, Adam state and statistics stay in step.
``on_init(model)`` runs once on a fresh run's initial model. ``timed = False`` pauses the
training stopwatch around the plugin (evaluation is not training time). Periodic plugins fire
when the schedule step enters a new period (``state.entered_period``), so they follow a time
budget (docs/method.md §7).

A plugin talks to the rest of the step through the state's named fields: it reads the step's
``state.record`` (``StepRecord``: loss, frame, scale, ...) and ``state.screen_grads``
(``ScreenGrads``), and adds to the record with ``state.record.replace(...)``. What it needs of
the run (its scene, config, folder, the camera extent, and ``note``: a line into the run log) it
gets when built, from the run's ``RunContext``: the set-up (``train/setup.py``) passes the
context's fields to the plugins it builds, and calls each builder given to the trainer (a class
or function of the context) with it.

The default list (``train/setup.py``, ``default_plugins``), in order:
1. ``HeldOutPSNR``: held-out PSNR on the model the optimiser produced, before pruning and
   densification change it;
2. ``GradientStatistics``: accumulates densification's screen-space gradients (before pruning
   removes rows);
3. ``Prune``: transparent, oversized and escaped Gaussians (``train/prune.py``);
4. ``Densify``: clone and split (``train/densify.py``);
   then ``OpacityReset`` when ``densify.opacity_reset_every`` > 0 (3DGS's opacity reset);
5. ``PoseSolver`` (name "pose_solver", ``train/pose_solver.py``, docs/method.md §5) when the
   config and the scene call for it (``use_pose_solver``).
Plugins a loss term needs (``term.plugins``: ``NeighbourRefresh`` of L_ts, ``DepthMemory`` of
L_reproj) run after the default ones, so they see this step's pruning and densification, and
before those passed to the trainer.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from d2gs_np.geometry.depth import depth_error_terms
from d2gs_np.pose.correspond import correspondences
from d2gs_np.losses.smoothness import knn
from d2gs_np.data.scene import Scene
from d2gs_np.scene import gaussians
from d2gs_np.scene.deformation import deform_basis
from d2gs_np.scene.gaussians import DYNAMIC, STATIC
from d2gs_np.scene.rigid import dynamic_positions
from d2gs_np.train import prune as prune_rules
from d2gs_np.train.config import ExperimentConfig
from d2gs_np.train.densify import (add_grad_stats, densify, dynamic_gaussian_cap, gaussian_cap, init_grad_stats,
                                   reset_opacity)
from d2gs_np.train.log import psnr_from_mse
from d2gs_np.train.learning_rates import size_extent
from d2gs_np.train.rows import SETS, num_rows
from d2gs_np.train.state import TrainState, entered_period

__all__ = ["RunContext", "Plugin", "plugin_states", "load_plugin_states", "HeldOutPSNR", "GradientStatistics", "Prune",
           "Densify", "OpacityReset", "NeighbourRefresh", "DepthMemory"]

PLUGINS_KEY = "plugins/"  # a plugin's arrays in a checkpoint: plugins/<name>/<key>


@dataclass(frozen=True)
class RunContext:
    """What a plugin may use of the run it is built for (module docstring); one per run, made by
    the set-up (``train/setup.py``)."""

    scene: Scene
    config: ExperimentConfig
    run_dir: Path  # the run folder: written from the first step on, never during the set-up
    note: Callable[[str], None]  # a line into the run log (printed too unless train.quiet)
    extent: float  # the camera extent (learning_rates.scene_extent), the unit of the size rules


class Plugin:
    """Base class: does nothing, keeps nothing (see the module docstring)."""

    name = "plugin"
    timed = True  # counts as training time

    def rows(self, params) -> dict:
        return {}

    def on_init(self, model):
        """Once, on a fresh run, with the initial model (not on resume: keep what it measured in
        ``state_dict``)."""

    def on_step(self, state: TrainState) -> TrainState:
        return state

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict):
        pass


def plugin_states(plugins):
    """(arrays, meta) of every plugin's ``state_dict`` for a checkpoint: arrays under
    ``plugins/<name>/<key>``, other values in meta[name][key] (JSON)."""
    arrays, meta = {}, {}
    for p in plugins:
        for key, v in p.state_dict().items():
            if isinstance(v, np.ndarray):
                arrays[f"{PLUGINS_KEY}{p.name}/{key}"] = v
            else:
                meta.setdefault(p.name, {})[key] = v
    return arrays, meta


def load_plugin_states(plugins, arrays, meta):
    """Inverse of ``plugin_states``: each plugin's ``load_state_dict`` with what the checkpoint
    (``arrays``, ``meta``) holds for it (empty if nothing)."""
    for p in plugins:
        prefix = f"{PLUGINS_KEY}{p.name}/"
        p.load_state_dict({**meta.get(p.name, {}),
                           **{k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}})


class HeldOutPSNR(Plugin):
    """Held-out PSNR every ``every`` steps and at the last: sharp renders at the optimised
    mid-exposure poses against the sharp frames (if the scene has them), on ``num_frames`` evenly
    spaced frames at full resolution. Recorded as ``heldout_psnr`` (None without sharp frames),
    and, for a scene with true depth maps, the same renders' depth AbsRel as
    ``heldout_depth_absrel`` (in the given poses' units, unaligned: ``d2gs eval`` aligns)."""

    name = "heldout_psnr"
    timed = False

    def __init__(self, scene, every: int, num_frames: int):
        self.scene, self.every, self.num_frames = scene, every, num_frames

    def on_step(self, state):
        if not (self.every and (state.step % self.every == 0 or state.last)):
            return state
        h = self.heldout(state.model)
        return state.replace(record=state.record.replace(heldout_psnr=h["psnr"],
                                                         heldout_depth_absrel=h["depth_absrel"]))

    def heldout(self, model) -> dict:
        """{"psnr": held-out PSNR or None, "depth_absrel": AbsRel or None} of one set of renders."""
        frames = self.scene.frames
        sharp = self.scene.has_sharp
        depth = self.scene.has_depth
        if not (sharp or depth):
            return {"psnr": None, "depth_absrel": None}
        idx = np.unique(np.linspace(0, len(frames) - 1, self.num_frames).round().astype(int))
        mses, rels = [], []
        for k in idx:
            out = model.render_outputs(int(k))
            if sharp:
                mses.append(float(np.mean((out["image"] - frames[k].sharp) ** 2)))
            if depth:
                rels.append(depth_error_terms(out["expected_depth"], frames[k].depth)[0])
        rel = np.concatenate(rels) if rels else np.zeros(0)
        return {"psnr": psnr_from_mse(float(np.mean(mses))) if mses else None,
                "depth_absrel": float(rel.mean()) if rel.size else None}


class GradientStatistics(Plugin):
    """Adds the step's screen-space mean gradients (full-resolution pixels) of the Gaussians
    visible in every sub-frame to densification's statistics (``train/densify.py``): the plain
    gradients, or with ``DensifyConfig.absgrad`` their sums of absolute per-pixel terms."""

    name = "gradient_statistics"

    def __init__(self, absgrad: bool = False):
        self.absgrad = bool(absgrad)  # DensifyConfig.absgrad

    def rows(self, params):
        return init_grad_stats(params)

    def on_step(self, state):
        g = state.screen_grads
        if g is None:  # a step without loss
            return state
        v = g.v_means2d_abs if self.absgrad else g.v_means2d
        visible = (np.asarray(g.radii).reshape(len(v), -1) > 0).all(axis=1)
        return state.replace(rows=add_grad_stats(state.rows, v, visible.astype(np.float64), g.num_static))


class Prune(Plugin):
    """Every ``train.prune_every`` steps until 90 % of the schedule, and with
    ``PruneConfig.past_schedule`` also past the schedule's end (a run that trains on to spend its
    budget, ``TrainConfig.stretch_to_budget``) until 90 % of the budget: remove transparent and
    oversized Gaussians, and dynamic ones that escaped their motion masks (``train/prune.py``).
    Past the schedule's end without it, long runs grow frame-wide translucent veils (docs/method.md
    §10, the veils)."""

    name = "prune"

    def __init__(self, config: ExperimentConfig, extent: float, masks):
        # the oversized rule's unit: the camera extent until on_init measures the scene's size
        # (learning_rates.size_extent) from the initial points
        self.config, self.extent = config, extent
        self.masks = list(masks)  # (H, W) bool per frame, or None each
        self.has_masks = all(m is not None for m in self.masks)  # as Scene.has_masks

    def on_init(self, model):
        self.extent = size_extent(model.poses_est, model.params[f"{STATIC}.means"], self.extent)

    def state_dict(self):
        return {"extent": float(self.extent)}

    def load_state_dict(self, state):
        self.extent = float(state.get("extent", self.extent))

    def on_step(self, state):
        tc = self.config.train
        if entered_period(state, tc.prune_every) and self.active(state):
            state, _ = self.prune(state)
        return state

    def active(self, state) -> bool:
        """Whether this step is inside a pruning window (the class docstring)."""
        iters = self.config.train.iters
        if state.sched < int(0.9 * iters):
            return True
        return (self.config.prune.past_schedule and state.sched >= iters and state.budget_fraction is not None
                and state.budget_fraction < 0.9)

    def prune(self, state):
        """(state, number removed) with the rules applied once."""
        thr, pc, p = self.config.train.prune_opacity, self.config.prune, state.params
        keep = {STATIC: ~(prune_rules.transparent(p[f"{STATIC}.opacity_logits"], thr) | prune_rules.oversized(
            p[f"{STATIC}.log_scales"], self.extent, pc.max_scale_fraction))}
        if gaussians.has_dynamic(p):
            drop = prune_rules.transparent(p[f"{DYNAMIC}.opacity_logits"], thr) | prune_rules.oversized(
                p[f"{DYNAMIC}.log_scales"], self.extent, pc.max_scale_fraction)
            if self.has_masks:
                m = state.model
                if gaussians.has_rigid(p):  # the clusters' poses carry their Gaussians
                    drop |= prune_rules.escaped_at(dynamic_positions(p, m.times, self.config.deform), m.mid_poses(),
                                                   m.Ks, self.masks, pc)
                else:
                    drop |= prune_rules.escaped(p[f"{DYNAMIC}.means"], p[f"{DYNAMIC}.deform_means"], m.times,
                                                m.mid_poses(), m.Ks, self.masks, self.config.deform, pc)
            keep[DYNAMIC] = ~drop
        removed = int(sum((~k).sum() for k in keep.values()))
        if removed:
            for prefix, k in keep.items():
                state = state.resize_rows(prefix, keep=k)
        return state, removed


def densifying(state, densify_config, total: int) -> bool:
    """Whether the schedule step lies in densification's window [start, stop) of ``total`` steps."""
    return densify_config.start_fraction * total <= state.sched < densify_config.stop_fraction * total


class Densify(Plugin):
    """Every ``densify.every`` steps inside [start, stop) of the run: clone and split
    (``train/densify.py``) up to the clip's cap (``gaussian_cap`` of its ``pixels``, observed
    pixels at full resolution) and the dynamic set's own (``dynamic_gaussian_cap`` of
    ``moving_pixels``, the motion masks' pixels), with a generator seeded by (seed, step) so a resumed run draws the
    same children; notes the cap once and what each densification did."""

    name = "densify"

    def __init__(self, config: ExperimentConfig, extent: float, width: int, pixels: int, note=None,
                 moving_pixels: int = 0):
        self.config, self.extent, self.width = config, extent, width
        self.note = note if note is not None else (lambda m: None)
        dc = config.densify
        cap = gaussian_cap(dc, pixels)
        why = (f"{pixels} observed pixels / densify.pixels_per_gaussian = {dc.pixels_per_gaussian:g}, at most "
               f"densify.max_gaussians = {dc.max_gaussians}" if dc.pixels_per_gaussian > 0
               else "densify.max_gaussians; densify.pixels_per_gaussian = 0")
        self.dynamic_cap = dynamic_gaussian_cap(dc, moving_pixels)
        dyn = (f"; the dynamic set up to {self.dynamic_cap} ({moving_pixels} moving pixels / "
               f"densify.dynamic_pixels_per_gaussian = {dc.dynamic_pixels_per_gaussian:g})"
               if self.dynamic_cap and moving_pixels else "")  # no moving pixels: no dynamic set to cap
        self.note(f"densification: up to {cap} Gaussians ({why}){dyn}")
        self.densify_config = dataclasses.replace(dc, max_gaussians=cap)  # the clip's cap, built once

    def on_step(self, state):
        dc, total = self.densify_config, self.config.train.iters
        if not (entered_period(state, dc.every) and densifying(state, dc, total)):
            return state
        rng = np.random.default_rng((self.config.train.seed, state.step, 7))
        params, adam_state, rows, info = densify(state.params, state.adam, state.rows, dc, self.extent, self.width, rng,
                                                  self.dynamic_cap)
        state = state.replace(model=state.model.replace(params=params), adam=adam_state, rows=rows)
        if info["cloned"] or info["split"]:
            dyn = (f"; dynamic set: cloned {info['dynamic_cloned']}, split {info['dynamic_split']}"
                   if info["dynamic_cloned"] or info["dynamic_split"] else "")
            self.note(f"step {state.step}: densified (cloned {info['cloned']}, split {info['split']}{dyn}) -> "
                      f"{state.model.num_gaussians()} Gaussians")
        return state


class OpacityReset(Plugin):
    """Every ``densify.opacity_reset_every`` schedule steps inside densification's [start, stop):
    every opacity lowered to at most ``densify.opacity_reset_value``, its Adam moments zeroed
    (``train/densify.py``, ``reset_opacity``; 3DGS's opacity reset). Gaussians the loss does not
    raise again fall to the prune's floor: floaters and faint layers that help a few views only."""

    name = "opacity_reset"

    def __init__(self, config: ExperimentConfig, note=None):
        self.config = config
        self.note = note if note is not None else (lambda m: None)

    def on_step(self, state):
        dc, total = self.config.densify, self.config.train.iters
        if not (dc.opacity_reset_every and entered_period(state, dc.opacity_reset_every)
                and densifying(state, dc, total)):
            return state
        params, adam_state, lowered = reset_opacity(state.params, state.adam, dc.opacity_reset_value)
        self.note(f"step {state.step}: opacity reset to {dc.opacity_reset_value:g} ({lowered} of "
                  f"{state.model.num_gaussians()} lowered)")
        return state.replace(model=state.model.replace(params=params), adam=adam_state)


class NeighbourRefresh(Plugin):
    """The K nearest dynamic Gaussians of each dynamic Gaussian, by base position
    (``losses.smoothness.knn``), for L_ts's spatial term (docs/method.md §6); name "knn".

    Rebuilt on the initial model, every ``every`` schedule steps (``entered_period``), and at the
    end of any step whose pruning or densification changed the dynamic set: a per-row marker
    (``rows``: 1 on the rows the lists were built for) goes through ``state.resize_rows`` with
    the parameters, so removed rows change the count and appended rows arrive with a 0 marker,
    even when a prune and a densification leave the count unchanged. The lists (``state_dict``)
    and the marker (a row statistic) are checkpointed, so a resumed run uses the same lists.

    With ``at_time`` (L_iso's lists, name "iso_knn") the neighbours are found among the deformed
    positions at that time instead of the base positions: a base position is the deformed one
    minus the deformation at that time, which need not keep an object's points together.
    """

    name = "knn"
    MARK = "knn_built"

    def __init__(self, k: int, every: int, at_time=None, name: str = "knn"):
        self.k, self.every = int(k), int(every)
        self.at_time, self.name = at_time, name
        self.MARK = "knn_built" if name == "knn" else f"{name}_built"
        self.lists = None  # (N_dynamic, min(k, N_dynamic - 1)) int64, or None before the first build

    def rows(self, params):
        return {self.MARK: {p: np.zeros(num_rows(params, p)) for p in SETS}}

    def _build(self, params, deform):
        means = params.get(f"{DYNAMIC}.means")
        if means is not None and self.at_time is not None:
            if gaussians.has_rigid(params):  # where the clusters' poses put them
                means = dynamic_positions(params, [self.at_time], deform)[0]
            else:
                b = deform_basis(self.at_time, deform)[0]
                means = means + np.einsum("k,nkd->nd", b.astype(means.dtype), params[f"{DYNAMIC}.deform_means"])
        self.lists = knn(means, self.k) if means is not None else np.zeros((0, 0), dtype=np.int64)
        return self.lists

    def on_init(self, model):
        self._build(model.params, model.config.deform)

    def neighbours(self, params, deform=None):
        """The lists for these parameters (built now if there are none for this many rows);
        ``deform`` (the run's DeformConfig) is needed with ``at_time``."""
        if self.lists is None or self.lists.shape[0] != num_rows(params, DYNAMIC):
            self._build(params, deform)
        return self.lists

    def on_step(self, state):
        n = num_rows(state.params, DYNAMIC)
        mark = state.rows[self.MARK][DYNAMIC]
        resized = self.lists is None or self.lists.shape[0] != n or not np.all(mark > 0.0)
        if not (resized or entered_period(state, self.every)):
            return state
        self._build(state.params, state.model.config.deform)
        return state.replace(rows={**state.rows, self.MARK: {**state.rows[self.MARK], DYNAMIC: np.ones(n)}})

    def state_dict(self):
        return {} if self.lists is None else {"lists": self.lists}

    def load_state_dict(self, state):
        if "lists" in state:
            self.lists = np.asarray(state["lists"], dtype=np.int64)


class DepthMemory(Plugin):
    """What L_reproj (``train.terms.Reprojection``) reads besides the step's render; name
    "reproj_depths".

    - The matches of the video (``correspond.correspondences`` with the pose solver's settings,
      cached in the run folder, so the solver and the term compute them once), by frame:
      ``partners(f)`` lists (g, pts_f, pts_g) for every used pair of f. Computed (or read from
      the cache) at the first step, as the pose solver's: the set-up writes nothing into the run
      folder (``train/setup.py``).
      ``matches``, a list of (k, j, pts_k, pts_j), replaces them (matches of your own, tests).
    - Each frame's rendered depth from its own last step (``store``; NaN where alpha is below
      POSE_DEPTH_ALPHA_MIN) with the render's scale (sx, sy) to full-resolution pixels, read by
      the term as the partner's constant depth (``depth``). Checkpointed (``state_dict``), so a
      resumed run reads the same depths.
    """

    name = "reproj_depths"

    def __init__(self, images, masks, correspond_config, run_dir=None, note=None, matches=None):
        self.images, self.masks, self.correspond_config = images, masks, correspond_config
        self.run_dir, self.note = run_dir, (note if note is not None else (lambda m: None))
        self._by_frame = None if matches is None else self._index(matches)
        self.maps = {}  # frame -> ((h, w) depth, (2,) scale)

    @staticmethod
    def _index(matches):
        by_frame = {}
        for k, j, pts_k, pts_j in matches:
            pts_k, pts_j = np.asarray(pts_k, dtype=np.float64), np.asarray(pts_j, dtype=np.float64)
            by_frame.setdefault(int(k), []).append((int(j), pts_k, pts_j))
            by_frame.setdefault(int(j), []).append((int(k), pts_j, pts_k))
        return by_frame

    def _pairs(self):
        if self._by_frame is None:
            masks = self.masks if all(m is not None for m in self.masks) else None
            corr = correspondences(self.images, masks, self.correspond_config, self.run_dir)
            self._by_frame = self._index([(p.k, p.j, p.pts_k, p.pts_j) for p in corr.used])
            self.note(f"L_reproj: {sum(p.num_matches for p in corr.used)} matches in {len(corr.used)} frame pairs")
        return self._by_frame

    def partners(self, f):
        """[(g, pts_f (M, 2), pts_g (M, 2)), ...]: the matches of frame f with each partner g."""
        return self._pairs().get(int(f), [])

    def depth(self, g):
        """(depth map, (sx, sy)) of frame g's last step, or None before its first."""
        return self.maps.get(int(g))

    def store(self, f, depth, scale):
        self.maps[int(f)] = (np.array(depth, dtype=np.float64), np.asarray(scale, dtype=np.float64).copy())

    def state_dict(self):
        out = {}
        for f, (d, s) in self.maps.items():
            out[f"depth_{f}"], out[f"scale_{f}"] = d, s
        return out

    def load_state_dict(self, state):
        self.maps = {}
        for key, value in state.items():
            if key.startswith("depth_"):
                f = int(key[len("depth_"):])
                self.maps[f] = (np.asarray(value, dtype=np.float64), np.asarray(state[f"scale_{f}"], dtype=np.float64))
