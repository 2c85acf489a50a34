"""The model a run trains: Gaussians, camera state, frame times and components in one record.

The trainer trains it, and evaluation, the command line and notebooks use it, all through the
same ``render`` and ``mid_pose`` (docs/method.md §4, §10). It holds plain arrays:

- ``params``: the named blocks Adam trains (docs/method.md §2, §4): the scene (``static.*``,
  ``dynamic.*``) and, with the blur model, the endpoint model (``camera.xi_start`` /
  ``camera.xi_end`` or ``posenet.*``) and a learned exposure length (``camera.exposure_logit``).
- camera state: ``poses_est`` (N, 4, 4), the given mid-exposure estimates, never changed (the
  'initial' trajectory of evaluation); ``poses_init`` (N, 4, 4), the poses training started
  from: the given ones, or their bundle adjustment before training (``pose_init.py``), which the
  pose solver's prior holds; ``poses_ref`` (N, 4, 4), the reference poses T̂_k the endpoints
  perturb, a copy of ``poses_init`` until a pose solver refines them (docs/method.md §5);
  intrinsics ``Ks`` (N, 3, 3) and image sizes of the training frames.
- ``times`` (N,), ``components`` (what the run models, ``train/components.py``) and the config.

The mid-exposure pose of frame k is the geodesic midpoint of its exposure endpoints with the blur
model, and T̂_k without it (where n = 1 renders).

Validation happens once: ``validate()`` checks every block, pose, time and intrinsic matrix, and
``from_scene`` / ``from_checkpoint`` call it. The training forward of a frame
(``frame_render_fwd`` / ``frame_render_bwd``) trusts a validated model and runs the private,
unvalidated paths of the trajectory, blur, scene and render modules: checking the blocks of
every sub-frame render of every step cost a measurable share of the step (the closing note of
the trainer split). Anything that writes the model outside the optimiser (a pose solver
plugin) calls ``validate()`` on what it wrote. The model is immutable; ``replace`` returns a
changed copy sharing unchanged arrays.
"""
from __future__ import annotations

import dataclasses
import numbers
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from d2gs_np.blur import endpoints as traj_model
from d2gs_np.blur.exposure import EXPOSURE_BLOCK, exposure_bwd, exposure_from_scene, exposure_fwd, init_exposure
from d2gs_np.blur.render import _blur_render_fwd, blur_render_bwd
from d2gs_np.blur.views import backward_subset, frame_views
from d2gs_np.geometry.camera import check_intrinsics
from d2gs_np.geometry.se3 import check_rigid, se3_exp, se3_interpolate
from d2gs_np.render import render_fwd
from d2gs_np.render.api import _render_bwd, _render_fwd
from d2gs_np.scene import gaussians
from d2gs_np.scene.gaussians import DYNAMIC, SCENE_PREFIXES, STATIC
from d2gs_np.scene.initialize import initialize_points, pixel_scale_cap
from d2gs_np.scene.render_inputs import RENDER_FIELDS, _render_inputs_bwd, _render_inputs_fwd, render_inputs_fwd
from d2gs_np.scene.motion_init import initialize_deformation
from d2gs_np.train.components import Components
from d2gs_np.train.config import ExperimentConfig

__all__ = ["Model", "SCENE_PREFIXES", "frame_render_fwd", "frame_render_bwd"]

PARAMS_KEY = "params/"  # checkpoint array keys of the blocks
POSES_REF_KEY = "camera/poses_ref"
POSES_INIT_KEY = "camera/poses_init"


