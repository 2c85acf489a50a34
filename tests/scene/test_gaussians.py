"""Scene parameter blocks: activations, initialisation, validation, pruning and appending."""
import numpy as np
import pytest

from d2gs_np.constants import INIT_DIST2_MIN
from d2gs_np.scene import (
    DeformConfig,
    append_gaussians,
    has_dynamic,
    init_params,
    logit,
    make_gaussians,
    num_dynamic,
    num_static,
    opacity_bwd,
    opacity_fwd,
    prune,
    scale_bwd,
    scale_fwd,
    sigmoid,
    validate_params,
)
from render_fixtures import central_fd

FD_H = 1e-6
FD_TOL = 1e-8  # central FD of exp / sigmoid on O(1) inputs: truncation ~1e-12, rounding ~1e-10
ULP_TOL = 1e-15  # same formula, different but exact-to-rounding evaluation


def test_sigmoid_logit():
    x = np.linspace(-30, 30, 61)
    np.testing.assert_allclose(sigmoid(x), 1.0 / (1.0 + np.exp(-x)), rtol=ULP_TOL)
    np.testing.assert_allclose(logit(sigmoid(np.linspace(-10, 10, 21))), np.linspace(-10, 10, 21), rtol=0, atol=1e-12)
    extreme = sigmoid(np.array([-1e4, 1e4]))  # exp(1e4) would overflow in the naive form
    np.testing.assert_array_equal(extreme, [0.0, 1.0])
    assert sigmoid(np.float32(3.0)).dtype == np.float32
    with pytest.raises(ValueError, match="strictly inside"):
        logit(np.array([0.0, 0.5]))


def test_activation_backwards_match_fd():
    rng = np.random.default_rng(0)
    x = rng.normal(size=7)
    w = rng.normal(size=7)
    o, saved = opacity_fwd(x)
    np.testing.assert_allclose(opacity_bwd(saved, w), central_fd(lambda y: float(w @ opacity_fwd(y)[0]), x, FD_H),
                               rtol=0, atol=FD_TOL)
    s = rng.normal(size=(3, 3))
    ws = rng.normal(size=(3, 3))
    _, saved = scale_fwd(s)
    np.testing.assert_allclose(scale_bwd(saved, ws), central_fd(lambda y: float(np.sum(ws * scale_fwd(y)[0])), s, FD_H),
                               rtol=0, atol=FD_TOL)


def brute_force_log_scales(points, k=3):
    d2 = np.sum((points[:, None] - points[None]) ** 2, axis=-1)
    np.fill_diagonal(d2, np.inf)
    nearest = np.sort(d2, axis=1)[:, :k]
    return 0.5 * np.log(np.maximum(nearest.mean(axis=1), INIT_DIST2_MIN))


def test_init_params_layout_and_values():
    rng = np.random.default_rng(1)
    config = DeformConfig(degree=3, order=1)
    sm, sc = rng.normal(size=(20, 3)), rng.uniform(size=(20, 3))
    dm, dc = rng.normal(size=(6, 3)) + 0.5, rng.uniform(size=(6, 3))
    params = init_params(sm, sc, dm, dc, deform_config=config)
    validate_params(params, config)
    assert num_static(params) == 20 and num_dynamic(params) == 6 and has_dynamic(params)
    assert params["dynamic.deform_quats"].shape == (6, 5, 4)
    expected = brute_force_log_scales(np.concatenate([sm, dm]))  # neighbours among all points
    np.testing.assert_allclose(params["static.log_scales"], np.repeat(expected[:20, None], 3, 1), rtol=0, atol=1e-12)
    np.testing.assert_allclose(params["dynamic.log_scales"], np.repeat(expected[20:, None], 3, 1), rtol=0, atol=1e-12)
    for prefix in ("static", "dynamic"):
        n = params[f"{prefix}.means"].shape[0]
        np.testing.assert_array_equal(params[f"{prefix}.quats"], np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)))
        np.testing.assert_allclose(sigmoid(params[f"{prefix}.opacity_logits"]), 0.1, rtol=1e-14)
        assert all(v.flags.c_contiguous for v in params.values())
    np.testing.assert_array_equal(params["static.colors"], sc)
    np.testing.assert_array_equal(params["dynamic.means"], dm)
    assert not np.shares_memory(params["static.means"], sm)
    for field in ("deform_means", "deform_quats", "deform_colors"):
        np.testing.assert_array_equal(params[f"dynamic.{field}"], 0.0)


def test_init_params_without_dynamic_set_and_float32():
    rng = np.random.default_rng(2)
    params = init_params(rng.normal(size=(5, 3)).astype(np.float32), rng.uniform(size=(5, 3)).astype(np.float32))
    assert not has_dynamic(params) and num_dynamic(params) == 0
    assert sorted(params) == sorted(f"static.{f}" for f in ("means", "log_scales", "quats", "opacity_logits", "colors"))
    assert all(v.dtype == np.float32 for v in params.values())
    validate_params(params)


def test_init_params_degenerate_points():
    # duplicates: clamped, finite; a single point: isolated_scale; deform_init_std draws from rng
    pts = np.zeros((4, 3))
    params = init_params(pts, np.zeros((4, 3)))
    np.testing.assert_allclose(params["static.log_scales"], 0.5 * np.log(INIT_DIST2_MIN), rtol=1e-15)
    one = init_params(np.zeros((1, 3)), np.zeros((1, 3)), isolated_scale=0.05)
    np.testing.assert_allclose(one["static.log_scales"], np.log(0.05), rtol=1e-15)
    two = init_params(np.zeros((1, 3)), np.zeros((1, 3)), np.ones((1, 3)), np.zeros((1, 3)))
    np.testing.assert_allclose(two["static.log_scales"], 0.5 * np.log(3.0), rtol=1e-15)  # its only neighbour
    rand = init_params(np.zeros((1, 3)), np.zeros((1, 3)), np.ones((2, 3)), np.zeros((2, 3)),
                       rng=np.random.default_rng(0), deform_init_std=0.1)
    assert np.std(rand["dynamic.deform_means"]) > 0.0
    with pytest.raises(TypeError, match="rng"):
        init_params(np.zeros((1, 3)), np.zeros((1, 3)), np.ones((2, 3)), np.zeros((2, 3)), deform_init_std=0.1)


