"""Tile-based rasterisation of projected Gaussians: intersection lists, compositing fwd/bwd.

Pipeline (docs/conventions.md §5-8, gsplat 1.5.3):

1. ``_tile_rects_kernel`` (serial loop over Gaussians): the tiles ``[floor((u-rx)/ts), ceil((u+rx)/ts))
   x [floor((v-ry)/ts), ceil((v+ry)/ts))`` clamped to the grid (gsplat's binning; their number is
   the ``num_intersections`` output), cut to the tiles that the Gaussian's row and column bands
   (step 3) reach: a tile whose pixels all have alpha < 1/255 for certain is not listed.
2. ``_isect_build_kernel`` (sequential, O(N log N + n_isect)): a stable argsort of the visible
   Gaussians by float32 camera depth (ties by Gaussian index), then a bucket pass over the
   Gaussians in that order that appends each to the lists of its tiles. The result, ``isect_gauss``,
   is ordered by tile, then front to back with ties by index: exactly the order of a per-tile
   stable sort of float32 depths, i.e. the reference's order. ``tile_offsets`` (n_tiles+1,)
   delimits each tile's run. ``slot_to_isect`` maps the Gaussian-major numbering of the
   intersections (Gaussian g owns slots ``goff[g]:goff[g+1]``, its tiles in row-major order) to
   positions in the tile-major list; the backward pass uses it to reduce deterministically.
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
   (``_composite_band``: every lane computes alpha with an inline polynomial exp, ``_exp_neg``,
   and changes state only when the rules say so) that LLVM vectorises (8 float64 lanes with
   AVX-512): more lanes than the exact per-row footprint (~1.6-2x), but each several times
   cheaper than in a scalar, branchy loop with a libm exp.
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

import functools
import math

import numpy as np
from numba import njit, prange

from d2gs_np import constants as C
from d2gs_np.render.project import (
    K_DET_MIN,
    K_TWO,
    K_ALPHA_MAX,
    K_ALPHA_THRESHOLD,
    K_HALF,
    K_ONE,
    K_T_MIN,
    K_TILE,
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
# on the sides, wider ones make longer runs (vector loops need several vectors per run). 4
# measured best with 8 float64 lanes per vector (examples/profile_step.py). The backward pass
# sums gradients in this lane order, so results depend on it (deterministically).
_STRIP = 8
_ROW_GROUP = 2  # bands are padded to a multiple of this many rows (``_pad_rows``): 16-lane runs
_TILE_ORDER_SEED = 0  # seed of the fixed tile permutation (load balance only; results never depend on it)


@njit(cache=True)
def _tile_rects_kernel(means2d, radii_f, sigma_cut, cov2d, consts, grid_w, grid_h, width, height, tight, rects,
                       counts, box_counts):
    """Tile rectangle [x0, x1) x [y0, y1) of each Gaussian (rects (N,4) int64) and its tile count.

    box_counts: the tiles of the 3.33-sigma box ``[floor((u-rx)/ts), ceil((u+rx)/ts)) x ...``
    clamped to the grid (gsplat's binning, the ``num_intersections`` output). rects and counts:
    that box cut to the tiles that hold a pixel of the Gaussian's row and column bands
    (``_band``, with the same operands as the rasterisers' ``_band_rows`` / ``_band_cols``), so
    a tile is left out of the lists only where every pixel has sigma > sigma_cut, i.e. alpha <
    1/255 for certain: where the rasterisers would skip the Gaussian anyway (results are the same
    to the last bit; low-opacity Gaussians reach fewer tiles). Culled Gaussians (a radius 0) get
    an empty rectangle and count 0. Serial on purpose: a few dozen flops per Gaussian, less than
    the cost of waking the threads of a parallel region. ``tight=False``: the boxes, uncut.
    """
    n = means2d.shape[0]
    zero = consts[K_ZERO]
    one = consts[K_ONE]
    two = consts[K_TWO]
    half = consts[K_HALF]
    det_min = consts[K_DET_MIN]
    ts = consts[K_TILE]
    tsi = int(ts)
    for i in range(n):
        rx = radii_f[i, 0]
        ry = radii_f[i, 1]
        rects[i, 0] = 0
        rects[i, 1] = 0
        rects[i, 2] = 0
        rects[i, 3] = 0
        counts[i] = 0
        box_counts[i] = 0
        if rx == zero or ry == zero:
            continue
        u = means2d[i, 0]
        v = means2d[i, 1]
        x0 = _clamp_tile(np.floor((u - rx) / ts), grid_w)
        x1 = _clamp_tile(np.ceil((u + rx) / ts), grid_w)
        y0 = _clamp_tile(np.floor((v - ry) / ts), grid_h)
        y1 = _clamp_tile(np.ceil((v + ry) / ts), grid_h)
        box_counts[i] = max(x1 - x0, 0) * max(y1 - y0, 0)
        if box_counts[i] == 0:
            continue
        if not tight:
            rects[i, 0] = x0
            rects[i, 1] = x1
            rects[i, 2] = y0
            rects[i, 3] = y1
            counts[i] = box_counts[i]
            continue
        ic00, ic11 = _inv_axis_vars(cov2d[i, 0], cov2d[i, 1], cov2d[i, 2], det_min, zero, one)
        ja, jb = _band(u, rx, ic00, sigma_cut[i], 0, width, half, one, two, zero)
        ia, ib = _band(v, ry, ic11, sigma_cut[i], 0, height, half, one, two, zero)
        if jb <= ja or ib <= ia:
            continue
        x0 = max(x0, ja // tsi)
        x1 = min(x1, (jb - 1) // tsi + 1)
        y0 = max(y0, ia // tsi)
        y1 = min(y1, (ib - 1) // tsi + 1)
        if x1 <= x0 or y1 <= y0:
            continue
        rects[i, 0] = x0
        rects[i, 1] = x1
        rects[i, 2] = y0
        rects[i, 3] = y1
        counts[i] = (x1 - x0) * (y1 - y0)


@njit(cache=True)
def _inv_axis_vars(c00, c01, c11, det_min, zero, one):
    """(1/c00, 1/c11): the coefficients of the column and row minima of sigma (``_band``), from the
    2D covariance; with a clamped det (only possible with eps2d = 0) conic = adj(cov) / DET_MIN,
    whose minima are d^2 det / (2 DET_MIN c) (<= 0 if det <= 0: the band keeps the box)."""
    det = c00 * c11 - c01 * c01  # bitwise the projection's det before its clamp
    if det >= det_min:
        return one / c00, one / c11
    return max(det, zero) / (det_min * c00), max(det, zero) / (det_min * c11)


@njit(cache=True)
def _clamp_tile(f, n):
    """int(clamp(f, 0, n)) for a float tile coordinate (clamped as a float: no int overflow)."""
    if f <= 0:
        return 0
    if f >= n:
        return n
    return int(f)


@njit(cache=True)
def _isect_build_kernel(depths, counts, rects, goff, grid_w, tile_offsets, isect_gauss, slot_to_isect):
    """Build the tile-major, depth-sorted intersection list (see the module docstring, step 2).

    depths (N,) camera z; counts (N,) tiles per Gaussian; rects (N,4); goff (N+1,) = cumsum of
    counts; outputs tile_offsets (n_tiles+1,), isect_gauss (n_isect,), slot_to_isect (n_isect,).
    """
    n = depths.shape[0]
    n_tiles = tile_offsets.shape[0] - 1
    nvis = 0
    for g in range(n):
        if counts[g] > 0:
            nvis += 1
    vis = np.empty(nvis, np.int64)
    d32 = np.empty(nvis, np.float32)
    k = 0
    for g in range(n):
        if counts[g] > 0:
            vis[k] = g
            d32[k] = np.float32(depths[g])
            k += 1
    order = np.argsort(d32, kind="mergesort")  # stable: equal float32 depths keep index order
    tile_count = np.zeros(n_tiles, np.int64)
    for k in range(nvis):
        g = vis[k]
        for ty in range(rects[g, 2], rects[g, 3]):
            for tx in range(rects[g, 0], rects[g, 1]):
                tile_count[ty * grid_w + tx] += 1
    tile_offsets[0] = 0
    for t in range(n_tiles):
        tile_offsets[t + 1] = tile_offsets[t] + tile_count[t]
    cursor = tile_offsets[:n_tiles].copy()
    for k in range(nvis):
        g = vis[order[k]]
        s = goff[g]
        for ty in range(rects[g, 2], rects[g, 3]):
            for tx in range(rects[g, 0], rects[g, 1]):
                t = ty * grid_w + tx
                pos = cursor[t]
                cursor[t] = pos + 1
                isect_gauss[pos] = g
                slot_to_isect[s] = pos
                s += 1


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
        loc[k, _IC00], loc[k, _IC11] = _inv_axis_vars(cov2d[g, 0], cov2d[g, 1], cov2d[g, 2], det_min, zero, one)
    return loc


@njit(cache=True)
def _box_range(c, r, lo, hi, half, one):
    """Pixels [a, b) of [lo, hi) whose centre p + 0.5 may lie within r of c: ceil(c - r - 1/2 - m)
    <= p <= floor(c + r - 1/2 + m), with a margin m = 1/64 px for the rounding of the bounds.

    Why that is enough (``_band`` gives r = the reach of sigma <= cut along the axis): the bounds
    round by e <= ~1.2e-7 (|c| + r) in float32, with |c| <= r + image size for a Gaussian that
    reaches the image. If e <= m (images up to ~1e5 px) every pixel within r is kept; otherwise a
    pixel left out still lies beyond r - e, where sigma >= cut (1 - e / r)^2 >= cut - 2.6e-6 cut
    (r >= 1 there), far inside the ALPHA_CUTOFF_SAFETY = 1e-3 that the cut carries above
    ln(255 o) (constants.py). Either way the pixels left out are only pixels the 1/255 rule
    skips. (Before, the interval was widened by one more pixel on each side: 1.5-2 px in all.)
    """
    m = half * half * half * half * half * half  # 1/64 px, exact and in the kernel's dtype
    fa = np.ceil(c - r - half - m)
    fb = np.floor(c + r - half + m)
    a = lo if fa <= lo else (hi if fa >= hi else int(fa))
    b = lo if fb < lo else (hi if fb >= hi else int(fb) + 1)
    return a, b


@njit(cache=True)
def _band(c, r_box, inv_var, cut, lo, hi, half, one, two, zero):
    """Pixels [a, b) of [lo, hi) along one axis where a Gaussian may have sigma <= cut.

    Along that axis the minimum of sigma over the other axis is d^2 inv_var / 2 (inv_var = 1/c11
    for rows, 1/c00 for columns, built from the covariance: no cancellation), so only
    |d| <= sqrt(2 cut / inv_var) can hold a pixel with sigma <= cut; the 3.33-sigma box (r_box)
    bounds it too. ``_box_range`` widens the interval by 1/64 px (rounding). A degenerate minimum
    (inv_var <= 0, only with a clamped det) keeps the box.
    """
    if inv_var > zero:
        r2 = two * cut / inv_var
        if not r2 >= zero:  # cut < 0 (alpha < 1/255 everywhere) or -inf (opacity 0)
            return lo, lo
        r = math.sqrt(r2)
        if r < r_box:
            r_box = r
    return _box_range(c, r_box, lo, hi, half, one)


@njit(cache=True)
def _band_rows(loc, k, y0, y1, half, one, two, zero):
    """Rows [ia, ib) of [y0, y1) where Gaussian k may have sigma <= sigma_cut (``_band``)."""
    return _band(loc[k, _V], loc[k, _RY], loc[k, _IC11], loc[k, _CUT], y0, y1, half, one, two, zero)


@njit(cache=True)
def _band_cols(loc, k, x0, x1, half, one, two, zero):
    """Columns [ja, jb) of [x0, x1) where Gaussian k may have sigma <= sigma_cut (``_band``)."""
    return _band(loc[k, _U], loc[k, _RX], loc[k, _IC00], loc[k, _CUT], x0, x1, half, one, two, zero)


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


@njit(cache=True, fastmath={"contract"})  # Horner steps as fused multiply-adds (deterministic)
def _exp_neg(s, ec):
    """exp(-s) for s in [0, EXP_ARG_MAX] (clamped into it), within 3 ulp; plain arithmetic so that
    a loop calling it vectorises (``math.exp`` is a scalar library call). ``ec``: ``_exp_consts``
    unpacked into a tuple (see there for the method and the error bound)."""
    (inv_ln2, ln2_hi, ln2_lo, s_max, half, one, zero, p1, p2, p4, p8, eight, four, two,
     c2, c3, c4, c5, c6, c7, c8, c9, c10, c11, c12, c13) = ec
    s = s_max if s > s_max else s
    s = zero if s < zero else s
    kf = np.floor(s * inv_ln2 + half)  # k = round(s / ln 2), 0 <= k <= 12
    r = (kf * ln2_hi - s) + kf * ln2_lo  # k ln2 - s in [-ln2/2, ln2/2]; k ln2_hi is exact
    p = c13
    p = p * r + c12
    p = p * r + c11
    p = p * r + c10
    p = p * r + c9
    p = p * r + c8
    p = p * r + c7
    p = p * r + c6
    p = p * r + c5
    p = p * r + c4
    p = p * r + c3
    p = p * r + c2
    p = p * r + one
    p = p * r + one  # exp(r)
    scale = one  # 2^-k from the bits of k (exact powers of two)
    if kf >= eight:
        kf = kf - eight
        scale = p8
    if kf >= four:
        kf = kf - four
        scale = scale * p4
    if kf >= two:
        kf = kf - two
        scale = scale * p2
    if kf >= one:
        scale = scale * p1
    return p * scale


def _exp_consts(dtype):
    """Constants of ``_exp_neg`` in ``dtype``: exp(-s) = 2^-k exp(r) with k = round(s / ln 2) and
    r = k ln 2 - s in [-ln2/2, ln2/2] (Cody-Waite: ln 2 = ln2_hi + ln2_lo with ln2_hi holding 12
    trailing zero bits, so k ln2_hi is exact for k <= 4096), exp(r) by its Taylor polynomial of
    degree 13 (remainder <= (ln2/2)^14 / 14! < 5e-18, far below float64 rounding; measured within
    3 ulp of numpy.exp in float64 and 1.1 ulp in float32 over [0, EXP_ARG_MAX], checked by
    tests/render/test_render_fast.py). Not bitwise ``math.exp``: results differ from a libm exp
    in the last bits (see docs/conventions.md §6)."""
    ln2 = math.log(2.0)
    ln2_hi = 0.693145751953125
    vals = [1.0 / ln2, ln2_hi, ln2 - ln2_hi, C.EXP_ARG_MAX, 0.5, 1.0, 0.0, 0.5, 0.25, 1.0 / 16.0, 1.0 / 256.0,
            8.0, 4.0, 2.0] + [1.0 / math.factorial(n) for n in range(2, 14)]
    return np.array(vals, dtype=dtype)


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
        alpha = o * _exp_neg(sigma, ec)
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
    ec = _unpack_exp_consts(exp_consts)
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


@njit(cache=True)
def _unpack_exp_consts(e):
    """The (26,) array of ``_exp_consts`` as a tuple (loop invariants LLVM keeps in registers)."""
    return (e[0], e[1], e[2], e[3], e[4], e[5], e[6], e[7], e[8], e[9], e[10], e[11], e[12], e[13], e[14], e[15],
            e[16], e[17], e[18], e[19], e[20], e[21], e[22], e[23], e[24], e[25])


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
        vis = _exp_neg(sigma, ec)
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
    ec = _unpack_exp_consts(exp_consts)
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


def grid_shape(width, height, tile_size):
    """(grid_w, grid_h) = (ceil(W / ts), ceil(H / ts))."""
    return -(-width // tile_size), -(-height // tile_size)


def build_intersections(proj, consts, width, height, tile_size, tight=True):
    """Steps 1-2 of the module docstring, from ``project_fwd``'s outputs. Returns a dict of the
    intersection structures, the per-Gaussian ``sigma_cut`` (``sigma_cutoffs``) and
    ``n_box_isect``, the tile-Gaussian pairs of the 3.33-sigma boxes (gsplat's count; the lists
    hold only the pairs of tiles the Gaussian's bands reach, ``n_isect``). ``tight=False`` lists
    every tile of the boxes (gsplat's lists; the renders are the same, only slower: for tests
    and benchmarks)."""
    means2d = proj["means2d"]
    n = means2d.shape[0]
    grid_w, grid_h = grid_shape(width, height, tile_size)
    sigma_cut = sigma_cutoffs(proj["opac_eff"])
    rects = np.empty((n, 4), np.int64)
    counts = np.empty(n, np.int64)
    box_counts = np.empty(n, np.int64)
    _tile_rects_kernel(means2d, proj["radii_f"], sigma_cut, proj["cov2d"], consts, grid_w, grid_h, width, height,
                       bool(tight), rects, counts, box_counts)
    goff = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=goff[1:])
    n_isect = int(goff[-1])
    tile_offsets = np.empty(grid_w * grid_h + 1, np.int64)
    isect_gauss = np.empty(n_isect, np.int64)
    slot_to_isect = np.empty(n_isect, np.int64)
    _isect_build_kernel(proj["depths"], counts, rects, goff, grid_w, tile_offsets, isect_gauss, slot_to_isect)
    return dict(grid_w=grid_w, grid_h=grid_h, goff=goff, tile_offsets=tile_offsets,
                isect_gauss=isect_gauss, slot_to_isect=slot_to_isect, n_isect=n_isect,
                n_box_isect=int(box_counts.sum()), sigma_cut=sigma_cut)


def pixel_centres(width, height, dtype):
    """(px (W,), py (H,)) pixel-centre coordinates j + 0.5, i + 0.5 in ``dtype``."""
    px = (np.arange(width, dtype=np.float64) + C.PIXEL_CENTER_OFFSET).astype(dtype)
    py = (np.arange(height, dtype=np.float64) + C.PIXEL_CENTER_OFFSET).astype(dtype)
    return px, py


def sigma_cutoffs(opac_eff):
    """Per-Gaussian sigma beyond which alpha < 1/255 for certain: ln(o / (1/255)) + safety (-inf for o = 0).

    See constants.ALPHA_CUTOFF_SAFETY: the skip it allows is exactly the 1/255 rule's decision.
    """
    with np.errstate(divide="ignore"):
        return np.log(opac_eff / C.ALPHA_THRESHOLD) + C.ALPHA_CUTOFF_SAFETY


@functools.lru_cache(maxsize=64)
def _tile_order(n_tiles):
    """A fixed pseudo-random permutation of the tiles, so that Numba's static split of the prange
    gives every thread a similar mix of busy and empty screen regions. Results never depend on it."""
    order = np.random.default_rng(_TILE_ORDER_SEED).permutation(n_tiles).astype(np.int64)
    order.flags.writeable = False
    return order


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
                          _tile_order(n_tiles), px, py, background, consts, _exp_consts(dtype), isect["grid_w"],
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
                          _tile_order(n_tiles), px, py, consts, _exp_consts(dtype), isect["grid_w"], tile_size,
                          raster["T_final"], raster["last_idx"], v_color_img, v_depth_img, v_T_img, buf)
    out = dict(v_means2d=np.zeros((n, 2), dtype), v_conics=np.zeros((n, 3), dtype),
               v_opac_eff=np.zeros(n, dtype), v_colors=np.zeros((n, 3), dtype),
               v_depths=np.zeros(n, dtype), v_means2d_abs=np.zeros((n, 2), dtype))
    _isect_reduce_kernel(buf, isect["slot_to_isect"], isect["goff"], out["v_means2d"], out["v_conics"],
                         out["v_opac_eff"], out["v_colors"], out["v_depths"], out["v_means2d_abs"])
    return out
