"""Scene parameters -> renderer inputs: forward structure, backward vs central FD, no-dynamic scenes."""
import numpy as np
import pytest

import d2gs_np.scene.render_inputs as model
from d2gs_np.scene import DeformConfig, deform_fwd, render_inputs_bwd, render_inputs_fwd, init_params, prune
from render_fixtures import central_fd

# Central FD, h = 1e-6, on O(1) smooth functions (exp, sigmoid, polynomial/trig in t,
# normalisation): truncation ~1e-12, rounding ~1e-10; any wrong term is >= 1e-3.
FD_H = 1e-6
FD_TOL = 1e-7


def random_params(rng, ns=5, nd=4, config=DeformConfig(), dtype=np.float64):
    params = init_params(
        rng.normal(size=(ns, 3)).astype(dtype), rng.uniform(size=(ns, 3)).astype(dtype),
        None if nd is None else rng.normal(size=(nd, 3)).astype(dtype),
        None if nd is None else rng.uniform(size=(nd, 3)).astype(dtype),
        deform_config=config, rng=rng, deform_init_std=0.2,
    )
    # move every block away from its initial value so that no derivative is trivially 0 or 1
    out = {}
    for k, v in params.items():
        out[k] = (v + 0.3 * rng.normal(size=v.shape)).astype(dtype)
    return out


def random_cotangents(rng, n, dtype=np.float64):
    return dict(
        means=rng.normal(size=(n, 3)).astype(dtype), quats=rng.normal(size=(n, 4)).astype(dtype),
        scales=rng.normal(size=(n, 3)).astype(dtype), opacities=rng.normal(size=n).astype(dtype),
        colors=rng.normal(size=(n, 3)).astype(dtype),
    )


def weighted(render_inputs, weights):
    return sum(float(np.sum(render_inputs[k] * weights[k])) for k in weights)


def test_forward_structure():
    rng = np.random.default_rng(0)
    config = DeformConfig()
    params = random_params(rng, 5, 4, config)
    t = 0.42
    out, _ = render_inputs_fwd(params, t, config)
    (dm, dq, dc), _ = deform_fwd(
        params["dynamic.means"], params["dynamic.quats"], params["dynamic.colors"],
        params["dynamic.deform_means"], params["dynamic.deform_quats"], params["dynamic.deform_colors"], t, config,
    )
    np.testing.assert_array_equal(out["means"], np.concatenate([params["static.means"], dm]))
    np.testing.assert_array_equal(out["quats"], np.concatenate([params["static.quats"], dq]))
    np.testing.assert_array_equal(out["colors"], np.concatenate([params["static.colors"], dc]))
    logs = np.concatenate([params["static.log_scales"], params["dynamic.log_scales"]])
    logits = np.concatenate([params["static.opacity_logits"], params["dynamic.opacity_logits"]])
    np.testing.assert_allclose(out["scales"], np.exp(logs), rtol=1e-15)
    np.testing.assert_allclose(out["opacities"], 1.0 / (1.0 + np.exp(-logits)), rtol=1e-15)
    for v in out.values():  # never views of the parameters
        assert not any(np.shares_memory(v, p) for p in params.values())


@pytest.mark.parametrize("nd", [4, 0, None], ids=["dynamic", "empty-dynamic", "no-dynamic"])
@pytest.mark.parametrize("config", [DeformConfig(), DeformConfig(1, 0), DeformConfig(0, 1)], ids=["P2L2", "P1L0", "P0L1"])
def test_backward_matches_central_fd(nd, config):
    rng = np.random.default_rng(1)
    params = random_params(rng, 4, nd, config)
    n = 4 + (nd or 0)
    t = 0.7
    weights = random_cotangents(rng, n)
    out, saved = render_inputs_fwd(params, t, config)
    v_params, v_t = render_inputs_bwd(saved, weights)
    assert v_params.keys() == params.keys()
    for name, x in params.items():
        fd = central_fd(lambda y, name=name: weighted(render_inputs_fwd(dict(params, **{name: y}), t, config)[0], weights),
                        x, FD_H)
        assert v_params[name].shape == x.shape and v_params[name].flags.c_contiguous
        np.testing.assert_allclose(v_params[name], fd, rtol=0, atol=FD_TOL, err_msg=name)
    fd_t = (weighted(render_inputs_fwd(params, t + FD_H, config)[0], weights)
            - weighted(render_inputs_fwd(params, t - FD_H, config)[0], weights)) / (2 * FD_H)
    assert abs(v_t - fd_t) <= FD_TOL * max(1.0, abs(fd_t))
    if nd:
        assert abs(fd_t) > 100 * FD_TOL  # the time derivative is really exercised


