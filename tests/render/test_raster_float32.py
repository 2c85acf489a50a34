"""RenderConfig(raster_float32=True): float64 inputs, projection in float64, binning and
compositing (forward and backward) in float32, float64 outputs and gradients.

What the option promises (d2gs_np/render/config.py): outputs and gradients within float32
rounding of the float64 render, float64 arrays out, no inf or NaN from the cast (renders whose
projected values do not fit float32 keep float64), and no effect on float32 inputs.
"""
from __future__ import annotations

import numpy as np
import pytest

import render_fixtures as rf
from d2gs_np.refcheck.scenes import extreme_anisotropy_scene, extreme_scales_scene, near_plane_scene
from d2gs_np.render import RenderConfig, render_bwd, render_fwd

MIXED = RenderConfig(raster_float32=True)
# Mixed vs float64, relative to each output's largest entry. The projection is float64, so the
# float32 error comes from the cast of its outputs (0.5 ulp, 6e-8) and the compositing's chains
# of ~10-100 float32 operations and sums over up to a few hundred (Gaussian, pixel) terms:
# ~1e-6 (observed <= 6e-6 on 5 000 Gaussians at 256 x 256). 1e-4 is the float32 tolerance of
# tests/render/test_render_fast.py (RTOL_F32), a 15x margin here.
RTOL_MIXED = 1e-4
# Scenes whose discrete decisions sit this far from their thresholds (relative): above float32
# rounding (6e-8), so no decision flips between the two paths (as test_render_fast.MARGIN).
MARGIN = 1e-4
OUT_KEYS = ("image", "alpha", "depth", "expected_depth")
GRAD_KEYS = ("means", "quats", "scales", "opacities", "colors", "cam_T_world", "background", "means2d")


def rel_err(a, b):
    scale = np.max(np.abs(b))
    return float(np.max(np.abs(a - b)) / scale) if scale > 0 else float(np.max(np.abs(a)))


def assert_bitwise_equal(out_a, out_b, g_a, g_b):
    for key in OUT_KEYS:
        np.testing.assert_array_equal(out_a[key], out_b[key], err_msg=key)
    for key in GRAD_KEYS:
        np.testing.assert_array_equal(g_a[key], g_b[key], err_msg=key)


def both(scene, cot):
    out64, s64 = render_fwd(**scene)
    outm, sm = render_fwd(**scene, config=MIXED)
    return out64, outm, render_bwd(s64, **cot), render_bwd(sm, **cot), sm


@pytest.mark.parametrize("seed", [50, 51, 52])
def test_mixed_agrees_with_float64_and_returns_float64(seed):
    rng = np.random.default_rng(seed)
    scene = rf.safe_random_scene(rng, 60, 37, 29, margin=MARGIN)
    cot = rf.random_cotangents(rng, 37, 29)
    out64, outm, g64, gm, saved = both(scene, cot)
    assert saved.rast is not None and saved.rast[0]["means2d"].dtype == np.float32  # it did run in float32
    differs = False
    for key in OUT_KEYS:
        assert outm[key].dtype == np.float64, key
        assert rel_err(outm[key], out64[key]) <= RTOL_MIXED, (key, rel_err(outm[key], out64[key]))
        differs |= not np.array_equal(outm[key], out64[key])
    for key in ("means2d", "depths", "conics", "radii"):  # projection outputs: float64, the same bits
        np.testing.assert_array_equal(outm[key], out64[key])
    assert outm["num_intersections"] == out64["num_intersections"]
    for key in GRAD_KEYS:
        assert gm[key].dtype == np.float64, key
        assert rel_err(gm[key], g64[key]) <= RTOL_MIXED, (key, rel_err(gm[key], g64[key]))
        differs |= not np.array_equal(gm[key], g64[key])
    assert differs, "raster_float32 changed nothing: the float32 kernels did not run"


def test_mixed_equals_float32_rasteriser_on_the_float64_projection():
    """The option is exactly: float64 projection, its outputs cast, the float32 rasteriser on a
    zero background, and the float64 background added after."""
    from d2gs_np.render.api import _raster_inputs
    from d2gs_np.render.binning import build_intersections
    from d2gs_np.render.project import make_consts, project_fwd
    from d2gs_np.render.rasterize import rasterize_fwd

    rng = np.random.default_rng(53)
    scene = rf.safe_random_scene(rng, 40, 31, 23, margin=MARGIN)
    outm, _ = render_fwd(**scene, config=MIXED)
    consts = make_consts(MIXED, 31, 23, np.float64)
    proj = project_fwd(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["cam_T_world"],
                       scene["K"], consts, False)
    proj32 = {k: v.astype(np.float32) for k, v in proj.items() if v.dtype == np.float64}
    consts32 = make_consts(MIXED, 31, 23, np.float32)
    isect = build_intersections(proj32, consts32, 31, 23, MIXED.tile_size)
    raster = rasterize_fwd(proj32, scene["colors"].astype(np.float32), np.zeros(3, np.float32),
                           consts32, isect, 31, 23, MIXED.tile_size)
    T = raster["T_final"].astype(np.float64)
    # the background is added in float64, to the float32 colour sum
    np.testing.assert_array_equal(outm["image"], raster["image"].astype(np.float64) + T[..., None] * scene["background"])
    np.testing.assert_array_equal(outm["alpha"], 1 - T)
    rast = _raster_inputs(proj, scene["colors"], MIXED, 31, 23, np.dtype(np.float64))
    assert rast is not None and set(rast[0]) <= set(proj32)