def test_init_params_errors():
    with pytest.raises(ValueError, match=r"static_means must have shape \(N, 3\); got \(4, 2\)"):
        init_params(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"static_colors must have shape \(4, 3\)"):
        init_params(np.zeros((4, 3)), np.zeros((3, 3)))
    with pytest.raises(TypeError, match="dtype float32"):
        init_params(np.zeros((4, 3)), np.zeros((4, 3), np.float32))
    with pytest.raises(ValueError, match="both dynamic_means and dynamic_colors"):
        init_params(np.zeros((4, 3)), np.zeros((4, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="init_opacity"):
        init_params(np.zeros((4, 3)), np.zeros((4, 3)), init_opacity=1.0)


def test_validate_params_errors():
    rng = np.random.default_rng(3)
    params = init_params(rng.normal(size=(4, 3)), rng.uniform(size=(4, 3)), rng.normal(size=(2, 3)),
                         rng.uniform(size=(2, 3)))
    with pytest.raises(ValueError, match=r"missing \['dynamic.deform_colors'\]"):
        validate_params({k: v for k, v in params.items() if k != "dynamic.deform_colors"})
    with pytest.raises(ValueError, match=r"unexpected \['static.sh'\]"):
        validate_params(dict(params, **{"static.sh": np.zeros((4, 3))}))
    with pytest.raises(ValueError, match=r"static.quats must have shape \(N, 4\)"):
        validate_params(dict(params, **{"static.quats": np.zeros((3, 4))}))
    with pytest.raises(TypeError, match="dtype float32"):
        validate_params(dict(params, **{"dynamic.colors": params["dynamic.colors"].astype(np.float32)}))
    with pytest.raises(ValueError, match="C-contiguous"):
        validate_params(dict(params, **{"static.means": np.asfortranarray(np.zeros((4, 3)))}))
    bad = params["static.colors"].copy()
    bad[0, 0] = np.inf
    with pytest.raises(ValueError, match="static.colors contains NaN or inf"):
        validate_params(dict(params, **{"static.colors": bad}))
    with pytest.raises(ValueError, match="expects 3"):
        validate_params(params, DeformConfig(1, 1))


def test_prune_and_append():
    rng = np.random.default_rng(4)
    params = init_params(rng.normal(size=(5, 3)), rng.uniform(size=(5, 3)), rng.normal(size=(3, 3)),
                         rng.uniform(size=(3, 3)), rng=rng, deform_init_std=0.1)
    keep_s = np.array([True, False, True, False, True])
    keep_d = np.array([False, True, True])
    pruned = prune(params, keep_s, keep_d)
    validate_params(pruned)
    for k, v in params.items():
        mask = keep_s if k.startswith("static.") else keep_d
        np.testing.assert_array_equal(pruned[k], v[mask])
    only_static = prune(params, keep_s)
    assert only_static["dynamic.deform_means"] is params["dynamic.deform_means"]
    empty = prune(params, keep_s, np.zeros(3, bool))
    assert num_dynamic(empty) == 0 and has_dynamic(empty)
    validate_params(empty)

    new = make_gaussians("dynamic", rng.normal(size=(2, 3)), rng.normal(size=(2, 3)), rng.normal(size=(2, 4)),
                         rng.normal(size=2), rng.uniform(size=(2, 3)), np.zeros((2, 6, 3)), np.zeros((2, 6, 4)),
                         np.zeros((2, 6, 3)))
    grown = append_gaussians(pruned, new)
    validate_params(grown)
    assert num_dynamic(grown) == 4 and num_static(grown) == 3
    np.testing.assert_array_equal(grown["dynamic.means"][2:], new["dynamic.means"])
    np.testing.assert_array_equal(grown["dynamic.means"][:2], pruned["dynamic.means"])
    assert grown["static.means"] is pruned["static.means"]

    static_only = init_params(rng.normal(size=(3, 3)), rng.uniform(size=(3, 3)))
    created = append_gaussians(static_only, new)
    validate_params(created)
    assert num_dynamic(created) == 2

    with pytest.raises(ValueError, match="keep_dynamic must have shape"):
        prune(params, keep_s, np.ones(4, bool))
    with pytest.raises(TypeError, match="boolean"):
        prune(params, np.ones(5, int))
    with pytest.raises(ValueError, match="no dynamic set"):
        prune(static_only, np.ones(3, bool), np.ones(0, bool))
    with pytest.raises(ValueError, match="trailing shape"):
        wrong_k = dict(new, **{"dynamic.deform_means": np.zeros((2, 4, 3)), "dynamic.deform_quats": np.zeros((2, 4, 4)),
                               "dynamic.deform_colors": np.zeros((2, 4, 3))})
        append_gaussians(pruned, wrong_k)
    with pytest.raises(ValueError, match="missing"):
        append_gaussians(pruned, {"static.means": np.zeros((1, 3))})
    with pytest.raises(ValueError, match="static set has no deformation"):
        make_gaussians("static", *[new[f"dynamic.{f}"] for f in ("means", "log_scales", "quats", "opacity_logits",
                                                                    "colors", "deform_means")])
