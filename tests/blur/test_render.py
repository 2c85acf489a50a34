"""Tests of the blurred render (d2gs_np.blur.render): the blurry render against sharp renders, its
gradients against central finite differences, the Numba renderer against the reference, and the
backward through a subset of the views.

Finite differences. The blurry render averages n sharp renders, each piecewise smooth in its
inputs (docs/conventions.md §8). FD test scenes are redrawn until EVERY sub-frame render (each virtual
pose and sub-frame time) has threshold margin >= MARGIN_MIN (tests/render_fixtures), and steps
are FD_STEP; the argument of tests/reference/test_render_reference.py then applies sub-frame by
sub-frame: a step moves any thresholded quantity by <= ~1e-5 relative, inside the margin (see MARGIN_MIN).
The FD loss uses the NumPy reference renderer (float64, ~1 ms per 24x24 render); one test checks
that the default Numba renderer gives the same blurry render and gradients.
"""
from __future__ import annotations

import numpy as np
import pytest

import render_fixtures as rf
from d2gs_np import reference
from d2gs_np.blur.config import BlurConfig
from d2gs_np.blur.exposure import EXPOSURE_BLOCK
from d2gs_np.blur.render import blur_render_bwd, blur_render_fwd
from d2gs_np.blur.views import backward_subset
from d2gs_np.blur.virtual_poses import subframe_times, three_knot_poses, virtual_poses
from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.gaussians import logit
from d2gs_np.scene.render_inputs import render_inputs_fwd

# Central-difference step for the render-level checks (see the module docstring and
# tests/reference/test_render_reference.py: round-off ~1e-16 |L| / h ~ 1e-7 on gradients of
# scale 1..1e2, truncation h^2 f''' negligible).
FD_STEP = 1e-7
# Minimum threshold margin of every sub-frame render of an FD scene. A step of FD_STEP moves a
# thresholded quantity by <= ~1e-5 relative (the bound argued in test_render_reference.py: <= ~1e2
# relative per unit of any input, including pose rotation ~f * 3/sigma_px ~ 1e2 per radian), so
# 1e-4 leaves a factor 10. The reference's 1e-3 is out of reach here: every one of the n
# sub-frames must have the margin, and the chance that some (Gaussian, pixel) pair sits within
# relative distance m of alpha = 1/255 grows like 2 pi m sigma_px^2 per Gaussian and render.
MARGIN_MIN = 1e-4
# |grad - fd| <= FD_RTOL * (scale of the gradient block): 100x the FD round-off estimate.
FD_RTOL = 1e-5
# Blurry render with the Numba renderer against the float64 reference (render contract: they
# agree to ~1e-10 relative; averaging n renders and summing gradients keeps that order).
FAST_RTOL = 1e-8

W = H = 24
DEFORM = DeformConfig(degree=1, order=1)  # K = 3 coefficients: every deformation term, fewer FD entries


# ---------------------------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------------------------


def _params_from_scene(rng, scene, num_dynamic, deform_std):
    """Scene blocks (static first, the last num_dynamic Gaussians dynamic) from render inputs."""
    n = scene["means"].shape[0]
    ns = n - num_dynamic
    logits = logit(scene["opacities"])
    params = {}
    for prefix, sl in (("static", slice(0, ns)), ("dynamic", slice(ns, n))):
        params[f"{prefix}.means"] = scene["means"][sl].copy()
        params[f"{prefix}.log_scales"] = np.log(scene["scales"][sl])
        params[f"{prefix}.quats"] = scene["quats"][sl].copy()
        params[f"{prefix}.opacity_logits"] = logits[sl].copy()
        params[f"{prefix}.colors"] = scene["colors"][sl].copy()
    K = DEFORM.num_coefs
    params["dynamic.deform_means"] = deform_std * rng.normal(size=(num_dynamic, K, 3))
    params["dynamic.deform_quats"] = deform_std * rng.normal(size=(num_dynamic, K, 4))
    params["dynamic.deform_colors"] = deform_std * rng.normal(size=(num_dynamic, K, 3))
    return params


