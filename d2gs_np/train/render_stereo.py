"""Stereo on the model's own renders: a depth prior that training makes for itself (docs/method.md §6,
L_stereo).

The seeds' plane sweep (``scene/stereo.py``) runs on the blurry input; on sparse, streaked texture
it keeps few pixels and those a few per cent off, and the photometric loss keeps the depth it starts
from. Once the model renders sharp training views, the same sweep over those renders (each frame
against its neighbours at ``InitConfig.frame_skips``, at the model's mid-exposure poses) is both
denser and more accurate than the model's own expected depth: the renders reproduce what each frame
saw, and only a surface at the right depth makes them agree across views.

``render_stereo_depths`` is that sweep for every training frame:

1. Render every frame at full resolution at its mid-exposure pose and time (``Model.render_outputs``,
   float64): the image (clipped to [0, 1]), expected depth and alpha.
2. The sweep's range per frame: the 2nd and 98th percentiles of the rendered depth where alpha >=
   POSE_DEPTH_ALPHA_MIN (the sweep widens it by ``StereoConfig.depth_margin``).
3. ``plane_sweep_depth`` of the frame's render against the renders of frames k +- s (s in
   ``skips``, clamped to the clip), the moving pixels (motion masks grown by ``dilation_px``) out in
   the reference and in every source; NaN where the sweep's checks do not trust it.

``RenderStereo`` is the step plugin that makes the maps at given fractions of the schedule and hands
them to the term (``train.terms.StereoPrior``), which pulls the rendered depth to their shape beyond
a tolerance, as L_depth does with a network's prior. The maps are checkpointed.
"""
from __future__ import annotations

import numpy as np

import dataclasses

from d2gs_np.constants import PIXEL_CENTER_OFFSET, POSE_DEPTH_ALPHA_MIN
from d2gs_np.pose.features import static_detector_mask
from d2gs_np.scene import gaussians
from d2gs_np.scene.config import StereoConfig
from d2gs_np.scene.gaussians import STATIC
from d2gs_np.scene.initialize import depth_from_trusted, initialize_points, pixel_scale_cap
from d2gs_np.scene.stereo import plane_sweep_depth
from d2gs_np.train.plugins import Plugin

__all__ = ["render_stereo_depths", "RenderStereo", "fill_depth_map", "reseed_static", "Reseed"]


def render_stereo_depths(model, masks, stereo: StereoConfig, skips=(2, 4, 8), dilation_px: int = 4):
    """Plane-sweep depth (H, W) of every training frame over the model's own renders (module
    docstring); NaN where untrusted. ``masks``: per frame (H, W) bool motion masks or None.
    Returns (list of depth maps, info: {"kept_share": per frame, "frames": N, "images": the renders,
    "rendered_depth": their expected depth, NaN where alpha < POSE_DEPTH_ALPHA_MIN})."""
    n = model.num_frames
    if len(masks) != n:
        raise ValueError(f"render_stereo_depths: {len(masks)} masks for {n} frames")
    poses = model.mid_poses()
    images, ranges, rendered = [], [], []
    for k in range(n):
        out = model.render_outputs(k)
        images.append(np.clip(out["image"], 0.0, 1.0))
        rendered.append(np.where(out["alpha"] >= POSE_DEPTH_ALPHA_MIN, out["expected_depth"], np.nan))
        d = out["expected_depth"][(out["alpha"] >= POSE_DEPTH_ALPHA_MIN) & np.isfinite(out["expected_depth"])
                                  & (out["expected_depth"] > 0)]
        ranges.append((float(np.percentile(d, 2)), float(np.percentile(d, 98))) if d.size >= 16 else None)
    moving = [None if m is None else static_detector_mask(m, dilation_px) == 0 for m in masks]
    maps, kept = [], []
    for k in range(n):
        rng = ranges[k]
        others = sorted({min(max(k + s * sgn, 0), n - 1) for s in skips for sgn in (-1, 1)} - {k})
        if rng is None or not rng[0] < rng[1] or not others:
            maps.append(np.full(images[k].shape[:2], np.nan))
            kept.append(0.0)
            continue
        sources = [(images[j], poses[j], model.Ks[j], moving[j]) for j in others]
        dmap, info = plane_sweep_depth(images[k], poses[k], model.Ks[k], sources, rng[0], rng[1], stereo, moving[k])
        maps.append(dmap)
        kept.append(info["kept_share"])
    return maps, {"kept_share": kept, "frames": n, "images": images, "rendered_depth": rendered}


