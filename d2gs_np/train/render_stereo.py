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

from d2gs_np.constants import POSE_DEPTH_ALPHA_MIN
from d2gs_np.pose.features import static_detector_mask
from d2gs_np.scene.config import StereoConfig
from d2gs_np.scene.stereo import plane_sweep_depth
from d2gs_np.train.plugins import Plugin

__all__ = ["render_stereo_depths", "RenderStereo"]


def render_stereo_depths(model, masks, stereo: StereoConfig, skips=(2, 4, 8), dilation_px: int = 4):
    """Plane-sweep depth (H, W) of every training frame over the model's own renders (module
    docstring); NaN where untrusted. ``masks``: per frame (H, W) bool motion masks or None.
    Returns (list of depth maps, info: {"kept_share": per frame, "frames": N})."""
    n = model.num_frames
    if len(masks) != n:
        raise ValueError(f"render_stereo_depths: {len(masks)} masks for {n} frames")
    poses = model.mid_poses()
    images, ranges = [], []
    for k in range(n):
        out = model.render_outputs(k)
        images.append(np.clip(out["image"], 0.0, 1.0))
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
    return maps, {"kept_share": kept, "frames": n}


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
            out["maps"] = np.stack(self.maps) if len({m.shape for m in self.maps}) == 1 else None
            if out["maps"] is None:
                del out["maps"]
                out.update({f"map_{k}": m for k, m in enumerate(self.maps)})
        return out

    def load_state_dict(self, state):
        self.made = int(state.get("made", 0))
        if "maps" in state:
            self.maps = [np.asarray(m, np.float64) for m in state["maps"]]
        elif any(k.startswith("map_") for k in state):
            self.maps = [np.asarray(state[f"map_{k}"], np.float64) for k in range(len(self.masks))]
        if self.maps is not None:
            self.on_maps(self.maps)
