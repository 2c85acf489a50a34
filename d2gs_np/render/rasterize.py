"""Compositing of projected Gaussians over screen tiles, forward and backward.

Pipeline (docs/conventions.md §5-8, gsplat 1.5.3). Steps 1-2, the tile lists, are render/binning.py's
``build_intersections``: per tile, the Gaussians whose bands reach it, front to back
(``isect_gauss``, delimited by ``tile_offsets``), and ``slot_to_isect``, which maps each Gaussian's
own numbering of its intersections to list positions. Here:

3. ``_rasterize_fwd_kernel`` (prange over tiles): every pixel composites its tile's list front to
   back with the exact rules of §6 (skip if sigma < 0 or alpha < 1/255; alpha clamped at 0.999;
   stop *before* a Gaussian that would bring T(1-alpha) <= 1e-4) and stores its final
   transmittance and the list position of its last contributor. Inside a tile the Gaussians are
   the outer loop (front to back) with per-pixel state in tile-local arrays laid out as column
   strips (``_STRIP`` wide, each row-major: ``_lane``). Each Gaussian visits its band: the rows
   and columns of its 3.33-sigma box where the row (column) minimum of sigma is <= ln(255 o) +
   ALPHA_CUTOFF_SAFETY (``_band_rows``, ``_band_cols``), rows padded to whole vectors
   (``_pad_rows``), as one contiguous run of lanes per strip it reaches. Outside the band alpha <
   1/255 for certain (with a relative margin of 1e-3 >> rounding), so the skipped pairs are
   exactly those the rule skips. Each run is composited by a branch-free loop
   (``_composite_band``: every lane computes alpha with an inline polynomial exp, ``exp_neg`` of
   render/fast_exp.py, and changes state only when the rules say so) that LLVM vectorises (8
   float64 lanes with AVX-512): more lanes than the exact per-row footprint (~1.6-2x), but each
   several times cheaper than in a scalar, branchy loop with a libm exp.
4. ``_rasterize_bwd_kernel`` (prange over tiles): the same bands, Gaussians from the tile's
   latest last contributor back to its first; each pixel walks its own contributors back to
   front, recovering T_k = T_{k+1} / (1 - alpha_k) (safe: alpha <= 0.999), as 3DGS and gsplat
   do. A vectorised branch-free pass (``_backprop_band``) updates the per-pixel state and writes
   three per-lane terms; a second vectorised pass (``_sum_terms``, reassociation allowed: the
   order is fixed by the build, not left to right) sums the ten gradient terms of the
   intersection over the band's lanes, strip by strip in order, and the absolute values of the
   per-pixel terms of dL/d(mean2d) (gsplat's ``absgrad``, AbsGS: what densification reads), and
   writes them once to its own row of ``buf`` (n_isect, 12); a row belongs to one tile, so to
   one thread.
5. ``_isect_reduce_kernel`` (prange over Gaussians): each Gaussian sums its own rows of ``buf``
   in its fixed slot order.

Determinism: no floating-point sum in the backward pass depends on thread scheduling (each sum
is owned by one loop iteration and runs in a fixed order), so gradients are bitwise identical
run to run and for any number of threads. Memory is O(N + n_isect + pixels), never O(N x pixels):
the per-tile scratch is O(tile pixels + tile list length).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from d2gs_np import constants as C
from d2gs_np.render.binning import band, inv_axis_vars, tile_order
from d2gs_np.render.fast_exp import exp_consts, exp_neg, unpack_exp_consts
from d2gs_np.render.project import (
    K_DET_MIN,
    K_TWO,
    K_ALPHA_MAX,
    K_ALPHA_THRESHOLD,
    K_HALF,
    K_ONE,
    K_T_MIN,
    K_ZERO,
)

# Columns of the tile-local packed parameters (all 16) and of the gradient buffer (the first 10,
# then _AU, _AV: the sums of |per-pixel dL/du|, |per-pixel dL/dv|).
_U, _V, _CA, _CB, _CC, _OP, _R, _G, _B, _Z, _RX, _RY, _CUT, _IC00, _IC11 = range(15)
_AU, _AV = 10, 11
_NCOL = 12
_NLOC = 15
# Tile-local pixel layout: the tile is cut into column strips _STRIP pixels wide, each stored
# row-major, one after the other, so that the rows [ia, ib) of one strip are one contiguous run of
# lanes. A Gaussian visits only the strips its columns reach: narrower strips waste fewer lanes
# on the sides, wider ones make longer runs (vector loops need several vectors per run); the width
# is chosen by examples/profile_step.py (docs/results.md §6). The backward pass
# sums gradients in this lane order, so results depend on it (deterministically).
_STRIP = 8
_ROW_GROUP = 2  # bands are padded to a multiple of this many rows (``_pad_rows``): 16-lane runs


@njit(cache=True)
def _gather_tile(start, end, isect_gauss, means2d, conics, opac_eff, colors, depths, radii_f, sigma_cut,
                 cov2d, consts):
    """Copy the parameters of a tile's Gaussians, in list order, into a (m, _NLOC) local array.

    Besides the parameters, each row gets the coefficients of the row and column minima of sigma
    used by ``_band_rows`` / ``_band_cols`` (1/c11 and 1/c00 of the covariance).
    """
    m = end - start
    zero = consts[K_ZERO]
    one = consts[K_ONE]
    det_min = consts[K_DET_MIN]
    loc = np.empty((m, _NLOC), consts.dtype)
    for k in range(m):
        g = isect_gauss[start + k]
        loc[k, _U] = means2d[g, 0]
        loc[k, _V] = means2d[g, 1]
        loc[k, _CA] = conics[g, 0]
        loc[k, _CB] = conics[g, 1]
        loc[k, _CC] = conics[g, 2]
        loc[k, _OP] = opac_eff[g]
        loc[k, _R] = colors[g, 0]
        loc[k, _G] = colors[g, 1]
        loc[k, _B] = colors[g, 2]
        loc[k, _Z] = depths[g]
        loc[k, _RX] = radii_f[g, 0]
        loc[k, _RY] = radii_f[g, 1]
        loc[k, _CUT] = sigma_cut[g]
        loc[k, _IC00], loc[k, _IC11] = inv_axis_vars(cov2d[g, 0], cov2d[g, 1], cov2d[g, 2], det_min, zero, one)
    return loc


@njit(cache=True)
def _band_rows(loc, k, y0, y1, half, one, two, zero):
    """Rows [ia, ib) of [y0, y1) where Gaussian k may have sigma <= sigma_cut (``band``)."""
    return band(loc[k, _V], loc[k, _RY], loc[k, _IC11], loc[k, _CUT], y0, y1, half, one, two, zero)


@njit(cache=True)
def _band_cols(loc, k, x0, x1, half, one, two, zero):
    """Columns [ja, jb) of [x0, x1) where Gaussian k may have sigma <= sigma_cut (``band``)."""
    return band(loc[k, _U], loc[k, _RX], loc[k, _IC00], loc[k, _CUT], x0, x1, half, one, two, zero)


@njit(cache=True)
def _lane(i, j, x0, x1, y0, th):
    """Tile-local lane of pixel (i, j) in the strip layout (see ``_STRIP``)."""
    s = (j - x0) // _STRIP
    c0 = x0 + s * _STRIP
    ws = min(_STRIP, x1 - c0)
    return s * _STRIP * th + (i - y0) * ws + (j - c0)


@njit(cache=True)
def _pad_rows(ia, ib, y0, y1):
    """[ia, ib) grown to a multiple of _ROW_GROUP rows inside [y0, y1) (downwards, else upwards):
    runs of whole vectors leave no scalar remainder loop. Extra rows only add lanes that the
    rules of §6 then decide on like any other (so results do not depend on it)."""
    n = ((ib - ia + _ROW_GROUP - 1) // _ROW_GROUP) * _ROW_GROUP
    if n > y1 - y0:
        n = y1 - y0
    if ia + n <= y1:
        return ia, ia + n
    return y1 - n, y1


@njit(cache=True)
def _strip_run(s, ia, ib, x0, x1, y0, th):
    """Lanes [qa, qb) of rows [ia, ib) of strip s."""
    c0 = x0 + s * _STRIP
    ws = min(_STRIP, x1 - c0)
    base = s * _STRIP * th
    return base + (ia - y0) * ws, base + (ib - y0) * ws


@njit(cache=True)
def _sigma(dx, dy, ca, cb, cc, half):
    """sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with d = mean2d - pixel centre.

    Shared by the forward and backward kernels so both take bitwise the same discrete decisions.
    """
    return half * (ca * dx * dx + cc * dy * dy) + cb * dx * dy


@njit(cache=True)
def _tile_pixel_centres(x0, x1, y0, y1, px_centres, py_centres, dtype_like):
    """(2, npix) pixel-centre x and y of the tile's pixels, in the lane layout (``_lane``)."""
    th = y1 - y0
    P = np.empty((2, (x1 - x0) * th), dtype_like.dtype)
    for i in range(y0, y1):
        for j in range(x0, x1):
            q = _lane(i, j, x0, x1, y0, th)
            P[0, q] = px_centres[j]
            P[1, q] = py_centres[i]
    return P


