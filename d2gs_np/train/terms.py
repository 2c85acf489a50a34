"""The training loss as a list of terms (docs/method.md §6, Eq. 18): total = sum of weight x term.

A term is a forward/backward pair over what the step has (``TermInputs``: the render outputs
of the frame, its target, the pixels that carry loss, the model, the frame and the stage):

    value, saved = term.fwd(inputs)     # a scalar
    grads = term.bwd(saved)             # TermGrads, already multiplied by term.weight

``TermGrads.render`` holds cotangents on render outputs ("image" (h, w, 3); "alpha", "depth",
"expected_depth" (h, w)): those of all terms are summed and go through the one render backward
of the step. ``TermGrads.params`` holds cotangents on parameter blocks by name (L_ts on
``dynamic.deform_*``, L_gs on ``*.opacity_logits``), added to the render backward's gradients.
The step logs each term's unweighted value by name (log column ``loss_<name>``). What a term
needs beyond these (nearest-neighbour lists for L_ts, correspondences for L_reproj) it reads from
the step plugin that keeps it up to date, built together with it: that plugin's state is
checkpointed, so the term sees the same data after a resume.

``loss_terms`` builds the list from ``LossConfig``: the photometric loss (L_render, weight 1 as
in Eq. 18) first. A regulariser enters with its weight from ``LossConfig`` when the weight is
> 0, under the names ``components.OPTIONAL_TERMS`` lists as left out while it is absent
("ts", "gs", "reproj", "freq"); the step loop does not change.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple, Optional

import numpy as np

from collections import OrderedDict

from d2gs_np.blur.endpoints import XI_END, XI_START
from d2gs_np.blur.exposure import EXPOSURE_BLOCK, exposure_bwd, exposure_fwd
from d2gs_np.losses.continuity import _continuity_fwd, continuity_bwd, pixel_weights, time_pairs
from d2gs_np.losses.depth_gradient import depth_gradient_bwd, depth_gradient_fwd
from d2gs_np.losses.depth_prior import depth_prior_bwd, depth_prior_fwd
from d2gs_np.losses.depth_variance import depth_variance_bwd, depth_variance_fwd, z_features_bwd, z_features_fwd
from d2gs_np.losses.entropy import _entropy_fwd, entropy_bwd
from d2gs_np.losses.frequency import _frequency_fwd, frequency_bwd, target_spectrum
from d2gs_np.losses.frequency import warm_up as _frequency_warm_up
from d2gs_np.losses.isometry import _isometry_fwd, isometry_bwd, pair_floor
from d2gs_np.losses.photometric import photometric_bwd, photometric_fwd
from d2gs_np.geometry.camera import scale_intrinsics
from d2gs_np.geometry.sampling import bilinear_bwd, bilinear_fwd
from d2gs_np.render.api import _render_bwd, _render_fwd
from d2gs_np.scene.render_inputs import RENDER_FIELDS, _render_inputs_bwd, _render_inputs_fwd
from d2gs_np.losses.reprojection import cycle_bwd, cycle_fwd
from d2gs_np.losses.smoothness import _spatial_fwd, _time_fwd, spatial_bwd, time_bwd
from d2gs_np.losses.ssim import SSIM_WINDOW
from d2gs_np.constants import GN_MIN_DEPTH, POSE_DEPTH_ALPHA_MIN
from d2gs_np.scene.config import InitConfig
from d2gs_np.scene.gaussians import DEFORM_FIELDS, DYNAMIC, STATIC
from d2gs_np.train.config import LossConfig
from d2gs_np.train.model import SCENE_PREFIXES
from d2gs_np.train.plugins import DepthMemory, NeighbourRefresh
from d2gs_np.train.render_stereo import RenderStereo
from d2gs_np.train.schedule import downsample_area

__all__ = ["TermInputs", "TermGrads", "Photometric", "Smoothness", "OpacityEntropy", "Frequency", "Reprojection",
           "DepthPrior", "DepthGradient", "StereoPrior", "ExposureContinuity", "Isometry", "DepthVariance", "loss_terms",
           "terms_fwd_bwd"]


class TermInputs(NamedTuple):
    out: dict  # render outputs of the step: "image" (h, w, 3), "alpha", "depth", "radii", ...
    target: np.ndarray  # (h, w, 3) target image at the render size
    loss_mask: Optional[np.ndarray]  # (h, w) 1 where a pixel carries loss, 0 elsewhere; None: every pixel
    model: object  # the train.model.Model being trained (its params, times, camera state)
    frame: int
    stage: object  # train.stages.Stage
    motion_mask: Optional[np.ndarray] = None  # (h, w) bool, the frame's moving pixels at the render size, if any


class TermGrads(NamedTuple):
    render: dict  # cotangents on render outputs, by output name
    params: dict  # cotangents on parameter blocks, by block name


class Photometric:
    """L_render = (1 - lambda) L1 + lambda (1 - SSIM) (docs/method.md §6, Eq. 17), on the pixels
    that carry loss. When no pixel inside the SSIM window's interior carries loss (a mask that
    covers it at a small render scale), the term is L1 alone for that step."""

    name = "photometric"

    def __init__(self, lambda_ssim: float, weight: float = 1.0):
        self.lambda_ssim = lambda_ssim
        self.weight = weight

    def fwd(self, x: TermInputs):
        lam = self.lambda_ssim
        if x.loss_mask is not None:
            pad = SSIM_WINDOW // 2
            if lam > 0 and not x.loss_mask[pad:-pad or None, pad:-pad or None].any():
                lam = 0.0  # no static pixel inside the SSIM interior at this size: L1 only
        return photometric_fwd(x.out["image"], x.target, lam, mask=x.loss_mask)

    def bwd(self, saved) -> TermGrads:
        return TermGrads(render={"image": photometric_bwd(saved, self.weight)}, params={})


class Smoothness:
    """L_ts = w_t l_time + w_s l_spatial of the deformation (docs/method.md §6, Eq. 11-13;
    ``losses/smoothness.py``) at the step frame's mid-exposure time t = model.times[frame], on
    every ``dynamic.deform_*`` block. Its neighbour lists come from the ``NeighbourRefresh``
    plugin it is built with (``plugins``). In a stage that renders only the static set (warm-up)
    the deformation is not trained and the term is 0 (not evaluated)."""

    name = "ts"

    def __init__(self, weight, time_weight, spatial_weight, time_offset, neighbours, knn_every):
        self.weight, self.time_weight, self.spatial_weight = weight, time_weight, spatial_weight
        self.time_offset = time_offset
        self.knn = NeighbourRefresh(neighbours, knn_every)
        self.plugins = [self.knn]

    def fwd(self, x: TermInputs):
        p = x.model.params
        if x.stage.static_only or f"{DYNAMIC}.means" not in p:
            return 0.0, None
        coefs = tuple(p[f"{DYNAMIC}.{f}"] for f in DEFORM_FIELDS)
        n, t, cfg = coefs[0].shape[0], float(x.model.times[x.frame]), x.model.config.deform
        lt, st = _time_fwd(coefs, t, self.time_offset, cfg, n)
        ls, ss = _spatial_fwd(coefs, self.knn.neighbours(p), t, cfg, n)
        return self.time_weight * lt + self.spatial_weight * ls, (st, ss)

    def bwd(self, saved) -> TermGrads:
        if saved is None:
            return TermGrads(render={}, params={})
        gt = time_bwd(saved[0], self.weight * self.time_weight)
        gs = spatial_bwd(saved[1], self.weight * self.spatial_weight)
        return TermGrads(render={}, params={f"{DYNAMIC}.{f}": a + b for f, a, b in zip(DEFORM_FIELDS, gt, gs)})


class Isometry:
    """L_iso: the dynamic set's neighbour distances at the step frame's time t = model.times[frame]
    and at t +- ``time_offset`` alike (docs/method.md §6; ``losses/isometry.py``), with gradients on
    ``dynamic.means`` and ``dynamic.deform_means``. The neighbours come from its own
    ``NeighbourRefresh`` plugin ("iso_knn"), found among the positions at mid-clip (t = 0.5). The
    floor is ``pair_floor`` of the present base positions. In a stage that renders only the
    static set (warm-up) the term is 0 (not evaluated)."""

    name = "iso"

    def __init__(self, weight, time_offset, neighbours, knn_every):
        self.weight, self.time_offset = weight, time_offset
        self.knn = NeighbourRefresh(neighbours, knn_every, at_time=0.5, name="iso_knn")
        self.plugins = [self.knn]

    def fwd(self, x: TermInputs):
        p = x.model.params
        if x.stage.static_only or f"{DYNAMIC}.means" not in p:
            return 0.0, None
        A0, C = p[f"{DYNAMIC}.means"], p[f"{DYNAMIC}.deform_means"]
        nb = self.knn.neighbours(p, x.model.config.deform)
        return _isometry_fwd(A0, C, nb, float(x.model.times[x.frame]), self.time_offset, pair_floor(A0, nb),
                             x.model.config.deform)

    def bwd(self, saved) -> TermGrads:
        if saved is None:
            return TermGrads(render={}, params={})
        v_A0, v_C = isometry_bwd(saved, self.weight)
        return TermGrads(render={}, params={f"{DYNAMIC}.means": v_A0, f"{DYNAMIC}.deform_means": v_C})


class OpacityEntropy:
    """L_gs: mean opacity entropy over all Gaussians, static and dynamic (docs/method.md §6,
    Eq. 14; ``losses/entropy.py``), with gradients on ``*.opacity_logits``."""

    name = "gs"

    def __init__(self, weight):
        self.weight = weight

    def fwd(self, x: TermInputs):
        p = x.model.params
        blocks = [b for b in (f"{STATIC}.opacity_logits", f"{DYNAMIC}.opacity_logits") if b in p]
        value, saved = _entropy_fwd(np.concatenate([p[b] for b in blocks]))
        return value, (saved, blocks, [p[b].shape[0] for b in blocks])

    def bwd(self, saved) -> TermGrads:
        s, blocks, sizes = saved
        v = entropy_bwd(s, self.weight)
        return TermGrads(render={}, params=dict(zip(blocks, np.split(v, np.cumsum(sizes)[:-1]))))


class Frequency:
    """L_freq of the rendered image against the target (docs/method.md §6, Eq. 15;
    ``losses/frequency.py``); with a loss mask (warm-up) both images are multiplied by it before
    the FFT, so pixels that carry no loss contribute nothing. With ``static_only``
    (``LossConfig.freq_static_only``) the frame's moving pixels are masked out the same way in
    every stage.

    The target's half spectrum is kept per frame and reused while the frame's target and loss
    mask are the same arrays' values (compared in full each step, ~0.1 ms; the progressive
    schedule changes the size, the warm-up's end drops the mask): one FFT of the two a step.
    The cache is not training state; a resumed run recomputes it to the same values."""

    name = "freq"

    def __init__(self, weight, cutoff, static_only=False):
        self.weight, self.cutoff, self.static_only = weight, cutoff, static_only
        self._spectra = {}  # frame -> (target copy, loss mask copy or None, target_spectrum)

    def _target_fft(self, x: TermInputs):
        hit = self._spectra.get(x.frame)
        if hit is not None:
            t, m, spectrum = hit
            same_mask = m is None if x.loss_mask is None else (m is not None and np.array_equal(m, x.loss_mask))
            if same_mask and np.array_equal(t, x.target):
                return spectrum
        spectrum = target_spectrum(x.target, x.loss_mask)
        self._spectra[x.frame] = (x.target.copy(), None if x.loss_mask is None else x.loss_mask.copy(), spectrum)
        return spectrum

    def warm_up(self):
        """Compile its kernel before the run's clock starts (the trainer calls it with the renderer's)."""
        _frequency_warm_up()

    def fwd(self, x: TermInputs):
        if self.static_only and x.motion_mask is not None:  # moving pixels out in every stage
            static = (~x.motion_mask).astype(np.float64)
            x = x._replace(loss_mask=static if x.loss_mask is None else x.loss_mask * static)
        return _frequency_fwd(x.out["image"], x.target, x.loss_mask, self.cutoff, self._target_fft(x))

    def bwd(self, saved) -> TermGrads:
        return TermGrads(render={"image": frequency_bwd(saved, self.weight)}, params={})


class Reprojection:
    """L_reproj on the rendered depth (docs/method.md §6; ``losses/reprojection.py``): the robust
    cycle residuals of the solver's matched pixels (docs/method.md §5), with the poses held, as a
    loss on the expected depth the step renders for its frame f. Every pair (f, g) of the
    correspondences contributes both directions, lift from f into g and from g into f, so the
    gradient on D_f is that of the pair's whole cost; the partner's depth D_g is the one frame
    g's own last step rendered (``DepthMemory``, checkpointed), a constant here: a pair whose
    partner has not been rendered yet contributes nothing. Pixels whose alpha is below
    POSE_DEPTH_ALPHA_MIN give no depth (as for the solver). The value is the mean robust cost per
    valid match and direction; the gradient goes to the Gaussians through the render's
    ``expected_depth`` (the mean over the virtual views with the blur model); the poses are the
    solver's to refine (their gradient here is not taken)."""

    name = "reproj"

    def __init__(self, weight, memory: DepthMemory, beta: float, robust_scale: float):
        self.weight, self.memory = weight, memory
        self.beta, self.robust_scale = float(beta), float(robust_scale)
        self.plugins = [memory]

    def fwd(self, x: TermInputs):
        f, model = x.frame, x.model
        depth = x.out["expected_depth"]
        h, w = depth.shape
        s_f = np.array([w / model.widths[f], h / model.heights[f]])
        own = np.where(x.out["alpha"] >= POSE_DEPTH_ALPHA_MIN, depth, np.nan)
        M_f, K_f = model.mid_pose(f), model.Ks[f]
        total, count, parts = 0.0, 0, []
        for g, pts_f, pts_g in self.memory.partners(f):
            stored = self.memory.depth(g)
            if stored is None:
                continue
            d_f, bsaved = bilinear_fwd(own, pts_f * s_f)
            d_g, _ = bilinear_fwd(stored[0], pts_g * stored[1])
            M_g, K_g = model.mid_pose(g), model.Ks[g]
            c1, s1 = cycle_fwd(d_f, pts_f, K_f, M_f, d_g, pts_g, K_g, M_g, self.beta, self.robust_scale)
            c2, s2 = cycle_fwd(d_g, pts_g, K_g, M_g, d_f, pts_f, K_f, M_f, self.beta, self.robust_scale)
            total += c1 + c2
            count += int(s1["valid"].sum() + s2["valid"].sum())
            parts.append((bsaved, s1, s2))
        self.memory.store(f, own, s_f)
        if count == 0:
            return 0.0, None
        return total / count, (parts, count, depth.shape, depth.dtype)

    def bwd(self, saved) -> TermGrads:
        if saved is None:
            return TermGrads(render={}, params={})
        parts, count, shape, dtype = saved
        v = np.zeros(shape, dtype=np.float64)
        scale = self.weight / count
        for bsaved, s1, s2 in parts:
            v_df = cycle_bwd(s1, scale)[0] + cycle_bwd(s2, scale)[1]
            v += bilinear_bwd(bsaved, v_df)
        return TermGrads(render={"expected_depth": v.astype(dtype, copy=False)}, params={})