@dataclass(frozen=True, eq=False)
class Model:
    params: dict  # block name -> array (module docstring)
    config: ExperimentConfig
    components: Components
    times: np.ndarray  # (N,) mid-exposure normalised times of the training frames
    poses_est: np.ndarray  # (N, 4, 4) given cam_T_world estimates
    poses_ref: np.ndarray  # (N, 4, 4) reference cam_T_world the endpoints perturb
    Ks: np.ndarray  # (N, 3, 3) intrinsics of the training frames
    widths: tuple  # (N,) ints
    heights: tuple  # (N,) ints
    poses_init: Optional[np.ndarray] = None  # (N, 4, 4) where training started; None: poses_est

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_scene(cls, scene, config: ExperimentConfig, components: Components, note=None,
                   poses=None, anchor_points=None) -> "Model":
        """The initial model of a scene (docs/method.md §8): initial static and dynamic points
        (``scene/initialize.py``), motion from mask tracks (``scene/motion_init.py``), the endpoint
        model and the exposure length. One seeded generator (``config.train.seed``) draws all of it,
        in this order. ``poses`` (N, 4, 4): start from these instead of the scene's given poses
        (the bundle adjustment of ``pose_init.py``); the given ones stay ``poses_est``.
        ``anchor_points`` (P, 3): that adjustment's points, which depth priors are aligned to."""
        say = note if note is not None else (lambda m: None)
        rng = np.random.default_rng(config.train.seed)
        given = np.stack([f.cam_T_world for f in scene.frames]).astype(np.float64)
        if poses is not None:
            poses = np.ascontiguousarray(poses, dtype=np.float64)
            if poses.shape != given.shape:
                raise ValueError(f"Model.from_scene: poses must have shape {given.shape}; got {poses.shape}")
            check_rigid(poses, "Model.from_scene poses")
            scene = dataclasses.replace(scene, frames=[dataclasses.replace(f, cam_T_world=P)
                                                       for f, P in zip(scene.frames, poses)])
        frames = scene.frames
        times = np.array([f.time for f in frames], dtype=np.float64)
        poses = np.stack([f.cam_T_world for f in frames]).astype(np.float64)
        t0 = time.perf_counter()
        s_pts, s_col, d_pts, d_col, info = initialize_points(scene, config.init, rng, anchor_points=anchor_points)
        if "auto" in (config.init.static_depth, config.init.dynamic_depth):
            say(f"seed depths decided by the scene (init.static_depth / dynamic_depth = 'auto'): static "
                f"{info['static_depth']}, dynamic {info['dynamic_depth']}, as the scene has "
                + ("depth priors" if scene.has_depth_prior else "no depth priors"))
        if not components.dynamic:
            d_pts, d_col = None, None
        elif info.get("dynamic_depth_prior") is not None:
            pi = info["dynamic_depth_prior"]
            failed = "".join(f"; frame {k}: {why}" for k, why in sorted(pi["failed"].items())[:3])
            rest = info["num_dynamic"] - pi["seeds_from_prior"]
            say(f"dynamic seeds at the depth prior aligned to {pi['reference']} in {pi['aligned']} of "
                f"{pi['frames']} frames (init.depth_prior_space = {config.init.depth_prior_space}; median "
                f"relative error {pi['median_rel_error']:.3f}; {pi['seeds_from_prior']} seeds from it"
                + (f", {rest} by the static-median rule" if rest else "") + f"{failed})")
        if info.get("static_depth_prior") is not None:
            pi = info["static_depth_prior"]
            failed = "".join(f"; frame {k}: {why}" for k, why in sorted(pi["failed"].items())[:3])
            say(f"static seeds at the depth prior aligned to {pi['reference']} in {pi['aligned']} of {pi['frames']} "
                f"frames (init.static_depth = {info['static_depth']}; median relative error "
                f"{pi['median_rel_error']:.3f}{failed})")
        params = gaussians.init_params(s_pts, s_col, d_pts, d_col, deform_config=config.deform, rng=rng)
        for prefix, pts, src in ((STATIC, s_pts, info["static_source_frames"]),
                                 (DYNAMIC, d_pts, info["dynamic_source_frames"])):
            if pts is not None and len(pts):
                cap = pixel_scale_cap(pts, src, frames, config.init.max_scale_px)
                params[f"{prefix}.log_scales"] = np.minimum(params[f"{prefix}.log_scales"], cap[:, None])
        if d_pts is not None and config.motion_init.enabled:
            means, coefs, minfo = initialize_deformation(
                scene, d_pts, info["dynamic_source_frames"], info["dynamic_source_pixels"], config.deform,
                config.motion_init, depth_maps=info.get("dynamic_depth_maps"))
            params[f"{DYNAMIC}.means"] = means
            params[f"{DYNAMIC}.deform_means"] = coefs
            say(f"dynamic motion initialised from {minfo['num_tracks']} mask tracks "
                f"({minfo['num_tracked_seeds']} of {len(means)} seeds tracked)")
            if config.motion_init.rigid:
                rigid = minfo["rigid"]
                params.update(rigid["blocks"])
                params[gaussians.CLUSTER] = rigid["cluster"]
                say(f"rigid movers (motion_init.rigid): {minfo['num_clusters']} tracks as rigid objects, "
                    f"{int(np.sum(rigid['cluster'] >= 0))} seeds in them, the rest deform freely")
                if "rigid_pairs" in minfo:
                    fit = config.motion_init.rigid_fit
                    say(f"rigid paths chained from frame pairs (motion_init.rigid_fit = {fit!r}): "
                        f"{minfo['rigid_pairs'] - minfo['rigid_pairs_missed']} of {minfo['rigid_pairs']} pairs "
                        "measured a rigid motion, the rest carried by the centroids' shift (no turn)")
                for c, b in enumerate(minfo.get("rigid_bundles", ())):
                    say(f"rigid path {c} refined by the object bundle: " + (
                        f"{b['points']} points, {b['observations']} observations, rms {b['rms_px']:.2f} px, "
                        f"{b['nfev']} evaluations" if b["points"] else "too few points seen twice, kept as chained"))
        say(f"initialised {gaussians.num_static(params)} static and {gaussians.num_dynamic(params)} "
            f"dynamic Gaussians in {time.perf_counter() - t0:.1f}s ({_short(info)})")
        if components.blur:
            params.update(traj_model.init_trajectory(
                config.trajectory, poses, times, rng,
                exposure_fraction=None if components.learn_exposure else components.exposure_fraction))
            if components.learn_exposure:
                params.update(init_exposure())
        return cls(params=params, config=config, components=components, times=times, poses_est=given,
                   poses_ref=poses.copy(), Ks=np.stack([np.asarray(f.K, dtype=np.float64) for f in frames]),
                   widths=tuple(int(f.width) for f in frames),
                   heights=tuple(int(f.height) for f in frames), poses_init=poses.copy()).validate()

    def to_checkpoint(self):
        """(arrays, meta) of the model, for ``train.checkpoint.save_checkpoint`` (which the trainer
        extends with its own state)."""
        arrays = {f"{PARAMS_KEY}{n}": v for n, v in self.params.items()}
        arrays[POSES_REF_KEY] = self.poses_ref
        arrays[POSES_INIT_KEY] = self.start_poses
        meta = {"config": self.config.to_dict(), "components": dataclasses.asdict(self.components),
                "poses_est": self.poses_est.tolist(), "times": self.times.tolist(),
                "K": [K.tolist() for K in self.Ks], "width": list(self.widths), "height": list(self.heights)}
        return arrays, meta

    @classmethod
    def from_checkpoint(cls, arrays: dict, meta: dict) -> "Model":
        """Inverse of ``to_checkpoint`` (checkpoints written before the camera state had
        ``poses_ref`` / ``poses_init`` load with ``poses_est`` there); validated."""
        params = {k[len(PARAMS_KEY):]: v for k, v in arrays.items() if k.startswith(PARAMS_KEY)}
        poses_est = np.asarray(meta["poses_est"], dtype=np.float64)
        poses_ref = np.array(arrays.get(POSES_REF_KEY, poses_est), dtype=np.float64)
        poses_init = np.array(arrays.get(POSES_INIT_KEY, poses_est), dtype=np.float64)
        return cls(params=params, config=ExperimentConfig.from_dict(meta["config"]),
                   components=Components(**meta["components"]), times=np.asarray(meta["times"], dtype=np.float64),
                   poses_est=poses_est, poses_ref=poses_ref, Ks=np.asarray(meta["K"], dtype=np.float64),
                   widths=tuple(int(w) for w in meta["width"]),
                   heights=tuple(int(h) for h in meta["height"]), poses_init=poses_init).validate()

    def replace(self, **changes) -> "Model":
        """A copy with some fields changed (``params=...``, ``poses_ref=...``); not validated."""
        return dataclasses.replace(self, **changes)

    def validate(self) -> "Model":
        """Raise a clear error unless every part is consistent and finite; returns the model."""
        N = len(self.times)
        for name, value, shape in (("times", self.times, (N,)), ("poses_est", self.poses_est, (N, 4, 4)),
                                   ("poses_ref", self.poses_ref, (N, 4, 4)), ("Ks", self.Ks, (N, 3, 3))):
            if not isinstance(value, np.ndarray) or value.dtype != np.float64 or value.shape != shape \
                    or not value.flags.c_contiguous:
                raise ValueError(f"Model.{name} must be a C-contiguous float64 array of shape {shape}; got "
                                 f"{getattr(value, 'dtype', type(value).__name__)} {np.shape(value)}")
        if N < 1 or not np.all(np.isfinite(self.times)):
            raise ValueError(f"Model.times must hold N >= 1 finite times; got {self.times}")
        check_rigid(self.poses_est, "Model.poses_est")
        check_rigid(self.poses_ref, "Model.poses_ref")
        if self.poses_init is not None:
            P = self.poses_init
            if not isinstance(P, np.ndarray) or P.dtype != np.float64 or P.shape != (N, 4, 4):
                raise ValueError(f"Model.poses_init must be None or a float64 array of shape {(N, 4, 4)}; got "
                                 f"{getattr(P, 'dtype', type(P).__name__)} {np.shape(P)}")
            check_rigid(P, "Model.poses_init")
        for k in range(N):
            check_intrinsics(self.Ks[k], f"Model.Ks[{k}]")
        for name, sizes in (("widths", self.widths), ("heights", self.heights)):
            if len(sizes) != N or not all(isinstance(v, numbers.Integral) and v >= 1 for v in sizes):
                raise ValueError(f"Model.{name} must hold {N} ints >= 1; got {sizes}")
        scene = {n: v for n, v in self.params.items() if n.startswith(SCENE_PREFIXES)}
        gaussians.validate_params(scene, self.config.deform)
        if gaussians.has_dynamic(scene) != self.components.dynamic:
            raise ValueError(f"components.dynamic = {self.components.dynamic} but the params "
                             f"{'have' if gaussians.has_dynamic(scene) else 'lack'} the dynamic set")
        camera = []
        if self.components.blur:
            camera = traj_model.trajectory_block_names(self.config.trajectory)
            traj_model.check_trajectory(self.params, self.config.trajectory, self.poses_ref, self.times)
            if self.components.learn_exposure:
                camera.append(EXPOSURE_BLOCK)
                exposure_fwd(self.params, N)
        extra = sorted(set(self.params) - set(scene) - set(camera))
        if extra:
            raise ValueError(f"params has blocks {extra} that this model ({self.components}) does not use; a new "
                             "kind of block needs its place in train/model.py (validate, render) first")
        return self

    # ------------------------------------------------------------------ queries
    @property
    def start_poses(self) -> np.ndarray:
        """(N, 4, 4) the poses training started from (``poses_init``, else the given ``poses_est``)."""
        return self.poses_est if self.poses_init is None else self.poses_init

    @property
    def num_frames(self) -> int:
        return len(self.times)

    @property
    def background(self) -> np.ndarray:
        """(3,) float64 background colour of every render."""
        return np.asarray(self.config.train.background, dtype=np.float64)

    def num_gaussians(self) -> int:
        return gaussians.num_static(self.params) + gaussians.num_dynamic(self.params)

    def exposure_tau(self) -> float:
        """Exposure length in normalised time: learned, from the scene, or 0 without the blur model."""
        if not self.components.blur:
            return 0.0
        if self.components.learn_exposure:
            return float(exposure_fwd(self.params, self.num_frames)[0])
        return exposure_from_scene(self.components.exposure_fraction, self.num_frames)

    def mid_pose(self, k: int) -> np.ndarray:
        """Mid-exposure cam_T_world (4, 4) of training frame k: the geodesic midpoint of its
        optimised exposure endpoints with the blur model (on the three-knot path its middle knot,
        exp(xi_mid) T̂), the reference pose without it."""
        k = self._frame(k)
        if not self.components.blur:
            return np.array(self.poses_ref[k], dtype=np.float64)
        idx = np.array([k], dtype=np.int64)
        xm = traj_model.mid_knots(self.params, self.config.trajectory, idx)
        if xm is not None:
            return se3_exp(np.asarray(xm[0], np.float64)) @ self.poses_ref[k]
        (xs, xe), _ = traj_model._endpoints_fwd(self.params, self.config.trajectory, idx, self.poses_ref, self.times)
        return se3_interpolate(se3_exp(xs[0]) @ self.poses_ref[k], se3_exp(xe[0]) @ self.poses_ref[k], 0.5)

    def mid_poses(self) -> np.ndarray:
        """(N, 4, 4) mid-exposure poses of all training frames."""
        return np.stack([self.mid_pose(k) for k in range(self.num_frames)])

    def render(self, view, t=None, K=None, width=None, height=None) -> np.ndarray:
        """Sharp render (H, W, 3) of the scene at time t, in float64 throughout (evaluation, reports
        and exports: the float32 rasterisation of training steps, RenderConfig.raster_float32, is
        not used here).

        view: a training frame index k (its mid-exposure pose; t, K and the size default to the
            frame's), or a (4, 4) cam_T_world pose (then t, K, width and height are required).
        """
        return self.render_outputs(view, t, K, width, height)["image"]

    def render_depth(self, view, t=None, K=None, width=None, height=None):
        """(expected depth (H, W), alpha (H, W)) of the same render as ``render`` (arguments alike):
        sum_i w_i z_i / alpha, the camera z the Gaussians composite to, and their coverage."""
        out = self.render_outputs(view, t, K, width, height)
        return out["expected_depth"], out["alpha"]

    def render_outputs(self, view, t=None, K=None, width=None, height=None) -> dict:
        """Everything the rasteriser returns for ``render``'s view (``render.api.render_fwd``'s out)."""
        if isinstance(view, numbers.Integral) and not isinstance(view, bool):
            k = self._frame(view)
            pose = self.mid_pose(k)
            t = self.times[k] if t is None else t
            K = self.Ks[k] if K is None else K
            width = self.widths[k] if width is None else width
            height = self.heights[k] if height is None else height
        else:
            pose = view
            if t is None or K is None or width is None or height is None:
                raise ValueError("Model.render(pose, t, K, width, height): a pose needs the time, the intrinsics and "
                                 "the image size; or pass a training frame index for its own")
        scene = {n: v for n, v in self.params.items() if n.startswith(SCENE_PREFIXES)}
        ri, _ = render_inputs_fwd(scene, float(t), self.config.deform)
        out, _ = render_fwd(ri["means"], ri["quats"], ri["scales"], ri["opacities"], ri["colors"],
                            np.asarray(pose, dtype=np.float64), np.asarray(K, dtype=np.float64), int(width),
                            int(height), self.background, dataclasses.replace(self.config.render, raster_float32=False))
        return out

    def _frame(self, k) -> int:
        if isinstance(k, bool) or not isinstance(k, numbers.Integral) or not 0 <= k < self.num_frames:
            raise ValueError(f"frame index must be an int in [0, {self.num_frames}); got {k!r}")
        return int(k)


