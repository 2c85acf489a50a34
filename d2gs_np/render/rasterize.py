"""Tile-based rasterisation of projected Gaussians: intersection lists, compositing fwd/bwd.

Pipeline (CONVENTIONS.md §5-8, gsplat 1.5.3):

1. ``_tile_rects_kernel`` (prange over Gaussians): the tiles ``[floor((u-rx)/ts), ceil((u+rx)/ts))
   x [floor((v-ry)/ts), ceil((v+ry)/ts))`` clamped to the grid, and their number per Gaussian.
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
   transmittance and the list position of its last contributor.
4. ``_rasterize_bwd_kernel`` (prange over tiles): every pixel walks back from its last
   contributor, recovering T_k = T_{k+1} / (1 - alpha_k) (safe: alpha <= 0.999), as 3DGS and
   gsplat do. Per-intersection gradients go to ``buf`` (n_isect, 10), row = list position, so a
   row is only ever written by the one thread that owns its tile, in a fixed pixel order.
5. ``_isect_reduce_kernel`` (prange over Gaussians): each Gaussian sums its own rows of ``buf``
   in its fixed slot order.

Determinism: no floating-point sum in the backward pass depends on thread scheduling (each sum
is owned by one loop iteration and runs in a fixed order), so gradients are bitwise identical
run to run and for any number of threads. Memory is O(N + n_isect + pixels), never O(N x pixels).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from d2gs_np.render.project import (
    K_ALPHA_MAX,
    K_ALPHA_THRESHOLD,
    K_HALF,
    K_ONE,
    K_T_MIN,
    K_TILE,
    K_ZERO,
)

# Columns of the per-Gaussian packed parameters and of the gradient buffer.
_U, _V, _CA, _CB, _CC, _OP, _R, _G, _B, _Z = range(10)
_NCOL = 10


@njit(cache=True, parallel=True)
def _tile_rects_kernel(means2d, radii_f, consts, grid_w, grid_h, rects, counts):
    """Tile rectangle [x0, x1) x [y0, y1) of each Gaussian (rects (N,4) int64) and its tile count.

    Culled Gaussians (a radius 0) get an empty rectangle and count 0.
    """
    n = means2d.shape[0]
    zero = consts[K_ZERO]
    ts = consts[K_TILE]
    for i in prange(n):
        rx = radii_f[i, 0]
        ry = radii_f[i, 1]
        if rx == zero or ry == zero:
            rects[i, 0] = 0
            rects[i, 1] = 0
            rects[i, 2] = 0
            rects[i, 3] = 0
            counts[i] = 0
            continue
        u = means2d[i, 0]
        v = means2d[i, 1]
        x0 = _clamp_tile(np.floor((u - rx) / ts), grid_w)
        x1 = _clamp_tile(np.ceil((u + rx) / ts), grid_w)
        y0 = _clamp_tile(np.floor((v - ry) / ts), grid_h)
        y1 = _clamp_tile(np.ceil((v + ry) / ts), grid_h)
        rects[i, 0] = x0
        rects[i, 1] = x1
        rects[i, 2] = y0
        rects[i, 3] = y1
        counts[i] = max(x1 - x0, 0) * max(y1 - y0, 0)


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
def _gather_tile(start, end, isect_gauss, means2d, conics, opac_eff, colors, depths, dtype_probe):
    """Copy the parameters of a tile's Gaussians, in list order, into a (m, 10) local array."""
    m = end - start
    loc = np.empty((m, _NCOL), dtype_probe.dtype)
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
    return loc


@njit(cache=True)
def _eval_gaussian(loc, k, px, py, half):
    """(dx, dy, sigma, exp(-sigma)) of local Gaussian k at pixel centre (px, py).

    Shared by the forward and backward kernels so both take bitwise the same discrete decisions.
    ``exp(-sigma)`` is only meaningful when sigma >= 0.
    """
    dx = loc[k, _U] - px
    dy = loc[k, _V] - py
    sigma = half * (loc[k, _CA] * dx * dx + loc[k, _CC] * dy * dy) + loc[k, _CB] * dx * dy
    if sigma < 0:
        return dx, dy, sigma, half  # unused: the caller skips this Gaussian
    return dx, dy, sigma, math.exp(-sigma)