class DepthPrior:
    """L_depth: 1 - the Pearson correlation of the rendered expected depth with the frame's depth
    prior (docs/method.md §6; ``losses/depth_prior.py``), over the pixels where the prior has an
    estimate, the render's alpha is at least POSE_DEPTH_ALPHA_MIN and the loss mask (warm-up: the
    static pixels) is on. Invariant to the prior's scale and shift, so it needs no alignment. The
    prior at a render size is the area mean of the full-resolution map where every pixel under it
    has an estimate (NaN elsewhere), kept per (frame, size) like the targets (``TargetCache``)."""

    name = "depth_prior"

    def __init__(self, weight, priors, space, tolerance=0.0, max_entries=256, tolerance_moving=None):
        self.weight, self.space, self.tolerance = weight, space, float(tolerance)
        self.tolerance_moving = None if tolerance_moving is None else float(tolerance_moving)
        self._priors = list(priors)
        self._sized = OrderedDict()
        self._max_entries = int(max_entries)

    def prior(self, frame, width, height):
        """The prior of ``frame`` at (width, height): (height, width) float64, NaN without an estimate."""
        key = (frame, width, height)
        hit = self._sized.get(key)
        if hit is not None:
            self._sized.move_to_end(key)
            return hit
        full = np.asarray(self._priors[frame], np.float64)
        if full.shape == (height, width):
            sized = full
        else:
            known = np.isfinite(full)
            share = downsample_area(known.astype(np.float64), width, height)
            mean = downsample_area(np.where(known, full, 0.0), width, height)
            sized = np.where(share >= 1.0 - 1e-9, mean, np.nan)  # only where every pixel under it is known
        self._sized[key] = sized
        while len(self._sized) > self._max_entries:
            self._sized.popitem(last=False)
        return sized

    def fwd(self, x: TermInputs):
        depth = x.out["expected_depth"]
        h, w = depth.shape
        tol = self.tolerance
        if self.tolerance_moving is not None and x.motion_mask is not None:
            tol = np.where(x.motion_mask, self.tolerance_moving, self.tolerance)
        return depth_prior_fwd(depth, self.prior(x.frame, w, h), x.out["alpha"], self.space,
                               POSE_DEPTH_ALPHA_MIN, GN_MIN_DEPTH, x.loss_mask, tol)

    def bwd(self, saved) -> TermGrads:
        if saved is None:
            return TermGrads(render={}, params={})
        return TermGrads(render={"expected_depth": depth_prior_bwd(saved, self.weight)}, params={})