# ---------------------------------------------------------------------------------------------
# The training forward and backward of one frame
# ---------------------------------------------------------------------------------------------


def frame_render_fwd(model: Model, k: int, K, width: int, height: int, static_only: bool = False):
    """What frame k's target is compared with, at one size of the progressive schedule.

    With the blur model the mean of n renders along the exposure (docs/method.md §4; fewer at a
    small render scale with ``blur.n_schedule = "scale"``, ``blur.views.frame_views``), else one
    sharp render at the reference pose. ``static_only`` renders only the static set (warm-up).
    K (3, 3) is the frame's intrinsics scaled to width x height. Trusts a validated model (module
    docstring). Returns (out, saved): out as ``blur.render.blur_render_fwd`` / ``render.render_fwd``.
    """
    cfg, params = model.config, model.params
    prefixes = (f"{STATIC}.",) if static_only else SCENE_PREFIXES
    scene = {n: v for n, v in params.items() if n.startswith(prefixes)}
    t = float(model.times[k])
    saved = {"blur": model.components.blur, "ratio": width / model.widths[k]}  # render px -> full-res px
    if model.components.blur:
        idx = np.array([k], dtype=np.int64)
        (xs, xe), saved["trajectory"] = traj_model._endpoints_fwd(params, cfg.trajectory, idx, model.poses_ref,
                                                                  model.times)
        xm = traj_model.mid_knots(params, cfg.trajectory, idx)
        saved["exposure"] = None
        if model.components.learn_exposure:
            tau, saved["exposure"] = exposure_fwd(params, model.num_frames)
            tau = float(tau)
        else:
            tau = exposure_from_scene(model.components.exposure_fraction, model.num_frames)
        n = frame_views(scene, t, tau, model.poses_ref[k], xs[0], xe[0], K, width, height, model.widths[k], cfg.blur,
                        cfg.deform)
        out, saved["render"] = _blur_render_fwd(
            scene, t, tau, model.poses_ref[k], xs[0], xe[0], K, width, height, model.background, n,
            cfg.deform, cfg.render, (_render_fwd, _render_bwd), (_render_inputs_fwd, _render_inputs_bwd),
            None if xm is None else xm[0])
        saved["backward_views"] = cfg.blur.backward_views
    else:
        ri, saved["scene"] = _render_inputs_fwd(scene, t, cfg.deform)
        out, saved["render"] = _render_fwd(ri["means"], ri["quats"], ri["scales"], ri["opacities"], ri["colors"],
                                           model.poses_ref[k], K, width, height, model.background, cfg.render)
    return out, saved


