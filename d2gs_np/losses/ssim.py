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

The filter is written as an explicit symmetric padding followed by a separable 11-tap
correlation, and its adjoint ``_blur_adjoint`` as the transpose of those two steps (scatter
through the taps, then fold the padded border back onto the pixels it copied). For this
padding the two coincide: in 1-D the operator is F[i, j] = sum over the mirror images j' of j
(j, -1 - j, 2n - 1 - j) of w(j' - i), and with a symmetric kernel each term is symmetric in
(i, j), so F = F^T (it would not be for 'nearest' or 'constant' padding). The tests check both
the transpose identity and F = F^T. Only the gradient w.r.t. ``img`` is returned (``ref`` is
the target).

Images are (H, W, C) float64 or float32 (kept: float32 in, float32 out), H, W >= 11.
"""
from __future__ import annotations

import numpy as np

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


def _correlate_axis0(x, w):
    """Symmetric pad by r along axis 0, then the 'valid' correlation with w (2r+1 taps)."""
    n = x.shape[0]
    pad = [(_RADIUS, _RADIUS)] + [(0, 0)] * (x.ndim - 1)
    xp = np.pad(x, pad, mode="symmetric")  # numpy 'symmetric' == scipy.ndimage 'reflect'
    out = w[0] * xp[0:n]
    for k in range(1, w.shape[0]):
        out = out + w[k] * xp[k:k + n]
    return out


def _correlate_axis0_adjoint(v, w):
    """Adjoint of ``_correlate_axis0``: scatter through the taps, then fold the padding back."""
    n, r = v.shape[0], _RADIUS
    v_xp = np.zeros((n + 2 * r,) + v.shape[1:], dtype=v.dtype)
    for k in range(w.shape[0]):
        v_xp[k:k + n] += w[k] * v
    v_x = v_xp[r:r + n].copy()
    v_x[:r] += v_xp[:r][::-1]  # padded entry j < r was a copy of x[r - 1 - j]
    v_x[n - r:] += v_xp[r + n:][::-1]  # padded entry r + n + m was a copy of x[n - 1 - m]
    return v_x


def _blur(x):
    """Gaussian filter of (H, W, ...) arrays along axes 0 and 1 (scipy's reflect semantics)."""
    w = _KERNEL64.astype(x.dtype)
    y = _correlate_axis0(x, w)
    return _correlate_axis0(y.swapaxes(0, 1), w).swapaxes(0, 1)


def _blur_adjoint(v):
    """Exact adjoint (transpose) of ``_blur``."""
    w = _KERNEL64.astype(v.dtype)
    y = _correlate_axis0_adjoint(v.swapaxes(0, 1), w).swapaxes(0, 1)
    return _correlate_axis0_adjoint(y, w)


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
    stats = _blur(np.stack([img, ref, img * img, ref * ref, img * ref], axis=-1))  # (H, W, C, 5)
    ux, uy, uxx, uyy, uxy = (stats[..., i] for i in range(5))
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
    back = _blur_adjoint(np.stack([v_ux, v_uxx, v_uxy], axis=-1))
    return back[..., 0] + 2 * img * back[..., 1] + ref * back[..., 2]
