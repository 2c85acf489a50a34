"""Numba fast splatter (d2gs_np.render) against the NumPy reference (d2gs_np.reference).

Layers: fast vs reference, forward and every gradient, on random and extreme scenes; the fast
backward against central finite differences (a small spot check; the reference has its own full
FD tests); properties (float32 stays float32, kernels typed float32 end to end, determinism
across runs and thread counts, NUMBA_DISABLE_JIT, input validation before any work).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numba
import numpy as np
import pytest
from numba import types

import render_fixtures as rf
from d2gs_np import constants as C
from d2gs_np import reference as ref
from d2gs_np.refcheck.scenes import (extreme_anisotropy_scene, extreme_scales_scene, flat_covariance_scene,
                                     near_plane_scene)
from d2gs_np.render import RenderConfig, render_bwd, render_fwd
from d2gs_np.render import api as fast_api
from d2gs_np.render import binning, fast_exp
from d2gs_np.render import project as fast_project
from d2gs_np.render import rasterize as fast_rasterize

# Fast vs reference in float64: the two compute the same formulas in a different order
# (scalar kernels vs vectorised matrix products; tile-local vs dense per-pixel sums; T recovered
# by division in the backward pass vs stored products), so they differ by rounding only:
# O(10-100) ulps relative to each output's largest entry (observed ~1e-15). 1e-10 leaves five
# orders of magnitude of headroom while still catching any wrong term (which shows at >= 1e-6).
RTOL_F64 = 1e-10
# float32 fast path vs float64 fast path, relative to each output's largest entry: float32
# carries ~6e-8 relative rounding per operation; chains of ~10-100 operations and sums over up
# to a few hundred (Gaussian, pixel) terms give ~1e-6 (observed <= 3e-6). 1e-4 is a 30x margin.
RTOL_F32 = 1e-4
# Scenes whose discrete decisions (alpha >= 1/255, the 0.999 clamp, the 1e-4 stop, depth order,
# the Jacobian clamp) sit at least this far (relative) from their thresholds: far above both
# float64 rounding (1e-16) and float32 rounding (1e-7), so no decision can flip between paths.
MARGIN = 1e-4
# Hand-built extreme scenes must keep at least this relative margin: rounding differences
# between the two float64 implementations are ~1e-15, so 1e-9 rules out any flipped decision.
MARGIN_EXTREME = 1e-9
# Ill-conditioned 2D covariances (extreme anisotropy): the cancellation in det amplifies the
# rounding differences by kappa = c00 c11 / det; 1e-13 per unit of kappa is ~500 ulps.
RTOL_PER_KAPPA = 1e-13
# Central finite differences of the fast forward pass (float64): step 1e-6 keeps the truncation
# error O(h^2 * f''') ~ 1e-10 and the rounding error O(eps * |L| / h) ~ 1e-8 relative; the scene
# margin (1e-4) is far larger than the relative change a step can make, so no threshold is
# crossed. 1e-5 relative to the largest gradient entry covers both errors with margin.
FD_STEP = 1e-6
RTOL_FD = 1e-5

OUT_KEYS = ("image", "alpha", "depth", "expected_depth", "means2d", "depths", "conics")
GRAD_KEYS = ("means", "quats", "scales", "opacities", "colors", "cam_T_world", "background", "means2d",
             "means2d_abs")


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def rel_err(a, b):
    """max |a - b| / max(|a|, |b|) over the array (0 if both are exactly zero)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    scale = max(np.abs(a).max(initial=0.0), np.abs(b).max(initial=0.0))
    if scale == 0.0:
        return 0.0
    return float(np.abs(a - b).max(initial=0.0) / scale)


def compare_with_reference(scene, config=None, seed=0, rtol=RTOL_F64):
    """Run fast and reference forward and backward on ``scene``; assert agreement; return both."""
    out, saved = render_fwd(**scene, config=config)
    out_r, saved_r = ref.render_fwd(**scene, config=config)
    for key in OUT_KEYS:
        assert out[key].shape == out_r[key].shape, key
        assert np.all(np.isfinite(out[key])), key
        assert rel_err(out[key], out_r[key]) <= rtol, (key, rel_err(out[key], out_r[key]))
    np.testing.assert_array_equal(out["radii"], out_r["radii"])
    cot = rf.random_cotangents(np.random.default_rng(seed), scene["width"], scene["height"])
    grads = render_bwd(saved, **cot)
    grads_r = ref.render_bwd(saved_r, **cot)
    for key in GRAD_KEYS:
        assert grads[key].shape == grads_r[key].shape, key
        assert np.all(np.isfinite(grads[key])), key
        assert rel_err(grads[key], grads_r[key]) <= rtol, (key, rel_err(grads[key], grads_r[key]))
    assert np.all(grads["cam_T_world"][3] == 0)
    return out, grads, saved


