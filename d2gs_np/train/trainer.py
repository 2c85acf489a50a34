"""The trainer: stages, a seeded frame sampler, Adam over named blocks, hooks, checkpoints.

One training step (``Trainer.step``):
  1. pick frame k (seeded permutation per epoch, reproducible after resume),
  2. pick the render scale of the progressive schedule (docs/method.md §7) and fetch
     the area-downsampled target and scaled intrinsics from the cache,
  3. render: with the blur model, the mean of n renders along the exposure's
     SE(3) path (docs/method.md §4); without it, one sharp render at the given pose,
  4. photometric loss and its gradient, back through renderer, blur model,
     trajectory model and deformation to every named parameter block,
  5. Adam on the blocks the current stage trains.

Stages (docs/method.md §8): ``warmup`` trains the static set and the camera model
on static pixels only (dynamic Gaussians are not rendered, masked pixels carry
no loss); ``deform`` trains the dynamic set and its deformation; ``joint``
trains everything. Stages a scene does not need are left out (no dynamic set:
no ``deform`` stage) and the run log says so.

Hooks: callables ``hook(trainer, info)`` run after every step with the step's
record; later components (the Gauss-Newton pose refinement, densification)
plug in here without changing the loop.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from d2gs_np import blur as blur_model
from d2gs_np import trajectory as traj_model
from d2gs_np.data.scene import Scene
from d2gs_np.geometry.se3 import se3_exp, se3_interpolate
from d2gs_np.losses.photometric import photometric_bwd, photometric_fwd
from d2gs_np.losses.ssim import SSIM_WINDOW
from d2gs_np.optim import adam
from d2gs_np.render import render_bwd, render_fwd
from d2gs_np.scene import gaussians
from d2gs_np.scene.initialize import initialize_points
from d2gs_np.scene.motion_init import initialize_deformation
from d2gs_np.scene.model import evaluate_bwd, evaluate_fwd
from d2gs_np.train.checkpoint import atomic_write_text, load_checkpoint, save_checkpoint
from d2gs_np.train.config import ExperimentConfig
from d2gs_np.train import prune as prune_rules
from d2gs_np.train.densify import GradientStats, densify
from d2gs_np.train.log import RunLog, Stopwatch, psnr_from_mse
from d2gs_np.train.schedule import TargetCache, schedule_step

CHECKPOINT_NAME = "checkpoint.npz"
FINAL_NAME = "final.npz"
PER_FRAME_BLOCKS = ("camera.xi_start", "camera.xi_end")  # one row per frame: row-sparse Adam


def latest_checkpoint(run_dir):
    """The checkpoint of a run with the most steps (final.npz or checkpoint.npz), or None."""
    best, best_step = None, -1
    for name in (CHECKPOINT_NAME, FINAL_NAME):
        path = Path(run_dir) / name
        if path.exists():
            step = int(load_checkpoint(path)[1]["step"])
            if step > best_step:
                best, best_step = path, step
    return best


@dataclass(frozen=True)
class Stage:
    name: str
    start: int  # first step (inclusive)
    stop: int  # last step (exclusive)
    trainable: tuple  # block-name prefixes trained in this stage
    static_only: bool  # render only the static set and ignore masked (moving) pixels


@dataclass(frozen=True)
class Components:
    """What this run models; decided from the scene and the config (docs/method.md §9)."""

    dynamic: bool
    blur: bool
    learn_exposure: bool
    exposure_fraction: float  # used when not learned

    def left_out(self) -> list:
        out = []
        if not self.dynamic:
            out += ["dynamic_set", "deformation"]
        if not self.blur:
            out += ["blur_model", "trajectory_model"]
        out += ["pose_refinement"]  # Gauss-Newton endpoint refinement: a later component
        out += ["loss_ts", "loss_gs", "loss_reproj", "loss_freq"]  # regularisers: a later component
        return out


def decide_components(scene: Scene, config: ExperimentConfig, log: Optional[RunLog] = None) -> Components:
    """Apply docs/method.md §9: leave out what the scene does not need, and say why."""
    tc = config.train
    say = log.note if log is not None else (lambda m: None)
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
        say(f"trajectory model: {config.trajectory.kind}")
    say("pose refinement (Gauss-Newton on reprojection residuals): not run (not part of this version)")
    say("regularisers L_ts, L_gs, L_reproj, L_freq: not applied (not part of this version); loss = L_render")
    return Components(dynamic=dynamic, blur=blur, learn_exposure=learn, exposure_fraction=float(ef or 0.0))


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


def scene_extent(poses, scene_scale=None) -> float:
    """1.1 x the radius of the camera centres around their mean (3DGS's 'cameras_extent'), which
    scales the position learning rates. A camera that does not move (tripod) has no such radius:
    then the scene's scene_scale is used, else 1."""
    centres = np.array([-T[:3, :3].T @ T[:3, 3] for T in poses])
    r = float(np.max(np.linalg.norm(centres - centres.mean(0), axis=1))) * 1.1
    if r > 1e-9 * max(1.0, float(np.max(np.abs(centres)))):
        return r
    return float(scene_scale) if scene_scale else 1.0


def size_extent(poses, points, camera_extent) -> float:
    """The scene's size for pruning's oversized rule: the larger of the camera extent and 1.1 x the
    90th percentile distance of the initial points from the camera centres' mean.

    3DGS measures both rules in units of the camera extent, which for a camera that circles the
    scene is the scene's size. A hand-held camera looking forward moves little against the depth
    it sees: on the suite's photo_room the camera radius is 0.51 against walls 5.5 away, so the
    oversized rule (0.1 x extent = 0.051, two pixels at the wall) pruned every seed larger than
    two pixels and the sharp render lost 3.2 dB (25.76 against 29.00 dB with the rule off,
    700 steps). The point cloud says how large the scene is, whichever way the camera moves.
    Densification keeps the camera extent for its clone/split boundary: measured in this unit it
    clones where it should split, and fine photographic detail fits worse (photo_room 28.23
    against 29.00 dB, 700 steps)."""
    if points is None or len(points) == 0:
        return float(camera_extent)
    centres = np.array([-T[:3, :3].T @ T[:3, 3] for T in poses])
    d = np.linalg.norm(np.asarray(points, dtype=np.float64) - centres.mean(0), axis=1)
    return max(float(camera_extent), 1.1 * float(np.percentile(d, 90)))


class Trainer:
    def __init__(self, scene: Scene, config: ExperimentConfig, run_dir, hooks: tuple = (), resume: bool = False):
        validate_scene_for_training(scene)
        self.scene = scene
        self.config = config
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.hooks: list = list(hooks)
        self._restored_stats = {}
        self.frames = scene.frames
        self.num_frames = len(self.frames)
        self.times = np.array([f.time for f in self.frames], dtype=np.float64)
        self.poses_est = np.stack([f.cam_T_world for f in self.frames]).astype(np.float64)
        self.background = np.asarray(config.train.background, dtype=np.float64)
        self.cache = TargetCache.from_scene(scene, mask_threshold=config.schedule.mask_threshold)
        self.stopwatch = Stopwatch()
        self.step_index = 0
        self.extent = scene_extent(self.poses_est, scene.scene_scale)  # scales the position learning rates
        self.size_extent = self.extent  # the oversized rule's unit; set from the initial points (size_extent)

        if resume:
            ckpt = latest_checkpoint(self.run_dir)
            if ckpt is None:
                raise FileNotFoundError(f"--resume: no checkpoint in {self.run_dir}; train without --resume first")
            self.log = RunLog(self.run_dir, quiet=config.train.quiet, resume=True)
            self._restore(ckpt)
        else:
            for stale in (CHECKPOINT_NAME, FINAL_NAME, "metrics.json"):  # a fresh run never mixes with an old one
                (self.run_dir / stale).unlink(missing_ok=True)
            self.log = RunLog(self.run_dir, quiet=config.train.quiet, resume=False)
            atomic_write_text(self.run_dir / "config.json", config.to_json())
            self.components = decide_components(scene, config, self.log)
            self._initialise()
        self.stages = self._make_stages()
        self.adam_config = self._make_adam_config()
        self.grad_stats = GradientStats(self.params) if config.densify.enabled else None
        if self.grad_stats is not None and self._restored_stats:
            for (slot, p), v in self._restored_stats.items():
                getattr(self.grad_stats, slot)[p] = v
        self._last_v_means2d = None
        # schedule step of the previous step (periodic housekeeping fires when it enters a new period)
        self._last_sched = self._restored_last_sched if resume else self.step_index - 1

    # ------------------------------------------------------------------ set-up
    def _initialise(self):
        cfg = self.config
        rng = np.random.default_rng(cfg.train.seed)
        t0 = time.perf_counter()
        s_pts, s_col, d_pts, d_col, info = initialize_points(self.scene, cfg.init, rng)
        if not self.components.dynamic:
            d_pts, d_col = None, None
        self.size_extent = size_extent(self.poses_est, s_pts, self.extent)
        self.params = gaussians.init_params(s_pts, s_col, d_pts, d_col, deform_config=cfg.deform, rng=rng)
        if d_pts is not None and cfg.motion_init.enabled:
            means, coefs, minfo = initialize_deformation(
                self.scene, d_pts, info["dynamic_source_frames"], info["dynamic_source_pixels"], cfg.deform,
                cfg.motion_init)
            self.params["dynamic.means"] = means
            self.params["dynamic.deform_means"] = coefs
            self.log.note(f"dynamic motion initialised from {minfo['num_tracks']} mask tracks "
                          f"({minfo['num_tracked_seeds']} of {len(means)} seeds tracked)")
        self.log.note(
            f"initialised {gaussians.num_static(self.params)} static and {gaussians.num_dynamic(self.params)} "
            f"dynamic Gaussians in {time.perf_counter() - t0:.1f}s ({_short(info)})")
        if self.components.blur:
            self.params.update(traj_model.init_trajectory(
                cfg.trajectory, self.poses_est, self.times, rng,
                exposure_fraction=None if self.components.learn_exposure else self.components.exposure_fraction))
            if self.components.learn_exposure:
                self.params.update(blur_model.init_exposure())
        self.adam_state = adam.adam_init(self.params)

    def _make_stages(self) -> list:
        tc = self.config.train
        n = tc.iters
        w = int(round(tc.warmup_fraction * n))
        d = int(round(tc.deform_fraction * n)) if self.components.dynamic else 0
        stages = []
        if w > 0:
            # camera.exposure_logit is not trained here: only the static set is rendered, and tau
            # only moves the dynamic set's sub-frame times, so its gradient is exactly zero.
            stages.append(Stage("warmup", 0, w, ("static.", "camera.xi", "posenet."), True))
        if d > 0:
            stages.append(Stage("deform", w, w + d, ("dynamic.",), False))
        stages.append(Stage("joint", w + d, n, ("static.", "dynamic.", "camera.", "posenet."), False))
        return [s for s in stages if s.stop > s.start]

    def _make_adam_config(self):
        lr = self.config.train.lr
        n = self.config.train.iters
        e = self.extent
        rates = {}
        for name in self.params:
            kind = name.split(".", 1)[1] if "." in name else name
            if name.startswith(("camera.xi", "posenet.")):
                # Per-frame rows are visited once per epoch: decay over the visits a row gets.
                visits = n // self.num_frames + 1 if name.startswith("camera.xi") else n
                rates[name] = adam.exponential_decay(lr.camera, lr.camera_final, visits)
            elif name == "camera.exposure_logit":
                rates[name] = lr.exposure
            elif kind == "means":
                rates[name] = adam.exponential_decay(lr.means * e, lr.means_final * e, n)
            elif kind == "deform_means":
                rates[name] = adam.exponential_decay(lr.deform * e, lr.means_final * e, n)
            elif kind.startswith("deform_"):
                rates[name] = lr.deform_other
            else:
                rates[name] = getattr(lr, kind)
        return adam.AdamConfig(lrs=rates)

    def stage_at(self, step: int) -> Stage:
        for s in self.stages:
            if s.start <= step < s.stop:
                return s
        return self.stages[-1]

    # ------------------------------------------------------------------ one step
    def scale_at(self, step: int) -> float:
        """Render scale of the progressive schedule, raised if needed so that the smallest image
        side keeps at least one SSIM window (11 px)."""
        if not self.config.train.progressive:
            return 1.0
        r = self.config.schedule.scale(step, self.config.train.iters)
        if self.config.loss.lambda_ssim > 0:
            side = min(min(f.width, f.height) for f in self.frames)
            r = max(r, min(1.0, SSIM_WINDOW / side))
        return r

    def frame_for_step(self, step: int) -> int:
        """Seeded permutation per epoch; depends only on (seed, step), so resuming reproduces it."""
        epoch, pos = divmod(step, self.num_frames)
        perm = np.random.default_rng((self.config.train.seed, epoch)).permutation(self.num_frames)
        return int(perm[pos])

    def exposure_tau(self, params=None):
        params = self.params if params is None else params
        if not self.components.blur:
            return 0.0
        if self.components.learn_exposure:
            tau, _ = blur_model.exposure_fwd(params, self.num_frames)
            return float(tau)
        return blur_model.exposure_from_scene(self.components.exposure_fraction, self.num_frames)

    def endpoints(self, frame_indices, params=None):
        params = self.params if params is None else params
        (xs, xe), saved = traj_model.endpoints_fwd(
            params, self.config.trajectory, np.asarray(frame_indices), self.poses_est, self.times)
        return xs, xe, saved

    def mid_pose(self, k: int, params=None) -> np.ndarray:
        """Optimised mid-exposure pose of frame k (geodesic midpoint of the endpoints)."""
        params = self.params if params is None else params
        return mid_exposure_pose(params, self.config, self.components.blur, self.poses_est, self.times, k)

    def render_frame(self, k: int, scale: float, static_only: bool, params=None):
        """Training forward of frame k at a render scale: the blurry render with the blur model,
        else a sharp render at the given pose. Returns (out, backward closure v_image -> v_params,
        target record of the schedule's cache)."""
        params = self.params if params is None else params
        cfg = self.config
        tgt = self.cache.get(k, scale)
        img_params = {n: v for n, v in params.items() if n.startswith("static.")} if static_only else params
        f = self.frames[k]
        if self.components.blur:
            xs, xe, tsaved = self.endpoints([k], params)
            tau = self.exposure_tau(params)
            out, bsaved = blur_model.blur_render_fwd(
                img_params, f.time, tau, self.poses_est[k], xs[0], xe[0], tgt.K, tgt.width, tgt.height,
                self.background, cfg.blur, cfg.deform, cfg.render)

            def backward(v_image):
                v_p, v_xs, v_xe, v_tau, aux = blur_model.blur_render_bwd(bsaved, v_image, return_aux=True)
                self._last_v_means2d = aux["v_means2d"].sum(axis=0) * (tgt.width / f.width)  # full-res px
                v_p = dict(v_p)
                v_p.update(traj_model.endpoints_bwd(tsaved, v_xs[None], v_xe[None]))
                if self.components.learn_exposure:
                    _, esaved = blur_model.exposure_fwd(params, self.num_frames)
                    v_p.update(blur_model.exposure_bwd(esaved, v_tau))
                return v_p
        else:
            ri, esaved = evaluate_fwd(img_params, f.time, cfg.deform)
            out, rsaved = render_fwd(ri["means"], ri["quats"], ri["scales"], ri["opacities"], ri["colors"],
                                     self.poses_est[k], tgt.K, tgt.width, tgt.height, self.background, cfg.render)

            def backward(v_image):
                g = render_bwd(rsaved, v_image)
                self._last_v_means2d = g["means2d"] * (tgt.width / f.width)  # full-res px
                v_p, _ = evaluate_bwd(esaved, {n: g[n] for n in ("means", "quats", "scales", "opacities", "colors")})
                return v_p
        return out, backward, tgt

    def step(self, step: int, sched: Optional[int] = None) -> dict:
        """One training step. ``sched`` is the step the schedules are read at (``schedule_step``:
        further along than ``step`` when a time budget binds); default ``step``."""
        sched = step if sched is None else sched
        stage = self.stage_at(sched)
        k = self.frame_for_step(step)
        scale = self.scale_at(sched)
        lr_scale = sched / step if sched > step > 0 else 1.0
        out, backward, tgt = self.render_frame(k, scale, stage.static_only)
        image = out["image"]
        ignore = tgt.mask if (stage.static_only and tgt.mask is not None) else None
        # Moving pixels carry no loss while only the static set is rendered (warm-up stage).
        weights = None if ignore is None else (~ignore).astype(image.dtype)
        lam = self.config.loss.lambda_ssim
        if weights is not None:
            if not weights.any():  # every pixel moving: nothing static to learn from in this frame
                return {"step": step, "frame": k, "stage": stage.name, "loss": float("nan"),
                        "train_psnr": float("nan"), "scale": scale, "width": tgt.width, "height": tgt.height}
            pad = SSIM_WINDOW // 2
            if lam > 0 and not weights[pad:-pad or None, pad:-pad or None].any():
                lam = 0.0  # no static pixel inside the SSIM interior at this size: L1 only
        loss, lsaved = photometric_fwd(image, tgt.image, lam, mask=weights)
        v_image = photometric_bwd(lsaved, 1.0)
        grads = backward(v_image)
        if self.grad_stats is not None:
            visible = (np.asarray(out["radii"]).reshape(len(self._last_v_means2d), -1) > 0).all(axis=1)
            self.grad_stats.add(self._last_v_means2d, visible.astype(np.float64),
                                gaussians.num_static(self.params))
        grads = {n: g for n, g in grads.items() if n.startswith(stage.trainable) and n in self.params}
        # Per-frame endpoint rows of other frames get no gradient this step: update only row k
        # (row-sparse Adam), so they do not drift on stale momentum.
        sparse = {n: grads.pop(n) for n in list(grads) if n in PER_FRAME_BLOCKS}
        self.params, self.adam_state = adam.adam_update(grads, self.adam_state, self.params, self.adam_config,
                                                        lr_step_scale=lr_scale)
        if sparse:
            self.params, self.adam_state = adam.adam_update_rows(
                sparse, {n: [k] for n in sparse}, self.adam_state, self.params, self.adam_config,
                lr_step_scale=lr_scale)
        mse = float(np.mean((image - tgt.image) ** 2)) if ignore is None else float(
            np.mean(((image - tgt.image) ** 2)[~ignore]))
        return {"step": step, "frame": k, "stage": stage.name, "loss": float(loss), "train_psnr": psnr_from_mse(mse),
                "scale": scale, "width": tgt.width, "height": tgt.height}

    # ------------------------------------------------------------------ housekeeping
    def prune(self):
        """Remove transparent and oversized Gaussians, and dynamic ones that escaped their masks
        (``train/prune.py``); Adam state and densification statistics follow the same masks."""
        thr = self.config.train.prune_opacity
        pc = self.config.prune
        p = self.params
        drop_s = prune_rules.transparent(p["static.opacity_logits"], thr) | prune_rules.oversized(
            p["static.log_scales"], self.size_extent, pc.max_scale_fraction)
        keep_s = ~drop_s
        keep_d = None
        if gaussians.has_dynamic(p):
            drop_d = prune_rules.transparent(p["dynamic.opacity_logits"], thr) | prune_rules.oversized(
                p["dynamic.log_scales"], self.size_extent, pc.max_scale_fraction)
            if self.scene.has_masks:
                drop_d |= prune_rules.escaped(
                    p["dynamic.means"], p["dynamic.deform_means"], self.times,
                    np.stack([self.mid_pose(k) for k in range(self.num_frames)]),
                    np.stack([f.K for f in self.frames]), [f.mask for f in self.frames], self.config.deform, pc)
            keep_d = ~drop_d
        removed = int((~keep_s).sum() + (0 if keep_d is None else (~keep_d).sum()))
        if removed == 0:
            return 0
        self.params = gaussians.prune(self.params, keep_s, keep_d)
        self.adam_state = adam.adam_select(self.adam_state, "static", keep_s)
        if keep_d is not None:
            self.adam_state = adam.adam_select(self.adam_state, "dynamic", keep_d)
        if self.grad_stats is not None:
            self.grad_stats.select("static", keep_s)
            if keep_d is not None:
                self.grad_stats.select("dynamic", keep_d)
        return removed

    def heldout_psnr(self) -> Optional[float]:
        """PSNR of sharp renders at the optimised mid-exposure poses against the sharp frames (if the
        scene has them), on ``eval_frames`` evenly spaced frames, at full resolution."""
        if not self.scene.has_sharp:
            return None
        idx = np.unique(np.linspace(0, self.num_frames - 1, self.config.train.eval_frames).round().astype(int))
        mses = []
        for k in idx:
            img = self.render_sharp(k)
            mses.append(float(np.mean((img - self.frames[k].sharp) ** 2)))
        return psnr_from_mse(float(np.mean(mses)))

    def render_sharp(self, k: int, params=None) -> np.ndarray:
        """Sharp render of training frame k at its optimised mid-exposure pose and time, full resolution."""
        params = self.params if params is None else params
        f = self.frames[k]
        return render_at(params, self.config, f.time, self.mid_pose(k, params), f.K, f.width, f.height,
                         self.background)

    def num_gaussians(self) -> int:
        return gaussians.num_static(self.params) + gaussians.num_dynamic(self.params)

    def checkpoint(self, final: bool = False):
        arrays = {f"params/{n}": v for n, v in self.params.items()}
        for slot, blocks in self.adam_state.items() if isinstance(self.adam_state, dict) else []:
            if isinstance(blocks, dict):
                for n, v in blocks.items():
                    arrays[f"adam/{slot}/{n}"] = v
            else:
                arrays[f"adam/{slot}"] = np.asarray(blocks)
        if self.grad_stats is not None:  # densification statistics, so a resume is exact
            for p in ("static", "dynamic"):
                arrays[f"densify/sum/{p}"] = self.grad_stats.sum[p]
                arrays[f"densify/count/{p}"] = self.grad_stats.count[p]
        meta = {
            "step": self.step_index, "seconds": self.stopwatch.seconds(), "config": self.config.to_dict(),
            "components": self.components.__dict__, "left_out": self.components.left_out(),
            "poses_est": self.poses_est.tolist(), "times": self.times.tolist(), "final": final,
            "last_sched": int(self._last_sched), "size_extent": float(self.size_extent),
            "scene_root": str(Path(self.scene.root).resolve()) if self.scene.root is not None else None,
            "K": [np.asarray(f.K).tolist() for f in self.frames], "width": [int(f.width) for f in self.frames],
            "height": [int(f.height) for f in self.frames],
        }
        save_checkpoint(self.run_dir / (FINAL_NAME if final else CHECKPOINT_NAME), arrays, meta)
        self.log.save()

    def _restore(self, path):
        arrays, meta = load_checkpoint(path)
        saved_cfg = ExperimentConfig.from_dict(meta["config"])
        # A resumed run continues the saved experiment: only the run length and output may change.
        free = {"iters", "time_budget", "quiet"}
        changed = [f"train.{k}" for k, v in self.config.train.__dict__.items()
                   if k not in free and getattr(saved_cfg.train, k) != v]
        changed += [k for k in saved_cfg.__dict__ if k != "train" and getattr(saved_cfg, k) != getattr(self.config, k)]
        if changed:
            raise ValueError(f"--resume with a config that differs from the saved run in {changed}; resume with the "
                             f"run's own config (RUN/config.json), changing only {sorted(free)}")
        if len(meta["times"]) != self.num_frames or not np.allclose(meta["times"], self.times):
            raise ValueError(f"--resume: the scene's frames do not match the run in {path.parent}")
        self.params = {k[len("params/"):]: v for k, v in arrays.items() if k.startswith("params/")}
        self._restored_stats = {tuple(k.split("/")[1:3]): v for k, v in arrays.items() if k.startswith("densify/")}
        state = {}
        for k, v in arrays.items():
            if k.startswith("adam/"):
                parts = k.split("/", 2)
                if len(parts) == 3:
                    state.setdefault(parts[1], {})[parts[2]] = v
                else:
                    state[parts[1]] = v.item() if v.ndim == 0 else v
        self.adam_state = state
        self.step_index = int(meta["step"])
        self._restored_last_sched = int(meta.get("last_sched", self.step_index - 1))
        self.size_extent = float(meta.get("size_extent", self.extent))
        self.stopwatch = Stopwatch(meta["seconds"])
        self.components = Components(**meta["components"])
        self.log.truncate(self.step_index)
        self.log.note(f"resumed from {path} at step {self.step_index} ({meta['seconds']:.1f}s of training)")

    # ------------------------------------------------------------------ the loop
    def run(self) -> dict:
        tc = self.config.train
        total = tc.iters
        t_start = time.perf_counter()
        t_jit = time.perf_counter()
        _warm_up_kernels(self.config)
        self.log.note(f"JIT warm-up (compile or cache load) took {time.perf_counter() - t_jit:.1f}s, not counted "
                      "as training time")
        if self.step_index == 0:
            self.log.note(f"training {total} steps; stages: " + ", ".join(
                f"{s.name} [{s.start}, {s.stop})" for s in self.stages))
        last_stage = None
        info = {"loss": float("nan"), "train_psnr": float("nan")}
        budget = tc.time_budget
        dc = self.config.densify
        while self.step_index < total:
            step = self.step_index
            # The step the schedules are read at: the step itself, or further along when a time
            # budget binds, so a budgeted run finishes its schedule (schedule.training_progress).
            sched = schedule_step(step, self.stopwatch.seconds(), total, budget)
            stage = self.stage_at(sched)
            if stage.name != last_stage:
                self.log.note(f"stage {stage.name} from step {step}" + (f" (schedule step {sched})"
                                                                        if sched != step else ""))
                last_stage = stage.name
            self.stopwatch.start()
            info = self.step(step, sched)
            for hook in self.hooks:
                hook(self, info)
            out_of_time = budget is not None and self.stopwatch.seconds() >= budget
            is_last = step + 1 >= total or out_of_time
            heldout = None
            if tc.eval_every and (step % tc.eval_every == 0 or is_last):
                # Evaluated on the model the Adam step produced, before pruning and densification
                # change it (a split moves its children apart and costs a few dB for some steps;
                # eval_every and the densify period share multiples, so evaluating after them would
                # log only those transients). Not counted as training time.
                self.stopwatch.pause()
                heldout = self.heldout_psnr()
                self.stopwatch.start()
            # Periodic housekeeping fires when the schedule step enters a new period (without a
            # budget: exactly at multiples of the period, as 3DGS).
            prev = self._last_sched if budget is not None else step - 1
            self._last_sched = sched
            if (tc.prune_every and sched > 0 and sched // tc.prune_every > prev // tc.prune_every
                    and sched < int(0.9 * total)):
                self.prune()
            if (dc.enabled and sched > 0 and sched // dc.every > prev // dc.every
                    and dc.start_fraction * total <= sched < dc.stop_fraction * total):
                self.params, self.adam_state, self.grad_stats, dinfo = densify(
                    self.params, self.adam_state, self.grad_stats, dc, self.extent,
                    max(f.width for f in self.frames), np.random.default_rng((tc.seed, step, 7)))
                if dinfo["cloned"] or dinfo["split"]:
                    self.log.note(f"step {step}: densified (cloned {dinfo['cloned']}, split {dinfo['split']}) -> "
                                  f"{self.num_gaussians()} Gaussians")
            self.stopwatch.pause()
            self.step_index = step + 1
            seconds = self.stopwatch.seconds()
            if step % tc.log_every == 0 or is_last or heldout is not None:
                self.log.row(step=step, seconds=round(seconds, 4), stage=stage.name, loss=info["loss"],
                             train_psnr=info["train_psnr"], heldout_psnr=heldout, scale=round(info["scale"], 4),
                             num_gaussians=self.num_gaussians())
                self.log.progress(self.step_index, total, seconds, info["loss"], info["train_psnr"], stage.name)
            if tc.checkpoint_every and self.step_index % tc.checkpoint_every == 0 and not is_last:
                self.checkpoint()
            if out_of_time and step + 1 < total:
                self.log.note(f"time budget of {budget:.0f}s reached at step {self.step_index} (schedule step "
                              f"{sched} of {total}: schedule complete); stopping")
                break
        self.checkpoint(final=True)
        wall = time.perf_counter() - t_start
        self.log.note(f"finished at step {self.step_index}: {self.stopwatch.seconds():.1f}s of training "
                      f"({wall:.1f}s wall including evaluation)")
        self.log.save()
        return {"steps": self.step_index, "train_seconds": self.stopwatch.seconds(), **info}


def _warm_up_kernels(config: ExperimentConfig):
    """Compile (or load from the Numba cache) the renderer's kernels on one tiny Gaussian so the
    first training step's time is training, not JIT."""
    one = np.ones((1, 3))
    out, saved = render_fwd(np.array([[0.0, 0.0, 2.0]]), np.array([[1.0, 0.0, 0.0, 0.0]]), 0.1 * one,
                            np.array([0.5]), 0.5 * one, np.eye(4), np.array([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]),
                            8, 8, np.zeros(3), config.render)
    render_bwd(saved, np.ones_like(out["image"]))


def mid_exposure_pose(params, config: ExperimentConfig, blur_on: bool, poses_est, times, k: int) -> np.ndarray:
    """Mid-exposure cam_T_world of frame k: the geodesic midpoint of the optimised exposure
    endpoints with the blur model, the given estimate without it."""
    if not blur_on:
        return np.array(poses_est[k], dtype=np.float64)
    (xs, xe), _ = traj_model.endpoints_fwd(params, config.trajectory, np.array([k]), poses_est, times)
    Ts = se3_exp(xs[0]) @ poses_est[k]
    Te = se3_exp(xe[0]) @ poses_est[k]
    return se3_interpolate(Ts, Te, 0.5)


def render_at(params, config: ExperimentConfig, t: float, cam_T_world, K, width, height, background=None):
    """Sharp render of a parameter set at time t and pose: the image (H, W, 3)."""
    bg = np.asarray(config.train.background if background is None else background, dtype=np.float64)
    scene_params = {n: v for n, v in params.items() if n.startswith(("static.", "dynamic."))}
    ri, _ = evaluate_fwd(scene_params, float(t), config.deform)
    out, _ = render_fwd(ri["means"], ri["quats"], ri["scales"], ri["opacities"], ri["colors"],
                        np.asarray(cam_T_world, dtype=np.float64), np.asarray(K, dtype=np.float64),
                        int(width), int(height), bg, config.render)
    return out["image"]


def _short(info: dict) -> str:
    items = []
    for k, v in info.items():
        if isinstance(v, (int, float, np.integer, np.floating)):
            items.append(f"{k}={v:.3g}" if isinstance(v, (float, np.floating)) else f"{k}={v}")
    return ", ".join(items[:6])
