"""DDDM deformation: fast path vs the per-Gaussian reference, backward vs central FD, properties."""
import math

import numpy as np
import pytest

from d2gs_np.constants import QUAT_NORM_MIN
from d2gs_np.reference.deformation import deform as deform_reference
from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.deformation import deform_basis, deform_bwd, deform_fwd
from render_fixtures import central_fd

# Fast path and reference sum the same <= 10 terms of magnitude O(1) in a different order:
# the results agree to a few ulps of O(10) values.
FWD_ATOL = 1e-13
# Central FD with h = 1e-6 on smooth O(1) functions: truncation ~h^2 = 1e-12, rounding
# ~eps/h = 1e-10; 1e-7 leaves a wide margin yet catches any missing term (O(1e-2) or more).
FD_H = 1e-6
FD_TOL = 1e-7
# float32 vs float64 evaluation of the same O(1) quantities: a few float32 ulps (6e-8 each)
# accumulated over ~10 terms.
F32_TOL = 2e-5

CONFIGS = [DeformConfig(), DeformConfig(0, 2), DeformConfig(2, 0), DeformConfig(0, 0), DeformConfig(3, 1, omega=3.0)]
CONFIG_IDS = ["P2L2", "P0L2", "P2L0", "P0L0", "P3L1w3"]


def random_inputs(rng, n, config, dtype=np.float64, coef_scale=0.3):
    K = config.num_coefs
    base_quats = rng.normal(size=(n, 4))
    base_quats[:, 0] += 2.0  # raw, not unit, and well away from zero norm
    return dict(
        base_means=rng.normal(size=(n, 3)).astype(dtype),
        base_quats=base_quats.astype(dtype),
        base_colors=rng.uniform(size=(n, 3)).astype(dtype),
        coef_means=(coef_scale * rng.normal(size=(n, K, 3))).astype(dtype),
        coef_quats=(coef_scale * rng.normal(size=(n, K, 4))).astype(dtype),
        coef_colors=(coef_scale * rng.normal(size=(n, K, 3))).astype(dtype),
    )


def weighted_sum(outputs, weights):
    return sum(float(np.sum(o * w)) for o, w in zip(outputs, weights))


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
@pytest.mark.parametrize("t", [0.0, 0.37, 1.0, -0.2, 1.3])
def test_forward_matches_reference(config, t):
    rng = np.random.default_rng(1)
    inputs = random_inputs(rng, 16, config)
    (means, quats, colors), _ = deform_fwd(**inputs, t=t, config=config)
    ref = deform_reference(**inputs, t=t, config=config)
    for got, want in zip((means, quats, colors), ref):
        np.testing.assert_allclose(got, want, rtol=0, atol=FWD_ATOL)
    np.testing.assert_allclose(np.linalg.norm(quats, axis=1), 1.0, rtol=0, atol=FWD_ATOL)


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
@pytest.mark.parametrize("t", [0.0, 0.61, -0.3])
def test_backward_matches_central_fd(config, t):
    rng = np.random.default_rng(2)
    inputs = random_inputs(rng, 4, config)
    weights = [rng.normal(size=(4, 3)), rng.normal(size=(4, 4)), rng.normal(size=(4, 3))]
    outputs, saved = deform_fwd(**inputs, t=t, config=config)
    grads = deform_bwd(saved, *weights)

    for name in inputs:
        def loss(x, name=name):
            perturbed = dict(inputs, **{name: x})
            return weighted_sum(deform_fwd(**perturbed, t=t, config=config)[0], weights)

        fd = central_fd(loss, inputs[name], FD_H)
        np.testing.assert_allclose(grads[name], fd, rtol=0, atol=FD_TOL, err_msg=name)

    def loss_t(tt):
        return weighted_sum(deform_fwd(**inputs, t=tt, config=config)[0], weights)

    fd_t = (loss_t(t + FD_H) - loss_t(t - FD_H)) / (2 * FD_H)
    assert abs(grads["t"] - fd_t) <= FD_TOL * max(1.0, abs(fd_t)), (grads["t"], fd_t)
    if config.num_coefs > 0:
        assert abs(fd_t) > 100 * FD_TOL  # the time derivative is really exercised


def test_none_cotangent_is_zero():
    rng = np.random.default_rng(3)
    config = DeformConfig()
    inputs = random_inputs(rng, 5, config)
    _, saved = deform_fwd(**inputs, t=0.4, config=config)
    v = rng.normal(size=(5, 4))
    a = deform_bwd(saved, None, v, None)
    b = deform_bwd(saved, np.zeros((5, 3)), v, np.zeros((5, 3)))
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