def tile_intersections_numpy(means2d, radii, width, height, ts=C.TILE_SIZE):
    """Independent count of (tile, Gaussian) pairs from the contract's tile formula."""
    gw, gh = -(-width // ts), -(-height // ts)
    vis = (radii[:, 0] > 0) & (radii[:, 1] > 0)
    u, v = means2d[vis, 0], means2d[vis, 1]
    rx, ry = radii[vis, 0], radii[vis, 1]
    x0 = np.clip(np.floor((u - rx) / ts), 0, gw)
    x1 = np.clip(np.ceil((u + rx) / ts), 0, gw)
    y0 = np.clip(np.floor((v - ry) / ts), 0, gh)
    y1 = np.clip(np.ceil((v + ry) / ts), 0, gh)
    return int(np.sum((x1 - x0) * (y1 - y0)))


# camera_scene: shared with the reference-check kit (d2gs_np/refcheck/scenes.py)
camera_scene = rf.camera_scene


def assert_margin(scene, config=None, margin=MARGIN_EXTREME, ignore=()):
    """The scene's discrete decisions are at least ``margin`` (relative) from their thresholds."""
    m = {k: v for k, v in rf.threshold_margins(scene, config).items() if k not in ignore}
    assert min(m.values()) >= margin, m


# ---------------------------------------------------------------------------------------------
# fast vs reference on random scenes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n,width,height,seed", [
    (1, 16, 16, 0),
    (12, 37, 23, 1),
    (40, 37, 23, 2),
    (64, 32, 32, 3),
    (30, 17, 33, 4),
    (25, 5, 40, 5),
])
def test_matches_reference_random(n, width, height, seed):
    rng = np.random.default_rng(seed)
    scene = rf.safe_random_scene(rng, n, width, height, margin=MARGIN)
    out, _, _ = compare_with_reference(scene, seed=seed)
    assert out["num_intersections"] == tile_intersections_numpy(out["means2d"], out["radii"], width, height)


@pytest.mark.parametrize("seed", [10, 11])
def test_matches_reference_antialiased(seed):
    cfg = RenderConfig(antialiased=True)
    scene = rf.safe_random_scene(np.random.default_rng(seed), 40, 29, 31, margin=MARGIN, config=cfg)
    compare_with_reference(scene, config=cfg, seed=seed)


@pytest.mark.parametrize("cfg", [RenderConfig(near_plane=1.0, eps2d=0.1, tile_size=7),
                                 RenderConfig(eps2d=0.0, tile_size=32)])
def test_matches_reference_other_config(cfg):
    """Non-default near plane, eps2d (including no dilation) and tile sizes (7: not a power of two)."""
    rng = np.random.default_rng(12)
    scene = rf.safe_random_scene(rng, 40, 30, 19, margin=MARGIN, config=cfg)
    out, _, _ = compare_with_reference(scene, config=cfg, seed=12)
    n_isect = tile_intersections_numpy(out["means2d"], out["radii"], 30, 19, ts=cfg.tile_size)
    assert out["num_intersections"] == n_isect