class RenderStereo(Plugin):
    """Makes the render-stereo maps (``render_stereo_depths``) at the first step whose schedule step
    reaches each of ``at`` (fractions of ``total`` schedule steps) and gives them to ``on_maps``
    (the term's setter); name "render_stereo". Its count of maps made and the maps themselves are
    checkpointed, so a resumed run pulls to the same maps and makes the remaining ones when due."""

    name = "render_stereo"

    def __init__(self, masks, stereo: StereoConfig, skips, dilation_px, at, total: int, on_maps, note=None):
        self.masks, self.stereo, self.skips, self.dilation_px = list(masks), stereo, tuple(skips), int(dilation_px)
        self.at, self.total, self.on_maps = tuple(sorted(at)), int(total), on_maps
        self.note = note if note is not None else (lambda m: None)
        self.made = 0
        self.maps = None

    def on_step(self, state):
        if self.made >= len(self.at) or state.sched < self.at[self.made] * self.total:
            return state
        while self.made < len(self.at) and state.sched >= self.at[self.made] * self.total:
            self.made += 1  # one sweep for every fraction passed since the last
        self.maps, info = render_stereo_depths(state.model, self.masks, self.stereo, self.skips, self.dilation_px)
        self.on_maps(self.maps)
        kept = np.asarray(info["kept_share"])
        self.note(f"step {state.step}: L_stereo's depth maps made from the renders of {info['frames']} frames "
                  f"(the sweep kept {100 * kept.mean():.0f} % of the pixels, {100 * kept.min():.0f}-"
                  f"{100 * kept.max():.0f} % per frame)")
        return state

    def state_dict(self):
        out = {"made": self.made}
        if self.maps is not None:
            out.update({f"map_{k}": m for k, m in enumerate(self.maps)})
        return out

    def load_state_dict(self, state):
        self.made = int(state.get("made", 0))
        keys = sorted((k for k in state if k.startswith("map_")), key=lambda k: int(k[len("map_"):]))
        if keys:
            self.maps = [np.asarray(state[k], np.float64) for k in keys]
            self.on_maps(self.maps)


def fill_depth_map(dmap, fallback, outlier_rel=0.15, max_anchors=4000):
    """``dmap`` (H, W) with its NaN pixels filled: inverse depth interpolated from up to
    ``max_anchors`` evenly spread trusted pixels (``interpolate_inverse_depth``, as the seeds'
    stereo fills its untextured pixels), else ``fallback`` (H, W) there, else the median of what is
    known (``scene.initialize.depth_from_trusted``). Returns a finite, positive (H, W) map; None
    when nothing at all is known."""
    out = np.array(dmap, dtype=np.float64)
    out[~(np.isfinite(out) & (out > 0))] = np.nan
    miss = np.isnan(out)
    if miss.any():
        q = np.argwhere(miss)
        filled = depth_from_trusted(out, np.stack([q[:, 1], q[:, 0]], axis=1) + PIXEL_CENTER_OFFSET, outlier_rel,
                                    max_anchors)
        if filled is not None:
            out[miss] = filled
    miss = ~(np.isfinite(out) & (out > 0))
    if miss.any() and fallback is not None:
        fb = np.asarray(fallback, np.float64)
        out[miss] = np.where(np.isfinite(fb[miss]) & (fb[miss] > 0), fb[miss], np.nan)
    known = np.isfinite(out) & (out > 0)
    if not known.any():
        return None
    out[~known] = float(np.median(out[known]))
    return out


