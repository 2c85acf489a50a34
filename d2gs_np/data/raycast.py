"""Ray casting through a pinhole camera: what the analytic worlds (data/synthetic.py, data/suite.py) share.

Each world casts rays against its own geometry with a function ``cast(origin (3,), dirs) -> (rgb
(3, R), depth (R,), moving (R,) bool)``, where ``dirs = (dx, dy, dz)``, each (R,), are the
world-frame directions ``R^T (x, y, 1)`` (camera z component 1, so a ray's parameter at a hit is
the camera depth). This module makes those rays for every pixel (``pixel_rays``, with
``supersample x supersample`` rays per pixel through ``(j + (a + 0.5 + ox)/s, i + (b + 0.5 + oy)/s)``,
where the sub-cell ``offset`` (ox, oy) in [-0.5, 0.5] is 0 unless a caller stratifies samples over
several casts)
and the images of a cast: the box-filtered colour and the moving-pixel mask (``cast_view``),
and the depth through the pixel centres (``cast_depth``). Pixel (i, j) has its centre at
(j + 0.5, i + 0.5) (docs/conventions.md §2).
"""
from __future__ import annotations

import numpy as np

from d2gs_np.base.checks import check_int
from d2gs_np.geometry.camera import check_intrinsics
from d2gs_np.geometry.se3 import check_rigid

__all__ = ["check_view", "check_offset", "stratified_offsets", "pixel_rays", "cast_view", "cast_depth"]

_GRID_CACHE = {}


def _camera_grid(K, width, height, supersample, offset=(0.0, 0.0)):
    """Normalised camera-plane coordinates (x, y), each (H*s*W*s,), row-major over the fine grid."""
    ox, oy = float(offset[0]), float(offset[1])
    key = (width, height, supersample, ox, oy, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    grid = _GRID_CACHE.get(key)
    if grid is None:
        s = supersample
        xs = ((np.arange(width * s) + 0.5 + ox) / s - K[0, 2]) / K[0, 0]  # sub-sample centres, continuous coords
        ys = ((np.arange(height * s) + 0.5 + oy) / s - K[1, 2]) / K[1, 1]
        X, Y = np.meshgrid(xs, ys)
        grid = (X.ravel(), Y.ravel())
        if len(_GRID_CACHE) > 64:  # a stratified blur uses one grid per sub-frame offset
            _GRID_CACHE.clear()
        _GRID_CACHE[key] = grid
    return grid


def pixel_rays(cam_T_world, K, width, height, supersample, offset=(0.0, 0.0)):
    """World origin (3,) and ray directions (dx, dy, dz) = R^T (x, y, 1), each (H*s*W*s,)."""
    X, Y = _camera_grid(K, width, height, supersample, offset)
    Rm, tv = cam_T_world[:3, :3], cam_T_world[:3, 3]
    dirs = tuple(X * Rm[0, a] + Y * Rm[1, a] + Rm[2, a] for a in range(3))  # sum_i d_cam_i R[i, a]
    return -Rm.T @ tv, dirs


def check_view(cam_T_world, K, width, height):
    """(cam_T_world, K) as float64 arrays, after checking the pose (rigid (4, 4)), the intrinsics
    and the image size (positive ints)."""
    T = np.asarray(cam_T_world, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"cam_T_world must have shape (4, 4); got {T.shape}")
    check_rigid(T, "cam_T_world")
    K = np.asarray(K, dtype=np.float64)
    check_intrinsics(K)
    for name, v in (("width", width), ("height", height)):
        check_int(v, name, 1)
    return T, K


def check_offset(offset):
    """(ox, oy) as floats, after checking it is two finite numbers in [-0.5, 0.5] (sub-cell units)."""
    o = np.asarray(offset, dtype=np.float64)
    if o.shape != (2,) or not np.all(np.isfinite(o)) or np.any(np.abs(o) > 0.5):
        raise ValueError(f"offset must be two finite numbers in [-0.5, 0.5] (a shift within one sub-sample "
                         f"cell); got {offset!r}")
    return float(o[0]), float(o[1])


def stratified_offsets(count):
    """Sub-cell offsets (count, 2) that spread ``count`` casts over an m x m grid of each sample's
    cell (m = ceil(sqrt(count))), one cell per cast in a fixed shuffled order (so a blur's early
    sub-frames do not all sample the same corner of the pixel). Casts beyond m^2 reuse the cells."""
    check_int(count, "count", 1)
    m = int(np.ceil(np.sqrt(count)))
    cells = np.random.default_rng(0).permutation(m * m)[np.arange(count) % (m * m)]
    return np.stack([(cells % m + 0.5) / m - 0.5, (cells // m + 0.5) / m - 0.5], axis=1)


def cast_view(cast, cam_T_world, K, width, height, supersample=2, offset=(0.0, 0.0)):
    """Sharp image of ``cast`` (module docstring) at pose ``cam_T_world`` (4, 4).

    Returns (rgb (H, W, 3) float64, moving (H, W) bool). Each pixel is the mean of supersample^2
    rays through (j + (a + 0.5 + ox)/s, i + (b + 0.5 + oy)/s) for ``offset`` (ox, oy) in [-0.5, 0.5];
    ``moving`` is True where any of them hits a moving object.
    """
    T, K = check_view(cam_T_world, K, width, height)
    check_int(supersample, "supersample", 1)
    offset = check_offset(offset)
    origin, dirs = pixel_rays(T, K, width, height, supersample, offset)
    rgb, _, dyn = cast(origin, dirs)
    s = supersample
    rgb = np.ascontiguousarray(rgb.reshape(3, height, s, width, s).mean(axis=(2, 4)).transpose(1, 2, 0))
    dyn = dyn.reshape(height, s, width, s).any(axis=(1, 3))
    return rgb, dyn


def cast_depth(cast, cam_T_world, K, width, height):
    """Depth (camera z, (H, W) float64) of ``cast``'s first hit through each pixel centre."""
    T, K = check_view(cam_T_world, K, width, height)
    origin, dirs = pixel_rays(T, K, width, height, 1)
    _, depth, _ = cast(origin, dirs)
    return depth.reshape(height, width)