def test_tile_border_straddling():
    """Gaussians centred exactly on tile corners and edges (u, v multiples of 16) of a 37x23 image."""
    rng = np.random.default_rng(3)
    W, H = 37, 23
    f = 40.0
    uv = np.array([(16, 16), (32, 16), (16, 0), (0, 16), (32, 8), (8, 16), (37, 23), (24, 16.0)])
    z = np.linspace(2.0, 4.0, len(uv))
    K_c = np.array([W / 2.0, H / 2.0])
    p_c = np.stack([(uv[:, 0] - K_c[0]) * z / f, (uv[:, 1] - K_c[1]) * z / (f * 1.02), z], axis=1)
    sig = np.array([2.0, 3.0, 5.0, 4.0, 2.5, 3.5, 6.0, 3.0])[:, None] * z[:, None] / f * np.array([[1.0, 0.6, 1.4]])
    # camera_scene applies a small random pose; build the camera-frame scene with identity pose
    scene = camera_scene(p_c, sig, rng.uniform(0.3, 0.9, len(uv)), rng.uniform(0, 1, (len(uv), 3)), W, H,
                         f=f, rng=rng)
    scene["cam_T_world"] = np.eye(4)
    scene["means"] = p_c
    scene["K"][1, 1] = f * 1.02
    assert_margin(scene)
    out, _, _ = compare_with_reference(scene, seed=3)
    rx = out["radii"][:, 0]
    assert np.all(rx > 0)
    n_isect = tile_intersections_numpy(out["means2d"], out["radii"], W, H)
    assert out["num_intersections"] == n_isect
    assert n_isect >= 3 * len(uv)  # every Gaussian straddles a border: several tiles each


def test_empty_scene():
    rng = np.random.default_rng(0)
    scene = rf.random_scene(rng, 0, 21, 18)
    out, saved = render_fwd(**scene)
    np.testing.assert_array_equal(out["image"], np.broadcast_to(scene["background"], (18, 21, 3)))
    assert np.all(out["alpha"] == 0) and np.all(out["depth"] == 0) and np.all(out["expected_depth"] == 0)
    assert out["num_intersections"] == 0 and out["radii"].shape == (0, 2)
    cot = rf.random_cotangents(rng, 21, 18)
    g = render_bwd(saved, **cot)
    for key, shape in [("means", (0, 3)), ("quats", (0, 4)), ("scales", (0, 3)), ("opacities", (0,)),
                       ("colors", (0, 3)), ("means2d", (0, 2))]:
        assert g[key].shape == shape
    assert np.all(g["cam_T_world"] == 0)
    np.testing.assert_allclose(g["background"], cot["v_image"].sum(axis=(0, 1)), rtol=1e-14)


def test_all_culled_scene_matches_reference():
    """Gaussians only behind the camera or off screen: image = background, zero gradients."""
    rng = np.random.default_rng(5)
    p_c = np.array([[0.0, 0.0, -2.0], [50.0, 0.0, 2.0], [0.0, -40.0, 3.0]])
    scene = camera_scene(p_c, np.full((3, 3), 0.05), [0.5, 0.6, 0.7], rng.uniform(0, 1, (3, 3)), 20, 20, rng=rng)
    out, g, _ = compare_with_reference(scene)
    assert np.all(out["radii"] == 0) and out["num_intersections"] == 0
    assert np.all(g["means"] == 0)


# ---------------------------------------------------------------------------------------------
# extreme / stiff cases: finite and equal to the reference
# ---------------------------------------------------------------------------------------------


def test_extreme_scale_magnitudes():
    """Scale magnitudes log-uniform in [1e-6, 1e3] (anisotropy <= 10 per Gaussian): sub-pixel
    points where the dilation dominates, up to Gaussians far larger than the image."""
    scene = extreme_scales_scene()
    assert_margin(scene)
    out, _, _ = compare_with_reference(scene, seed=21)
    assert out["radii"][1, 0] > 1000  # far larger than the image
    assert out["radii"][0, 0] == np.ceil(C.RADIUS_SIGMA * np.sqrt(C.EPS2D))  # dilation only


def test_extreme_anisotropy():
    """Needles and pancakes: per-Gaussian scale ratios up to 1e9 (scales in [1e-6, 1e3]).

    The 2D determinant det = c00 c11 - c01^2 then cancels: both implementations lose
    log10(kappa) digits, kappa = c00 c11 / det (the dilation keeps det >= 0.09, so kappa stays
    finite). Their difference is ~eps * kappa relative, so the tolerance is scaled by kappa_max.
    """
    scene = extreme_anisotropy_scene()
    assert_margin(scene)
    _, saved_r = ref.render_fwd(**scene)
    cov, det = saved_r["proj"]["cov"], saved_r["proj"]["det"]
    kappa = float(np.max(cov[:, 0, 0] * cov[:, 1, 1] / det))
    assert kappa > 1e5  # the scene is genuinely ill-conditioned
    compare_with_reference(scene, seed=22, rtol=max(RTOL_F64, RTOL_PER_KAPPA * kappa))