@njit(cache=True)
def _composite_band(S, last, P, qa, qb, u, v, ca, cb, cc, o, cut, col0, col1, col2, zk, idx, amax, athr, tmin,
                    zero, one, half, ec):
    """Forward compositing of one Gaussian over the tile lanes [qa, qb) (uint64; whole tile rows).

    S (6, npix) = per-pixel (T, r, g, b, depth, stopped flag), last (npix,) int64, P (2, npix)
    pixel centres. Branch-free, so that LLVM vectorises it: every lane computes sigma and alpha,
    and a lane changes state only when the rules of docs/conventions.md §6 make the Gaussian
    contribute (sigma in [0, cut], alpha >= 1/255, the pixel not stopped, T(1 - alpha) > 1e-4);
    otherwise it adds exact zeros (x + 0 = x) and keeps T and last. Returns the number of pixels
    that stopped here.
    """
    n_stop = 0
    for q in range(qa, qb):
        dx = u - P[0, q]
        dy = v - P[1, q]
        sigma = _sigma(dx, dy, ca, cb, cc, half)
        alpha = o * exp_neg(sigma, ec)
        alpha = amax if alpha > amax else alpha
        T = S[0, q]
        next_T = T * (one - alpha)
        ok = (sigma >= zero) & (sigma <= cut) & (alpha >= athr) & (S[5, q] == zero)
        stop = ok & (next_T <= tmin)
        use = ok & (next_T > tmin)
        # Every store is unconditional and exact for lanes that do not change (x + 0 = x,
        # T (1 - 0) = T, last + 0 = last): a select of the old value would become a masked store.
        a_used = alpha if use else zero
        w = a_used * T
        S[1, q] += col0 * w
        S[2, q] += col1 * w
        S[3, q] += col2 * w
        S[4, q] += zk * w
        S[0, q] = T * (one - a_used)
        lq = last[q]
        last[q] = lq + ((idx - lq) if use else 0)
        S[5, q] += one if stop else zero
        n_stop += 1 if stop else 0
    return n_stop


