"""Front-to-back alpha compositing of projected Gaussians, dense NumPy: forward and backward.

Every Gaussian of the given front-to-back order is evaluated on every pixel at once ((H, W)
arrays); a pixel outside a Gaussian's 3.33 sigma box always has alpha < 1/255 (docs/conventions.md §4),
so this dense evaluation gives the same image as the tiled one. Per pixel (docs/conventions.md §6):

    d = mean2d - (j + 0.5, i + 0.5)
    sigma = 0.5 (a dx^2 + c dy^2) + b dx dy
    alpha = min(0.999, o exp(-sigma))
    skip if sigma < 0 or alpha < 1/255
    stop (pixel done, this Gaussian not added) if T (1 - alpha) <= 1e-4
    w = alpha T;  C += color w;  D += z w;  T *= (1 - alpha)

Outputs: image = C + T_final background, alpha = 1 - T_final, depth = D,
expected_depth = D / max(alpha, 1e-10).

The forward stores, per step (one Gaussian of the order), the per-pixel transmittance before the
step, alpha, the unclamped o exp(-sigma) and the masks of evaluated / used pixels; the backward
walks the order back to front with the colour and depth accumulated behind each Gaussian.
"""
from __future__ import annotations

import numpy as np

from d2gs_np import constants as C


def _offsets(mean2d, px, py):
    """d = mean2d - pixel centre, as a (1, W) row of dx and an (H, 1) column of dy."""
    dx = mean2d[0] - px[None, :]
    dy = mean2d[1] - py[:, None]
    return dx, dy


def rasterize_fwd(means2d, conics, colors, opacities, depths, order, width, height, background):
    """Composite Gaussians in ``order`` (front to back) into an image.

    means2d (N,2), conics (N,3), colors (N,3), opacities (N,) effective, depths (N,) camera z,
    order (S,) int indices of the Gaussians to composite, front to back; background (3,).
    Returns (out, saved); out has "image" (H,W,3), "alpha", "depth", "expected_depth" (H,W) and
    "num_intersections" = number of (Gaussian, pixel) evaluations made (pixels not yet stopped).
    """
    dtype = means2d.dtype
    H, W = int(height), int(width)
    px = np.arange(W, dtype=dtype) + C.PIXEL_CENTER_OFFSET  # (W,) pixel centre x
    py = np.arange(H, dtype=dtype) + C.PIXEL_CENTER_OFFSET  # (H,) pixel centre y

    T = np.ones((H, W), dtype=dtype)
    done = np.zeros((H, W), dtype=bool)
    Cimg = np.zeros((H, W, 3), dtype=dtype)
    D = np.zeros((H, W), dtype=dtype)
    steps = {"T": [], "alpha": [], "raw_alpha": [], "evaluated": [], "used": []}
    n_eval = 0
    order = np.asarray(order, dtype=np.int64)
    n_steps = 0
    for g in order:
        if done.all():  # every pixel stopped: later Gaussians cannot change anything
            break
        a, b, c = conics[g]
        dx, dy = _offsets(means2d[g], px, py)
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy  # (H, W)
        raw = opacities[g] * np.exp(-sigma)
        alpha = np.minimum(C.ALPHA_MAX, raw)
        evaluated = ~done
        passed = evaluated & ~(sigma < 0) & ~(alpha < C.ALPHA_THRESHOLD)
        next_T = T * (1 - alpha)
        stop = passed & (next_T <= C.TRANSMITTANCE_MIN)
        used = passed & ~stop
        w = np.where(used, alpha * T, 0)
        Cimg += colors[g] * w[:, :, None]
        D += depths[g] * w

        steps["T"].append(T)
        steps["alpha"].append(alpha)
        steps["raw_alpha"].append(raw)
        steps["evaluated"].append(evaluated)
        steps["used"].append(used)
        n_eval += int(evaluated.sum())
        n_steps += 1

        T = np.where(used, next_T, T)
        done = done | stop

    alpha_out = 1 - T
    out = {
        "image": Cimg + T[:, :, None] * background,
        "alpha": alpha_out,
        "depth": D,
        "expected_depth": D / np.maximum(alpha_out, C.EXPECTED_DEPTH_ALPHA_MIN),
        "num_intersections": n_eval,
    }

    def _stack(key, dt):
        if n_steps:
            return np.stack(steps[key])
        return np.zeros((0, H, W), dtype=dt)

    saved = {
        "means2d": means2d, "conics": conics, "colors": colors, "opacities": opacities,
        "depths": depths, "background": background, "px": px, "py": py,
        "order": order[:n_steps],
        "T": _stack("T", dtype), "alpha": _stack("alpha", dtype), "raw_alpha": _stack("raw_alpha", dtype),
        "evaluated": _stack("evaluated", bool), "used": _stack("used", bool),
        "T_final": T, "C": Cimg, "D": D, "alpha_out": alpha_out,
    }
    return out, saved