def test_near_plane_and_behind_camera():
    """z just above the near plane (huge footprint), z == near, z below it, z < 0."""
    near = C.NEAR_PLANE
    scene = near_plane_scene()  # exact camera-frame depths, so z == near is exactly representable
    p_c = scene["means"]
    # the fixture's near-plane margin is signed (negative for the Gaussians culled on purpose)
    assert_margin(scene, ignore=("near_plane",))
    z = p_c[:, 2]
    assert np.all((z <= near) | (z - near >= 0.4 * near))  # no z within rounding of the plane but z == near
    out, g, _ = compare_with_reference(scene, seed=22)
    assert out["radii"][0, 0] > 0  # in front of the near plane: kept
    assert np.all(out["radii"][1:4] == 0)  # at, below the near plane and behind the camera: culled
    assert np.all(g["means"][1:4] == 0) and np.all(g["opacities"][1:4] == 0)


@pytest.mark.parametrize("antialiased", [False, True])
def test_flat_covariance(antialiased):
    """Degenerate 3D covariances: one, two or all three scales exactly 0."""
    cfg = RenderConfig(antialiased=antialiased)
    scene = flat_covariance_scene()
    assert_margin(scene, cfg)
    out, _, _ = compare_with_reference(scene, config=cfg, seed=23)
    assert np.all(out["radii"] > 0)


def test_opacity_zero_and_one_and_colors_outside_unit():
    """Opacity 0 (never contributes), opacity 1 (alpha clamped at 0.999 near the centre, where no
    gradient flows through the clamp), colours and background outside [0, 1]."""
    rng = np.random.default_rng(24)
    n, W, H = 10, 22, 19
    p_c = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(2, 4, n)], axis=1)
    sig = rng.uniform(0.05, 0.3, (n, 3))
    p_c[3] = [0.013, -0.021, 1.5]  # in front of everything, wide: many pixels with o exp(-sigma) > 0.999
    sig[3] = [3.0, 2.0, 2.5]
    opac = rng.uniform(0.1, 0.9, n)
    opac[:3] = 0.0
    opac[3:6] = 1.0
    colors = rng.uniform(-2.0, 3.0, (n, 3))
    scene = camera_scene(p_c, sig, opac, colors, W, H, rng=rng)
    scene["background"] = np.array([-0.5, 1.5, 0.3])
    assert_margin(scene)
    _, saved_r = ref.render_fwd(**scene)
    ras = saved_r["raster"]
    assert np.count_nonzero(ras["evaluated"] & (ras["raw_alpha"] > C.ALPHA_MAX)) >= 4  # clamp active
    out, g, _ = compare_with_reference(scene, seed=24)
    assert np.all(g["colors"][:3] == 0)  # opacity 0 never contributes
    assert out["image"].min() < 0 or out["image"].max() > 1  # colours are not clamped


def test_gaussian_covering_whole_image():
    rng = np.random.default_rng(25)
    p_c = np.array([[0.0, 0.0, 2.0], [0.05, -0.02, 3.0]])
    sig = np.array([[5.0, 4.0, 3.0], [0.1, 0.2, 0.1]])
    scene = camera_scene(p_c, sig, [0.6, 0.8], rng.uniform(0, 1, (2, 3)), 33, 21, rng=rng)
    assert_margin(scene)
    out, _, _ = compare_with_reference(scene, seed=25)
    assert np.all(out["alpha"] > 0.5)
    gw, gh = 3, 2
    assert out["num_intersections"] >= gw * gh


def test_many_gaussians_on_one_pixel_early_stop():
    """1e5 Gaussians over a 1x1 image: the pixel stops long before the end of its list."""
    rng = np.random.default_rng(26)
    n, W, H = 100_000, 1, 1
    z = rng.uniform(2.0, 50.0, n)
    p_c = np.stack([rng.uniform(-0.1, 0.1, n) * z, rng.uniform(-0.1, 0.1, n) * z, z], axis=1)
    sig = rng.uniform(0.5, 1.0, (n, 3)) * z[:, None] / 3.0
    scene = camera_scene(p_c, sig, rng.uniform(0.3, 0.6, n), rng.uniform(0, 1, (n, 3)), W, H, f=3.0, rng=rng)
    out, g, saved = compare_with_reference(scene, seed=26)
    assert out["num_intersections"] == n  # every Gaussian is listed in the single tile
    # early stop: the pixel stops after ~log(1e-4) / log(1 - 0.45) ~ 15 contributors
    assert saved.num_evaluations < 100
    assert out["alpha"][0, 0] > 1 - C.TRANSMITTANCE_MIN / (1 - 0.6)  # stopped: T <= 1e-4 / (1 - max opacity)
    assert np.count_nonzero(np.any(g["colors"] != 0, axis=1)) < 100