def test_no_dynamic_set_does_no_deformation(monkeypatch):
    rng = np.random.default_rng(2)
    config = DeformConfig()
    params = random_params(rng, 6, None, config)
    assert not any(k.startswith("dynamic.") for k in params)

    def forbidden(*args, **kwargs):
        raise AssertionError("deformation evaluated for a scene without a dynamic set")

    monkeypatch.setattr(model, "_deform_fwd", forbidden)  # the names render_inputs_fwd / render_inputs_bwd call
    monkeypatch.setattr(model, "_deform_bwd", forbidden)
    out, saved = render_inputs_fwd(params, 0.3, config)
    np.testing.assert_array_equal(out["means"], params["static.means"])
    v_params, v_t = render_inputs_bwd(saved, random_cotangents(rng, 6))
    assert set(v_params) == set(params)
    assert v_t == 0.0


def test_output_independent_of_t_without_dynamic_set():
    rng = np.random.default_rng(3)
    params = random_params(rng, 6, None)
    a, _ = render_inputs_fwd(params, 0.0, DeformConfig())
    b, _ = render_inputs_fwd(params, 0.9, DeformConfig())
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_missing_cotangents_count_as_zero():
    rng = np.random.default_rng(4)
    params = random_params(rng, 3, 2)
    _, saved = render_inputs_fwd(params, 0.5, DeformConfig())
    w = random_cotangents(rng, 5)
    partial = {"means": w["means"], "opacities": w["opacities"]}
    full = dict(partial, quats=np.zeros((5, 4)), scales=np.zeros((5, 3)), colors=np.zeros((5, 3)))
    a, ta = render_inputs_bwd(saved, partial)
    b, tb = render_inputs_bwd(saved, full)
    assert ta == tb
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_float32_stays_float32():
    rng = np.random.default_rng(5)
    params = random_params(rng, 3, 2, dtype=np.float32)
    out, saved = render_inputs_fwd(params, 0.25, DeformConfig())
    assert all(v.dtype == np.float32 for v in out.values())
    v_params, v_t = render_inputs_bwd(saved, random_cotangents(rng, 5, np.float32))
    assert all(v.dtype == np.float32 for v in v_params.values())
    assert np.asarray(v_t).dtype == np.float32
    with pytest.raises(TypeError, match="float32"):
        render_inputs_bwd(saved, random_cotangents(rng, 5, np.float64))


def test_pruned_scene_evaluates():
    rng = np.random.default_rng(6)
    params = random_params(rng, 5, 3)
    pruned = prune(params, np.array([True, False, True, True, False]), np.zeros(3, bool))
    out, saved = render_inputs_fwd(pruned, 0.5, DeformConfig())
    assert out["means"].shape == (3, 3)
    v_params, v_t = render_inputs_bwd(saved, random_cotangents(rng, 3))
    assert v_params["dynamic.deform_means"].shape == (0, 6, 3)
    assert v_t == 0.0


def test_validation():
    rng = np.random.default_rng(7)
    params = random_params(rng, 3, 2)
    with pytest.raises(ValueError, match="K=6 coefficients but deform_config expects 3"):
        render_inputs_fwd(params, 0.0, DeformConfig(degree=1, order=1))
    with pytest.raises(ValueError, match="missing"):
        render_inputs_fwd({k: v for k, v in params.items() if k != "dynamic.colors"}, 0.0, DeformConfig())
    with pytest.raises(TypeError, match="DeformConfig"):
        render_inputs_fwd(params, 0.0, None)
    _, saved = render_inputs_fwd(params, 0.0, DeformConfig())
    with pytest.raises(ValueError, match=r"v_render_inputs\['means'\] must have shape \(5, 3\)"):
        render_inputs_bwd(saved, {"means": np.zeros((4, 3))})
    with pytest.raises(ValueError, match="unknown keys"):
        render_inputs_bwd(saved, {"mean": np.zeros((5, 3))})