class DepthGradient(DepthPrior):
    """L_dgrad: the rendered expected depth's log differences between neighbouring pixels against the
    frame's depth prior's (docs/method.md §6; ``losses/depth_gradient.py``), over the pixels where
    the prior has an estimate, the render's alpha is at least POSE_DEPTH_ALPHA_MIN, the loss mask is
    on and, with ``region = "moving"``, the frame's motion mask is (a frame without one adds
    nothing). The prior at a render size is L_depth's (``DepthPrior.prior``)."""

    name = "depth_grad"

    def __init__(self, weight, priors, region="moving", max_entries=256):
        super().__init__(weight, priors, "depth", max_entries=max_entries)
        self.region = region

    def fwd(self, x: TermInputs):
        depth = x.out["expected_depth"]
        h, w = depth.shape
        mask = x.loss_mask
        if self.region == "moving":
            if x.motion_mask is None:
                return 0.0, None
            mask = x.motion_mask if mask is None else (mask > 0) & x.motion_mask
        return depth_gradient_fwd(depth, self.prior(x.frame, w, h), x.out["alpha"], POSE_DEPTH_ALPHA_MIN,
                                  GN_MIN_DEPTH, mask)

    def bwd(self, saved) -> TermGrads:
        if saved is None:
            return TermGrads(render={}, params={})
        return TermGrads(render={"expected_depth": depth_gradient_bwd(saved, self.weight)}, params={})


