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

from typing import NamedTuple, Optional

import numpy as np

from d2gs_np.losses.entropy import _entropy_fwd, entropy_bwd
from d2gs_np.losses.frequency import _frequency_fwd, frequency_bwd
from d2gs_np.losses.photometric import photometric_bwd, photometric_fwd
from d2gs_np.losses.smoothness import _spatial_fwd, _time_fwd, spatial_bwd, time_bwd
from d2gs_np.losses.ssim import SSIM_WINDOW
from d2gs_np.scene.gaussians import DEFORM_FIELDS, DYNAMIC, STATIC
from d2gs_np.train.config import LossConfig
from d2gs_np.train.plugins import NeighbourRefresh

__all__ = ["TermInputs", "TermGrads", "Photometric", "Smoothness", "OpacityEntropy", "Frequency", "loss_terms",
           "terms_fwd_bwd"]


class TermInputs(NamedTuple):
    out: dict  # render outputs of the step: "image" (h, w, 3), "alpha", "depth", "radii", ...
    target: np.ndarray  # (h, w, 3) target image at the render size
    loss_mask: Optional[np.ndarray]  # (h, w) 1 where a pixel carries loss, 0 elsewhere; None: every pixel
    model: object  # the train.model.Model being trained (its params, times, camera state)
    frame: int
    stage: object  # train.stages.Stage


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
    the FFT, so pixels that carry no loss contribute nothing."""

    name = "freq"

    def __init__(self, weight, cutoff):
        self.weight, self.cutoff = weight, cutoff

    def fwd(self, x: TermInputs):
        return _frequency_fwd(x.out["image"], x.target, x.loss_mask, self.cutoff)

    def bwd(self, saved) -> TermGrads:
        return TermGrads(render={"image": frequency_bwd(saved, self.weight)}, params={})


def loss_terms(config: LossConfig, components=None, note=None) -> list:
    """The loss terms of a run, photometric first (module docstring). ``components``
    (``train/components.py``): what the run models; L_ts is left out without a dynamic set (and
    ``note`` says so)."""
    say = note if note is not None else (lambda m: None)
    terms = [Photometric(config.lambda_ssim)]
    if config.lambda_ts > 0:
        if components is not None and not components.dynamic:
            say("L_ts: left out (no dynamic set, nothing deforms), although loss.lambda_ts > 0")
        else:
            terms.append(Smoothness(config.lambda_ts, config.ts_time_weight, config.ts_spatial_weight,
                                    config.ts_time_offset, config.ts_neighbours, config.ts_knn_every))
    if config.lambda_gs > 0:
        terms.append(OpacityEntropy(config.lambda_gs))
    if config.lambda_freq > 0:
        terms.append(Frequency(config.lambda_freq, config.freq_cutoff))
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
