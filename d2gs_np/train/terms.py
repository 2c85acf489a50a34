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

from d2gs_np.losses.photometric import photometric_bwd, photometric_fwd
from d2gs_np.losses.ssim import SSIM_WINDOW
from d2gs_np.train.config import LossConfig

__all__ = ["TermInputs", "TermGrads", "Photometric", "loss_terms", "terms_fwd_bwd"]


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


def loss_terms(config: LossConfig) -> list:
    """The loss terms of a run, photometric first (module docstring)."""
    return [Photometric(config.lambda_ssim)]


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
