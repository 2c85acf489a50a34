"""Tile binning (d2gs_np/render/binning.py): the bands hold every pixel that can pass the 1/255
rule, and the tile lists cut to them hold every reachable tile and change no result."""
from __future__ import annotations

import numpy as np
import pytest

import render_fixtures as rf
from d2gs_np import constants as C
from d2gs_np.render import RenderConfig
from d2gs_np.render import binning
from d2gs_np.render import project as fast_project
from d2gs_np.render import rasterize as fast_rasterize


def test_band_rows_hold_every_pixel_below_the_cutoff():
    """Every pixel of a tile whose sigma <= sigma_cut (the only pixels that can pass the 1/255
    rule) lies in the rows ``_band_rows`` gives, for random anisotropic Gaussians of random
    opacity around and inside one tile; and the band is much tighter than the 3.33-sigma box
    for faint Gaussians (so the test can fail both ways)."""
    rng = np.random.default_rng(7)
    consts = fast_project.make_consts(RenderConfig(), 64, 64, np.float64)
    y0, y1 = 16, 32
    py = np.arange(64) + 0.5
    px = np.arange(64) + 0.5
    tighter = 0
    for _ in range(400):
        L = rng.normal(size=(2, 2)) * rng.uniform(0.5, 6.0)
        cov = L @ L.T + 0.3 * np.eye(2)
        det = cov[0, 0] * cov[1, 1] - cov[0, 1] ** 2
        conic = np.array([cov[1, 1], -cov[0, 1], cov[0, 0]]) / det
        o = rng.uniform(0.0, 1.0)
        cut = binning.sigma_cutoffs(np.array([o]))
        mean = rng.uniform(0.0, 48.0, 2)
        radii = np.ceil(C.RADIUS_SIGMA * np.sqrt([cov[0, 0], cov[1, 1]]))
        loc = fast_rasterize._gather_tile(0, 1, np.zeros(1, np.int64), mean[None], conic[None], np.array([o]),
                                         np.zeros((1, 3)), np.ones(1), radii[None], cut,
                                         np.array([[cov[0, 0], cov[0, 1], cov[1, 1]]]), consts)
        ia, ib = fast_rasterize._band_rows(loc, 0, y0, y1, 0.5, 1.0, 2.0, 0.0)
        dx = mean[0] - px[None, :]
        dy = mean[1] - py[y0:y1, None]
        sigma = 0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) + conic[1] * dx * dy
        rows = np.flatnonzero(np.any(sigma <= cut[0], axis=1)) + y0
        assert np.all((rows >= ia) & (rows < ib)), (rows, ia, ib)
        ja, jb = fast_rasterize._band_cols(loc, 0, 16, 32, 0.5, 1.0, 2.0, 0.0)
        dx_all = mean[0] - px[None, 16:32]
        dy_all = mean[1] - py[:, None]
        sig_all = 0.5 * (conic[0] * dx_all * dx_all + conic[2] * dy_all * dy_all) + conic[1] * dx_all * dy_all
        cols = np.flatnonzero(np.any(sig_all <= cut[0], axis=0)) + 16
        assert np.all((cols >= ja) & (cols < jb)), (cols, ja, jb)
        box = binning._box_range(mean[1], radii[1], y0, y1, 0.5, 1.0)
        assert box[0] <= ia or ib <= ia
        assert ib <= box[1] or ib <= ia
        tighter += (ib - ia) < (box[1] - box[0]) - 2
    assert tighter > 10  # 29 of the 400 (most miss the tile or are bright)


def _render_with_lists(scene, tight, config=None):
    """Forward + backward of the fast renderer with the tile lists cut to the bands (``tight``) or
    holding every tile of the 3.33-sigma boxes (gsplat's lists)."""
    config = config or RenderConfig()
    W, H, ts = scene["width"], scene["height"], int(config.tile_size)
    inputs = {k: scene[k] for k in ("means", "quats", "scales", "opacities", "colors", "cam_T_world", "K",
                                    "background")}
    consts = fast_project.make_consts(config, W, H, np.float64)
    proj = fast_project.project_fwd(inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"],
                                    inputs["cam_T_world"], inputs["K"], consts, config.antialiased)
    isect = binning.build_intersections(proj, consts, W, H, ts, tight=tight)
    raster = fast_rasterize.rasterize_fwd(proj, inputs["colors"], inputs["background"], consts, isect, W, H, ts)
    rng = np.random.default_rng(1)
    grads = fast_rasterize.rasterize_bwd(proj, inputs["colors"], consts, isect, raster, ts,
                                         rng.normal(size=(H, W, 3)), rng.normal(size=(H, W)), rng.normal(size=(H, W)))
    return proj, isect, raster, grads


@pytest.mark.parametrize("seed, config", [(0, RenderConfig()), (1, RenderConfig(eps2d=0.0, tile_size=7)),
                                          (2, RenderConfig(antialiased=True))])
def test_tight_tile_lists_list_every_reachable_tile_and_change_nothing(seed, config):
    """The tile lists cut to the Gaussians' bands (``build_intersections``) hold every (Gaussian,
    tile) pair with a pixel of sigma <= sigma_cut (checked densely in NumPy), are a subset of the
    3.33-sigma boxes' pairs (whose count stays ``num_intersections``), are strictly smaller on faint
    Gaussians (so the test can fail both ways), and give the same image, depth, transmittance and
    gradients to the last bit as the box lists (a left-out tile only ever added exact zeros)."""
    rng = np.random.default_rng(seed)
    scene = rf.random_scene(rng, 300, 61, 45, sigma_px_range=(0.3, 6.0), opacity_range=(0.0, 1.0))
    proj, tight, ras_t, g_t = _render_with_lists(scene, True, config)
    _, box, ras_b, g_b = _render_with_lists(scene, False, config)
    ts, gw = int(config.tile_size), tight["grid_w"]
    assert tight["n_box_isect"] == box["n_box_isect"] == box["n_isect"] > tight["n_isect"]

    def pairs(isect):
        off = isect["tile_offsets"]
        return {(int(g), t) for t in range(off.size - 1) for g in isect["isect_gauss"][off[t]:off[t + 1]]}

    listed, boxed = pairs(tight), pairs(box)
    assert listed <= boxed
    H, W = ras_t["T_final"].shape
    py, px = np.mgrid[0:H, 0:W] + 0.5
    for g, t in boxed - listed:
        a, b, c = proj["conics"][g]
        ty, tx = divmod(t, gw)
        sl = np.s_[ty * ts:(ty + 1) * ts, tx * ts:(tx + 1) * ts]
        dx, dy = proj["means2d"][g, 0] - px[sl], proj["means2d"][g, 1] - py[sl]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        assert not np.any((sigma >= 0) & (sigma <= tight["sigma_cut"][g])), (g, t)
    for k in ("image", "depth", "T_final"):
        np.testing.assert_array_equal(ras_t[k], ras_b[k])
    for k in g_t:
        np.testing.assert_array_equal(g_t[k], g_b[k])
