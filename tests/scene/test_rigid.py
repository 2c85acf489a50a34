"""Rigid cluster motion (scene/rigid.py): forward against the per-Gaussian loop, backward against
central differences through the whole parameter map, rigidity, extreme rotations, layout."""
import numpy as np
import pytest

from d2gs_np.reference.rigid import rigid_transform
from d2gs_np.scene import DeformConfig, init_params, prune, render_inputs_bwd, render_inputs_fwd
from d2gs_np.scene.deformation import deform_fwd
from d2gs_np.scene.gaussians import CLUSTER, append_gaussians, make_gaussians, validate_params
from d2gs_np.scene.rigid import dynamic_positions, rigid_fwd
from render_fixtures import central_fd

# Central FD, h = 1e-6, on O(1) smooth maps (polynomial / trig in t, normalisation, products of
# quaternions): truncation ~1e-12, rounding ~1e-10; any wrong or missing term is >= 1e-3.
FD_H = 1e-6
FD_TOL = 1e-7


def rigid_params(rng, ns=3, nd=7, C=2, config=DeformConfig(), std=0.3, clusters=None):
    params = init_params(rng.normal(size=(ns, 3)), rng.uniform(size=(ns, 3)), rng.normal(size=(nd, 3)),
                         rng.uniform(size=(nd, 3)), deform_config=config, rng=rng, deform_init_std=0.2)
    params = {k: v + 0.3 * rng.normal(size=v.shape) for k, v in params.items()}
    K = config.num_coefs
    params.update({"rigid.means": rng.normal(size=(C, 3)), "rigid.quats": rng.normal(size=(C, 4)),
                   "rigid.deform_means": std * rng.normal(size=(C, K, 3)),
                   "rigid.deform_quats": std * rng.normal(size=(C, K, 4))})
    ids = np.arange(nd) % (C + 1) - 1.0 if clusters is None else np.asarray(clusters, dtype=np.float64)
    params[CLUSTER] = ids  # -1, 0, 1, -1, ...: both kinds of rows
    validate_params(params, config)
    return params


def deformed_local(params, t, config):
    return deform_fwd(*(params[f"dynamic.{f}"] for f in ("means", "quats", "colors", "deform_means",
                                                        "deform_quats", "deform_colors")), t, config)[0]


def weighted(out, w):
    return sum(float(np.sum(out[k] * w[k])) for k in w)


@pytest.mark.parametrize("t", [0.0, 0.37, 1.2])
def test_forward_matches_the_loop(t):
    rng = np.random.default_rng(0)
    config = DeformConfig()
    params = rigid_params(rng, config=config)
    m, q, _ = deformed_local(params, t, config)
    (wm, wq), _ = rigid_fwd(m, q, params[CLUSTER], params, t, config)
    rm, rq = rigid_transform(m, q, params[CLUSTER], params, t, config)
    np.testing.assert_allclose(wm, rm, rtol=0, atol=1e-13)
    np.testing.assert_allclose(wq, rq, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(wq, axis=1), 1.0, atol=1e-14)
    free = params[CLUSTER] < 0
    np.testing.assert_array_equal(wm[free], m[free])  # no cluster: the deformation is the world motion
    out, _ = render_inputs_fwd(params, t, config)
    np.testing.assert_array_equal(out["means"][3:], wm)
    np.testing.assert_array_equal(out["quats"][3:], wq)
    np.testing.assert_array_equal(dynamic_positions(params, [t], config)[0], wm)


