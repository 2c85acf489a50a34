"""Tests of the NumPy reference renderer (d2gs_np.reference): gradients against central finite
differences in float64, forward against independent hand computations, stiff and extreme cases.

Finite differences and discontinuities. The loss is only piecewise smooth (docs/conventions.md §8).
Every FD test uses a scene whose threshold margin (tests/render_fixtures.threshold_margins: the
smallest relative distance of any (Gaussian, pixel) evaluation to 1/255, 0.999, 1e-4, the near
plane, a depth-order swap or the Jacobian clamp's kink) is at least MARGIN_MIN = 1e-3, and steps
of FD_STEP = 1e-7. In these scenes a thresholded quantity changes by at most ~1e2 relative per
unit of any input (e.g. d ln(alpha)/d scale ~ 2 sigma / s ~ 10 / 0.07 for the smallest scales
drawn), so one step moves it by <= 1e-5 relative: 100x inside the margin, no threshold is crossed
and the central difference sees a smooth function.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import render_fixtures as rf
from d2gs_np import constants as C
from d2gs_np.reference import render, render_bwd, render_fwd
from d2gs_np.reference.rasterize import rasterize_bwd, rasterize_fwd
from d2gs_np.render.config import RenderConfig

# Step of the central differences. Round-off error of the FD is ~ 1e-16 |L| / h with |L| ~ 1e2
# (random weights on ~1e3 outputs), i.e. ~1e-7 absolute on gradients of scale 1..1e2; truncation
# error h^2 f''' / 6 ~ 1e-14 f''' is negligible. Small enough for the margin argument above.
FD_STEP = 1e-7
# Minimum relative distance to any threshold of an FD test scene (see the module docstring).
MARGIN_MIN = 1e-3
# A Gaussian drawn through the 0.999 clamp cannot be 1e-3 away from it (o <= 1 caps the relative
# distance at 1e-3); near its mean sigma is stationary, so raw alpha moves by ~ h / o per step:
# half the margin still leaves a factor > 1e3.
MARGIN_MIN_CLAMP = 5e-4
# max |grad - fd| <= FD_RTOL * max |fd| per input block: 100x the FD round-off estimate above.
FD_RTOL = 1e-5
# Forward against closed forms: both sides are a few dozen float64 operations.
FWD_RTOL = 1e-12
# Projection against an independent EWA computation whose Jacobian is itself a central FD with
# step 1e-5 (truncation ~ 1e-10 relative, round-off ~ 1e-11).
EWA_RTOL = 1e-7
# float32 against float64 renders of a scene with margin >= 1e-3 (no threshold can flip under
# float32 rounding, ~1e-7 relative). Measured: outputs ~3e-7, gradients ~2e-6 of their scale (eps32 =
# 6e-8 amplified by the chains of ~1e2 operations and the det / 1 - alpha cancellations); the
# tolerances leave a factor ~30-50 (gsplat's own float32 gradient checks use 2e-3).
F32_OUT_RTOL = 1e-5
F32_GRAD_RTOL = 1e-4

INPUT_KEYS = ("means", "quats", "scales", "opacities", "colors", "background")


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def _loss(scene, cot, config):
    out, _ = render_fwd(**scene, config=config)
    return rf.weighted_loss(out, cot)


def gradient_errors(scene, config=None, seed=0, keys=INPUT_KEYS, pose=True):
    """Relative discrepancy max|grad - fd| / max|fd| for each input (and the pose), plus scales.

    Returns (errors, scales): dicts keyed by input name, "pose_tangent" and "pose_matrix".
    """
    rng = np.random.default_rng(seed)
    cot = rf.random_cotangents(rng, scene["width"], scene["height"])
    _, saved = render_fwd(**scene, config=config)
    grads = render_bwd(saved, **cot)
    errors, scales = {}, {}

    def _record(name, g, fd):
        scale = float(np.abs(fd).max())
        scales[name] = scale
        errors[name] = float(np.abs(g - fd).max()) / max(scale, np.finfo(float).tiny)

    for key in keys:
        def f(x, key=key):
            sc = rf.copy_scene(scene)
            sc[key] = x
            return _loss(sc, cot, config)

        _record(key, grads[key], rf.central_fd(f, scene[key], FD_STEP))

    if pose:
        T = scene["cam_T_world"]
        G = grads["cam_T_world"]
        assert np.all(G[3] == 0), "bottom row of the pose gradient must be exactly zero"
        tangent = rf.left_tangent_from_matrix_grad(T, G)
        fd_tan = np.zeros(6)
        for i in range(6):
            def g_of_h(h, i=i):
                sc = rf.copy_scene(scene)
                sc["cam_T_world"] = rf.left_perturb(T, i, h)
                return _loss(sc, cot, config)

            fd_tan[i] = rf.central_fd_scalar(g_of_h, FD_STEP)
        _record("pose_tangent", tangent, fd_tan)

        def f_top(top):
            sc = rf.copy_scene(scene)
            sc["cam_T_world"] = np.vstack([top, T[3:]])
            return _loss(sc, cot, config)

        _record("pose_matrix", G[:3], rf.central_fd(f_top, T[:3], FD_STEP))
    return errors, scales


def assert_gradients_match(scene, config=None, seed=0, keys=INPUT_KEYS, pose=True, margin_min=MARGIN_MIN):
    margin = rf.threshold_margin(scene, config)
    assert margin >= margin_min, f"test scene too close to a threshold: margin {margin:.3g}"
    errors, scales = gradient_errors(scene, config, seed, keys, pose)
    for name, err in errors.items():
        assert scales[name] > 0, f"gradient of {name} is identically zero: the test would be vacuous"
        assert err <= FD_RTOL, f"{name}: max |grad - fd| / max |fd| = {err:.3g} > {FD_RTOL}"
    return errors


def _find_scene(make, config=None, tries=100, margin_min=MARGIN_MIN):
    """Call make(rng) with successive seeds until the scene has margin >= margin_min."""
    for seed in range(tries):
        scene = make(np.random.default_rng(seed))
        if rf.threshold_margin(scene, config) >= margin_min:
            return scene
    raise AssertionError("no scene with the required threshold margin found")


def _used_counts(saved):
    """Per pixel, how many Gaussians were composited."""
    return saved["raster"]["used"].sum(axis=0)


def _stopped_any(saved):
    r = saved["raster"]
    stopped = r["evaluated"] & (r["alpha"] >= C.ALPHA_THRESHOLD) & ~r["used"]
    return bool(stopped.any())


def _axis_camera(width, height, f=None, cx=None, cy=None):
    f = float(max(width, height)) if f is None else f
    cx = width / 2 if cx is None else cx
    cy = height / 2 if cy is None else cy
    return np.array([[f, 0.0, cx], [0.0, 1.1 * f, cy], [0.0, 0.0, 1.0]])


def _pose(seed=7):
    T = np.eye(4)
    rng = np.random.default_rng(seed)
    T[:3, :3] = rf.random_rotation(rng, 0.8)
    T[:3, 3] = rng.normal(size=3)
    return T


def _world(T, p_c):
    """World points whose camera coordinates under T are p_c (…,3)."""
    return (np.asarray(p_c, float) - T[:3, 3]) @ T[:3, :3]


def _axis_scene(gaussians, width, height, K=None, T=None, background=(0.2, 0.3, 0.4)):
    """Isotropic Gaussians on the optical axis: gaussians = [(z, s, opacity, color), ...]."""
    K = _axis_camera(width, height) if K is None else K
    T = _pose() if T is None else T
    zs = np.array([g[0] for g in gaussians], float)
    p_c = np.stack([np.zeros_like(zs), np.zeros_like(zs), zs], -1)
    rng = np.random.default_rng(3)
    quats = rng.normal(size=(len(gaussians), 4))  # any rotation: the Gaussians are isotropic
    return dict(
        means=_world(T, p_c),
        quats=quats,
        scales=np.array([[g[1]] * 3 for g in gaussians], float),
        opacities=np.array([g[2] for g in gaussians], float),
        colors=np.array([g[3] for g in gaussians], float),
        cam_T_world=T,
        K=K,
        width=width,
        height=height,
        background=np.array(background, float),
    )


def _axis_expected(scene):
    """Closed-form render of an _axis_scene: on the axis, J = diag(fx/z, fy/z) (x = y = 0), so
    cov2d = diag((fx s/z)^2 + eps2d, (fy s/z)^2 + eps2d) and
    alpha = min(0.999, o exp(-(dx^2/cov_xx + dy^2/cov_yy)/2)) with d = (cx, cy) - pixel centre.
    Composited front to back with the skip and stop rules of docs/conventions.md §6."""
    K, W, H = scene["K"], scene["width"], scene["height"]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    dx, dy = cx - (jj + 0.5), cy - (ii + 0.5)
    R_v, t_v = scene["cam_T_world"][:3, :3], scene["cam_T_world"][:3, 3]
    z_all = (scene["means"] @ R_v.T + t_v)[:, 2]
    T = np.ones((H, W))
    done = np.zeros((H, W), bool)
    Cimg = np.zeros((H, W, 3))
    D = np.zeros((H, W))
    for k in np.argsort(z_all, kind="stable"):
        z, s, o = z_all[k], scene["scales"][k, 0], scene["opacities"][k]
        cxx = (fx * s / z) ** 2 + C.EPS2D
        cyy = (fy * s / z) ** 2 + C.EPS2D
        alpha = np.minimum(C.ALPHA_MAX, o * np.exp(-0.5 * (dx**2 / cxx + dy**2 / cyy)))
        ok = ~done & (alpha >= C.ALPHA_THRESHOLD)
        stop = ok & (T * (1 - alpha) <= C.TRANSMITTANCE_MIN)
        use = ok & ~stop
        Cimg += np.where(use, alpha * T, 0)[..., None] * scene["colors"][k]
        D += np.where(use, alpha * T, 0) * z
        T = np.where(use, T * (1 - alpha), T)
        done |= stop
    alpha = 1 - T
    return dict(image=Cimg + T[..., None] * scene["background"], alpha=alpha, depth=D,
                expected_depth=D / np.maximum(alpha, C.EXPECTED_DEPTH_ALPHA_MIN))


def _assert_outputs_close(out, expected, rtol=FWD_RTOL):
    for key in rf.OUTPUT_KEYS:
        scale = max(1.0, float(np.abs(expected[key]).max()))
        err = float(np.abs(out[key] - expected[key]).max())
        assert err <= rtol * scale, f"{key}: max error {err:.3g} > {rtol} * {scale:.3g}"


def _assert_finite_grads(grads):
    for key, g in grads.items():
        assert np.all(np.isfinite(g)), f"gradient {key} is not finite"


def _random_cot(scene, seed=0):
    return rf.random_cotangents(np.random.default_rng(seed), scene["width"], scene["height"],
                                scene["means"].dtype)


# ---------------------------------------------------------------------------------------------
# 1. Backward against central finite differences (float64)
# ---------------------------------------------------------------------------------------------


def test_gradients_single_gaussian():
    scene = _find_scene(lambda rng: rf.random_scene(rng, 1, 16, 16, sigma_px_range=(2.0, 6.0), border_px=-4.0))
    assert_gradients_match(scene)


def test_gradients_overlapping_gaussians():
    def make(rng):
        return rf.random_scene(rng, 8, 20, 16, sigma_px_range=(3.0, 8.0), border_px=-3.0)

    scene = _find_scene(make)
    _, saved = render_fwd(**scene)
    assert _used_counts(saved).max() >= 4, "scene should have pixels covered by several Gaussians"
    assert_gradients_match(scene)


def test_gradients_saturated_with_early_stop_and_alpha_clamp():
    """Opaque Gaussians stacked on the centre: some pixels stop (T (1 - alpha) <= 1e-4) and the
    front Gaussian has o exp(-sigma) > 0.999 near its mean (no gradient through the clamp)."""

    def make(rng):
        sc = rf.random_scene(rng, 6, 16, 16, sigma_px_range=(3.0, 5.0), opacity_range=(0.9, 0.99),
                             border_px=-5.0, depth_range=(3.0, 6.0))
        # Front Gaussian: nearly opaque, mean 0.02 px from a pixel centre.
        K, T = sc["K"], sc["cam_T_world"]
        z = 2.0
        u, v = 8.52, 7.48
        p_c = np.array([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])
        sc["means"][0] = _world(T, p_c)
        sc["opacities"][0] = 0.9999
        return sc

    scene = _find_scene(make, margin_min=MARGIN_MIN_CLAMP)
    _, saved = render_fwd(**scene)
    assert _stopped_any(saved), "scene should exercise the early stop"
    r = saved["raster"]
    assert np.any(r["used"] & (r["raw_alpha"] > C.ALPHA_MAX)), "scene should exercise the 0.999 clamp"
    assert_gradients_match(scene, margin_min=MARGIN_MIN_CLAMP)


def test_gradients_jacobian_clamp_active():
    """Two large Gaussians with x/z (resp. y/z) beyond the clamp limits of J, boxes overlapping."""

    def make(rng):
        sc = rf.random_scene(rng, 4, 24, 24, sigma_px_range=(2.0, 5.0), border_px=-3.0)
        K, T = sc["K"], sc["cam_T_world"]
        for i, (u, v) in enumerate([(24 + 14.0, 10.0), (9.0, -14.0)]):
            z = 3.0 + i
            p_c = np.array([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])
            sc["means"][i] = _world(T, p_c)
            sc["scales"][i] = np.array([9.0, 7.0, 8.0]) * z / K[0, 0]
            sc["opacities"][i] = 0.8
        return sc

    scene = _find_scene(make)
    out, saved = render_fwd(**scene)
    p = saved["proj"]
    assert p["x_over_z"][0] > p["lim_x"][1] and p["y_over_z"][1] < p["lim_y"][0], "clamp must be active"
    assert np.all(out["radii"][:2] > 0)
    used_per_gaussian = {int(g): int(u.sum()) for g, u in zip(saved["order"], saved["raster"]["used"])}
    assert used_per_gaussian[0] > 0 and used_per_gaussian[1] > 0, "clamped Gaussians must be drawn"
    assert_gradients_match(scene)


def test_gradients_antialiased():
    config = RenderConfig(antialiased=True)
    scene = _find_scene(lambda rng: rf.random_scene(rng, 6, 20, 16, sigma_px_range=(0.3, 5.0)), config)
    _, saved = render_fwd(**scene, config=config)
    comp = saved["proj"]["comp"][saved["proj"]["visible"]]
    assert np.all(comp < 1) and comp.min() < 0.8, "antialiasing factor should matter in this scene"
    assert_gradients_match(scene, config)


def test_gradients_flat_covariance():
    """One scale exactly 0: the covariance is rank 2 (flat disc). The zero scale gets an exactly
    zero gradient (Sigma depends on s^2); the others match FD (scales are not perturbed by FD
    because a negative scale is rejected)."""

    def make(rng):
        sc = rf.random_scene(rng, 3, 16, 16, sigma_px_range=(2.0, 5.0), border_px=-4.0)
        sc["scales"][0, 1] = 0.0
        return sc

    scene = _find_scene(make)
    assert_gradients_match(scene, keys=("means", "quats", "opacities", "colors", "background"))
    _, saved = render_fwd(**scene)
    g = render_bwd(saved, **_random_cot(scene))
    assert g["scales"][0, 1] == 0.0
    _assert_finite_grads(g)


def test_rasterizer_gradients_match_fd():
    """The compositing stage alone: d/d(means2d, conics, opacities, depths, colors, background),
    which checks the "means2d" gradient of render_bwd directly."""
    scene = _find_scene(lambda rng: rf.random_scene(rng, 8, 20, 16, sigma_px_range=(2.0, 6.0)))
    out, saved = render_fwd(**scene)
    cot = _random_cot(scene, seed=5)
    r = saved["raster"]
    args = dict(means2d=r["means2d"], conics=r["conics"], colors=r["colors"], opacities=r["opacities"],
                depths=r["depths"], order=saved["order"], width=scene["width"], height=scene["height"],
                background=r["background"])
    _, ras_saved = rasterize_fwd(**args)
    g = rasterize_bwd(ras_saved, cot["v_image"], cot["v_alpha"], cot["v_depth"], cot["v_expected_depth"])
    np.testing.assert_array_equal(g["means2d"], render_bwd(saved, **cot)["means2d"])
    for key in ("means2d", "conics", "opacities", "depths", "colors", "background"):
        def f(x, key=key):
            a = dict(args)
            a[key] = x
            return rf.weighted_loss(rasterize_fwd(**a)[0], cot)

        fd = rf.central_fd(f, args[key], FD_STEP)
        scale = np.abs(fd).max()
        assert scale > 0
        err = np.abs(g[key] - fd).max() / scale
        assert err <= FD_RTOL, f"{key}: {err:.3g}"


def test_gradient_properties():
    """Raw-quaternion gradients are orthogonal to q; culled Gaussians get exactly zero gradient."""
    scene = rf.random_scene(np.random.default_rng(11), 10, 20, 16)
    T = scene["cam_T_world"]
    scene["means"][0] = _world(T, [0.0, 0.0, -2.0])  # behind the camera
    scene["means"][1] = _world(T, [100.0, 0.0, 2.0])  # far outside the view
    out, saved = render_fwd(**scene)
    assert np.all(out["radii"][:2] == 0) and np.any(out["radii"][2:] > 0)
    g = render_bwd(saved, **_random_cot(scene))
    dots = np.abs(np.sum(g["quats"] * scene["quats"], axis=1))
    # Orthogonality holds to round-off: |g.q| <= 1e-12 |g| |q|.
    assert np.all(dots <= 1e-12 * np.linalg.norm(g["quats"], axis=1) * np.linalg.norm(scene["quats"], axis=1))
    for key in ("means", "quats", "scales", "opacities", "colors", "means2d"):
        assert np.all(g[key][:2] == 0), key
    assert np.all(g["cam_T_world"][3] == 0)


def test_permuting_gaussians_permutes_everything():
    """The order is by depth, not by index: a permutation of the inputs permutes the per-Gaussian
    outputs and gradients and leaves the images unchanged (bitwise)."""
    scene = rf.random_scene(np.random.default_rng(12), 12, 20, 16)
    perm = np.random.default_rng(0).permutation(12)
    scene_p = dict(scene)
    for key in ("means", "quats", "scales", "opacities", "colors"):
        scene_p[key] = scene[key][perm]
    out, saved = render_fwd(**scene)
    out_p, saved_p = render_fwd(**scene_p)
    for key in rf.OUTPUT_KEYS:
        np.testing.assert_array_equal(out[key], out_p[key])
    cot = _random_cot(scene)
    g, g_p = render_bwd(saved, **cot), render_bwd(saved_p, **cot)
    for key in ("means", "quats", "scales", "opacities", "colors", "means2d"):
        np.testing.assert_allclose(g_p[key], g[key][perm], rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# 2. Forward against independent computations
# ---------------------------------------------------------------------------------------------


def test_single_isotropic_gaussian_on_axis_closed_form():
    scene = _axis_scene([(4.0, 0.25, 0.7, (0.9, 0.1, 0.5))], 16, 14)
    out, _ = render_fwd(**scene)
    expected = _axis_expected(scene)
    _assert_outputs_close(out, expected)
    # Spot value at the pixel containing the mean, written out: cov_xx = (fx s/z)^2 + 0.3.
    K = scene["K"]
    j, i = 8, 7  # pixel centre (8.5, 7.5); mean at (cx, cy) = (8, 7)
    cxx = (K[0, 0] * 0.25 / 4.0) ** 2 + 0.3
    cyy = (K[1, 1] * 0.25 / 4.0) ** 2 + 0.3
    alpha = 0.7 * np.exp(-0.5 * (0.25 / cxx + 0.25 / cyy))
    assert abs(out["alpha"][i, j] - alpha) <= FWD_RTOL
    assert abs(out["expected_depth"][i, j] - 4.0) <= FWD_RTOL * 4.0
    np.testing.assert_allclose(out["means2d"][0], [K[0, 2], K[1, 2]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(out["conics"][0], [1 / cxx, 0.0, 1 / cyy], rtol=FWD_RTOL, atol=1e-15)
    assert tuple(out["radii"][0]) == (np.ceil(3.33 * np.sqrt(cxx)), np.ceil(3.33 * np.sqrt(cyy)))
    assert abs(out["depths"][0] - 4.0) <= 1e-12


def test_two_gaussians_compose_front_to_back():
    """Inputs listed back first: the renderer must sort by depth. Closed form per pixel:
    image = c1 a1 + c2 a2 (1 - a1) + (1 - a1)(1 - a2) bg, depth = z1 a1 + z2 a2 (1 - a1)."""
    back = (6.0, 0.8, 0.6, (0.1, 0.8, 0.3))
    front = (3.0, 0.2, 0.5, (0.9, 0.2, 0.1))
    scene = _axis_scene([back, front], 16, 16)
    out, _ = render_fwd(**scene)
    K = scene["K"]
    jj, ii = np.meshgrid(np.arange(16), np.arange(16))
    dx, dy = K[0, 2] - (jj + 0.5), K[1, 2] - (ii + 0.5)

    def alpha_of(z, s, o):
        cxx, cyy = (K[0, 0] * s / z) ** 2 + 0.3, (K[1, 1] * s / z) ** 2 + 0.3
        a = o * np.exp(-0.5 * (dx**2 / cxx + dy**2 / cyy))
        return np.where(a >= 1 / 255, a, 0.0)

    a1, a2 = alpha_of(*front[:3]), alpha_of(*back[:3])
    c1, c2, bg = np.array(front[3]), np.array(back[3]), scene["background"]
    image = a1[..., None] * c1 + (a2 * (1 - a1))[..., None] * c2 + ((1 - a1) * (1 - a2))[..., None] * bg
    depth = 3.0 * a1 + 6.0 * a2 * (1 - a1)
    alpha = 1 - (1 - a1) * (1 - a2)
    expected = dict(image=image, alpha=alpha, depth=depth, expected_depth=depth / np.maximum(alpha, 1e-10))
    _assert_outputs_close(out, expected)
    assert np.any(a1 > 0) and np.any(a2 * (1 - a1) > 0.05)  # both contribute


def test_projection_matches_independent_ewa():
    """Means, conics, radii and depths against scipy's quaternion convention (scalar last) and a
    Jacobian of the pinhole map obtained by central differences (clamp inactive here)."""
    scene = rf.random_scene(np.random.default_rng(21), 12, 24, 20, border_px=-2.0)
    out, _ = render_fwd(**scene)
    K, T = scene["K"], scene["cam_T_world"]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    def pinhole(p):
        return np.array([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy])

    for k in range(12):
        R = Rotation.from_quat(scene["quats"][k][[1, 2, 3, 0]]).as_matrix()
        Sigma = R @ np.diag(scene["scales"][k] ** 2) @ R.T
        p_c = T[:3, :3] @ scene["means"][k] + T[:3, 3]
        Sigma_c = T[:3, :3] @ Sigma @ T[:3, :3].T
        h = 1e-5 * p_c[2]
        Jfd = np.stack([(pinhole(p_c + h * e) - pinhole(p_c - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
        cov = Jfd @ Sigma_c @ Jfd.T + C.EPS2D * np.eye(2)
        inv = np.linalg.inv(cov)
        np.testing.assert_allclose(out["conics"][k], [inv[0, 0], inv[0, 1], inv[1, 1]], rtol=EWA_RTOL,
                                   atol=EWA_RTOL * np.abs(inv).max())
        np.testing.assert_allclose(out["means2d"][k], pinhole(p_c), rtol=FWD_RTOL)
        assert abs(out["depths"][k] - p_c[2]) <= FWD_RTOL * p_c[2]
        radii = np.ceil(C.RADIUS_SIGMA * np.sqrt(np.diag(cov)))
        np.testing.assert_array_equal(out["radii"][k], radii)


def test_compositing_matches_scalar_per_pixel_loop():
    """The dense vectorised loop against a literal scalar transcription of docs/conventions.md §6, on a
    saturated scene where many pixels stop early."""
    scene = rf.random_scene(np.random.default_rng(5), 16, 12, 10, sigma_px_range=(3.0, 8.0),
                            opacity_range=(0.9, 1.0))
    out, saved = render_fwd(**scene)
    assert _stopped_any(saved)
    _assert_matches_scalar_loop(scene, out)


def _assert_matches_scalar_loop(scene, out):
    m2, con, op, z = out["means2d"], out["conics"], scene["opacities"], out["depths"]
    vis = np.flatnonzero(out["radii"][:, 0] > 0)
    order = sorted(vis, key=lambda g: (np.float32(z[g]), g))
    for i in range(scene["height"]):
        for j in range(scene["width"]):
            T, Cp, Dp = 1.0, np.zeros(3), 0.0
            for g in order:
                dx, dy = m2[g, 0] - (j + 0.5), m2[g, 1] - (i + 0.5)
                sigma = 0.5 * (con[g, 0] * dx * dx + con[g, 2] * dy * dy) + con[g, 1] * dx * dy
                alpha = min(0.999, op[g] * np.exp(-sigma))
                if sigma < 0 or alpha < 1 / 255:
                    continue
                if T * (1 - alpha) <= 1e-4:
                    break
                Cp += scene["colors"][g] * alpha * T
                Dp += z[g] * alpha * T
                T *= 1 - alpha
            np.testing.assert_allclose(out["image"][i, j], Cp + T * scene["background"], rtol=0, atol=1e-13)
            assert abs(out["alpha"][i, j] - (1 - T)) <= 1e-13
            assert abs(out["depth"][i, j] - Dp) <= 1e-13 * max(1.0, Dp)


def test_used_pairs_lie_in_the_gaussians_tiles():
    """Every composited (Gaussian, pixel) pair lies inside the Gaussian's 3.33 sigma box and so in
    its tiles: the dense evaluation equals the tiled one."""
    scene = rf.random_scene(np.random.default_rng(8), 40, 32, 32, sigma_px_range=(0.5, 10.0), border_px=10.0)
    out, saved = render_fwd(**scene)
    jj, ii = np.meshgrid(np.arange(32) + 0.5, np.arange(32) + 0.5)
    for g, used in zip(saved["order"], saved["raster"]["used"]):
        (u, v), (rx, ry) = out["means2d"][g], out["radii"][g]
        assert np.all(np.abs(jj[used] - u) < rx) and np.all(np.abs(ii[used] - v) < ry)


# ---------------------------------------------------------------------------------------------
# 3. Stiff and extreme cases
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1.0, 1e3])
def test_extreme_scales(scale):
    scene = _axis_scene([(5.0, scale, 0.6, (0.3, 0.6, 0.9))], 16, 16)
    with np.errstate(divide="raise", invalid="raise", over="raise"):
        out, saved = render_fwd(**scene)
        g = render_bwd(saved, **_random_cot(scene))
    _assert_outputs_close(out, _axis_expected(scene))
    _assert_finite_grads(g)
    K = scene["K"]
    cxx = (K[0, 0] * scale / 5.0) ** 2 + C.EPS2D
    assert out["radii"][0, 0] == np.ceil(C.RADIUS_SIGMA * np.sqrt(cxx))
    if scale <= 1e-3:  # tiny: the eps2d dilation alone sets the footprint
        assert out["radii"][0, 0] == np.ceil(C.RADIUS_SIGMA * np.sqrt(C.EPS2D)) == 2
        assert np.count_nonzero(out["alpha"]) > 0
    if scale >= 1e3:  # huge: covers the whole image with alpha ~ opacity
        assert out["radii"][0, 0] > 16
        np.testing.assert_allclose(out["alpha"], 0.6, rtol=1e-5)


def test_near_plane_is_exclusive_and_behind_camera_is_culled():
    K = _axis_camera(8, 8)
    T = np.eye(4)  # identity: camera z equals the world z exactly
    bg = np.array([0.1, 0.2, 0.3])

    def scene_at(z):
        return dict(means=np.array([[0.0, 0.0, z]]), quats=np.array([[1.0, 0, 0, 0]]),
                    scales=np.array([[1e-4, 1e-4, 1e-4]]), opacities=np.array([0.8]),
                    colors=np.array([[1.0, 1.0, 1.0]]), cam_T_world=T, K=K, width=8, height=8, background=bg)

    for z in (C.NEAR_PLANE, 0.0, -1.0, -C.NEAR_PLANE):
        with np.errstate(divide="raise", invalid="raise", over="raise"):
            out, saved = render_fwd(**scene_at(z))
            g = render_bwd(saved, **_random_cot(scene_at(z)))
        assert out["radii"][0, 0] == 0, f"z = {z} must be culled"
        np.testing.assert_array_equal(out["image"], np.broadcast_to(bg, (8, 8, 3)))
        assert np.all(out["alpha"] == 0) and np.all(out["expected_depth"] == 0)
        for key in ("means", "quats", "scales", "opacities", "colors"):
            assert np.all(g[key] == 0)
    out, _ = render_fwd(**scene_at(C.NEAR_PLANE * (1 + 1e-9)))  # just in front: drawn
    assert out["radii"][0, 0] > 0 and out["alpha"].max() > 0.1


def test_flat_and_point_covariance():
    """One zero scale (flat disc) renders like its independent EWA; all scales zero in antialiased
    mode gives det_orig = 0, compensation 0, an invisible Gaussian and finite (zero) gradients."""
    scene = _axis_scene([(4.0, 0.3, 0.7, (0.5, 0.5, 0.5))], 12, 12)
    scene["scales"][0] = [0.3, 0.0, 0.3]
    out, saved = render_fwd(**scene)
    assert np.all(np.isfinite(out["image"])) and out["alpha"].max() > 0.1
    _assert_finite_grads(render_bwd(saved, **_random_cot(scene)))

    scene["scales"][0] = 0.0
    config = RenderConfig(antialiased=True)
    with np.errstate(divide="raise", invalid="raise", over="raise"):
        out, saved = render_fwd(**scene, config=config)
        g = render_bwd(saved, **_random_cot(scene))
    np.testing.assert_array_equal(out["image"], np.broadcast_to(scene["background"], (12, 12, 3)))
    _assert_finite_grads(g)
    assert np.all(g["opacities"] == 0) and np.all(g["scales"] == 0)


def test_opacity_zero_gives_background_exactly():
    scene = rf.random_scene(np.random.default_rng(2), 5, 12, 10)
    scene["opacities"][:] = 0.0
    out, saved = render_fwd(**scene)
    np.testing.assert_array_equal(out["image"], np.broadcast_to(scene["background"], (10, 12, 3)))
    for key in ("alpha", "depth", "expected_depth"):
        assert np.all(out[key] == 0)
    g = render_bwd(saved, **_random_cot(scene))
    _assert_finite_grads(g)
    assert np.all(g["colors"] == 0)


def test_opacity_one_caps_alpha_and_blocks_the_gradient():
    K = _axis_camera(9, 9, cx=4.5, cy=4.5)  # the mean lands exactly on the centre of pixel (4, 4)
    scene = _axis_scene([(3.0, 0.2, 1.0, (1.0, 0.5, 0.0))], 9, 9, K=K, T=np.eye(4))
    out, saved = render_fwd(**scene)
    assert abs(out["alpha"][4, 4] - C.ALPHA_MAX) <= 1e-15
    assert out["alpha"].max() <= C.ALPHA_MAX + 1e-15
    _assert_outputs_close(out, _axis_expected(scene))
    # A 1x1 image on that pixel: alpha clamped there, so nothing flows to o, sigma or the 2D mean;
    # the colour and (through depth) the camera z still get gradient.
    K1 = _axis_camera(1, 1, f=9.0, cx=0.5, cy=0.5)
    scene1 = _axis_scene([(3.0, 0.2, 1.0, (1.0, 0.5, 0.0))], 1, 1, K=K1, T=np.eye(4))
    out1, saved1 = render_fwd(**scene1)
    g = render_bwd(saved1, **_random_cot(scene1))
    assert out1["alpha"][0, 0] == pytest.approx(C.ALPHA_MAX, abs=1e-15)
    for key in ("opacities", "scales", "quats", "means2d"):
        assert np.all(g[key] == 0), key
    assert np.all(g["colors"] != 0) and g["means"][0, 2] != 0


def test_colors_outside_unit_range_pass_through():
    scene = _axis_scene([(4.0, 0.4, 0.8, (-0.5, 2.0, 10.0))], 12, 12)
    out, saved = render_fwd(**scene)
    _assert_outputs_close(out, _axis_expected(scene))
    assert out["image"].min() < 0 and out["image"].max() > 5
    _assert_finite_grads(render_bwd(saved, **_random_cot(scene)))


def test_gaussian_covering_the_whole_image():
    scene = _axis_scene([(2.0, 5.0, 0.5, (0.2, 0.9, 0.4))], 16, 12)
    out, saved = render_fwd(**scene)
    assert np.all(out["alpha"] >= C.ALPHA_THRESHOLD)
    assert out["radii"][0, 0] > 16 and out["radii"][0, 1] > 12
    _assert_outputs_close(out, _axis_expected(scene))
    _assert_finite_grads(render_bwd(saved, **_random_cot(scene)))


def test_many_gaussians_on_one_pixel_stop_early():
    """1e5 Gaussians of alpha o = 0.01 exactly on a 1x1 image. The transmittance after k of them
    is 0.99^k; the compositing stops before the first k with 0.99^(k+1) <= 1e-4, so exactly
    n = ceil(ln 1e-4 / ln 0.99) - 1 = 916 are used (ln ratio 916.4: no rounding ambiguity) and T
    never drops to <= 1e-4."""
    n, o = 100_000, 0.01
    rng = np.random.default_rng(0)
    z = 1.0 + 1e-3 * rng.permutation(n)  # distinct in float32, listed in random order
    K = _axis_camera(1, 1, f=1.0, cx=0.5, cy=0.5)
    scene = dict(means=np.stack([np.zeros(n), np.zeros(n), z], -1), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
                 scales=np.full((n, 3), 0.1), opacities=np.full(n, o), colors=rng.uniform(size=(n, 3)),
                 cam_T_world=np.eye(4), K=K, width=1, height=1, background=np.array([0.3, 0.3, 0.3]))
    out, saved = render_fwd(**scene)
    n_used = int(np.ceil(np.log(C.TRANSMITTANCE_MIN) / np.log(1 - o))) - 1
    assert n_used == 916
    T_final = 1 - out["alpha"][0, 0]
    assert T_final > C.TRANSMITTANCE_MIN and T_final * (1 - o) <= C.TRANSMITTANCE_MIN
    assert round(np.log(T_final) / np.log(1 - o)) == n_used
    front = np.argsort(z)[:n_used]
    weights = o * (1 - o) ** np.arange(n_used)
    np.testing.assert_allclose(T_final, (1 - o) ** n_used, rtol=1e-12)
    np.testing.assert_allclose(out["depth"][0, 0], np.sum(weights * z[front]), rtol=1e-12)
    np.testing.assert_allclose(out["image"][0, 0], weights @ scene["colors"][front] + T_final * 0.3, rtol=1e-12)
    assert out["num_intersections"] == n_used + 1  # the stopping Gaussian is evaluated, not added
    g = render_bwd(saved, **_random_cot(scene))
    _assert_finite_grads(g)
    used = np.zeros(n, bool)
    used[front] = True
    assert np.all(np.any(g["colors"][used] != 0, axis=1)) and np.all(g["colors"][~used] == 0)


@pytest.mark.parametrize("width,height", [(1, 9), (11, 1), (1, 1)])
def test_width_or_height_one(width, height):
    """Single-row / single-column / single-pixel images: an on-axis Gaussian against its closed
    form, and a random scene against the scalar per-pixel loop; gradients finite."""
    scene = _axis_scene([(4.0, 0.3, 0.8, (0.9, 0.4, 0.1)), (6.0, 0.6, 0.5, (0.1, 0.4, 0.9))], width, height,
                        K=_axis_camera(width, height, f=10.0))
    out, saved = render_fwd(**scene)
    for key in rf.OUTPUT_KEYS:
        assert out[key].shape[:2] == (height, width)
    _assert_outputs_close(out, _axis_expected(scene))
    _assert_finite_grads(render_bwd(saved, **_random_cot(scene)))

    scene = rf.random_scene(np.random.default_rng(4), 8, width, height, sigma_px_range=(1.0, 4.0))
    out, saved = render_fwd(**scene)
    assert out["alpha"].max() > 0
    _assert_matches_scalar_loop(scene, out)
    _assert_finite_grads(render_bwd(saved, **_random_cot(scene)))


def test_no_gaussians():
    scene = rf.random_scene(np.random.default_rng(1), 0, 7, 5)
    out, saved = render_fwd(**scene)
    np.testing.assert_array_equal(out["image"], np.broadcast_to(scene["background"], (5, 7, 3)))
    assert np.all(out["alpha"] == 0) and np.all(out["depth"] == 0) and np.all(out["expected_depth"] == 0)
    assert out["radii"].shape == (0, 2) and out["means2d"].shape == (0, 2) and out["conics"].shape == (0, 3)
    cot = _random_cot(scene)
    g = render_bwd(saved, **cot)
    assert g["means"].shape == (0, 3) and g["quats"].shape == (0, 4) and g["opacities"].shape == (0,)
    np.testing.assert_allclose(g["background"], cot["v_image"].sum(axis=(0, 1)), rtol=1e-14)
    assert np.all(g["cam_T_world"] == 0)


def test_float32_stays_float32_and_matches_float64():
    scene64 = _find_scene(lambda rng: rf.random_scene(rng, 8, 16, 12))
    scene32 = rf.cast_scene(scene64, np.float32)
    out64, saved64 = render_fwd(**scene64)
    out32, saved32 = render_fwd(**scene32)
    for key in ("image", "alpha", "depth", "expected_depth", "means2d", "depths", "conics"):
        assert out32[key].dtype == np.float32, key
        scale = max(1.0, np.abs(out64[key]).max())
        assert np.abs(out32[key] - out64[key]).max() <= F32_OUT_RTOL * scale, key
    assert out32["radii"].dtype == np.int32
    np.testing.assert_array_equal(out32["radii"], out64["radii"])
    cot64 = _random_cot(scene64)
    cot32 = {k: v.astype(np.float32) for k, v in cot64.items()}
    g64, g32 = render_bwd(saved64, **cot64), render_bwd(saved32, **cot32)
    for key, val in g32.items():
        assert val.dtype == np.float32, key
        scale = np.abs(g64[key]).max()
        assert np.abs(val - g64[key]).max() <= F32_GRAD_RTOL * scale, key


def test_render_alias():
    assert render is render_fwd


# ---------------------------------------------------------------------------------------------
# Bad inputs
# ---------------------------------------------------------------------------------------------


def _base_scene():
    return rf.random_scene(np.random.default_rng(0), 3, 8, 6)


def _with(**changes):
    sc = _base_scene()
    sc.update(changes)
    return sc


@pytest.mark.parametrize(
    "make,exc,match",
    [
        (lambda: _with(means=np.zeros((3, 4))), ValueError, r"means must have shape \(N, 3\); got \(3, 4\)"),
        (lambda: _with(quats=np.ones((2, 4))), ValueError, r"quats must have shape \(3, 4\); got \(2, 4\)"),
        (lambda: _with(opacities=np.ones((3, 1))), ValueError, r"opacities must have shape \(3\)"),
        (lambda: _with(K=np.eye(4)), ValueError, r"K must have shape \(3, 3\)"),
        (lambda: _with(background=np.zeros(4)), ValueError, r"background must have shape \(3\)"),
        (lambda: _with(means=np.array([[np.nan, 0, 1]] * 3)), ValueError, r"means contains NaN"),
        (lambda: _with(colors=np.array([[np.inf, 0, 1]] * 3)), ValueError, r"colors contains NaN or inf"),
        (lambda: _with(K=np.array([[10.0, 0.5, 4], [0, 10, 3], [0, 0, 1]])), ValueError, r"zero skew"),
        (lambda: _with(K=np.array([[-10.0, 0, 4], [0, 10, 3], [0, 0, 1]])), ValueError, r"positive focal"),
        (lambda: _with(quats=np.zeros((3, 4))), ValueError, r"quats must have non-zero norm"),
        (lambda: _with(scales=-np.ones((3, 3))), ValueError, r"scales are linear and must be >= 0"),
        (lambda: _with(opacities=np.full(3, 1.5)), ValueError, r"opacities must lie in \[0, 1\]"),
        (lambda: _with(width=0), ValueError, r"width must be >= 1"),
        (lambda: _with(height=4.0), TypeError, r"height must be an int"),
        (lambda: _with(means=np.zeros((3, 3), np.int64)), TypeError, r"means must be a float64"),
        (lambda: _with(quats=np.ones((3, 4), np.float32)), TypeError,
         r"quats has dtype float32 but means has dtype float64"),
        (lambda: dict(rf.cast_scene(_base_scene(), np.float32), background=np.zeros(3)), TypeError,
         r"background has dtype float64 but means has dtype float32"),
    ],
)
def test_bad_inputs_raise_clear_errors(make, exc, match):
    with pytest.raises(exc, match=match):
        render_fwd(**make())


def test_bad_config_and_cotangents_raise():
    scene = _base_scene()
    with pytest.raises(TypeError, match="config must be"):
        render_fwd(**scene, config={"antialiased": True})
    _, saved = render_fwd(**scene)
    with pytest.raises(ValueError, match=r"v_image must have shape \(6, 8, 3\)"):
        render_bwd(saved, np.zeros((6, 8)))
    with pytest.raises(TypeError, match="v_alpha must have the render's dtype float64"):
        render_bwd(saved, np.zeros((6, 8, 3)), v_alpha=np.zeros((6, 8), np.float32))
    with pytest.raises(ValueError, match="v_depth contains NaN"):
        render_bwd(saved, np.zeros((6, 8, 3)), v_depth=np.full((6, 8), np.nan))
    with pytest.raises(TypeError, match="saved must be"):
        render_bwd({"x": 1}, np.zeros((6, 8, 3)))