def _subframe_margin(case):
    """Smallest threshold margin over the sub-frame renders of a blur case."""
    n = case["blur_config"].num_virtual
    poses = virtual_poses(case["pose_est"], case["xi_start"], case["xi_end"], n)
    times = subframe_times(case["frame_time"], case["tau"], n)
    margin = np.inf
    for T, t in zip(poses, times):
        inputs, _ = render_inputs_fwd(case["params"], float(t), DEFORM)
        scene = dict(inputs, cam_T_world=T, K=case["K"], width=W, height=H, background=case["background"])
        margin = min(margin, rf.threshold_margin(scene))
    return margin


def make_case(seed, xi_start=None, xi_end=None, tau=0.1, n=8, spread=0.01, num_gaussians=12,
              num_dynamic=4, deform_std=0.05, margin=MARGIN_MIN, max_tries=200):
    """A blur FD case whose every sub-frame render has threshold margin >= margin.

    xi_start / xi_end: callables rng -> (6,) (None: random with rotation and translation ~ spread).
    """
    rng = np.random.default_rng(seed)
    for _ in range(max_tries):
        scene = rf.random_scene(rng, num_gaussians, W, H)
        xs = rng.normal(size=6) * spread if xi_start is None else xi_start(rng)
        xe = rng.normal(size=6) * spread if xi_end is None else xi_end(rng)
        case = dict(
            params=_params_from_scene(rng, scene, num_dynamic, deform_std),
            frame_time=0.4, tau=tau, pose_est=scene["cam_T_world"], xi_start=np.asarray(xs, np.float64),
            xi_end=np.asarray(xe, np.float64), K=scene["K"], width=W, height=H, background=scene["background"],
            blur_config=BlurConfig(num_virtual=n), deform_config=DEFORM,
        )
        if _subframe_margin(case) >= margin:
            return case
    raise RuntimeError(f"no blur case with sub-frame margin >= {margin} in {max_tries} draws")


def _render(case, renderer=reference, **overrides):
    args = dict(case, **overrides)
    return blur_render_fwd(**args, renderer=renderer)


def _loss(case, cot, **overrides):
    out, _ = _render(case, **overrides)
    return rf.weighted_loss(out, cot)


# ---------------------------------------------------------------------------------------------
# Blurry render: forward properties
# ---------------------------------------------------------------------------------------------


def _sharp(case, t, T):
    inputs, _ = render_inputs_fwd(case["params"], t, DEFORM)
    out, _ = reference.render_fwd(**inputs, cam_T_world=T, K=case["K"], width=W, height=H,
                                  background=case["background"])
    return out


def test_n1_is_the_sharp_render_at_the_estimate_bitwise():
    case = make_case(10, n=1, spread=0.05, tau=0.2, margin=0.0)
    out, _ = _render(case)
    sharp = _sharp(case, case["frame_time"], case["pose_est"])
    for key in rf.OUTPUT_KEYS:
        np.testing.assert_array_equal(out[key], sharp[key])


def test_zero_spread_zero_tau_is_the_sharp_render():
    case = make_case(11, n=8, xi_start=lambda r: np.zeros(6), xi_end=lambda r: np.zeros(6), tau=0.0, margin=0.0)
    out, _ = _render(case)
    sharp = _sharp(case, case["frame_time"], case["pose_est"])
    for key in rf.OUTPUT_KEYS:  # the mean of 8 identical renders: equal up to the rounding of the mean
        np.testing.assert_allclose(out[key], sharp[key], rtol=4 * np.finfo(float).eps, atol=1e-15)