@pytest.mark.parametrize("make", [extreme_scales_scene, near_plane_scene, extreme_anisotropy_scene],
                         ids=["extreme_scales", "near_plane", "extreme_anisotropy"])
def test_mixed_is_finite_and_close_on_extreme_scenes(make):
    """Scales from 1e-6 to 1e3, Gaussians at and behind the near plane, 2D covariances with
    condition numbers to 1e17 (whose conics the pure float32 path gets wrong; here they come from
    the float64 projection): finite outputs and gradients, within float32 rounding of float64
    except where a discrete decision sits within float32 rounding of its threshold (checked
    through the image only, which such a flip moves by at most one Gaussian's 1/255 step)."""
    scene = make()
    H, W = scene["height"], scene["width"]
    cot = rf.random_cotangents(np.random.default_rng(54), W, H)
    out64, outm, g64, gm, _ = both(scene, cot)
    for key in OUT_KEYS:
        assert np.all(np.isfinite(outm[key])), key
    for key in GRAD_KEYS:
        assert np.all(np.isfinite(gm[key])), key
    assert rel_err(outm["image"], out64["image"]) <= 1.0 / 255, rel_err(outm["image"], out64["image"])
    if make is not extreme_anisotropy_scene:
        for key in ("image", "alpha"):
            assert rel_err(outm[key], out64[key]) <= RTOL_MIXED, key
        for key in ("colors", "opacities", "background"):
            assert rel_err(gm[key], g64[key]) <= RTOL_MIXED, key


def test_opacity_zero_and_one():
    """Opacities exactly 0 (sigma cut-off -inf: never composited) and 1 (alpha at the 0.999 clamp)."""
    rng = np.random.default_rng(55)
    scene = rf.safe_random_scene(rng, 30, 29, 25, margin=MARGIN)
    scene["opacities"] = scene["opacities"].copy()
    scene["opacities"][:10] = 0.0
    scene["opacities"][10:20] = 1.0
    cot = rf.random_cotangents(rng, 29, 25)
    out64, outm, g64, gm, _ = both(scene, cot)
    for key in OUT_KEYS:
        assert np.all(np.isfinite(outm[key])) and rel_err(outm[key], out64[key]) <= RTOL_MIXED, key
    for key in ("colors", "opacities", "background"):
        assert np.all(np.isfinite(gm[key])) and rel_err(gm[key], g64[key]) <= RTOL_MIXED, key
    np.testing.assert_array_equal(gm["colors"][:10], 0.0)  # opacity 0 contributes nothing


def test_values_beyond_float32_keep_float64():
    """A Gaussian whose 2D covariance overflows float32 (scale 1e21 at depth 3: 1e44 px^2): the
    render keeps float64 (bitwise the float64 render) instead of compositing an inf."""
    rng = np.random.default_rng(56)
    scene = rf.safe_random_scene(rng, 12, 21, 17, margin=MARGIN)
    scene["scales"] = scene["scales"].copy()
    scene["scales"][0] = 1e21
    cot = rf.random_cotangents(rng, 21, 17)
    out64, outm, g64, gm, saved = both(scene, cot)
    assert saved.rast is None
    assert_bitwise_equal(outm, out64, gm, g64)


def test_no_effect_on_float32_inputs():
    rng = np.random.default_rng(57)
    scene = rf.cast_scene(rf.safe_random_scene(rng, 20, 19, 15, margin=MARGIN), np.float32)
    cot = rf.cast_scene(rf.random_cotangents(rng, 19, 15), np.float32)
    out_a, sa = render_fwd(**scene)
    out_b, sb = render_fwd(**scene, config=MIXED)
    assert_bitwise_equal(out_b, out_a, render_bwd(sb, **cot), render_bwd(sa, **cot))


def test_empty_scene():
    rng = np.random.default_rng(58)
    scene = rf.safe_random_scene(rng, 5, 9, 7, margin=MARGIN)
    scene = {k: (v[:0] if isinstance(v, np.ndarray) and v.ndim and v.shape[0] == 5 else v) for k, v in scene.items()}
    out, saved = render_fwd(**scene, config=MIXED)
    g = render_bwd(saved, np.ones((7, 9, 3)))
    np.testing.assert_array_equal(out["image"], np.broadcast_to(scene["background"], (7, 9, 3)))
    assert out["image"].dtype == np.float64 and g["means"].shape == (0, 3)


def test_config_rejects_non_bool():
    with pytest.raises(ValueError, match="raster_float32"):
        RenderConfig(raster_float32="yes")