class DepthVariance:
    """L_var: the squared coefficient of variation of the Gaussians' depths along each pixel's ray
    (docs/method.md §6; ``losses/depth_variance.py``), from one more sharp render of the frame at
    its mid-exposure pose and time, at the step's size, whose colours are each Gaussian's (z, z^2,
    0) over black: its image holds D = sum w z and D2 = sum w z^2. The pixels are those of the step's
    loss mask with alpha >= POSE_DEPTH_ALPHA_MIN; the set rendered is the step's (the static set
    alone in the warm-up). Its gradient reaches the Gaussians' blocks, not the camera (the pose
    is held for this term)."""

    name = "depth_var"

    def __init__(self, weight):
        self.weight = weight

    def fwd(self, x: TermInputs):
        m, k = x.model, x.frame
        h, w = x.out["alpha"].shape
        prefixes = (f"{STATIC}.",) if x.stage is not None and x.stage.static_only else SCENE_PREFIXES
        scene = {n: v for n, v in m.params.items() if n.startswith(prefixes)}
        ri, saved_scene = _render_inputs_fwd(scene, float(m.times[k]), m.config.deform)
        pose = m.mid_pose(k)
        K = scale_intrinsics(m.Ks[k], w / m.widths[k], h / m.heights[k])
        feats, z = z_features_fwd(ri["means"], pose)
        out, saved_render = _render_fwd(ri["means"], ri["quats"], ri["scales"], ri["opacities"], feats, pose, K, w, h,
                                        np.zeros(3, dtype=feats.dtype), m.config.render)
        value, saved = depth_variance_fwd(out["image"][..., 0], out["image"][..., 1], out["alpha"],
                                          POSE_DEPTH_ALPHA_MIN, GN_MIN_DEPTH, x.loss_mask)
        return value, None if saved is None else (saved, saved_scene, saved_render, z, pose, out["image"].dtype)

    def bwd(self, saved) -> TermGrads:
        if saved is None:
            return TermGrads(render={}, params={})
        saved_var, saved_scene, saved_render, z, pose, dtype = saved
        v_d, v_d2, v_a = depth_variance_bwd(saved_var, self.weight)
        v_image = np.zeros(v_d.shape + (3,), dtype=dtype)
        v_image[..., 0], v_image[..., 1] = v_d, v_d2
        g = _render_bwd(saved_render, v_image, v_a.astype(dtype))
        g = dict(g, means=g["means"] + z_features_bwd(g["colors"], z, pose).astype(g["means"].dtype), colors=None)
        v_params, _ = _render_inputs_bwd(saved_scene, {n: g[n] for n in RENDER_FIELDS})
        # the features stand in for the colours: the colour blocks get nothing from this term
        return TermGrads(render={}, params={n: v for n, v in v_params.items() if not n.endswith(".colors")
                                            and not n.endswith(".deform_colors")})


