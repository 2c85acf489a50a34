"""Tile binning of projected Gaussians: the tiles each one reaches and the depth-sorted tile lists.

Steps 1-2 of the fast rasteriser (docs/conventions.md §5, gsplat 1.5.3); steps 3-5, the
compositing and its backward over these lists, are in render/rasterize.py.

1. ``_tile_rects_kernel`` (serial loop over Gaussians): the tiles ``[floor((u-rx)/ts), ceil((u+rx)/ts))
   x [floor((v-ry)/ts), ceil((v+ry)/ts))`` clamped to the grid (gsplat's binning; their number is
   the ``num_intersections`` output), cut to the tiles that the Gaussian's row and column bands
   (``band``, below) reach: a tile whose pixels all have alpha < 1/255 for certain is not listed.
2. ``_isect_build_kernel`` (sequential, O(N log N + n_isect)): a stable argsort of the visible
   Gaussians by float32 camera depth (ties by Gaussian index), then a bucket pass over the
   Gaussians in that order that appends each to the lists of its tiles. The result, ``isect_gauss``,
   is ordered by tile, then front to back with ties by index: exactly the order of a per-tile
   stable sort of float32 depths, i.e. the reference's order. ``tile_offsets`` (n_tiles+1,)
   delimits each tile's run. ``slot_to_isect`` maps the Gaussian-major numbering of the
   intersections (Gaussian g owns slots ``goff[g]:goff[g+1]``, its tiles in row-major order) to
   positions in the tile-major list; the backward pass uses it to reduce deterministically.

Band geometry (``band``, ``inv_axis_vars``): along one axis, the pixels where a Gaussian may have
sigma <= its cut-off (``sigma_cutoffs``: beyond it alpha < 1/255 for certain). The binning cuts
each Gaussian's tiles to its bands and the compositing kernels visit only the bands' pixels, with
the same operands, so the pairs either leaves out are only pairs the 1/255 rule skips.

Numba caches a kernel under its own file's time stamp only: the kernels of rasterize.py that call
``band`` and ``inv_axis_vars`` are not recompiled when only this file changes. After editing it,
clear the cache (NUMBA_CACHE_DIR).
"""
from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit

from d2gs_np import constants as C
from d2gs_np.render.project import K_DET_MIN, K_HALF, K_ONE, K_TILE, K_TWO, K_ZERO

_TILE_ORDER_SEED = 0  # seed of the fixed tile permutation (load balance only; results never depend on it)


@njit(cache=True)
def _tile_rects_kernel(means2d, radii_f, sigma_cut, cov2d, consts, grid_w, grid_h, width, height, tight, rects,
                       counts, box_counts):
    """Tile rectangle [x0, x1) x [y0, y1) of each Gaussian (rects (N,4) int64) and its tile count.

    box_counts: the tiles of the 3.33-sigma box ``[floor((u-rx)/ts), ceil((u+rx)/ts)) x ...``
    clamped to the grid (gsplat's binning, the ``num_intersections`` output). rects and counts:
    that box cut to the tiles that hold a pixel of the Gaussian's row and column bands
    (``band``, with the same operands as the compositing kernels' ``_band_rows`` / ``_band_cols``
    in rasterize.py), so a tile is left out of the lists only where every pixel has sigma >
    sigma_cut, i.e. alpha < 1/255 for certain: where the compositing would skip the Gaussian
    anyway (results are the same to the last bit; low-opacity Gaussians reach fewer tiles).
    Culled Gaussians (a radius 0) get an empty rectangle and count 0. Serial on purpose: a few
    dozen flops per Gaussian, less than the cost of waking the threads of a parallel region.
    ``tight=False``: the boxes, uncut.
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
        ic00, ic11 = inv_axis_vars(cov2d[i, 0], cov2d[i, 1], cov2d[i, 2], det_min, zero, one)
        ja, jb = band(u, rx, ic00, sigma_cut[i], 0, width, half, one, two, zero)
        ia, ib = band(v, ry, ic11, sigma_cut[i], 0, height, half, one, two, zero)
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
def inv_axis_vars(c00, c01, c11, det_min, zero, one):
    """(1/c00, 1/c11): the coefficients of the column and row minima of sigma (``band``), from the
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
def _box_range(c, r, lo, hi, half, one):
    """Pixels [a, b) of [lo, hi) whose centre p + 0.5 may lie within r of c: ceil(c - r - 1/2 - m)
    <= p <= floor(c + r - 1/2 + m), with a margin m = 1/64 px for the rounding of the bounds.

    Why that is enough (``band`` gives r = the reach of sigma <= cut along the axis): the bounds
    round by e <= ~1.2e-7 (|c| + r) in float32, with |c| <= r + image size for a Gaussian that
    reaches the image. If e <= m (images up to ~1e5 px) every pixel within r is kept; otherwise a
    pixel left out still lies beyond r - e, where sigma >= cut (1 - e / r)^2 >= cut - 2.6e-6 cut
    (r >= 1 there), far inside the ALPHA_CUTOFF_SAFETY = 1e-3 that the cut carries above
    ln(255 o) (constants.py). Either way the pixels left out are only pixels the 1/255 rule
    skips. (The speed-up of this margin over the earlier 1.5-2 px: docs/results.md §6.)
    """
    m = half * half * half * half * half * half  # 1/64 px, exact and in the kernel's dtype
    fa = np.ceil(c - r - half - m)
    fb = np.floor(c + r - half + m)
    a = lo if fa <= lo else (hi if fa >= hi else int(fa))
    b = lo if fb < lo else (hi if fb >= hi else int(fb) + 1)
    return a, b


@njit(cache=True)
def band(c, r_box, inv_var, cut, lo, hi, half, one, two, zero):
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


def sigma_cutoffs(opac_eff):
    """Per-Gaussian sigma beyond which alpha < 1/255 for certain: ln(o / (1/255)) + safety (-inf for o = 0).

    See constants.ALPHA_CUTOFF_SAFETY: the skip it allows is exactly the 1/255 rule's decision.
    """
    with np.errstate(divide="ignore"):
        return np.log(opac_eff / C.ALPHA_THRESHOLD) + C.ALPHA_CUTOFF_SAFETY


@functools.lru_cache(maxsize=64)
def tile_order(n_tiles):
    """A fixed pseudo-random permutation of the tiles, so that Numba's static split of the prange
    gives every thread a similar mix of busy and empty screen regions. Results never depend on it."""
    order = np.random.default_rng(_TILE_ORDER_SEED).permutation(n_tiles).astype(np.int64)
    order.flags.writeable = False
    return order