@njit(cache=True, parallel=True)
def _rasterize_fwd_kernel(means2d, conics, opac_eff, colors, depths, radii_f, sigma_cut, cov2d, isect_gauss,
                          tile_offsets, tile_order, px_centres, py_centres, background, consts, exp_consts, grid_w,
                          tile_size, image, depth_img, T_final, last_idx, n_eval_tile):
    """Front-to-back compositing, prange over tiles (each pixel written by its tile only).

    Within a tile the Gaussians are the outer loop, in list order (front to back), and each
    visits the rows and column strips of its band (``_band_rows``, ``_band_cols``: they hold every
    pixel with sigma <= sigma_cut) in vectorised passes (``_composite_band``, one per strip),
    keeping per-pixel T, C, D, last contributor and a "stopped" flag. So every pixel still sees
    its Gaussians front to back and applies the exact rules of docs/conventions.md §6; the
    pixels not visited are only pixels the 1/255 rule skips.

    Outputs: image (H,W,3) = C + T_final background, depth_img (H,W) = sum w z, T_final (H,W),
    last_idx (H,W) int64 (list position of the last contributor, -1 if none), n_eval_tile
    (n_tiles,) int64 (number of (Gaussian, pixel) sigma evaluations, for benchmarks).
    """
    H = image.shape[0]
    W = image.shape[1]
    n_tiles = tile_offsets.shape[0] - 1
    zero = consts[K_ZERO]
    one = consts[K_ONE]
    two = consts[K_TWO]
    half = consts[K_HALF]
    amax = consts[K_ALPHA_MAX]
    athr = consts[K_ALPHA_THRESHOLD]
    tmin = consts[K_T_MIN]
    bg0 = background[0]
    bg1 = background[1]
    bg2 = background[2]
    ec = unpack_exp_consts(exp_consts)
    for it in prange(n_tiles):
        t = tile_order[it]
        start = tile_offsets[t]
        end = tile_offsets[t + 1]
        ty = t // grid_w
        tx = t - ty * grid_w
        x0 = tx * tile_size
        y0 = ty * tile_size
        x1 = min(x0 + tile_size, W)
        y1 = min(y0 + tile_size, H)
        tw = x1 - x0
        npix = tw * (y1 - y0)
        S = np.zeros((6, npix), image.dtype)  # T, r, g, b, depth, stopped
        S[0, :] = one
        last = np.full(npix, -1, np.int64)
        P = _tile_pixel_centres(x0, x1, y0, y1, px_centres, py_centres, consts)
        n_stopped = 0
        count = 0
        loc = _gather_tile(start, end, isect_gauss, means2d, conics, opac_eff, colors, depths, radii_f,
                           sigma_cut, cov2d, consts)
        th = y1 - y0
        for k in range(end - start):
            if n_stopped == npix:
                break
            ia, ib = _band_rows(loc, k, y0, y1, half, one, two, zero)
            ja, jb = _band_cols(loc, k, x0, x1, half, one, two, zero)
            if ib <= ia or jb <= ja:
                continue
            ia, ib = _pad_rows(ia, ib, y0, y1)
            for s in range((ja - x0) // _STRIP, (jb - 1 - x0) // _STRIP + 1):
                qa, qb = _strip_run(s, ia, ib, x0, x1, y0, th)
                count += qb - qa
                n_stopped += _composite_band(S, last, P, np.uint64(qa), np.uint64(qb), loc[k, _U], loc[k, _V],
                                             loc[k, _CA], loc[k, _CB], loc[k, _CC], loc[k, _OP], loc[k, _CUT],
                                             loc[k, _R], loc[k, _G], loc[k, _B], loc[k, _Z], start + k, amax,
                                             athr, tmin, zero, one, half, ec)
        for i in range(y0, y1):
            for j in range(x0, x1):
                q = _lane(i, j, x0, x1, y0, th)
                T = S[0, q]
                image[i, j, 0] = S[1, q] + T * bg0
                image[i, j, 1] = S[2, q] + T * bg1
                image[i, j, 2] = S[3, q] + T * bg2
                depth_img[i, j] = S[4, q]
                T_final[i, j] = T
                last_idx[i, j] = last[q]
        n_eval_tile[t] = count


# error_model="numpy": no zero-division check (alpha <= 0.999), which would stop vectorisation
@njit(cache=True, error_model="numpy")
def _backprop_band(S, X, P, V, last, qa, qb, row, u, v, ca, cb, cc, o, cut, col0, col1, col2, zk, amax, athr,
                   zero, one, half, ec):
    """Backward of one Gaussian over the tile lanes [qa, qb) (uint64), branch-free (vectorises).

    S (5, npix) = per-pixel (T behind, sums behind of r, g, b, depth times weight), V (5, npix) =
    per-pixel (dL/dr, dL/dg, dL/db, dL/dD, dL/dT_final x T_final), last (npix,) the last
    contributor of each pixel, P (2, npix) the pixel centres. A lane takes part when the pixel
    composited this Gaussian in the forward pass (row <= last, sigma in [0, cut], alpha >= 1/255:
    the forward's exact decisions); it then recovers T in front (T / (1 - alpha)) and updates S.
    X (3, npix) gets per lane the weight alpha T, dL/dalpha x exp(-sigma) (= dL/dopacity) and
    dL/dsigma = -dL/dalpha x alpha_raw (these two zero through the 0.999 clamp), all zero for
    lanes that do not take part; ``_rasterize_bwd_kernel`` sums the ten gradient terms from them.
    (Three output rows, not ten: more written arrays need more runtime alias checks than LLVM
    allows, and the loop would stay scalar.)
    """
    for q in range(qa, qb):
        dx = u - P[0, q]
        dy = v - P[1, q]
        sigma = _sigma(dx, dy, ca, cb, cc, half)
        vis = exp_neg(sigma, ec)
        raw = o * vis
        alpha = amax if raw > amax else raw
        ok = (row <= last[q]) & (sigma >= zero) & (sigma <= cut) & (alpha >= athr)
        ra = one / (one - alpha)
        T = S[0, q] * ra  # transmittance in front of this Gaussian
        fac = alpha * T
        v_alpha = ((col0 * T - S[1, q] * ra) * V[0, q] + (col1 * T - S[2, q] * ra) * V[1, q]
                   + (col2 * T - S[3, q] * ra) * V[2, q] + (zk * T - S[4, q] * ra) * V[3, q] - V[4, q] * ra)
        S[0, q] = S[0, q] * (ra if ok else one)  # T in front if ok, else unchanged (x 1 is exact)
        S[1, q] += col0 * fac if ok else zero
        S[2, q] += col1 * fac if ok else zero
        S[3, q] += col2 * fac if ok else zero
        S[4, q] += zk * fac if ok else zero
        geo = ok & (raw <= amax)  # no gradient through the 0.999 clamp
        X[0, q] = fac if ok else zero
        X[1, q] = v_alpha * vis if geo else zero
        X[2, q] = -v_alpha * raw if geo else zero


@njit(cache=True, fastmath={"reassoc", "contract"})
def _sum_terms(X, V, P, qa, qb, u, v, ca, cb, cc, half, zero):
    """The ten gradient terms of one Gaussian summed over lanes [qa, qb) (``_backprop_band``'s
    outputs; lanes that did not take part hold zeros and add nothing), and the sums of the
    absolute per-lane terms of dL/du and dL/dv. Reassociation lets LLVM
    vectorise the sums (per-lane partial sums combined at the end): a fixed order for a given
    build, the same for any thread count, but not the plain left-to-right order."""
    g_u = zero
    g_v = zero
    g_a = zero
    g_b = zero
    g_c = zero
    g_o = zero
    g_r = zero
    g_g = zero
    g_bl = zero
    g_z = zero
    g_au = zero
    g_av = zero
    for q in range(qa, qb):
        fac = X[0, q]
        g_r += fac * V[0, q]
        g_g += fac * V[1, q]
        g_bl += fac * V[2, q]
        g_z += fac * V[3, q]
        g_o += X[1, q]
        v_sigma = X[2, q]
        dx = u - P[0, q]
        dy = v - P[1, q]
        g_a += half * dx * dx * v_sigma
        g_b += dx * dy * v_sigma
        g_c += half * dy * dy * v_sigma
        t_u = v_sigma * (ca * dx + cb * dy)
        t_v = v_sigma * (cb * dx + cc * dy)
        g_u += t_u
        g_v += t_v
        g_au += abs(t_u)
        g_av += abs(t_v)
    return g_u, g_v, g_a, g_b, g_c, g_o, g_r, g_g, g_bl, g_z, g_au, g_av


@njit(cache=True, parallel=True)
def _rasterize_bwd_kernel(means2d, conics, opac_eff, colors, depths, radii_f, sigma_cut, cov2d, isect_gauss,
                          tile_offsets, tile_order, px_centres, py_centres, consts, exp_consts, grid_w, tile_size,
                          T_final, last_idx, v_color_img, v_depth_img, v_T_img, buf):
    """Back-to-front gradient of the compositing, prange over tiles.

    v_color_img (H,W,3) = dL/dC, v_depth_img (H,W) = dL/dD, v_T_img (H,W) = dL/dT_final (all
    paths: background, alpha, expected depth). Gaussians are the outer loop, from the tile's
    latest last contributor back to its first, over the same bands as the forward pass
    (``_backprop_band``, vectorised); every pixel walks its own contributors back to front from
    its last one, recovering T_k = T_{k+1} / (1 - alpha_k) (alpha <= 0.999, so the division is
    safe), as 3DGS and gsplat do. The gradient of intersection ``start + k`` (dL/d(u, v, conic
    a, b, c, opacity_eff, r, g, b, z)) is summed over the band's lanes (``_sum_terms``; the lanes
    that do not take part hold zeros) and written once to row start + k of buf
    (n_isect, 12), with the sums of |per-pixel dL/du| and |per-pixel dL/dv| in its last two
    columns; rows no pixel uses stay as given (zero).
    """
    H = T_final.shape[0]
    W = T_final.shape[1]
    n_tiles = tile_offsets.shape[0] - 1
    zero = consts[K_ZERO]
    one = consts[K_ONE]
    two = consts[K_TWO]
    half = consts[K_HALF]
    amax = consts[K_ALPHA_MAX]
    athr = consts[K_ALPHA_THRESHOLD]
    ec = unpack_exp_consts(exp_consts)
    for it in prange(n_tiles):
        t = tile_order[it]
        start = tile_offsets[t]
        end = tile_offsets[t + 1]
        if end == start:
            continue
        ty = t // grid_w
        tx = t - ty * grid_w
        x0 = tx * tile_size
        y0 = ty * tile_size
        x1 = min(x0 + tile_size, W)
        y1 = min(y0 + tile_size, H)
        tw = x1 - x0
        npix = tw * (y1 - y0)
        th = y1 - y0
        last = np.empty(npix, np.int64)
        kmax = -1
        for i in range(y0, y1):
            for j in range(x0, x1):
                q = _lane(i, j, x0, x1, y0, th)
                last[q] = last_idx[i, j]
                if last[q] > kmax:
                    kmax = last[q]
        if kmax < start:
            continue
        S = np.zeros((5, npix), T_final.dtype)  # T behind, sums behind: color * weight (r, g, b), depth * weight
        V = np.empty((5, npix), T_final.dtype)
        for i in range(y0, y1):
            for j in range(x0, x1):
                q = _lane(i, j, x0, x1, y0, th)
                S[0, q] = T_final[i, j]
                V[0, q] = v_color_img[i, j, 0]
                V[1, q] = v_color_img[i, j, 1]
                V[2, q] = v_color_img[i, j, 2]
                V[3, q] = v_depth_img[i, j]
                V[4, q] = v_T_img[i, j] * T_final[i, j]
        X = np.empty((3, npix), T_final.dtype)  # per-lane weight, dL/dopacity, dL/dsigma
        P = _tile_pixel_centres(x0, x1, y0, y1, px_centres, py_centres, consts)
        loc = _gather_tile(start, kmax + 1, isect_gauss, means2d, conics, opac_eff, colors, depths, radii_f,
                           sigma_cut, cov2d, consts)
        for k in range(kmax - start, -1, -1):
            row = start + k
            ia, ib = _band_rows(loc, k, y0, y1, half, one, two, zero)
            ja, jb = _band_cols(loc, k, x0, x1, half, one, two, zero)
            if ib <= ia or jb <= ja:
                continue
            ia, ib = _pad_rows(ia, ib, y0, y1)
            u = loc[k, _U]
            v = loc[k, _V]
            ca = loc[k, _CA]
            cb = loc[k, _CB]
            cc = loc[k, _CC]
            g_u = zero
            g_v = zero
            g_a = zero
            g_b = zero
            g_c = zero
            g_o = zero
            g_r = zero
            g_g = zero
            g_bl = zero
            g_z = zero
            g_au = zero
            g_av = zero
            for s in range((ja - x0) // _STRIP, (jb - 1 - x0) // _STRIP + 1):
                qa, qb = _strip_run(s, ia, ib, x0, x1, y0, th)
                _backprop_band(S, X, P, V, last, np.uint64(qa), np.uint64(qb), row, u, v, ca, cb, cc,
                               loc[k, _OP], loc[k, _CUT], loc[k, _R], loc[k, _G], loc[k, _B], loc[k, _Z], amax,
                               athr, zero, one, half, ec)
                (t_u, t_v, t_a, t_b, t_c, t_o, t_r, t_g, t_bl, t_z, t_au, t_av) = _sum_terms(
                    X, V, P, np.uint64(qa), np.uint64(qb), u, v, ca, cb, cc, half, zero)
                g_u += t_u
                g_v += t_v
                g_a += t_a
                g_b += t_b
                g_c += t_c
                g_o += t_o
                g_r += t_r
                g_g += t_g
                g_bl += t_bl
                g_z += t_z
                g_au += t_au
                g_av += t_av
            buf[row, _U] = g_u
            buf[row, _V] = g_v
            buf[row, _CA] = g_a
            buf[row, _CB] = g_b
            buf[row, _CC] = g_c
            buf[row, _OP] = g_o
            buf[row, _R] = g_r
            buf[row, _G] = g_g
            buf[row, _B] = g_bl
            buf[row, _Z] = g_z
            buf[row, _AU] = g_au
            buf[row, _AV] = g_av


@njit(cache=True, parallel=True)
def _isect_reduce_kernel(buf, slot_to_isect, goff, v_means2d, v_conics, v_opac_eff, v_colors, v_depths,
                         v_means2d_abs):
    """Per-Gaussian sums of its intersection rows of buf, in its fixed slot order (prange over N)."""
    n = goff.shape[0] - 1
    for g in prange(n):
        s0 = goff[g]
        s1 = goff[g + 1]
        if s1 == s0:
            continue
        row = slot_to_isect[s0]
        a_u = buf[row, _U]
        a_v = buf[row, _V]
        a_a = buf[row, _CA]
        a_b = buf[row, _CB]
        a_c = buf[row, _CC]
        a_o = buf[row, _OP]
        a_r = buf[row, _R]
        a_g = buf[row, _G]
        a_bl = buf[row, _B]
        a_z = buf[row, _Z]
        a_au = buf[row, _AU]
        a_av = buf[row, _AV]
        for s in range(s0 + 1, s1):
            row = slot_to_isect[s]
            a_u += buf[row, _U]
            a_v += buf[row, _V]
            a_a += buf[row, _CA]
            a_b += buf[row, _CB]
            a_c += buf[row, _CC]
            a_o += buf[row, _OP]
            a_r += buf[row, _R]
            a_g += buf[row, _G]
            a_bl += buf[row, _B]
            a_z += buf[row, _Z]
            a_au += buf[row, _AU]
            a_av += buf[row, _AV]
        v_means2d[g, 0] = a_u
        v_means2d[g, 1] = a_v
        v_means2d_abs[g, 0] = a_au
        v_means2d_abs[g, 1] = a_av
        v_conics[g, 0] = a_a
        v_conics[g, 1] = a_b
        v_conics[g, 2] = a_c
        v_opac_eff[g] = a_o
        v_colors[g, 0] = a_r
        v_colors[g, 1] = a_g
        v_colors[g, 2] = a_bl
        v_depths[g] = a_z


def pixel_centres(width, height, dtype):
    """(px (W,), py (H,)) pixel-centre coordinates j + 0.5, i + 0.5 in ``dtype``."""
    px = (np.arange(width, dtype=np.float64) + C.PIXEL_CENTER_OFFSET).astype(dtype)
    py = (np.arange(height, dtype=np.float64) + C.PIXEL_CENTER_OFFSET).astype(dtype)
    return px, py


def rasterize_fwd(proj, colors, background, consts, isect, width, height, tile_size):
    """Step 3. Returns dict(image (H,W,3), depth (H,W), T_final (H,W), last_idx (H,W),
    n_eval_tile (n_tiles,), sigma_cut (N,))."""
    dtype = colors.dtype
    px, py = pixel_centres(width, height, dtype)
    n_tiles = isect["tile_offsets"].shape[0] - 1
    sigma_cut = isect["sigma_cut"]
    image = np.empty((height, width, 3), dtype)
    depth = np.empty((height, width), dtype)
    T_final = np.empty((height, width), dtype)
    last_idx = np.empty((height, width), np.int64)
    n_eval_tile = np.zeros(n_tiles, np.int64)
    _rasterize_fwd_kernel(proj["means2d"], proj["conics"], proj["opac_eff"], colors, proj["depths"],
                          proj["radii_f"], sigma_cut, proj["cov2d"], isect["isect_gauss"], isect["tile_offsets"],
                          tile_order(n_tiles), px, py, background, consts, exp_consts(dtype), isect["grid_w"],
                          tile_size, image, depth, T_final, last_idx, n_eval_tile)
    return dict(image=image, depth=depth, T_final=T_final, last_idx=last_idx, n_eval_tile=n_eval_tile,
                sigma_cut=sigma_cut)


def rasterize_bwd(proj, colors, consts, isect, raster, tile_size, v_color_img, v_depth_img, v_T_img):
    """Steps 4-5. Returns dict of per-Gaussian v_means2d (N,2), v_conics (N,3), v_opac_eff (N,),
    v_colors (N,3), v_depths (N,), and v_means2d_abs (N,2): per axis, the sum over pixels of the
    absolute value of each pixel's term of v_means2d (gsplat's ``absgrad``; AbsGS). Where a
    Gaussian's pixels pull its mean different ways (fine texture it is too coarse for) their
    terms cancel in v_means2d but not here; densification can read it (``DensifyConfig.absgrad``)."""
    n = colors.shape[0]
    dtype = colors.dtype
    height, width = raster["T_final"].shape
    px, py = pixel_centres(width, height, dtype)
    n_tiles = isect["tile_offsets"].shape[0] - 1
    buf = np.zeros((isect["n_isect"], _NCOL), dtype)
    _rasterize_bwd_kernel(proj["means2d"], proj["conics"], proj["opac_eff"], colors, proj["depths"],
                          proj["radii_f"], raster["sigma_cut"], proj["cov2d"], isect["isect_gauss"], isect["tile_offsets"],
                          tile_order(n_tiles), px, py, consts, exp_consts(dtype), isect["grid_w"], tile_size,
                          raster["T_final"], raster["last_idx"], v_color_img, v_depth_img, v_T_img, buf)
    out = dict(v_means2d=np.zeros((n, 2), dtype), v_conics=np.zeros((n, 3), dtype),
               v_opac_eff=np.zeros(n, dtype), v_colors=np.zeros((n, 3), dtype),
               v_depths=np.zeros(n, dtype), v_means2d_abs=np.zeros((n, 2), dtype))
    _isect_reduce_kernel(buf, isect["slot_to_isect"], isect["goff"], out["v_means2d"], out["v_conics"],
                         out["v_opac_eff"], out["v_colors"], out["v_depths"], out["v_means2d_abs"])
    return out