def frame_render_bwd(saved, v_image, v_alpha=None, v_depth=None, v_expected_depth=None, rng=None):
    """Backward of ``frame_render_fwd``: (v_params, v_means2d, v_means2d_abs). v_params is keyed
    by block (every block the forward used, dense); v_means2d (M, 2) is the screen-space gradient
    of each rendered Gaussian's mean in full-resolution pixels (summed over sub-frames), for
    densification, and v_means2d_abs (M, 2) the same as sums of absolute per-pixel terms.

    With ``blur.backward_views = m`` (0 < m < the forward's n views) the backward runs through m
    views drawn by ``blur.views.backward_subset`` from ``rng`` (a numpy Generator; required then): an
    unbiased estimate of the gradient at about m / n of the backward's cost."""
    cot = (v_image, v_alpha, v_depth, v_expected_depth)
    if saved["blur"]:
        n, m = saved["render"]["n"], saved["backward_views"]
        views = None
        if 0 < m < n:
            if rng is None:
                raise ValueError(f"blur.backward_views = {m} of n = {n} views: frame_render_bwd needs rng, a numpy "
                                 "Generator that draws the views (the trainer seeds one per step)")
            views = backward_subset(n, m, rng)
        v_p, v_xs, v_xe, v_tau, aux = blur_render_bwd(saved["render"], *cot, return_aux=True, views=views)
        v_means2d = aux["v_means2d"].sum(axis=0) * saved["ratio"]
        v_means2d_abs = aux["v_means2d_abs"].sum(axis=0) * saved["ratio"]
        v_p = dict(v_p)
        v_xm = aux["v_xi_mid"]
        v_p.update(traj_model.endpoints_bwd(saved["trajectory"], v_xs[None], v_xe[None],
                                            None if v_xm is None else v_xm[None]))
        if saved["exposure"] is not None:
            v_p.update(exposure_bwd(saved["exposure"], v_tau))
    else:
        g = _render_bwd(saved["render"], *cot)
        v_means2d = g["means2d"] * saved["ratio"]
        v_means2d_abs = g["means2d_abs"] * saved["ratio"]
        v_p, _ = _render_inputs_bwd(saved["scene"], {n: g[n] for n in RENDER_FIELDS})
    return v_p, v_means2d, v_means2d_abs


def _short(info: dict) -> str:
    items = []
    for k, v in info.items():
        if isinstance(v, (int, float, np.integer, np.floating)):
            items.append(f"{k}={v:.3g}" if isinstance(v, (float, np.floating)) else f"{k}={v}")
    return ", ".join(items[:6])