@pytest.mark.parametrize("config", CONFIGS, ids=CONFIG_IDS)
@pytest.mark.parametrize("t", [0.0, 0.5, 2.7])
def test_zero_coefficients_are_identity(config, t):
    rng = np.random.default_rng(4)
    inputs = random_inputs(rng, 12, config)
    for key in ("coef_means", "coef_quats", "coef_colors"):
        inputs[key] = np.zeros_like(inputs[key])
    (means, quats, colors), _ = deform_fwd(**inputs, t=t, config=config)
    np.testing.assert_array_equal(means, inputs["base_means"])
    np.testing.assert_array_equal(colors, inputs["base_colors"])
    q0 = inputs["base_quats"]
    # identity map up to the normalisation of the raw base quaternion (2 ulp of O(1) entries)
    np.testing.assert_allclose(quats, q0 / np.linalg.norm(q0, axis=1, keepdims=True), rtol=0, atol=4.5e-16)


def test_cos_terms_make_nonzero_offset_at_t0():
    # D(0) = sum_l f_cos,l: not zero in general (docs/method.md §2 has no n = 0 term but the cos
    # terms are 1 at t = 0). Guards against dropping or mis-indexing the cos block.
    config = DeformConfig(degree=1, order=2)
    n = 1
    inputs = random_inputs(np.random.default_rng(5), n, config)
    (means, _, _), _ = deform_fwd(**inputs, t=0.0, config=config)
    expected = inputs["base_means"] + inputs["coef_means"][:, 3] + inputs["coef_means"][:, 4]  # the two f_cos rows
    np.testing.assert_allclose(means, expected, rtol=0, atol=FWD_ATOL)


def test_basis_order_and_derivative():
    config = DeformConfig(degree=3, order=2, omega=2.5)
    t = 0.7
    b, db = deform_basis(t, config)
    w = 2.5
    np.testing.assert_allclose(
        b, [t, t**2, t**3, math.sin(w * t), math.sin(2 * w * t), math.cos(w * t), math.cos(2 * w * t)],
        rtol=0, atol=1e-15,
    )
    fd = (deform_basis(t + FD_H, config)[0] - deform_basis(t - FD_H, config)[0]) / (2 * FD_H)
    np.testing.assert_allclose(db, fd, rtol=0, atol=FD_TOL)


@pytest.mark.parametrize("norm_factor", [0.0, 0.5, 2.0, 1e3])
def test_quaternion_norm_threshold(norm_factor):
    # r = q0 + a_1 t with a_1 = -(1 - s) q0 at t = 1 gives r = s q0: |r| = norm_factor * QUAT_NORM_MIN.
    config = DeformConfig(degree=1, order=0)
    rng = np.random.default_rng(6)
    inputs = random_inputs(rng, 3, config)
    q0 = inputs["base_quats"][1] / np.linalg.norm(inputs["base_quats"][1])
    inputs["base_quats"][1] = q0
    s = norm_factor * QUAT_NORM_MIN
    inputs["coef_quats"][1, 0] = -(1.0 - s) * q0
    (means, quats, colors), saved = deform_fwd(**inputs, t=1.0, config=config)
    r = q0 + inputs["coef_quats"][1, 0]
    assert np.all(np.isfinite(quats))
    np.testing.assert_allclose(np.linalg.norm(quats, axis=1), 1.0, rtol=0, atol=FWD_ATOL)
    v_quats = rng.normal(size=(3, 4))
    grads = deform_bwd(saved, None, v_quats, None)
    for g in grads.values():
        assert np.all(np.isfinite(g))
    if np.linalg.norm(r) < QUAT_NORM_MIN:  # below threshold: identity fallback, zero gradient
        np.testing.assert_array_equal(quats[1], [1.0, 0.0, 0.0, 0.0])
        np.testing.assert_array_equal(grads["base_quats"][1], 0.0)
        np.testing.assert_array_equal(grads["coef_quats"][1], 0.0)
    else:  # above: the normalised residual, and the exact normalisation Jacobian
        np.testing.assert_allclose(quats[1], r / np.linalg.norm(r), rtol=0, atol=1e-9)
        q = quats[1]
        expected = (v_quats[1] - q * (q @ v_quats[1])) / np.linalg.norm(r)
        np.testing.assert_allclose(grads["base_quats"][1], expected, rtol=1e-6)
    # the other Gaussians are untouched by the degenerate one
    ref = deform_reference(**inputs, t=1.0, config=config)
    np.testing.assert_allclose(quats[[0, 2]], ref[1][[0, 2]], rtol=0, atol=FWD_ATOL)
    np.testing.assert_allclose(quats[1], ref[1][1], rtol=0, atol=1e-9)


