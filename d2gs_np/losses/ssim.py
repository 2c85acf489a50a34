"""SSIM with scikit-image's exact semantics, and its exact backward.

The value is that of ``skimage.metrics.structural_similarity(img, ref, channel_axis=-1,
data_range=1.0, gaussian_weights=True, sigma=1.5)`` (scikit-image 0.26):

- local statistics by a Gaussian filter, sigma = 1.5, truncate = 3.5 -> radius 5, 11 taps,
  ``scipy.ndimage.gaussian_filter`` semantics with mode 'reflect' (half-sample symmetric:
  ``d c b a | a b c d | d c b a``);
- sample covariances: cov_norm = NP / (NP - 1) with NP = 11 * 11 = 121 (skimage's default
  ``use_sample_covariance=True``; NP is win_size ** ndim of the per-channel 2D image);
- C1 = (0.01 * 1)^2, C2 = (0.03 * 1)^2 (``SSIM_C1``, ``SSIM_C2``);
- S = (2 ux uy + C1)(2 vxy + C2) / ((ux^2 + uy^2 + C1)(vx + vy + C2)) per pixel and channel;
- the value is the mean of S over the interior (a 5-pixel border, (win - 1) // 2, is cropped),
  averaged over channels (equal weights, so the plain mean over interior pixels and channels).

The filter and its adjoint. The backward needs G^T, the transpose of the padded filter. In 1-D
the filter with 'reflect' padding (valid for n >= radius, guaranteed by n >= 11) is the matrix

    F[i, j] = sum over the mirror images j' of j in {j, -1 - j, 2n - 1 - j} of w(j' - i),

and with a symmetric kernel, w(-1 - j - i) and w(2n - 1 - j - i) are symmetric in (i, j) like
w(j - i); so F = F^T and the 2-D separable filter is self-adjoint: ``_blur_adjoint`` is
``_blur``. (This is a property of the half-sample symmetric padding: with 'nearest' or
'constant' padding F is not symmetric.) The tests build the dense F for several n and check
F = F^T, and check the whole backward, border pixels included, against central differences.
The filter itself is ``scipy.ndimage.correlate1d`` along H then W with scipy's own kernel,
i.e. exactly the call skimage makes through ``gaussian_filter``.

Only the gradient w.r.t. ``img`` is returned (``ref`` is the target).

Images are (H, W, C) float64 or float32 (kept: float32 in, float32 out), H, W >= 11.
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import correlate1d

from d2gs_np.constants import SSIM_C1, SSIM_C2

__all__ = ["SSIM_WINDOW", "ssim_map", "ssim_fwd", "ssim_bwd"]

_SIGMA = 1.5  # skimage's gaussian_weights sigma (Wang et al. 2004)
_TRUNCATE = 3.5  # skimage fixes truncate = 3.5 for gaussian_weights: an 11-tap window
_RADIUS = int(_TRUNCATE * _SIGMA + 0.5)  # 5, as scipy.ndimage computes it
SSIM_WINDOW = 2 * _RADIUS + 1  # 11
_NP = SSIM_WINDOW**2  # pixels in the 2D window
_COV_NORM = _NP / (_NP - 1.0)  # sample covariance, skimage's default


def _kernel():
    """scipy.ndimage._gaussian_kernel1d(1.5, 0, 5): symmetric, so correlation = convolution."""
    x = np.arange(-_RADIUS, _RADIUS + 1)
    phi = np.exp(-0.5 / (_SIGMA * _SIGMA) * x**2)
    return phi / phi.sum()


_KERNEL64 = _kernel()


def _blur(x):
    """Gaussian filter along axes 1 and 2 of a (S, H, W, C) stack (scipy's reflect semantics)."""
    w = _KERNEL64.astype(x.dtype)
    y = correlate1d(x, w, axis=1, mode="reflect")
    return correlate1d(y, w, axis=2, mode="reflect")


def _blur_adjoint(v):
    """Exact adjoint of ``_blur``: the filter itself, which is symmetric (module docstring)."""
    return _blur(v)


def _check_images(img, ref):
    for name, x in (("img", img), ("ref", ref)):
        if not isinstance(x, np.ndarray):
            raise TypeError(f"{name} must be a numpy array; got {type(x).__name__}")
        if x.dtype not in (np.float64, np.float32):
            raise TypeError(f"{name} must be float64 or float32; got {x.dtype}")
        if x.ndim != 3:
            raise ValueError(f"{name} must have shape (H, W, C); got {x.shape}")
    if ref.dtype != img.dtype:
        raise TypeError(f"ref has dtype {ref.dtype} but img has {img.dtype}; cast both to one dtype")
    if ref.shape != img.shape:
        raise ValueError(f"ref must have the shape of img {img.shape}; got {ref.shape}")
    H, W = img.shape[:2]
    if H < SSIM_WINDOW or W < SSIM_WINDOW:
        raise ValueError(
            f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels (its Gaussian window has "
            f"{SSIM_WINDOW} taps); got {H}x{W}. Evaluate at a higher resolution or drop the SSIM term "
            "(lambda_ssim=0)"
        )
    for name, x in (("img", img), ("ref", ref)):
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{name} contains NaN or inf; every pixel must be finite")


def _ssim_parts(img, ref):
    """Local statistics and the SSIM map S (H, W, C), with everything the backward needs."""
    stats = _blur(np.stack([img, ref, img * img, ref * ref, img * ref]))  # (5, H, W, C)
    ux, uy, uxx, uyy, uxy = stats
    vx = _COV_NORM * (uxx - ux * ux)
    vy = _COV_NORM * (uyy - uy * uy)
    vxy = _COV_NORM * (uxy - ux * uy)
    A1 = 2 * ux * uy + SSIM_C1
    A2 = 2 * vxy + SSIM_C2
    B1 = ux**2 + uy**2 + SSIM_C1
    B2 = vx + vy + SSIM_C2
    D = B1 * B2
    S = (A1 * A2) / D
    return dict(img=img, ref=ref, ux=ux, uy=uy, A1=A1, A2=A2, B1=B1, B2=B2, D=D, S=S)


def _interior_weights(shape, dtype, pixel_weights=None):
    """Weights (H, W, 1) such that SSIM value = sum(weights * S).

    Without ``pixel_weights``: 1 / (Hc Wc C) on the interior (border of (win - 1) // 2 cropped),
    0 on the border: the mean over interior pixels and channels. With ``pixel_weights`` (H, W) >= 0:
    the weighted mean over the interior, weights pixel_weights / (C * sum over the interior).
    """
    H, W, C = shape
    r = _RADIUS
    inner = np.zeros((H, W), dtype=np.float64)
    inner[r:H - r, r:W - r] = 1.0
    if pixel_weights is not None:
        inner = inner * pixel_weights
    total = inner.sum()
    if not total > 0.0:
        raise ValueError(
            f"the mask has no weight inside the SSIM interior (the {r}-pixel border is cropped); "
            "enlarge the mask or drop the SSIM term"
        )
    return (inner / (C * total)).astype(dtype)[:, :, None]


def ssim_map(img, ref):
    """Per-pixel, per-channel SSIM map S (H, W, C) of img against ref (skimage's ``full=True`` S).

    img, ref: (H, W, C) in [0, 1] (data_range = 1), same float dtype, H, W >= 11. The SSIM value
    is the mean of this map over ``S[5:-5, 5:-5, :]``.
    """
    _check_images(img, ref)
    return _ssim_parts(img, ref)["S"]


def _ssim_fwd_weighted(img, ref, pixel_weights=None):
    """SSIM value with optional per-pixel weights (H, W) over the interior; see ``ssim_fwd``."""
    _check_images(img, ref)
    parts = _ssim_parts(img, ref)
    weights = _interior_weights(img.shape, img.dtype, pixel_weights)
    value = img.dtype.type(np.sum(weights * parts["S"], dtype=np.float64))  # float64 accumulation, as skimage
    parts["weights"] = weights
    return value, parts


def ssim_fwd(img, ref):
    """Mean SSIM of img against ref, exactly skimage's (see the module docstring).

    img, ref: (H, W, C), same float dtype, H, W >= 11. Returns (value, saved); value is a scalar
    of the images' dtype.
    """
    return _ssim_fwd_weighted(img, ref)


def ssim_bwd(saved, v_value=1.0):
    """Gradient of ``v_value * ssim_fwd(img, ref)[0]`` w.r.t. img, (H, W, C), img's dtype."""
    img, ref, ux, uy = saved["img"], saved["ref"], saved["ux"], saved["uy"]
    A1, A2, B1, B2, D, S = (saved[k] for k in ("A1", "A2", "B1", "B2", "D", "S"))
    cn = _COV_NORM
    v_S = (img.dtype.type(v_value) * saved["weights"]) * np.ones_like(S)
    # S = A1 A2 / (B1 B2)
    v_A1 = v_S * A2 / D
    v_A2 = v_S * A1 / D
    v_B1 = -v_S * S / B1
    v_B2 = -v_S * S / B2
    # A1 = 2 ux uy + C1, B1 = ux^2 + uy^2 + C1
    v_ux = 2 * uy * v_A1 + 2 * ux * v_B1
    # A2 = 2 vxy + C2, B2 = vx + vy + C2; vx = cn (uxx - ux^2), vxy = cn (uxy - ux uy)
    v_vx = v_B2
    v_vxy = 2 * v_A2
    v_uxx = cn * v_vx
    v_uxy = cn * v_vxy
    v_ux = v_ux - 2 * cn * ux * v_vx - cn * uy * v_vxy
    # ux = G img, uxx = G (img^2), uxy = G (img ref)
    back = _blur_adjoint(np.stack([v_ux, v_uxx, v_uxy]))  # (3, H, W, C)
    return back[0] + 2 * img * back[1] + ref * back[2]