def test_blurry_render_is_the_mean_of_subframe_renders():
    case = make_case(12, n=4, margin=0.0)
    out, _ = _render(case)
    poses = virtual_poses(case["pose_est"], case["xi_start"], case["xi_end"], 4)
    times = subframe_times(case["frame_time"], case["tau"], 4)
    subs = [_sharp(case, float(t), T) for T, t in zip(poses, times)]
    for key in rf.OUTPUT_KEYS:
        np.testing.assert_allclose(out[key], np.mean([s[key] for s in subs], axis=0), rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(out["radii"], np.max([s["radii"] for s in subs], axis=0))
    # the blur is real: sub-frames differ from each other (camera and object motion)
    assert np.abs(subs[0]["image"] - subs[-1]["image"]).max() > 1e-3


def test_scene_blocks_only_and_extra_keys_ignored():
    case = make_case(13, n=2, margin=0.0)
    out, _ = _render(case)
    extra = dict(case["params"], **{"camera.xi_start": np.zeros((3, 6)), EXPOSURE_BLOCK: np.zeros(1)})
    out2, saved = _render(case, params=extra)
    np.testing.assert_array_equal(out["image"], out2["image"])
    v_params, *_ = blur_render_bwd(saved, np.ones((H, W, 3)))
    assert set(v_params) == set(case["params"])


# ---------------------------------------------------------------------------------------------
# Blurry render: gradients against central finite differences
# ---------------------------------------------------------------------------------------------

_HALF_ROLL = 0.5 * (np.pi - 0.05)  # roll about the optical axis keeps the scene in view


def _gradient_cases():
    return {
        "generic": dict(seed=20),
        "zero_length": dict(seed=21, xi_start=lambda r: 0.01 * np.ones(6), xi_end=lambda r: 0.01 * np.ones(6)),
        "near_pi": dict(seed=22, n=8,
                        xi_start=lambda r: np.r_[0.01 * r.normal(size=3), 0.0, 0.0, -_HALF_ROLL],
                        xi_end=lambda r: np.r_[0.01 * r.normal(size=3), 0.0, 0.0, _HALF_ROLL]),
        "tiny": dict(seed=23, xi_start=lambda r: np.full(6, 0.005),
                     xi_end=lambda r: np.full(6, 0.005) + 1e-9 * r.normal(size=6)),
        "n2": dict(seed=24, n=2),
        "n1": dict(seed=25, n=1),
    }


def _check_block(name, grad, fd, scale):
    err = np.abs(np.asarray(grad) - np.asarray(fd)).max()
    assert err <= FD_RTOL * max(scale, 1e-12), f"{name}: max |grad - fd| = {err:.3g}, scale {scale:.3g}"


@pytest.mark.parametrize("name", list(_gradient_cases()))
def test_blur_gradients_match_fd(name):
    case = make_case(**_gradient_cases()[name])
    rng = np.random.default_rng(100)
    cot = rf.random_cotangents(rng, W, H)
    out, saved = _render(case)
    v_params, v_xs, v_xe, v_tau = blur_render_bwd(saved, **cot)
    assert set(v_params) == set(case["params"])

    # endpoints (every entry; xi are the coordinates the optimiser moves) and tau
    for key, grad in (("xi_start", v_xs), ("xi_end", v_xe)):
        fd = rf.central_fd(lambda x, key=key: _loss(case, cot, **{key: x}), case[key], FD_STEP)
        _check_block(key, grad, fd, np.abs(fd).max())
        if case["blur_config"].num_virtual == 1:
            np.testing.assert_array_equal(grad, 0.0)
    fd_tau = rf.central_fd_scalar(lambda h: _loss(case, cot, tau=case["tau"] + h), FD_STEP)
    _check_block("tau", v_tau, fd_tau, abs(fd_tau) + 1.0)

    # scene blocks: a random direction per block plus a few single entries
    for key, grad in v_params.items():
        base = case["params"][key]
        d = rng.normal(size=base.shape)

        def along(h, key=key, d=d):
            p = dict(case["params"], **{key: case["params"][key] + h * d})
            return _loss(case, cot, params=p)

        fd_dir = rf.central_fd_scalar(along, FD_STEP)
        _check_block(key + " (direction)", np.sum(grad * d), fd_dir, np.sum(np.abs(grad * d)))
        for flat in rng.choice(base.size, size=min(3, base.size), replace=False):
            idx = np.unravel_index(flat, base.shape)
            e = np.zeros(base.shape)
            e[idx] = 1.0

            def single(h, key=key, e=e):
                p = dict(case["params"], **{key: case["params"][key] + h * e})
                return _loss(case, cot, params=p)

            _check_block(f"{key}{idx}", grad[idx], rf.central_fd_scalar(single, FD_STEP), np.abs(grad).max())


def test_blur_gradient_is_not_trivial():
    """The endpoint, tau and deformation gradients are non-zero in a blurry dynamic case (so the
    FD checks above compare real numbers)."""
    case = make_case(20)
    cot = rf.random_cotangents(np.random.default_rng(100), W, H)
    _, saved = _render(case)
    v_params, v_xs, v_xe, v_tau = blur_render_bwd(saved, **cot)
    assert np.abs(v_xs).max() > 1e-3 and np.abs(v_xe).max() > 1e-3 and abs(v_tau) > 1e-3
    assert np.abs(v_params["dynamic.deform_means"]).max() > 1e-3


def test_default_numba_renderer_matches_reference():
    case = make_case(30, n=3)
    cot = rf.random_cotangents(np.random.default_rng(101), W, H)
    out_ref, saved_ref = _render(case)
    out_fast, saved_fast = blur_render_fwd(**case)  # renderer=None: d2gs_np.render
    for key in rf.OUTPUT_KEYS:
        np.testing.assert_allclose(out_fast[key], out_ref[key], rtol=FAST_RTOL, atol=FAST_RTOL)
    g_ref = blur_render_bwd(saved_ref, **cot)
    g_fast = blur_render_bwd(saved_fast, **cot)
    for k in g_ref[0]:
        scale = np.abs(g_ref[0][k]).max()
        np.testing.assert_allclose(g_fast[0][k], g_ref[0][k], rtol=0, atol=FAST_RTOL * max(scale, 1.0))
    for a, b in zip(g_fast[1:], g_ref[1:]):
        np.testing.assert_allclose(a, b, rtol=0, atol=FAST_RTOL * max(np.abs(b).max(), 1.0))


def test_float32_stays_float32():
    case = make_case(31, n=3, margin=0.0)
    case32 = dict(case)
    for key in ("pose_est", "xi_start", "xi_end", "K", "background"):
        case32[key] = case[key].astype(np.float32)
    case32["params"] = {k: v.astype(np.float32) for k, v in case["params"].items()}
    out, saved = _render(case32)
    assert out["image"].dtype == np.float32 and out["poses"].dtype == np.float32
    v_params, v_xs, v_xe, _ = blur_render_bwd(saved, np.ones((H, W, 3), np.float32))
    assert all(v.dtype == np.float32 for v in v_params.values())
    assert v_xs.dtype == np.float32 and v_xe.dtype == np.float32
    with pytest.raises(TypeError, match="pose_est must be a numpy array of the scene dtype"):
        _render(case32, pose_est=case["pose_est"])


def test_return_aux():
    case = make_case(32, n=3, margin=0.0)
    _, saved = _render(case)
    *_, aux = blur_render_bwd(saved, np.ones((H, W, 3)), return_aux=True)
    assert aux["v_means2d"].shape == (3, 12, 2) and aux["v_pose_tangents"].shape == (3, 6)


def test_unvalidated_fast_path_is_bitwise_the_public_one():
    # The trainer's step calls _blur_render_fwd with the private render and scene-model fast
    # paths (validation once at the public boundary); outputs and gradients must not change.
    from d2gs_np.blur.render import _blur_render_fwd
    from d2gs_np.render.api import _render_bwd, _render_fwd
    from d2gs_np.render.config import RenderConfig
    from d2gs_np.scene.render_inputs import _render_inputs_bwd, _render_inputs_fwd

    case = make_case(33, n=4, margin=0.0)
    out, saved = blur_render_fwd(**case)  # default: the Numba renderer, validated
    fast, fsaved = _blur_render_fwd(case["params"], case["frame_time"], case["tau"], case["pose_est"],
                                    case["xi_start"], case["xi_end"], case["K"], W, H, case["background"], 4,
                                    DEFORM, RenderConfig(), (_render_fwd, _render_bwd), (_render_inputs_fwd, _render_inputs_bwd))
    for key in ("image", "alpha", "depth", "expected_depth", "radii", "poses", "times"):
        np.testing.assert_array_equal(fast[key], out[key], err_msg=key)
    v = np.random.default_rng(0).normal(size=(H, W, 3))
    a, b = blur_render_bwd(saved, v, return_aux=True), blur_render_bwd(fsaved, v, return_aux=True)
    for name in a[0]:
        np.testing.assert_array_equal(b[0][name], a[0][name], err_msg=name)
    for x, y in zip(a[1:4], b[1:4]):
        np.testing.assert_array_equal(y, x)
    np.testing.assert_array_equal(b[4]["v_means2d"], a[4]["v_means2d"])


# ---------------------------------------------------------------------------------------------
# Backward through a subset of the views (BlurConfig.backward_views)
# ---------------------------------------------------------------------------------------------

# Averaging the subset estimates over every draw, each weighted by its probability, must give the
# exact gradient: the same sums of the same per-view gradients in another order and grouping, so
# they agree to float64 round-off (~1e-16 relative per term, a few dozen terms): 1e-12 relative
# to the block's scale leaves a wide margin, and a wrong run weight is off by O(1).
SUBSET_RTOL = 1e-12


def test_views_of_every_view_with_equal_weights_reproduce_the_exact_backward():
    case = make_case(34, n=5, margin=0.0)
    _, saved = blur_render_fwd(**case)
    v = np.random.default_rng(1).normal(size=(H, W, 3))
    exact = blur_render_bwd(saved, v, return_aux=True)
    every = blur_render_bwd(saved, v, return_aux=True, views=backward_subset(5, 0, None))
    for name in exact[0]:
        np.testing.assert_allclose(every[0][name], exact[0][name], rtol=1e-14, atol=1e-14 * np.abs(exact[0][name]).max(),
                                   err_msg=name)
    np.testing.assert_allclose(every[4]["v_pose_tangents"], exact[4]["v_pose_tangents"], rtol=1e-14, atol=1e-16)


@pytest.mark.parametrize("n, m", [(5, 2), (6, 3), (4, 1)])
def test_subset_backward_is_unbiased_over_every_draw(n, m):
    # Enumerate every draw of backward_subset (one view per run, each with probability 1/|run|)
    # and average the subset gradients with those probabilities: the exact gradient, for every
    # block (static, dynamic, deformation), the endpoints and the exposure length.
    import itertools

    case = make_case(35, n=n, margin=0.0)
    _, saved = blur_render_fwd(**case)
    rng = np.random.default_rng(2)
    v_img, v_alpha = rng.normal(size=(H, W, 3)), rng.normal(size=(H, W))
    exact = blur_render_bwd(saved, v_img, v_alpha, return_aux=True)
    edges = (np.arange(m + 1) * n) // m
    runs = [range(edges[j], edges[j + 1]) for j in range(m)]
    weights = np.diff(edges) / n
    mean = None
    for draw in itertools.product(*runs):
        p = np.prod([1.0 / len(r) for r in runs])
        g = blur_render_bwd(saved, v_img, v_alpha, return_aux=True, views=(np.array(draw), weights))
        flat = [*g[0].values(), g[1], g[2], np.array([g[3]]), g[4]["v_means2d"].sum(axis=0)]
        mean = [p * x for x in flat] if mean is None else [a + p * x for a, x in zip(mean, flat)]
        assert g[4]["v_means2d"].shape[0] == m
    want = [*exact[0].values(), exact[1], exact[2], np.array([exact[3]]), exact[4]["v_means2d"].sum(axis=0)]
    names = [*exact[0], "xi_start", "xi_end", "tau", "means2d"]
    for name, a, b in zip(names, mean, want):
        scale = max(np.abs(b).max(), 1e-300)
        np.testing.assert_allclose(a, b, rtol=0, atol=SUBSET_RTOL * scale, err_msg=name)
    # ...while a single draw is not the exact gradient (the test can tell them apart)
    g = blur_render_bwd(saved, v_img, v_alpha, views=(np.array([e for e in edges[:-1]]), weights))
    assert not np.allclose(g[0]["static.means"], exact[0]["static.means"], rtol=1e-3)


def test_subset_backward_refuses_bad_views():
    case = make_case(36, n=4, margin=0.0)
    _, saved = blur_render_fwd(**case)
    v = np.ones((H, W, 3))
    for bad in ((np.array([0, 4]), np.array([0.5, 0.5])), (np.array([1, 1]), np.array([0.5, 0.5])),
                (np.array([0, 2]), np.array([0.5])), (np.array([0.0, 2.0]), np.array([0.5, 0.5])),
                (np.array([0, 2]), np.array([np.nan, 0.5])), "views"):
        with pytest.raises(ValueError, match="views must be"):
            blur_render_bwd(saved, v, views=bad)


# ---------------------------------------------------------------------------------------------
# The three-knot path (TrajectoryConfig.path = "three_knot")
# ---------------------------------------------------------------------------------------------


def _three_knot_case(seed, n=8, margin=MARGIN_MIN, max_tries=50):
    """A blur FD case with a middle knot whose every three-knot sub-frame render has the margin."""
    rng = np.random.default_rng(seed + 1000)
    for _ in range(max_tries):
        case = make_case(seed, n=n)
        case["xi_mid"] = rng.normal(size=6) * 0.01
        poses = three_knot_poses(case["pose_est"], case["xi_start"], case["xi_mid"], case["xi_end"], n)
        m = np.inf
        for T, t in zip(poses, subframe_times(case["frame_time"], case["tau"], n)):
            inputs, _ = render_inputs_fwd(case["params"], float(t), DEFORM)
            m = min(m, rf.threshold_margin(dict(inputs, cam_T_world=T, K=case["K"], width=W, height=H,
                                                background=case["background"])))
        if m >= margin:
            return case
        seed += 100
    raise RuntimeError("no three-knot case with the sub-frame margin")


@pytest.mark.parametrize("n", [1, 8])
def test_three_knot_blur_gradients_match_fd(n):
    case = _three_knot_case(40, n=n)
    cot = rf.random_cotangents(np.random.default_rng(102), W, H)
    _, saved = _render(case)
    v_params, v_xs, v_xe, v_tau, aux = blur_render_bwd(saved, **cot, return_aux=True)
    for key, grad in (("xi_start", v_xs), ("xi_end", v_xe), ("xi_mid", aux["v_xi_mid"])):
        fd = rf.central_fd(lambda x, key=key: _loss(case, cot, **{key: x}), case[key], FD_STEP)
        _check_block(key, grad, fd, np.abs(fd).max())
    assert np.abs(aux["v_xi_mid"]).max() > 1e-3  # a real number was compared
    fd_tau = rf.central_fd_scalar(lambda h: _loss(case, cot, tau=case["tau"] + h), FD_STEP)
    _check_block("tau", v_tau, fd_tau, abs(fd_tau) + 1.0)
    # the middle knot moves the render: it is not the geodesic's
    geodesic, _ = _render(dict(case, xi_mid=None))
    assert np.abs(_render(case)[0]["image"] - geodesic["image"]).max() > 1e-3


def test_three_knot_numba_renderer_matches_reference():
    case = _three_knot_case(41, n=3)
    cot = rf.random_cotangents(np.random.default_rng(103), W, H)
    out_ref, saved_ref = _render(case)
    out_fast, saved_fast = blur_render_fwd(**case)
    for key in rf.OUTPUT_KEYS:
        np.testing.assert_allclose(out_fast[key], out_ref[key], rtol=FAST_RTOL, atol=FAST_RTOL)
    g_ref = blur_render_bwd(saved_ref, **cot, return_aux=True)
    g_fast = blur_render_bwd(saved_fast, **cot, return_aux=True)
    for a, b in ((g_fast[1], g_ref[1]), (g_fast[2], g_ref[2]), (g_fast[4]["v_xi_mid"], g_ref[4]["v_xi_mid"])):
        np.testing.assert_allclose(a, b, rtol=0, atol=FAST_RTOL * max(np.abs(b).max(), 1.0))