class StereoPrior(DepthPrior):
    """L_stereo: L_depth's "depth" or "metric" form (``space``) against depth maps the run makes
    for itself, the plane sweep over the model's own renders (``train/render_stereo.py``,
    docs/method.md §6), made by its ``RenderStereo`` plugin at ``at`` (fractions of ``total``
    schedule steps). 0 before the first maps; the maps' NaN pixels (untrusted, moving) pull nothing."""

    name = "stereo"

    def __init__(self, weight, tolerance, masks, stereo, skips, dilation_px, at, total, note=None, space="depth"):
        super().__init__(weight, [], space, tolerance)
        self.plugins = [RenderStereo(masks, stereo, skips, dilation_px, at, total, self.set_maps, note)]

    def set_maps(self, maps):
        """Pull to ``maps`` (per frame (H, W), NaN without an estimate) from now on."""
        self._priors = [np.asarray(m, np.float64) for m in maps]
        self._sized.clear()

    def fwd(self, x: TermInputs):
        if not self._priors:
            return 0.0, None
        return super().fwd(x)


class ExposureContinuity:
    """L_cont: the step frame's exposure and its neighbours' in time lie on one constant-velocity
    path (docs/method.md §6; ``losses/continuity.py``): the residuals of the (at most two) pairs of
    neighbouring frames that hold the step's frame, in pixels (``weights``, the full-resolution
    focal over the scene's depth on the translation, the focal on the rotation). The gradient goes
    to the endpoint rows (the optimiser takes the step frame's row) and, where the exposure length
    is learned, to ``camera.exposure_logit``. Without the blur model, or with a PoseNet
    trajectory (no per-frame endpoint rows), it is 0."""

    name = "continuity"

    def __init__(self, weight, weights):
        self.weight, self.weights = weight, np.asarray(weights, dtype=np.float64)

    def fwd(self, x: TermInputs):
        m = x.model
        if not m.components.blur or XI_START not in m.params:
            return 0.0, None
        e_saved = None
        if m.components.learn_exposure:
            tau, e_saved = exposure_fwd(m.params, m.num_frames)
        else:
            tau = m.exposure_tau()
        pairs = time_pairs(m.times, [x.frame])
        value, saved = _continuity_fwd(m.params[XI_START], m.params[XI_END], m.poses_ref, m.times, tau, pairs,
                                       self.weights)
        return value, (saved, e_saved)

    def bwd(self, saved) -> TermGrads:
        if saved is None:
            return TermGrads(render={}, params={})
        g_s, g_e, g_tau = continuity_bwd(saved[0], self.weight)
        params = {XI_START: g_s, XI_END: g_e}
        if saved[1] is not None:
            params[EXPOSURE_BLOCK] = exposure_bwd(saved[1], g_tau)[EXPOSURE_BLOCK]
        return TermGrads(render={}, params=params)