def reseed_static(model, scene, config, maps, info, rng):
    """New static-set blocks seeded as the initialisation seeds them (``initialize_points``), from
    the model's renders in place of the blurry frames, at its mid-exposure poses, with the filled
    render-stereo maps as the frames' depth (``InitConfig.static_depth = "scene"``): dense seeds on
    the keyframes and the fill at those depths, coloured by the sharp renders; triangulated points
    from the renders' matches. Returns (blocks of the static set, a summary dict)."""
    poses = model.mid_poses()
    depths = [fill_depth_map(m, r) for m, r in zip(maps, info["rendered_depth"])]
    if any(d is None for d in depths):
        return None, {"reason": "a frame renders nothing opaque"}
    frames = [dataclasses.replace(f, image=img, cam_T_world=P, depth=d)
              for f, img, P, d in zip(scene.frames, info["images"], poses, depths)]
    reseeding = dataclasses.replace(scene, frames=frames)
    init = dataclasses.replace(config.init, static_depth="scene", dynamic_points=0)
    pts, cols, _, _, pinfo = initialize_points(reseeding, init, rng)
    blocks = gaussians.init_params(np.ascontiguousarray(pts, np.float64), np.ascontiguousarray(cols, np.float64))
    cap = pixel_scale_cap(pts, pinfo["static_source_frames"], frames, init.max_scale_px)
    blocks[f"{STATIC}.log_scales"] = np.minimum(blocks[f"{STATIC}.log_scales"], cap[:, None])
    dtype = model.params[f"{STATIC}.means"].dtype
    blocks = {n: v.astype(dtype, copy=False) for n, v in blocks.items() if n.startswith(f"{STATIC}.")}
    return blocks, {"points": len(pts), "triangulated": pinfo["num_static_triangulated"],
                    "dense": pinfo["num_static_dense"], "fill": pinfo["num_static_fill"]}


class Reseed(Plugin):
    """Once, at the first step whose schedule step reaches ``InitConfig.reseed_at`` of the
    schedule: the static set replaced by ``reseed_static``'s (its Adam moments and row statistics
    new, the dynamic set and the cameras kept); name "reseed". The seeds' plane sweep runs on the
    blurry frames; this one on the model's sharp renders (module docstring), so the new seeds start
    where the surfaces are, as seeds at the true depth do (docs/method.md §8, the re-seed)."""

    name = "reseed"

    def __init__(self, scene, config, note=None):
        self.scene, self.config = scene, config
        self.note = note if note is not None else (lambda m: None)
        ic = config.init
        self.stereo = dataclasses.replace(ic.stereo, enabled=True, num_depths=config.loss.stereo_depths)
        self.done = False

    def on_step(self, state):
        ic, total = self.config.init, self.config.train.iters
        if self.done or state.sched < ic.reseed_at * total:
            return state
        self.done = True
        masks = [f.mask for f in self.scene.frames]
        maps, info = render_stereo_depths(state.model, masks, self.stereo, ic.frame_skips,
                                          ic.features.mask_dilation_px)
        rng = np.random.default_rng((self.config.train.seed, state.step, 11))
        blocks, summary = reseed_static(state.model, self.scene, self.config, maps, info, rng)
        if blocks is None:
            self.note(f"step {state.step}: static set not re-seeded ({summary['reason']})")
            return state
        old = gaussians.num_static(state.params)
        keep = np.r_[np.zeros(old, bool), np.ones(summary["points"], bool)]
        state = state.resize_rows(STATIC, keep=keep, new=blocks)
        kept = np.asarray(info["kept_share"])
        self.note(f"step {state.step}: static set re-seeded from a plane sweep over the renders ({old} -> "
                  f"{summary['points']} Gaussians: {summary['triangulated']} triangulated, {summary['dense']} "
                  f"dense, {summary['fill']} fill; the sweep kept {100 * kept.mean():.0f} % of the pixels)")
        return state

    def state_dict(self):
        return {"done": self.done}

    def load_state_dict(self, state):
        self.done = bool(state.get("done", False))