def test_tiny_quaternion_gradient_matches_fd():
    # |r| ~ 1e-6: far above the threshold, gradients ~1e6. The raw quaternion itself is tiny
    # (not a cancellation of O(1) terms), so a step h = 1e-12 is exact to ~1e-10 relative and
    # the truncation error is ~(h/|r|)^2 = 1e-12 relative.
    config = DeformConfig(degree=1, order=0)
    rng = np.random.default_rng(7)
    inputs = random_inputs(rng, 1, config)
    inputs["base_quats"] = 1e-6 * rng.normal(size=(1, 4))
    inputs["coef_quats"] = 1e-7 * rng.normal(size=(1, 1, 4))
    weights = [np.zeros((1, 3)), rng.normal(size=(1, 4)), np.zeros((1, 3))]
    _, saved = deform_fwd(**inputs, t=1.0, config=config)
    grads = deform_bwd(saved, *weights)

    def loss(x):
        return weighted_sum(deform_fwd(**dict(inputs, base_quats=x), t=1.0, config=config)[0], weights)

    fd = central_fd(loss, inputs["base_quats"], 1e-12)
    scale = np.max(np.abs(fd))
    assert scale > 1e4
    np.testing.assert_allclose(grads["base_quats"], fd, rtol=0, atol=1e-7 * scale)


@pytest.mark.parametrize("t", [25.0, -40.0, 1e3])
def test_large_t_finite_and_correct(t):
    config = DeformConfig()
    rng = np.random.default_rng(8)
    inputs = random_inputs(rng, 6, config)
    weights = [rng.normal(size=(6, 3)), rng.normal(size=(6, 4)), rng.normal(size=(6, 3))]
    outputs, saved = deform_fwd(**inputs, t=t, config=config)
    ref = deform_reference(**inputs, t=t, config=config)
    scale = t * t  # the t^2 term dominates the magnitudes
    for got, want in zip(outputs, ref):
        assert np.all(np.isfinite(got))
        np.testing.assert_allclose(got, want, rtol=0, atol=FWD_ATOL * scale)
    grads = deform_bwd(saved, *weights)
    for g in grads.values():
        assert np.all(np.isfinite(g))
    h = FD_H * abs(t)

    def loss_t(tt):
        return weighted_sum(deform_fwd(**inputs, t=tt, config=config)[0], weights)

    fd_t = (loss_t(t + h) - loss_t(t - h)) / (2 * h)
    assert abs(grads["t"] - fd_t) <= 1e-6 * abs(fd_t), (grads["t"], fd_t)
    fd_coef = central_fd(
        lambda x: weighted_sum(deform_fwd(**dict(inputs, coef_means=x), t=t, config=config)[0], weights),
        inputs["coef_means"], FD_H,
    )
    np.testing.assert_allclose(grads["coef_means"], fd_coef, rtol=0, atol=FD_TOL * scale)


def test_float32_stays_float32():
    config = DeformConfig()
    rng = np.random.default_rng(9)
    inputs64 = random_inputs(rng, 8, config)
    inputs32 = {k: v.astype(np.float32) for k, v in inputs64.items()}
    out32, saved32 = deform_fwd(**inputs32, t=0.3, config=config)
    out64, saved64 = deform_fwd(**{k: v.astype(np.float64) for k, v in inputs32.items()}, t=0.3, config=config)
    for a, b in zip(out32, out64):
        assert a.dtype == np.float32
        np.testing.assert_allclose(a, b, rtol=0, atol=F32_TOL)
    v = [rng.normal(size=(8, 3)), rng.normal(size=(8, 4)), rng.normal(size=(8, 3))]
    g32 = deform_bwd(saved32, *[x.astype(np.float32) for x in v])
    g64 = deform_bwd(saved64, *[x.astype(np.float32).astype(np.float64) for x in v])
    for key in g32:
        assert np.asarray(g32[key]).dtype == np.float32, key
        np.testing.assert_allclose(g32[key], g64[key], rtol=F32_TOL, atol=F32_TOL * 10, err_msg=key)


def test_validation_errors():
    config = DeformConfig()
    inputs = random_inputs(np.random.default_rng(10), 3, config)
    with pytest.raises(ValueError, match=r"coef_means must have shape \(3, 6, 3\); got \(3, 4, 3\)"):
        deform_fwd(**dict(inputs, coef_means=np.zeros((3, 4, 3))), t=0.0, config=config)
    with pytest.raises(ValueError, match=r"base_quats must have shape \(3, 4\)"):
        deform_fwd(**dict(inputs, base_quats=np.zeros((3, 3))), t=0.0, config=config)
    with pytest.raises(TypeError, match="base_colors has dtype float32"):
        deform_fwd(**dict(inputs, base_colors=inputs["base_colors"].astype(np.float32)), t=0.0, config=config)
    bad = inputs["coef_quats"].copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="coef_quats contains NaN"):
        deform_fwd(**dict(inputs, coef_quats=bad), t=0.0, config=config)
    with pytest.raises(ValueError, match="t must be a finite number"):
        deform_fwd(**inputs, t=float("inf"), config=config)
    with pytest.raises(ValueError, match="t must be a scalar"):
        deform_fwd(**inputs, t=np.zeros(2), config=config)
    with pytest.raises(TypeError, match="DeformConfig"):
        deform_fwd(**inputs, t=0.0, config=None)