@pytest.mark.parametrize("width,height", [(1, 1), (1, 23), (29, 1)])
def test_width_or_height_one(width, height):
    scene = rf.safe_random_scene(np.random.default_rng(27), 20, width, height, margin=MARGIN)
    out, _, _ = compare_with_reference(scene, seed=27)
    assert out["image"].shape == (height, width, 3)


def test_equal_float32_depths_keep_index_order():
    """Depths equal in float32 but not in float64: the order is by Gaussian index (stable sort)."""
    rng = np.random.default_rng(28)
    z0 = 3.0
    z_close = np.nextafter(np.float64(z0), 10.0)  # same float32 depth as z0
    assert np.float32(z_close) == np.float32(z0)
    p_c = np.array([[0.0, 0.0, z_close], [0.02, 0.01, z0], [0.01, -0.01, z_close]])
    sig = np.full((3, 3), 0.3) * np.array([[1.0, 0.7, 1.3]])
    scene = camera_scene(p_c, sig, [0.7, 0.8, 0.6], np.eye(3), 16, 16, rng=rng)
    scene["cam_T_world"] = np.eye(4)
    scene["means"] = p_c
    out, _, _ = compare_with_reference(scene, seed=28)
    # Gaussian 0 (red, farther in float64) is composited first because of its index.
    assert out["image"][8, 8, 0] > out["image"][8, 8, 1]


# ---------------------------------------------------------------------------------------------
# finite differences of the fast path itself (spot check)
# ---------------------------------------------------------------------------------------------


def test_fast_backward_vs_finite_differences():
    rng = np.random.default_rng(31)
    scene = rf.safe_random_scene(rng, 6, 16, 14, margin=1e-3)
    cot = rf.random_cotangents(rng, 16, 14)
    _, saved = render_fwd(**scene)
    g = render_bwd(saved, **cot)

    def loss_with(key, value):
        s = rf.copy_scene(scene)
        s[key] = value
        return rf.weighted_loss(render_fwd(**s)[0], cot)

    for key in ("means", "quats", "scales", "opacities", "colors", "background"):
        fd = rf.central_fd(lambda x, key=key: loss_with(key, x), scene[key], FD_STEP)
        assert rel_err(g[key], fd) <= RTOL_FD, (key, rel_err(g[key], fd))
    # pose, on the manifold: left perturbations exp(h e_i) T
    T = scene["cam_T_world"]
    fd_pose = np.array([rf.central_fd_scalar(lambda h, i=i: loss_with("cam_T_world", rf.left_perturb(T, i, h)),
                                             FD_STEP) for i in range(6)])
    tangent = rf.left_tangent_from_matrix_grad(T, g["cam_T_world"])
    assert rel_err(tangent, fd_pose) <= RTOL_FD


def test_means2d_abs_is_the_sum_of_each_pixels_absolute_term():
    """``means2d_abs`` (gsplat's absgrad) by its definition: a pixel's term of dL/d(mean2d) is the
    gradient of the loss with the cotangents zero at every other pixel (the image at a pixel depends
    on a mean only through that pixel), so it is the sum over pixels of |that gradient|, per axis.
    Rounding: a few 1e-16 relative per pixel, summed over 224 pixels; 1e-12 catches a missing abs."""
    rng = np.random.default_rng(32)
    W, H = 16, 14
    scene = rf.safe_random_scene(rng, 6, W, H, margin=1e-3)
    cot = rf.random_cotangents(rng, W, H)
    _, saved = render_fwd(**scene)
    g = render_bwd(saved, **cot)
    expected = np.zeros_like(g["means2d_abs"])
    for i in range(H):
        for j in range(W):
            one = {}
            for k, v in cot.items():
                m = np.zeros_like(v)
                m[i, j] = v[i, j]
                one[k] = m
            expected += np.abs(render_bwd(saved, **one)["means2d"])
    assert rel_err(g["means2d_abs"], expected) <= 1e-12, rel_err(g["means2d_abs"], expected)
    assert np.all(g["means2d_abs"] >= np.abs(g["means2d"]) - 1e-15)
    # pixels pull some mean different ways here, so the plain gradient loses part of the sum
    assert np.any(g["means2d_abs"] > 1.5 * np.abs(g["means2d"]))