@njit(cache=True, parallel=True)
def _rasterize_fwd_kernel(means2d, conics, opac_eff, colors, depths, isect_gauss, tile_offsets,
                          px_centres, py_centres, background, consts, grid_w, tile_size,
                          image, depth_img, T_final, last_idx, n_eval):
    """Front-to-back compositing, prange over tiles (each pixel written by its tile only).

    Outputs: image (H,W,3) = C + T_final background, depth_img (H,W) = sum w z, T_final (H,W),
    last_idx (H,W) int64 (list position of the last contributor, -1 if none), n_eval (H,W) int64
    (number of (Gaussian, pixel) evaluations, for benchmarks).
    """
    H = image.shape[0]
    W = image.shape[1]
    n_tiles = tile_offsets.shape[0] - 1
    zero = consts[K_ZERO]
    one = consts[K_ONE]
    half = consts[K_HALF]
    amax = consts[K_ALPHA_MAX]
    athr = consts[K_ALPHA_THRESHOLD]
    tmin = consts[K_T_MIN]
    bg0 = background[0]
    bg1 = background[1]
    bg2 = background[2]
    for t in prange(n_tiles):
        start = tile_offsets[t]
        end = tile_offsets[t + 1]
        ty = t // grid_w
        tx = t - ty * grid_w
        x0 = tx * tile_size
        y0 = ty * tile_size
        x1 = min(x0 + tile_size, W)
        y1 = min(y0 + tile_size, H)
        loc = _gather_tile(start, end, isect_gauss, means2d, conics, opac_eff, colors, depths, consts)
        m = end - start
        for i in range(y0, y1):
            py = py_centres[i]
            for j in range(x0, x1):
                px = px_centres[j]
                T = one
                c0 = zero
                c1 = zero
                c2 = zero
                d = zero
                last = -1
                evaluated = m
                for k in range(m):
                    dx, dy, sigma, vis = _eval_gaussian(loc, k, px, py, half)
                    if sigma < zero:
                        continue
                    alpha = loc[k, _OP] * vis
                    if alpha > amax:
                        alpha = amax
                    if alpha < athr:
                        continue
                    next_T = T * (one - alpha)
                    if next_T <= tmin:
                        evaluated = k + 1
                        break
                    w = alpha * T
                    c0 += loc[k, _R] * w
                    c1 += loc[k, _G] * w
                    c2 += loc[k, _B] * w
                    d += loc[k, _Z] * w
                    T = next_T
                    last = start + k
                image[i, j, 0] = c0 + T * bg0
                image[i, j, 1] = c1 + T * bg1
                image[i, j, 2] = c2 + T * bg2
                depth_img[i, j] = d
                T_final[i, j] = T
                last_idx[i, j] = last
                n_eval[i, j] = evaluated


@njit(cache=True, parallel=True)
def _rasterize_bwd_kernel(means2d, conics, opac_eff, colors, depths, isect_gauss, tile_offsets,
                          px_centres, py_centres, consts, grid_w, tile_size, T_final, last_idx,
                          v_color_img, v_depth_img, v_T_img, buf):
    """Back-to-front gradient of the compositing, prange over tiles.

    v_color_img (H,W,3) = dL/dC, v_depth_img (H,W) = dL/dD, v_T_img (H,W) = dL/dT_final (all
    paths: background, alpha, expected depth). Writes buf (n_isect, 10) rows [start, end) of each
    tile: dL/d(u, v, conic a, b, c, opacity_eff, r, g, b, z) of that intersection (must be zero on
    entry).
    """
    H = T_final.shape[0]
    W = T_final.shape[1]
    n_tiles = tile_offsets.shape[0] - 1
    zero = consts[K_ZERO]
    one = consts[K_ONE]
    half = consts[K_HALF]
    amax = consts[K_ALPHA_MAX]
    athr = consts[K_ALPHA_THRESHOLD]
    for t in prange(n_tiles):
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
        loc = _gather_tile(start, end, isect_gauss, means2d, conics, opac_eff, colors, depths, consts)
        for i in range(y0, y1):
            py = py_centres[i]
            for j in range(x0, x1):
                last = last_idx[i, j]
                if last < start:
                    continue
                px = px_centres[j]
                Tf = T_final[i, j]
                T = Tf
                vc0 = v_color_img[i, j, 0]
                vc1 = v_color_img[i, j, 1]
                vc2 = v_color_img[i, j, 2]
                vd = v_depth_img[i, j]
                v_Tf = v_T_img[i, j]
                acc0 = zero  # sum over the Gaussians behind k of color * weight
                acc1 = zero
                acc2 = zero
                accd = zero
                for k in range(last - start, -1, -1):
                    dx, dy, sigma, vis = _eval_gaussian(loc, k, px, py, half)
                    if sigma < zero:
                        continue
                    raw = loc[k, _OP] * vis
                    alpha = raw
                    if alpha > amax:
                        alpha = amax
                    if alpha < athr:
                        continue
                    ra = one / (one - alpha)
                    T = T * ra  # transmittance in front of Gaussian k
                    fac = alpha * T
                    col0 = loc[k, _R]
                    col1 = loc[k, _G]
                    col2 = loc[k, _B]
                    zk = loc[k, _Z]
                    row = start + k
                    buf[row, _R] += fac * vc0
                    buf[row, _G] += fac * vc1
                    buf[row, _B] += fac * vc2
                    buf[row, _Z] += fac * vd
                    v_alpha = ((col0 * T - acc0 * ra) * vc0 + (col1 * T - acc1 * ra) * vc1
                               + (col2 * T - acc2 * ra) * vc2 + (zk * T - accd * ra) * vd
                               - v_Tf * Tf * ra)
                    acc0 += col0 * fac
                    acc1 += col1 * fac
                    acc2 += col2 * fac
                    accd += zk * fac
                    if raw <= amax:  # no gradient through the 0.999 clamp
                        buf[row, _OP] += v_alpha * vis
                        v_sigma = -v_alpha * raw
                        buf[row, _CA] += half * dx * dx * v_sigma
                        buf[row, _CB] += dx * dy * v_sigma
                        buf[row, _CC] += half * dy * dy * v_sigma
                        buf[row, _U] += v_sigma * (loc[k, _CA] * dx + loc[k, _CB] * dy)
                        buf[row, _V] += v_sigma * (loc[k, _CB] * dx + loc[k, _CC] * dy)