def loss_terms(config: LossConfig, components=None, note=None, scene=None, run_dir=None, pose_solver=None,
               prior_space="depth", init=None, iters=None) -> list:
    """The loss terms of a run, photometric first (module docstring). ``components``
    (``train/components.py``): what the run models; L_ts is left out without a dynamic set (and
    ``note`` says so). L_reproj needs the ``scene`` (its frames and masks, for the matches), the
    run folder (the matches' cache) and the ``PoseSolverConfig`` (matching settings, beta and the
    robust scale of the solver's residuals); without a scene of two frames or more it is left
    out and ``note`` says so. L_depth needs the scene's depth priors (``prior_space``: what they
    hold, ``InitConfig.depth_prior_space``); without them it is left out and ``note`` says so. L_stereo
    needs the ``InitConfig`` (its sweep's settings, frame skips, mask dilation) and the run's
    schedule steps ``iters``."""
    say = note if note is not None else (lambda m: None)
    terms = [Photometric(config.lambda_ssim)]
    if config.lambda_ts > 0:
        if components is not None and not components.dynamic:
            say("L_ts: left out (no dynamic set, nothing deforms), although loss.lambda_ts > 0")
        else:
            terms.append(Smoothness(config.lambda_ts, config.ts_time_weight, config.ts_spatial_weight,
                                    config.ts_time_offset, config.ts_neighbours, config.ts_knn_every))
    if config.lambda_depth_var > 0:
        terms.append(DepthVariance(config.lambda_depth_var))
        say(f"L_var: weight {config.lambda_depth_var:g}, the spread of the Gaussians' depths along each ray "
            "(one more sharp render per step)")
    if config.lambda_iso > 0:
        if components is not None and not components.dynamic:
            say("L_iso: left out (no dynamic set, nothing moves), although loss.lambda_iso > 0")
        else:
            terms.append(Isometry(config.lambda_iso, config.iso_time_offset, config.ts_neighbours,
                                  config.ts_knn_every))
            say(f"L_iso: weight {config.lambda_iso:g}, the dynamic set's distances to its {config.ts_neighbours} "
                f"nearest neighbours at t and t + {config.iso_time_offset:g} alike")
    if config.lambda_gs > 0:
        terms.append(OpacityEntropy(config.lambda_gs))
    if config.lambda_freq > 0:
        terms.append(Frequency(config.lambda_freq, config.freq_cutoff, config.freq_static_only))
        where = ("the static pixels only (loss.freq_static_only; the whole image of a frame without moving pixels)"
                 if config.freq_static_only else "the whole image (in the warm-up stage: the static pixels)")
        say(f"L_freq: weight {config.lambda_freq:g}, on {where}")
    if config.lambda_reproj > 0:
        if scene is None or pose_solver is None or scene.num_frames < 2:
            say("L_reproj: left out (it needs a scene of two frames or more and the pose solver's matching "
                "settings), although loss.lambda_reproj > 0")
        else:
            gc = pose_solver.gauss_newton
            memory = DepthMemory([f.image for f in scene.frames], [f.mask for f in scene.frames],
                                 pose_solver.correspond, run_dir, note)
            terms.append(Reprojection(config.lambda_reproj, memory, gc.beta, gc.robust_scale))
    if config.lambda_depth_prior > 0:
        if scene is None or not scene.has_depth_prior:
            say("L_depth: left out (the scene has no depth priors: depth_prior_file_path, docs/dataset_format.md "
                "§3), although loss.lambda_depth_prior > 0")
        else:
            tm = config.depth_prior_tolerance_moving
            terms.append(DepthPrior(config.lambda_depth_prior, [f.depth_prior for f in scene.frames], prior_space,
                                    config.depth_prior_tolerance, tolerance_moving=tm))
            how = "the correlation of the rendered disparity"
            if prior_space == "depth":
                on_movers = f" ({tm:g} on the moving pixels)" if tm is not None else ""
                how = f"the log depth ratios beyond {config.depth_prior_tolerance:g}{on_movers}"
            say(f"L_depth: weight {config.lambda_depth_prior:g}, {how} against the scene's depth priors (held as "
                f"{prior_space}) on every frame")
    if config.lambda_depth_grad > 0:
        if scene is None or not scene.has_depth_prior:
            say("L_dgrad: left out (the scene has no depth priors: depth_prior_file_path, docs/dataset_format.md "
                "§3), although loss.lambda_depth_grad > 0")
        elif prior_space == "disparity":
            say("L_dgrad: left out (the depth priors are disparities up to a shift, whose log differences the "
                "shift moves: InitConfig.depth_prior_space), although loss.lambda_depth_grad > 0")
        else:
            terms.append(DepthGradient(config.lambda_depth_grad, [f.depth_prior for f in scene.frames],
                                       config.depth_grad_region))
            where = "the moving pixels" if config.depth_grad_region == "moving" else "every pixel"
            say(f"L_dgrad: weight {config.lambda_depth_grad:g}, the rendered depth's log differences between "
                f"neighbours against the depth priors', on {where}")
    if config.lambda_stereo > 0:
        if scene is None or scene.num_frames < 2:
            say("L_stereo: left out (it needs a scene of two frames or more), although loss.lambda_stereo > 0")
        else:
            if iters is None:
                raise ValueError("loss_terms: L_stereo (loss.lambda_stereo > 0) needs the run's schedule steps: "
                                 "pass iters=config.train.iters")
            total = int(iters)
            init = init if init is not None else InitConfig()
            sweep = dataclasses.replace(init.stereo, enabled=True, num_depths=config.stereo_depths)
            terms.append(StereoPrior(config.lambda_stereo, config.stereo_tolerance, [f.mask for f in scene.frames],
                                     sweep, init.frame_skips, init.features.mask_dilation_px,
                                     config.stereo_at, total, note, config.stereo_space))
            what = "log depth ratios" if config.stereo_space == "depth" else "log depths"
            say(f"L_stereo: weight {config.lambda_stereo:g}, the {what} beyond {config.stereo_tolerance:g} "
                f"against a plane sweep over the model's own renders, made at "
                f"{', '.join(f'{a:g}' for a in config.stereo_at)} of the schedule")
    if config.lambda_continuity > 0:
        blur = components is None or components.blur
        if not blur or scene is None or scene.num_frames < 2:
            say("L_cont: left out (it needs the blur model and two frames or more), although "
                "loss.lambda_continuity > 0")
        else:
            focal = float(scene.frames[0].K[0, 0])
            terms.append(ExposureContinuity(config.lambda_continuity, pixel_weights(focal, scene.scene_scale)))
            depth = f"{scene.scene_scale:.3g}" if scene.scene_scale else "1 (the scene gives no scale)"
            say(f"L_cont: weight {config.lambda_continuity:g}, neighbouring exposures on one constant-velocity path, "
                f"in pixels (focal {focal:.4g}, translation at depth {depth})")
    return terms


def terms_fwd_bwd(terms, inputs: TermInputs):
    """Forward and backward of every term. Returns (total, values, v_render, v_params): the
    weighted sum (a scalar), the unweighted value of each term by name, and the summed
    cotangents on render outputs and on parameter blocks."""
    total, values, v_render, v_params = None, {}, {}, {}
    for term in terms:
        value, saved = term.fwd(inputs)
        values[term.name] = float(value)
        weighted = term.weight * value
        total = weighted if total is None else total + weighted
        grads = term.bwd(saved)
        for into, add in ((v_render, grads.render), (v_params, grads.params)):
            for key, v in add.items():
                into[key] = v if key not in into else into[key] + v
    return total, values, v_render, v_params