def rasterize_bwd(saved, v_image, v_alpha, v_depth, v_expected_depth):
    """Backward of ``rasterize_fwd``. All cotangents are arrays ((H,W,3) and (H,W)).

    Returns dict: "means2d" (N,2), "conics" (N,3), "colors" (N,3), "opacities" (N,) (effective),
    "depths" (N,), "background" (3,).
    """
    s = saved
    means2d, conics, colors, opac, depths = s["means2d"], s["conics"], s["colors"], s["opacities"], s["depths"]
    dtype = means2d.dtype
    n = means2d.shape[0]
    T_f, D, A = s["T_final"], s["D"], s["alpha_out"]
    bg = s["background"]

    # expected_depth = D / max(A, 1e-10):
    # dL_dD += v_ed / max(A, 1e-10); dL_dA += -v_ed D / A^2 unless the clamp is active.
    A_c = np.maximum(A, C.EXPECTED_DEPTH_ALPHA_MIN)
    ed_free = A >= C.EXPECTED_DEPTH_ALPHA_MIN
    v_D = v_depth + v_expected_depth / A_c
    v_A = v_alpha + np.where(ed_free, -v_expected_depth * D / (A_c * A_c), 0)
    # image = C + T_f bg, alpha = 1 - T_f:  dL_dT_f = v_image . bg - dL_dA;  dL_dbg = sum v_image T_f
    v_C = v_image
    v_Tf = np.sum(v_image * bg, axis=-1) - v_A
    v_background = np.sum(v_image * T_f[:, :, None], axis=(0, 1))

    v_means2d = np.zeros((n, 2), dtype=dtype)
    v_means2d_abs = np.zeros((n, 2), dtype=dtype)  # sums of |each pixel's term| (gsplat's absgrad)
    v_conics = np.zeros((n, 3), dtype=dtype)
    v_colors = np.zeros((n, 3), dtype=dtype)
    v_opac = np.zeros(n, dtype=dtype)
    v_depths = np.zeros(n, dtype=dtype)

    # Colour and depth accumulated behind the current Gaussian: S_C = sum_{j>i} c_j w_j,
    # S_D = sum_{j>i} z_j w_j (weights w_j = alpha_j T_j, not renormalised).
    H, W = T_f.shape
    S_C = np.zeros((H, W, 3), dtype=dtype)
    S_D = np.zeros((H, W), dtype=dtype)
    # Background term of dL/dalpha_i: T_f depends on alpha_i through the factor (1 - alpha_i).
    bg_term = v_Tf * T_f
    order = s["order"]
    for k in range(len(order) - 1, -1, -1):
        g = order[k]
        used = s["used"][k]
        if not used.any():
            continue
        T, alpha, raw = s["T"][k], s["alpha"][k], s["raw_alpha"][k]
        w = np.where(used, alpha * T, 0)

        # C += c_i w_i, D += z_i w_i:  dL_dc_i = sum_pix v_C w_i;  dL_dz_i = sum_pix v_D w_i
        v_colors[g] = np.sum(v_C * w[:, :, None], axis=(0, 1))
        v_depths[g] = np.sum(v_D * w)

        # dC/dalpha_i = c_i T_i - S_C,i / (1 - alpha_i)  (each later weight carries (1 - alpha_i));
        # the same for D, and dT_f/dalpha_i = -T_f / (1 - alpha_i).
        one_minus = 1 - alpha
        v_alpha_i = (T * (np.sum(v_C * colors[g], axis=-1) + v_D * depths[g])
                     - (np.sum(v_C * S_C, axis=-1) + v_D * S_D + bg_term) / one_minus)

        # alpha = min(0.999, o exp(-sigma)): no gradient once o exp(-sigma) > 0.999
        v_raw = np.where(used & (raw <= C.ALPHA_MAX), v_alpha_i, 0)
        # raw = o exp(-sigma):  dL_do = sum v_raw exp(-sigma);  dL_dsigma = -v_raw raw
        a, b, c = conics[g]
        dx, dy = _offsets(means2d[g], s["px"], s["py"])
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        v_opac[g] = np.sum(v_raw * np.exp(-sigma))
        v_sigma = -v_raw * raw
        # sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with d = mean2d - pixel centre
        v_conics[g, 0] = np.sum(0.5 * dx * dx * v_sigma)
        v_conics[g, 1] = np.sum(dx * dy * v_sigma)
        v_conics[g, 2] = np.sum(0.5 * dy * dy * v_sigma)
        v_means2d[g, 0] = np.sum(v_sigma * (a * dx + b * dy))
        v_means2d[g, 1] = np.sum(v_sigma * (b * dx + c * dy))
        v_means2d_abs[g, 0] = np.sum(np.abs(v_sigma * (a * dx + b * dy)))
        v_means2d_abs[g, 1] = np.sum(np.abs(v_sigma * (b * dx + c * dy)))

        S_C += colors[g] * w[:, :, None]
        S_D += depths[g] * w

    return {
        "means2d": v_means2d,
        "means2d_abs": v_means2d_abs,
        "conics": v_conics,
        "colors": v_colors,
        "opacities": v_opac,
        "depths": v_depths,
        "background": v_background,
    }
