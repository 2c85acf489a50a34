"""Evaluation metrics: image quality (PSNR, SSIM, FLIP) and camera trajectory (ATE, RPE, re-exported).

Definitions follow ``docs/dataset_format.md §6`` (the evaluation protocol) and
``docs/method.md §10``.

Images
- Images are (H, W, C) floating-point arrays with values nominally in [0, 1]
  (data range 1). float32 inputs are accepted; every metric is accumulated in
  float64 and returned as a Python float.
- ``psnr`` = 10 log10(data_range^2 / MSE), the MSE taken over all pixels and
  channels (or over the pixels of ``mask``). Identical images give +inf.
- ``ssim`` matches scikit-image's
  ``structural_similarity(img, ref, channel_axis=-1, data_range=1.0,
  gaussian_weights=True, sigma=1.5)``: Gaussian window sigma 1.5 truncated at
  3.5 sigma (11 taps), 'reflect' borders, K1 = 0.01, K2 = 0.03, *sample*
  covariances (factor 121/120), and the SSIM map averaged over the interior
  (a 5-pixel border is dropped) and over channels. The map comes from
  ``d2gs_np.losses.ssim.ssim_map``, the same code as the training loss.
- ``flip`` is the mean LDR-FLIP error (Andersson et al. 2020, "FLIP: A Difference Evaluator for
  Alternating Images"), computed by NVIDIA's reference implementation (the ``flip-evaluator``
  package): a perceptual difference in [0, 1], 0 for identical images, lower is better, at
  67 pixels per degree (FLIP's default viewing condition: a 0.7 m wide 4K monitor seen from
  0.7 m). Inputs are treated as sRGB display values, as our PNG frames are, and clipped to
  [0, 1] first (FLIP's LDR mode requires it; a render may overshoot by rounding). It is the
  offline perceptual metric of docs/method.md §10: LPIPS needs network weights we cannot
  fetch.
- Masks are (H, W) bool arrays; a masked metric averages over the pixels where
  the mask is True (for SSIM: the True pixels of the interior).

Depth (``depth_errors``): AbsRel and delta < 1.25 of a rendered depth map against the true one,
over the pixels with a finite positive true depth, in the true depth's units (the caller scales
a reconstruction's depths into them).

Trajectories: ``ate``, ``rpe`` and the Sim(3) alignment are defined in
``d2gs_np.geometry.trajectory`` (so that the pose solver and the video importer, below this layer,
can use them) and re-exported here.
- Degenerate inputs raise ValueError instead of returning NaN.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.geometry.camera import project_points
from d2gs_np.geometry.depth import depth_error_terms
from d2gs_np.geometry.trajectory import align_trajectory, ate, rpe, sim3_apply_to_poses, sim3_inverse, umeyama
from d2gs_np.losses.ssim import SSIM_WINDOW, ssim_map
from d2gs_np.scene.deformation import deform_basis

__all__ = [
    "psnr",
    "ssim",
    "flip",
    "gradient_energy",
    "depth_error_terms",
    "depth_errors",
    "lpips",
    "umeyama",
    "align_trajectory",
    "sim3_inverse",
    "sim3_apply_to_poses",
    "ate",
    "rpe",
    "seed_depth_ratio",
]

# Border dropped before averaging the SSIM map: (win_size - 1) // 2 = 5 for the 11-tap window.
_SSIM_PAD = (SSIM_WINDOW - 1) // 2


# --------------------------------------------------------------------------- images
def _check_image_pair(img, ref):
    for name, a in (("img", img), ("ref", ref)):
        if not isinstance(a, np.ndarray):
            raise TypeError(f"{name} must be a numpy array; got {type(a).__name__}")
        if not np.issubdtype(a.dtype, np.floating):
            raise TypeError(
                f"{name} must be a floating-point image in [0, 1]; got dtype {a.dtype} "
                f"(convert 8-bit images with img.astype(np.float64) / 255)"
            )
        if a.ndim != 3:
            raise ValueError(f"{name} must have shape (H, W, C); got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or inf values")
    if img.shape != ref.shape:
        raise ValueError(f"img and ref must have the same shape; got {img.shape} and {ref.shape}")
    return img.astype(np.float64, copy=False), ref.astype(np.float64, copy=False)


def _check_mask(mask, shape):
    if mask is None:
        return None
    if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_:
        got = mask.dtype if isinstance(mask, np.ndarray) else type(mask).__name__
        raise TypeError(f"mask must be a bool numpy array of shape (H, W); got {got}")
    if mask.shape != tuple(shape[:2]):
        raise ValueError(f"mask must have shape (H, W) = {tuple(shape[:2])}; got {mask.shape}")
    return mask


def psnr(img, ref, mask=None, data_range=1.0):
    """Peak signal-to-noise ratio in dB.

    img, ref: (H, W, C) float arrays. mask: optional (H, W) bool; the MSE is
    then taken over the masked pixels (all channels). data_range: the peak
    value (1 for images in [0, 1]). Returns +inf for identical images.
    Unmasked, equals ``skimage.metrics.peak_signal_noise_ratio(ref, img,
    data_range=data_range)``.
    """
    img, ref = _check_image_pair(img, ref)
    mask = _check_mask(mask, img.shape)
    data_range = float(data_range)
    if not (np.isfinite(data_range) and data_range > 0):
        raise ValueError(f"data_range must be a positive finite number; got {data_range}")
    sq = (img - ref) ** 2
    if mask is not None:
        if not np.any(mask):
            raise ValueError("mask selects no pixels; PSNR over an empty set is undefined")
        sq = sq[mask]
    mse = float(np.mean(sq, dtype=np.float64))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range * data_range / mse))


def ssim(img, ref, mask=None):
    """Structural similarity (Gaussian window 11, sigma 1.5, data range 1).

    img, ref: (H, W, C) float arrays, H and W at least 11. mask: optional
    (H, W) bool. The per-pixel, per-channel SSIM map is averaged over the
    interior (a border of 5 pixels dropped, as scikit-image does) and over
    channels; with a mask, only over interior pixels where the mask is True.
    Unmasked, equals ``skimage.metrics.structural_similarity(img, ref,
    channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5)``.
    """
    img, ref = _check_image_pair(img, ref)
    mask = _check_mask(mask, img.shape)
    h, w = img.shape[:2]
    if min(h, w) < SSIM_WINDOW:
        raise ValueError(
            f"ssim needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels (the window size); got {h}x{w}"
        )
    smap = ssim_map(img, ref)  # the training loss's implementation (d2gs_np.losses.ssim)
    interior = (slice(_SSIM_PAD, h - _SSIM_PAD), slice(_SSIM_PAD, w - _SSIM_PAD))
    smap = smap[interior]
    if mask is None:
        return float(np.mean(smap, dtype=np.float64))
    m = mask[interior]
    if not np.any(m):
        raise ValueError(
            f"mask selects no pixels inside the SSIM interior (the {_SSIM_PAD}-pixel border "
            "is excluded); SSIM over an empty set is undefined"
        )
    return float(np.mean(smap[m], dtype=np.float64))


FLIP_PPD = 67.02064514160156  # FLIP's default pixels per degree (0.7 m wide 3840-px monitor at 0.7 m)


def flip(img, ref, ppd=FLIP_PPD):
    """Mean LDR-FLIP error of ``img`` against ``ref`` (module docstring), in [0, 1]; 0 when equal.

    img, ref: (H, W, 3) float arrays of sRGB values, clipped to [0, 1]. ppd: pixels per degree of
    visual angle (FLIP's default 67; larger = viewed from farther, small errors matter less).
    """
    img, ref = _check_image_pair(img, ref)
    if img.shape[2] != 3:
        raise ValueError(f"flip needs RGB images (H, W, 3); got {img.shape}")
    ppd = float(ppd)
    if not (np.isfinite(ppd) and ppd > 0):
        raise ValueError(f"ppd (pixels per degree) must be a positive finite number; got {ppd}")
    try:
        import flip_evaluator
    except ImportError as e:  # a dependency in setup.cfg; only a broken install gets here
        raise ImportError("flip needs the flip-evaluator package (pip install flip-evaluator)") from e
    a = np.ascontiguousarray(np.clip(img, 0.0, 1.0), dtype=np.float32)
    b = np.ascontiguousarray(np.clip(ref, 0.0, 1.0), dtype=np.float32)
    _, mean, _ = flip_evaluator.evaluate(b, a, "LDR", inputsRGB=True, applyMagma=False,
                                         computeMeanError=True, parameters={"ppd": ppd})
    return float(mean)


def gradient_energy(img):
    """Mean squared forward difference of the image's grey level (the channel mean), horizontal
    plus vertical: the energy of its finest detail. Blur lowers it; without ground truth, a render's
    gradient energy over the blurry input's says whether the render is sharper (> 1) or not.

    img: (H, W) or (H, W, C) float array with H, W >= 2; accumulated in float64.
    """
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 3:
        a = a.mean(axis=2)
    if a.ndim != 2 or min(a.shape) < 2:
        raise ValueError(f"img must have shape (H, W) or (H, W, C) with H, W >= 2; got {np.shape(img)}")
    if not np.all(np.isfinite(a)):
        raise ValueError("img contains NaN or inf; every pixel must be finite")
    return float(np.mean(np.diff(a, axis=1) ** 2) + np.mean(np.diff(a, axis=0) ** 2))


def depth_errors(pred, true, mask=None) -> dict:
    """AbsRel (mean |pred - true| / true) and delta1 (share of pixels with max(pred/true,
    true/pred) < 1.25) of a depth map over the scored pixels of ``depth_error_terms``;
    ``num_pixels`` 0 gives None for both."""
    if mask is not None:
        _check_mask(mask, np.shape(true))
    rel, ratio = depth_error_terms(pred, true, mask)
    if rel.size == 0:
        return {"absrel": None, "delta1": None, "num_pixels": 0}
    return {"absrel": float(rel.mean()), "delta1": float(np.mean(ratio < 1.25)), "num_pixels": int(rel.size)}


def seed_depth_ratio(frames, points, source_frames, source_pixels):
    """Each initial point's depth in its source frame over that frame's true depth (``depth``) at
    the pixel that holds its source pixel (pixel centres at +0.5): (P,) floats, 1 where a seed sits
    on the true surface. How far the dynamic seeds' depth rule is from the movers
    (docs/method.md §8)."""
    src, pix = np.asarray(source_frames), np.asarray(source_pixels, dtype=np.float64)
    ratio = np.empty(len(src))
    for k in np.unique(src):
        f = frames[int(k)]
        if f.depth is None:
            raise ValueError(f"seed_depth_ratio: frame {int(k)} has no true depth map")
        _, z = project_points(np.asarray(points)[src == k], f.cam_T_world, f.K)
        p = pix[src == k]
        row = np.clip(p[:, 1].astype(int), 0, f.height - 1)
        col = np.clip(p[:, 0].astype(int), 0, f.width - 1)
        ratio[src == k] = z / f.depth[row, col]
    return ratio


def lpips(img, ref, *args, **kwargs):
    """LPIPS is not available: it needs pretrained network weights (AlexNet/VGG
    plus the LPIPS linear heads) that cannot be downloaded in this environment.
    Always raises NotImplementedError; nothing is approximated."""
    raise NotImplementedError(
        "LPIPS needs pretrained network weights (AlexNet/VGG and the LPIPS linear layers) "
        "that cannot be downloaded in this environment, so d2gs_np does not compute it. "
        "Report PSNR, SSIM and FLIP (d2gs_np.evaluation.metrics.flip), or compute LPIPS offline (e.g. with the `lpips` package) "
        "on the saved renders."
    )


def trajectory_reprojection_error(means, coefs, deform_config, frames, truth):
    """How far dynamic Gaussians' trajectories (base ``means`` (P, 3) plus deformation ``coefs``
    (P, K, 3) of ``deform_config``) project from where their points truly are: ``truth`` (M, P, 2)
    pixels in each of the M ``frames`` (objects with cam_T_world, K, time, width, height), NaN
    where unknown (e.g. ``d2gs_np.data.suite.mover_point_tracks``). Returns (M,): per frame the
    median error in pixels over the points whose true pixel is inside that image (a trajectory
    behind the camera counts as infinitely far); NaN in a frame with none."""
    means = np.asarray(means, dtype=np.float64)
    coefs = np.asarray(coefs, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if truth.shape != (len(frames), len(means), 2) or coefs.shape[::2] != (len(means), 3):
        raise ValueError(f"trajectory_reprojection_error: truth must have shape ({len(frames)}, {len(means)}, 2) "
                         f"and coefs ({len(means)}, K, 3); got {truth.shape} and {coefs.shape}")
    out = np.full(len(frames), np.nan)
    for m, f in enumerate(frames):
        b = deform_basis(float(f.time), deform_config)[0]
        uv, z = project_points(means + np.einsum("k,nkd->nd", b, coefs), f.cam_T_world, f.K)
        t = truth[m]
        inview = np.isfinite(t).all(axis=1) & (t[:, 0] >= 0) & (t[:, 0] < f.width) & (t[:, 1] >= 0) \
            & (t[:, 1] < f.height)
        if inview.any():
            err = np.linalg.norm(uv[inview] - t[inview], axis=1)
            err[z[inview] <= 0] = np.inf
            out[m] = float(np.median(err))
    return out