# ---------------------------------------------------------------------------------------------
# float32
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [40, 41])
def test_float32_stays_float32_and_agrees(seed):
    rng = np.random.default_rng(seed)
    scene = rf.safe_random_scene(rng, 48, 33, 27, margin=MARGIN)
    s32 = rf.cast_scene(scene, np.float32)
    out64, saved64 = render_fwd(**scene)
    out32, saved32 = render_fwd(**s32)
    cot = rf.random_cotangents(rng, 33, 27)
    g64 = render_bwd(saved64, **cot)
    g32 = render_bwd(saved32, **rf.cast_scene(cot, np.float32))
    for key in OUT_KEYS:
        assert out32[key].dtype == np.float32, key
        assert rel_err(out32[key], out64[key]) <= RTOL_F32, (key, rel_err(out32[key], out64[key]))
    np.testing.assert_array_equal(out32["radii"], out64["radii"])
    assert out32["num_intersections"] == out64["num_intersections"]
    for key in GRAD_KEYS:
        assert g32[key].dtype == np.float32, key
        assert rel_err(g32[key], g64[key]) <= RTOL_F32, (key, rel_err(g32[key], g64[key]))


@pytest.mark.parametrize("x0, x1, y0, y1", [(0, 16, 0, 16), (32, 45, 16, 23), (0, 3, 0, 1), (16, 17, 0, 16)])
def test_lane_layout_is_a_bijection_with_contiguous_strip_runs(x0, x1, y0, y1):
    """Every tile pixel has its own lane in [0, npix) (full and partial tiles), and the lanes of rows
    [ia, ib) of strip s (``_strip_run``, after ``_pad_rows``) are exactly that strip's pixels of
    those rows."""
    th = y1 - y0
    lanes = {(i, j): fast_rasterize._lane(i, j, x0, x1, y0, th) for i in range(y0, y1) for j in range(x0, x1)}
    assert sorted(lanes.values()) == list(range((x1 - x0) * th))
    st = fast_rasterize._STRIP
    for ia in range(y0, y1):
        for ib in range(ia + 1, y1 + 1):
            pa, pb = fast_rasterize._pad_rows(ia, ib, y0, y1)
            assert y0 <= pa <= ia and ib <= pb <= y1
            assert (pb - pa) % fast_rasterize._ROW_GROUP == 0 or pb - pa == th
            for s_ in range(-(-(x1 - x0) // st)):
                qa, qb = fast_rasterize._strip_run(s_, pa, pb, x0, x1, y0, th)
                cols = range(x0 + s_ * st, min(x0 + s_ * st + st, x1))
                want = sorted(lanes[i, j] for i in range(pa, pb) for j in cols)
                assert list(range(qa, qb)) == want


def _float64_variables(dispatcher, sig):
    """Names of float64-typed variables when ``dispatcher``'s Python function is typed for ``sig``.

    Compiled afresh without cache or parallelism (typing is the same) so the typemap is available.
    """
    fresh = numba.njit(dispatcher.py_func)
    fresh.compile(sig)
    typemap = fresh.overloads[sig].type_annotation.typemap
    bad = []
    for name, typ in typemap.items():
        if typ == types.float64 or (isinstance(typ, types.BaseTuple) and types.float64 in getattr(typ, "types", ())):
            bad.append(name)
    return bad


def _jitted_functions(*modules):
    """The Numba dispatchers of ``modules``, each once (a module also holds the ones it imports)."""
    found = {}
    for module in modules:
        for obj in vars(module).values():
            if isinstance(obj, numba.core.registry.CPUDispatcher):
                found[id(obj)] = obj
    return list(found.values())


def test_float32_kernels_compute_in_float32():
    """No float64 variable in the float32 specialisation of any kernel or helper (no silent promotion)."""
    if numba.config.DISABLE_JIT:
        pytest.skip("typing information needs the JIT")
    rng = np.random.default_rng(42)
    s32 = rf.cast_scene(rf.random_scene(rng, 8, 20, 18), np.float32)
    _, saved = render_fwd(**s32)
    render_bwd(saved, np.ones((18, 20, 3), np.float32))
    kernels = _jitted_functions(fast_project, binning, fast_exp, fast_rasterize)
    names = {k.py_func.__name__ for k in kernels}
    assert {"_project_fwd_kernel", "_project_bwd_kernel", "_rasterize_fwd_kernel", "_rasterize_bwd_kernel",
            "_isect_reduce_kernel", "_gather_tile", "_sigma", "_band_rows", "exp_neg", "_composite_band",
            "_backprop_band", "_tile_rects_kernel", "band", "inv_axis_vars"} <= names
    def float32_sigs(kern):
        return [s for s in kern.signatures if any(getattr(a, "dtype", a) == types.float32 for a in s)]

    # Typing a function afresh also types (or loads from the cache) the helpers it calls, so
    # sweep until every helper has a float32 signature and has been checked.
    todo = [k for k in kernels if k.py_func.__name__ not in ("_isect_build_kernel", "_clamp_tile", "_lane", "_pad_rows",
                                                              "_strip_run")]  # integer-only helpers
    checked = 0
    while todo:
        ready = [k for k in todo if float32_sigs(k)]
        assert ready, [k.py_func.__name__ for k in todo]  # a helper never used in float32?
        for kern in ready:
            assert _float64_variables(kern, float32_sigs(kern)[0]) == [], kern.py_func.__name__
            todo.remove(kern)
            checked += 1
    assert checked >= 12


def test_float64_detector_can_fail():
    """The detector above flags a float32 kernel that promotes through a Python float literal."""
    if numba.config.DISABLE_JIT:
        pytest.skip("typing information needs the JIT")

    @numba.njit
    def promotes(x):
        return x[0] * 0.5

    sig = (types.float32[::1],)
    assert _float64_variables(promotes, sig) != []


# ---------------------------------------------------------------------------------------------
# determinism, threads, NUMBA_DISABLE_JIT
# ---------------------------------------------------------------------------------------------


def test_backward_bitwise_deterministic_across_runs_and_threads():
    rng = np.random.default_rng(50)
    scene = rf.random_scene(rng, 64, 32, 32, sigma_px_range=(2.0, 12.0))
    cot = rf.random_cotangents(rng, 32, 32)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        out_a, saved_a = render_fwd(**scene)
        g_a = render_bwd(saved_a, **cot)
        g_b = render_bwd(render_fwd(**scene)[1], **cot)
        numba.set_num_threads(1)
        out_c, saved_c = render_fwd(**scene)
        g_c = render_bwd(saved_c, **cot)
    finally:
        numba.set_num_threads(old)
    for key in GRAD_KEYS:
        assert np.array_equal(g_a[key], g_b[key]), key
        assert np.array_equal(g_a[key], g_c[key]), key
    for key in OUT_KEYS:
        assert np.array_equal(out_a[key], out_c[key]), key


def test_runs_with_jit_disabled():
    """The kernels run as plain Python under NUMBA_DISABLE_JIT=1 and give the reference's result."""
    code = textwrap.dedent("""
        import json, sys
        import numpy as np
        sys.path.insert(0, sys.argv[1])
        import numba
        assert numba.config.DISABLE_JIT
        import render_fixtures as rf
        from d2gs_np import reference as ref
        from d2gs_np.render import render_bwd, render_fwd
        rng = np.random.default_rng(3)
        scene = rf.safe_random_scene(rng, 5, 19, 17, margin=1e-4)
        cot = rf.random_cotangents(rng, 19, 17)
        out, saved = render_fwd(**scene)
        out_r, saved_r = ref.render_fwd(**scene)
        g = render_bwd(saved, **cot)
        g_r = ref.render_bwd(saved_r, **cot)
        def rel(a, b):
            s = max(np.abs(a).max(initial=0.0), np.abs(b).max(initial=0.0))
            return 0.0 if s == 0 else float(np.abs(a - b).max() / s)
        res = {k: rel(out[k], out_r[k]) for k in ("image", "alpha", "depth")}
        res.update({"v_" + k: rel(g[k], g_r[k]) for k in g})
        print(json.dumps(res))
    """)
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    tests_dir = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run([sys.executable, "-c", code, tests_dir], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(res) == 3 + len(GRAD_KEYS)
    for key, err in res.items():
        assert err <= RTOL_F64, (key, err)


# ---------------------------------------------------------------------------------------------
# validation: clear errors before any work
# ---------------------------------------------------------------------------------------------


def _good_scene():
    return rf.random_scene(np.random.default_rng(60), 5, 12, 10)


def _bad(key, value):
    def make():
        s = _good_scene()
        s[key] = value(s) if callable(value) else value
        return s
    return make


BAD_INPUTS = [
    (_bad("means", lambda s: np.zeros((5, 4))), ValueError, "means must have shape (N, 3); got (5, 4)"),
    (_bad("quats", lambda s: s["quats"][:4]), ValueError, "quats must have shape"),
    (_bad("quats", lambda s: s["quats"].astype(np.float32)), TypeError, "quats has dtype float32"),
    (_bad("colors", lambda s: s["colors"].tolist()), TypeError, "colors must be a numpy.ndarray"),
    (_bad("scales", lambda s: s["scales"].astype(np.int64)), TypeError, "scales must have dtype float64"),
    (_bad("opacities", lambda s: np.where(np.arange(5) == 2, np.nan, s["opacities"])), ValueError,
     "opacities contains NaN"),
    (_bad("opacities", lambda s: s["opacities"] + 1.0), ValueError, "opacities must lie in [0, 1]"),
    (_bad("scales", lambda s: -s["scales"]), ValueError, "scales are linear and must be >= 0"),
    (_bad("quats", lambda s: np.where(np.arange(5)[:, None] == 1, 0.0, s["quats"])), ValueError,
     "quats must have norm"),
    (_bad("K", lambda s: s["K"] + np.array([[0, 0.1, 0], [0, 0, 0], [0, 0, 0]])), ValueError, "zero skew"),
    (_bad("K", lambda s: s["K"] * np.array([[-1.0], [1.0], [1.0]])), ValueError, "positive focal"),
    (_bad("cam_T_world", lambda s: np.eye(3)), ValueError, "cam_T_world must have shape (4, 4)"),
    (_bad("cam_T_world", lambda s: np.where(np.eye(4) > 0, np.inf, s["cam_T_world"])), ValueError,
     "cam_T_world contains NaN or inf"),
    (_bad("background", lambda s: np.zeros(4)), ValueError, "background must have shape (3,)"),
    (_bad("width", 0), ValueError, "width must be >= 1"),
    (_bad("height", 2.5), TypeError, "height must be an int"),
    (_bad("width", True), TypeError, "width must be an int"),
]


@pytest.mark.parametrize("make,exc,msg", BAD_INPUTS)
def test_bad_forward_inputs_raise_before_any_work(make, exc, msg, monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("validation must happen before any kernel runs")

    monkeypatch.setattr(fast_api, "project_fwd", no_work)
    with pytest.raises(exc) as info:
        render_fwd(**make())
    assert msg in str(info.value)


def test_bad_config_raises():
    with pytest.raises(TypeError, match="config must be"):
        render_fwd(**_good_scene(), config={"antialiased": True})


def test_bad_backward_inputs_raise_before_any_work(monkeypatch):
    _, saved = render_fwd(**_good_scene())
    v = np.ones((10, 12, 3))

    def no_work(*args, **kwargs):
        raise AssertionError("validation must happen before any kernel runs")

    monkeypatch.setattr(fast_api, "rasterize_bwd", no_work)
    with pytest.raises(ValueError, match=r"v_image must have shape \(H, W, 3\) = \(10, 12, 3\); got \(12, 10, 3\)"):
        render_bwd(saved, np.ones((12, 10, 3)))
    with pytest.raises(TypeError, match="v_image has dtype float32 but the render ran in float64"):
        render_bwd(saved, v.astype(np.float32))
    with pytest.raises(ValueError, match="v_alpha contains NaN"):
        render_bwd(saved, v, v_alpha=np.full((10, 12), np.nan))
    with pytest.raises(ValueError, match="v_expected_depth must have shape"):
        render_bwd(saved, v, v_expected_depth=np.ones((10, 13)))
    with pytest.raises(TypeError, match="saved must be the RenderSaved"):
        render_bwd({"raster": None}, v)