@pytest.mark.parametrize("config", [DeformConfig(), DeformConfig(1, 0), DeformConfig(0, 1)], ids=["P2L2", "P1L0", "P0L1"])
def test_backward_matches_central_fd(config):
    rng = np.random.default_rng(1)
    params = rigid_params(rng, config=config)
    n = 3 + 7
    t = 0.61
    w = dict(means=rng.normal(size=(n, 3)), quats=rng.normal(size=(n, 4)), scales=rng.normal(size=(n, 3)),
             opacities=rng.normal(size=n), colors=rng.normal(size=(n, 3)))
    _, saved = render_inputs_fwd(params, t, config)
    v_params, v_t = render_inputs_bwd(saved, w)
    assert set(v_params) == set(params) - {CLUSTER}  # the ids are not trained
    for name, x in params.items():
        if name == CLUSTER:
            continue
        fd = central_fd(lambda y, name=name: weighted(render_inputs_fwd(dict(params, **{name: y}), t, config)[0], w),
                        x, FD_H)
        np.testing.assert_allclose(v_params[name], fd, rtol=0, atol=FD_TOL, err_msg=name)
        if name.startswith("rigid."):
            assert np.max(np.abs(fd)) > 1e-2, name  # the block really moves the output
    fd_t = (weighted(render_inputs_fwd(params, t + FD_H, config)[0], w)
            - weighted(render_inputs_fwd(params, t - FD_H, config)[0], w)) / (2 * FD_H)
    assert abs(v_t - fd_t) <= FD_TOL * max(1.0, abs(fd_t)) and abs(fd_t) > 1e-2


def test_a_cluster_keeps_its_shape_over_time():
    """Without residual motion a cluster's Gaussians keep their distances at every time (one
    object, one scale), while its pose moves them."""
    rng = np.random.default_rng(2)
    config = DeformConfig()
    params = rigid_params(rng, nd=6, C=1, clusters=np.zeros(6), std=0.5)
    for f in ("deform_means", "deform_quats"):
        params[f"dynamic.{f}"] = np.zeros_like(params[f"dynamic.{f}"])
    pos = dynamic_positions(params, np.linspace(-0.2, 1.2, 8), config)
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    np.testing.assert_allclose(d, np.broadcast_to(d[0], d.shape), rtol=0, atol=1e-12)
    assert np.ptp(pos[:, 0, 0]) > 0.1  # and they did move


def test_identity_cluster_is_exact():
    rng = np.random.default_rng(3)
    config = DeformConfig()
    params = rigid_params(rng, C=2)
    params["rigid.means"] = np.zeros((2, 3))
    params["rigid.quats"] = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
    params["rigid.deform_means"] = np.zeros_like(params["rigid.deform_means"])
    params["rigid.deform_quats"] = np.zeros_like(params["rigid.deform_quats"])
    m, q, _ = deformed_local(params, 0.3, config)
    (wm, wq), _ = rigid_fwd(m, q, params[CLUSTER], params, 0.3, config)
    np.testing.assert_array_equal(wm, m)
    np.testing.assert_array_equal(wq, q)


@pytest.mark.parametrize("quat", [[1e-9, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], [1.0, 1e-12, 0.0, 0.0],
                                  [1e-320, 0.0, 0.0, 0.0]], ids=["near-pi", "pi", "near-identity", "degenerate"])
def test_extreme_cluster_rotations(quat):
    """Turns near 0 and near pi are exact against the loop; a cluster quaternion of (near) zero norm
    falls back to the identity with a zero, finite gradient through it."""
    rng = np.random.default_rng(4)
    config = DeformConfig()
    params = rigid_params(rng, C=1, clusters=np.zeros(7))
    params["rigid.quats"] = np.array([quat])
    params["rigid.deform_quats"] = np.zeros_like(params["rigid.deform_quats"])
    out, saved = render_inputs_fwd(params, 0.5, config)
    m, q, _ = deformed_local(params, 0.5, config)
    degenerate = np.linalg.norm(quat) < 1e-300
    if degenerate:  # the identity turn: only the cluster's position path moves its Gaussians
        p = dynamic_positions(dict(params, **{"dynamic.means": np.zeros((7, 3)),
                                              "dynamic.deform_means": np.zeros_like(params["dynamic.deform_means"])}),
                              [0.5], config)[0]
        np.testing.assert_allclose(out["means"][3:], m + p, rtol=0, atol=1e-14)
        np.testing.assert_array_equal(out["quats"][3:], q)
    else:
        rm, rq = rigid_transform(m, q, params[CLUSTER], params, 0.5, config)
        np.testing.assert_allclose(out["means"][3:], rm, rtol=0, atol=1e-12)
        np.testing.assert_allclose(out["quats"][3:], rq, rtol=0, atol=1e-14)
    w = {k: np.ones_like(v) for k, v in out.items()}
    v_params, v_t = render_inputs_bwd(saved, w)
    assert all(np.all(np.isfinite(v)) for v in v_params.values()) and np.isfinite(v_t)
    if degenerate:
        assert np.all(v_params["rigid.quats"] == 0.0)