@njit(cache=True, parallel=True)
def _isect_reduce_kernel(buf, slot_to_isect, goff, v_means2d, v_conics, v_opac_eff, v_colors, v_depths):
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
        v_means2d[g, 0] = a_u
        v_means2d[g, 1] = a_v
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


def build_intersections(means2d, radii_f, depths, consts, width, height, tile_size):
    """Steps 1-2 of the module docstring. Returns a dict of the intersection structures."""
    n = means2d.shape[0]
    grid_w, grid_h = grid_shape(width, height, tile_size)
    rects = np.empty((n, 4), np.int64)
    counts = np.empty(n, np.int64)
    _tile_rects_kernel(means2d, radii_f, consts, grid_w, grid_h, rects, counts)
    goff = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=goff[1:])
    n_isect = int(goff[-1])
    tile_offsets = np.empty(grid_w * grid_h + 1, np.int64)
    isect_gauss = np.empty(n_isect, np.int64)
    slot_to_isect = np.empty(n_isect, np.int64)
    _isect_build_kernel(depths, counts, rects, goff, grid_w, tile_offsets, isect_gauss, slot_to_isect)
    return dict(grid_w=grid_w, grid_h=grid_h, goff=goff, tile_offsets=tile_offsets,
                isect_gauss=isect_gauss, slot_to_isect=slot_to_isect, n_isect=n_isect)


def pixel_centres(width, height, dtype):
    """(px (W,), py (H,)) pixel-centre coordinates j + 0.5, i + 0.5 in ``dtype``."""
    from d2gs_np.constants import PIXEL_CENTER_OFFSET

    px = (np.arange(width, dtype=np.float64) + PIXEL_CENTER_OFFSET).astype(dtype)
    py = (np.arange(height, dtype=np.float64) + PIXEL_CENTER_OFFSET).astype(dtype)
    return px, py


def rasterize_fwd(proj, colors, background, consts, isect, width, height, tile_size):
    """Step 3. Returns dict(image (H,W,3), depth (H,W), T_final (H,W), last_idx, n_eval)."""
    dtype = colors.dtype
    px, py = pixel_centres(width, height, dtype)
    image = np.empty((height, width, 3), dtype)
    depth = np.empty((height, width), dtype)
    T_final = np.empty((height, width), dtype)
    last_idx = np.empty((height, width), np.int64)
    n_eval = np.empty((height, width), np.int64)
    _rasterize_fwd_kernel(proj["means2d"], proj["conics"], proj["opac_eff"], colors, proj["depths"],
                          isect["isect_gauss"], isect["tile_offsets"], px, py, background, consts,
                          isect["grid_w"], tile_size, image, depth, T_final, last_idx, n_eval)
    return dict(image=image, depth=depth, T_final=T_final, last_idx=last_idx, n_eval=n_eval)


def rasterize_bwd(proj, colors, consts, isect, raster, tile_size, v_color_img, v_depth_img, v_T_img):
    """Steps 4-5. Returns dict of per-Gaussian v_means2d (N,2), v_conics (N,3), v_opac_eff (N,),
    v_colors (N,3), v_depths (N,)."""
    n = colors.shape[0]
    dtype = colors.dtype
    height, width = raster["T_final"].shape
    px, py = pixel_centres(width, height, dtype)
    buf = np.zeros((isect["n_isect"], _NCOL), dtype)
    _rasterize_bwd_kernel(proj["means2d"], proj["conics"], proj["opac_eff"], colors, proj["depths"],
                          isect["isect_gauss"], isect["tile_offsets"], px, py, consts, isect["grid_w"],
                          tile_size, raster["T_final"], raster["last_idx"], v_color_img, v_depth_img,
                          v_T_img, buf)
    out = dict(v_means2d=np.zeros((n, 2), dtype), v_conics=np.zeros((n, 3), dtype),
               v_opac_eff=np.zeros(n, dtype), v_colors=np.zeros((n, 3), dtype),
               v_depths=np.zeros(n, dtype))
    _isect_reduce_kernel(buf, isect["slot_to_isect"], isect["goff"], out["v_means2d"], out["v_conics"],
                         out["v_opac_eff"], out["v_colors"], out["v_depths"])
    return out