def test_rows_keep_their_clusters():
    rng = np.random.default_rng(5)
    params = rigid_params(rng, nd=7, C=2)
    keep = np.array([True, False, True, True, False, True, True])
    pruned = prune(params, np.ones(3, bool), keep)
    np.testing.assert_array_equal(pruned[CLUSTER], params[CLUSTER][keep])
    # cloned rows carry their ids; rows seeded in world coordinates get -1
    clone = {k: v[[1, 2]] for k, v in params.items() if k.startswith("dynamic.")}
    grown = append_gaussians(params, clone)
    np.testing.assert_array_equal(grown[CLUSTER], np.r_[params[CLUSTER], params[CLUSTER][[1, 2]]])
    fresh = {k: v for k, v in clone.items() if k != CLUSTER}
    grown = append_gaussians(params, fresh)
    np.testing.assert_array_equal(grown[CLUSTER][-2:], [-1.0, -1.0])
    validate_params(grown, DeformConfig())
    assert "dynamic.cluster" in make_gaussians("dynamic", **{k.split(".", 1)[1]: v for k, v in clone.items()})


def test_bad_layouts_are_named():
    rng = np.random.default_rng(6)
    config = DeformConfig()
    params = rigid_params(rng)
    for ids, what in ((np.full(7, 2.0), "from -1"), (np.full(7, 0.5), "whole numbers"), (np.full(7, -2.0), "from -1")):
        with pytest.raises(ValueError, match=what):
            validate_params(dict(params, **{CLUSTER: ids}), config)
    with pytest.raises(ValueError, match="missing"):
        validate_params({k: v for k, v in params.items() if k != CLUSTER}, config)
    with pytest.raises(ValueError, match="missing"):
        validate_params({k: v for k, v in params.items() if k != "rigid.quats"}, config)
    with pytest.raises(ValueError, match=r"rigid.deform_quats must have shape \(C, K, 4\)"):
        validate_params(dict(params, **{"rigid.deform_quats": np.zeros((2, 1, 4))}), config)
    with pytest.raises(ValueError, match="only the dynamic set"):
        make_gaussians("static", *(np.zeros((1, d)) for d in (3, 3, 4)), np.zeros(1), np.zeros((1, 3)),
                       cluster=np.zeros(1))


def test_float32_stays_float32():
    rng = np.random.default_rng(7)
    config = DeformConfig()
    params = {k: v.astype(np.float32) for k, v in rigid_params(rng).items()}
    out, saved = render_inputs_fwd(params, 0.4, config)
    assert all(v.dtype == np.float32 for v in out.values())
    v_params, v_t = render_inputs_bwd(saved, {k: np.ones_like(v) for k, v in out.items()})
    assert all(v.dtype == np.float32 for v in v_params.values()) and v_t.dtype == np.float32
    ref, _ = render_inputs_fwd({k: v.astype(np.float64) for k, v in params.items()}, 0.4, config)
    np.testing.assert_allclose(out["means"], ref["means"], rtol=0, atol=1e-5)  # float32 rounding of O(1-10) values


def test_no_clusters_is_the_plain_deformation():
    """A rigid layout with C = 0 clusters (no track long enough) renders exactly as the scene
    without it, and its (empty) rigid blocks get empty gradients."""
    rng = np.random.default_rng(8)
    config = DeformConfig()
    params = rigid_params(rng, C=0, clusters=np.full(7, -1.0))
    plain = {k: v for k, v in params.items() if not k.startswith("rigid.") and k != CLUSTER}
    out, saved = render_inputs_fwd(params, 0.2, config)
    ref, ref_saved = render_inputs_fwd(plain, 0.2, config)
    for k in out:
        np.testing.assert_array_equal(out[k], ref[k], err_msg=k)
    w = {k: np.ones_like(v) for k, v in out.items()}
    v_params, v_t = render_inputs_bwd(saved, w)
    v_ref, v_t_ref = render_inputs_bwd(ref_saved, w)
    assert v_params["rigid.means"].shape == (0, 3) and v_t == v_t_ref
    for k in v_ref:
        np.testing.assert_array_equal(v_params[k], v_ref[k], err_msg=k)
