"""Adam over named blocks: exact single steps, convergence, schedules, state surgery, errors."""
import json
import math

import numpy as np
import pytest

from d2gs_np.constants import ADAM_EPS
from d2gs_np.optim import adam
from d2gs_np.optim import (
    AdamConfig,
    Constant,
    adam_extend,
    adam_init,
    adam_select,
    adam_update,
    constant,
    exponential_decay,
)


def hand_adam(p, g_seq, lr_seq, b1=0.9, b2=0.999, eps=ADAM_EPS):
    """Scalar, element-by-element Adam written from the textbook formula."""
    p = [float(x) for x in p]
    m = [0.0] * len(p)
    v = [0.0] * len(p)
    for k, (g, lr) in enumerate(zip(g_seq, lr_seq), start=1):
        for i in range(len(p)):
            m[i] = b1 * m[i] + (1.0 - b1) * g[i]
            v[i] = b2 * v[i] + (1.0 - b2) * (g[i] * g[i])
            m_hat = m[i] / (1.0 - b1**k)
            v_hat = v[i] / (1.0 - b2**k)
            p[i] = p[i] - lr * m_hat / (math.sqrt(v_hat) + eps)
    return np.array(p), np.array(m), np.array(v)


def test_matches_hand_written_steps_exactly():
    rng = np.random.default_rng(0)
    p0 = rng.normal(size=5)
    grads = [rng.normal(size=5) for _ in range(3)]
    schedule = exponential_decay(1e-2, 1e-3, 10)
    config = AdamConfig(lrs={"w": schedule}, betas=(0.8, 0.95), eps=1e-8)
    params = {"w": p0.copy()}
    state = adam_init(params)
    for g in grads:
        params, state = adam_update({"w": g}, state, params, config)
    expected_p, expected_m, expected_v = hand_adam(p0, grads, [schedule(s) for s in range(3)], 0.8, 0.95, 1e-8)
    # same IEEE operations in the same order: bitwise equal
    np.testing.assert_array_equal(params["w"], expected_p)
    np.testing.assert_array_equal(state["m"]["w"], expected_m)
    np.testing.assert_array_equal(state["v"]["w"], expected_v)
    assert state["step"]["w"] == 3


def test_bias_correction_at_step_one():
    # m_hat = g, v_hat = g^2 after one step: the update is -lr * g / (|g| + eps) = -lr sign(g)
    g = np.array([3.0, -1e-3, 250.0, -7.0])
    params = {"w": np.zeros(4)}
    params, _ = adam_update({"w": g}, adam_init(params), params, AdamConfig(lrs={"w": 0.1}))
    # bias corrections 1 - b^1 divide out up to rounding (a few ulp): rtol 1e-15
    np.testing.assert_allclose(params["w"], -0.1 * g / (np.abs(g) + ADAM_EPS), rtol=1e-15)
    # without bias correction the first step would be -lr (1 - b1) / sqrt(1 - b2) g/|g| = -0.316 lr sign(g)
    np.testing.assert_allclose(params["w"], -0.1 * np.sign(g), rtol=2e-12)  # eps / |g| <= 1e-12


def test_converges_on_ill_conditioned_quadratic():
    rng = np.random.default_rng(1)
    Q, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    A = Q @ np.diag([100.0, 10.0, 1.0, 1.0]) @ Q.T  # condition number 100
    c = rng.normal(size=4)
    config = AdamConfig(lrs={"*": exponential_decay(0.1, 1e-5, 3000)})
    params = {"x": np.zeros(4)}
    state = adam_init(params)
    for _ in range(3000):
        params, state = adam_update({"x": A @ (params["x"] - c)}, state, params, config)
    # the final step length is <= 1e-5: the iterate must be within a few final step lengths
    np.testing.assert_allclose(params["x"], c, rtol=0, atol=1e-4)


def test_converges_on_rosenbrock():
    def grad(p):
        x, y = p
        return np.array([-2.0 * (1.0 - x) - 400.0 * x * (y - x * x), 200.0 * (y - x * x)])

    config = AdamConfig(lrs={"*": exponential_decay(5e-2, 1e-5, 10000)})
    params = {"xy": np.array([-1.5, 2.0])}  # the far side of the banana
    state = adam_init(params)
    for _ in range(10000):
        params, state = adam_update({"xy": grad(params["xy"])}, state, params, config)
    # tolerance: 10x the residual measured with this schedule (3.5e-5 in y, 1.8e-5 in x)
    np.testing.assert_allclose(params["xy"], [1.0, 1.0], rtol=0, atol=4e-4)


def get_expon_lr_func(lr_init, lr_final, lr_delay_steps=0, lr_delay_mult=1.0, max_steps=1000000):
    """3DGS's utils/general_utils.py:get_expon_lr_func, transcribed."""
    def helper(step):
        if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
            return 0.0
        if lr_delay_steps > 0:
            delay_rate = lr_delay_mult + (1 - lr_delay_mult) * np.sin(0.5 * np.pi * np.clip(step / lr_delay_steps, 0, 1))
        else:
            delay_rate = 1.0
        t = np.clip(step / max_steps, 0, 1)
        log_lerp = np.exp(np.log(lr_init) * (1 - t) + np.log(lr_final) * t)
        return delay_rate * log_lerp
    return helper


def test_schedules():
    s = exponential_decay(1.6e-4, 1.6e-6, 30000)
    assert s(0) == pytest.approx(1.6e-4, rel=1e-15)
    assert s(30000) == pytest.approx(1.6e-6, rel=1e-14)
    assert s(60000) == pytest.approx(1.6e-6, rel=1e-14)
    assert s(15000) == pytest.approx(1.6e-5, rel=1e-14)  # geometric mean half way
    assert s(-1) == 0.0
    delayed = exponential_decay(1e-2, 1e-4, 100, delay_steps=20, delay_mult=0.01)
    ref = get_expon_lr_func(1e-2, 1e-4, 20, 0.01, 100)
    for step in [0, 1, 7, 20, 21, 50, 100, 150]:
        assert delayed(step) == pytest.approx(float(ref(step)), rel=1e-14), step
    assert delayed(0) == pytest.approx(1e-4, rel=1e-14)  # delay_mult * lr_init
    assert exponential_decay(0.0, 0.0, 10)(3) == 0.0
    assert constant(3e-3)(0) == 3e-3 and constant(3e-3)(10**6) == 3e-3
    with pytest.raises(ValueError, match="both > 0"):
        exponential_decay(1e-2, 0.0, 10)
    with pytest.raises(ValueError, match="max_steps"):
        exponential_decay(1e-2, 1e-3, 0)
    with pytest.raises(ValueError, match="Constant.lr"):
        constant(-1.0)


def test_schedule_uses_per_block_step():
    config = AdamConfig(lrs={"a": exponential_decay(1.0, 1e-2, 2), "b": exponential_decay(1.0, 1e-2, 2)})
    params = {"a": np.zeros(1), "b": np.zeros(1)}
    state = adam_init(params)
    g = {"a": np.ones(1), "b": np.ones(1)}
    params, state = adam_update({"a": g["a"]}, state, params, config)  # b not trained yet
    params, state = adam_update(g, state, params, config)
    assert state["step"] == {"a": 2, "b": 1}
    # b's first update used lr(0) = 1 and a full-size step: -1 (up to eps)
    np.testing.assert_allclose(params["b"], [-1.0], rtol=1e-12)
    # a: -1 (lr(0)) then -lr(1) = -0.1
    np.testing.assert_allclose(params["a"], [-1.1], rtol=1e-12)


def test_missing_blocks_are_left_alone_and_inputs_not_modified():
    rng = np.random.default_rng(2)
    params = {"static.means": rng.normal(size=(3, 3)), "static.colors": rng.normal(size=(3, 3))}
    state = adam_init(params)
    before = {k: v.copy() for k, v in params.items()}
    config = AdamConfig(lrs={"means": 0.1, "colors": 0.2})
    new_params, new_state = adam_update({"static.means": rng.normal(size=(3, 3)), "static.colors": None},
                                        state, params, config)
    assert new_params["static.colors"] is params["static.colors"]
    assert new_state["m"]["static.colors"] is state["m"]["static.colors"]
    assert new_state["step"]["static.colors"] == 0 and new_state["step"]["static.means"] == 1
    for k in params:
        np.testing.assert_array_equal(params[k], before[k])
    np.testing.assert_array_equal(state["m"]["static.means"], 0.0)
    assert state["step"]["static.means"] == 0
    assert not np.array_equal(new_params["static.means"], params["static.means"])


def test_learning_rate_lookup_order():
    config = AdamConfig(lrs={"dynamic.means": 1.0, "means": 2.0, "*": 3.0})
    assert config.lr("dynamic.means", 0) == 1.0
    assert config.lr("static.means", 0) == 2.0
    assert config.lr("static.colors", 0) == 3.0
    with pytest.raises(ValueError, match="no learning rate for block 'static.colors'"):
        AdamConfig(lrs={"means": 1.0}).lr("static.colors", 0)


def test_config_round_trips_through_json():
    config = AdamConfig(lrs={"means": exponential_decay(1.6e-4, 1.6e-6, 30000, 5, 0.1), "*": 1e-3},
                        betas=(0.9, 0.99), eps=1e-12)
    again = AdamConfig.from_dict(json.loads(json.dumps(config.to_dict())))
    assert again == config
    assert isinstance(again.lrs["*"], Constant)
    with pytest.raises(TypeError):
        config.lrs["x"] = 1.0  # read-only
    with pytest.raises(ValueError, match="betas"):
        AdamConfig(betas=(0.9, 1.0))
    with pytest.raises(ValueError, match="eps"):
        AdamConfig(eps=0.0)
    with pytest.raises(ValueError, match="unknown schedule kind"):
        AdamConfig(lrs={"*": {"kind": "cosine"}})


def test_select_and_extend_keep_moments_consistent():
    rng = np.random.default_rng(3)
    params = {"static.means": rng.normal(size=(5, 3)), "static.opacity_logits": rng.normal(size=5),
              "dynamic.means": rng.normal(size=(2, 3))}
    config = AdamConfig(lrs={"*": 0.05})
    state = adam_init(params)
    for _ in range(3):
        params, state = adam_update({k: rng.normal(size=v.shape) for k, v in params.items()}, state, params, config)
    keep = np.array([True, False, True, True, False])
    grads = {k: rng.normal(size=v.shape) for k, v in params.items()}
    # Adam is elementwise: pruning then stepping equals stepping then pruning, bitwise
    full_params, full_state = adam_update(grads, state, params, config)
    pruned_params = {k: (v[keep] if k.startswith("static.") else v) for k, v in params.items()}
    pruned_grads = {k: (v[keep] if k.startswith("static.") else v) for k, v in grads.items()}
    p2, s2 = adam_update(pruned_grads, adam_select(state, "static", keep), pruned_params, config)
    for k in params:
        sel = keep if k.startswith("static.") else slice(None)
        np.testing.assert_array_equal(p2[k], full_params[k][sel])
        np.testing.assert_array_equal(s2["m"][k], full_state["m"][k][sel])
        np.testing.assert_array_equal(s2["v"][k], full_state["v"][k][sel])
    assert s2["step"] == full_state["step"]

    extended = adam_extend(state, "dynamic", 4)
    assert extended["m"]["dynamic.means"].shape == (6, 3)
    np.testing.assert_array_equal(extended["m"]["dynamic.means"][2:], 0.0)
    np.testing.assert_array_equal(extended["v"]["dynamic.means"][:2], state["v"]["dynamic.means"])
    assert extended["m"]["static.means"] is state["m"]["static.means"]
    grown = dict(params, **{"dynamic.means": np.concatenate([params["dynamic.means"], np.zeros((4, 3))])})
    grown_params, _ = adam_update({"dynamic.means": np.ones((6, 3))}, extended, grown, config)
    assert np.all(np.isfinite(grown_params["dynamic.means"]))
    with pytest.raises(ValueError, match="adam_select / adam_extend"):
        adam_update({"dynamic.means": np.ones((6, 3))}, state, grown, config)
    with pytest.raises(ValueError, match="keep_mask has 4 entries"):
        adam_select(state, "static", np.ones(4, bool))


def test_new_block_gets_lazy_state():
    params = {"a": np.zeros(2)}
    state = adam_init(params)
    params["b"] = np.zeros(3)
    params, state = adam_update({"b": np.array([1.0, -2.0, 3.0])}, state, params, AdamConfig(lrs={"*": 0.5}))
    np.testing.assert_allclose(params["b"], [-0.5, 0.5, -0.5], rtol=1e-12)
    assert state["step"]["b"] == 1


def test_float32_stays_float32():
    rng = np.random.default_rng(4)
    params = {"w": rng.normal(size=4).astype(np.float32)}
    state = adam_init(params)
    params, state = adam_update({"w": rng.normal(size=4).astype(np.float32)}, state, params, AdamConfig(lrs={"*": 0.1}))
    assert params["w"].dtype == np.float32 and state["m"]["w"].dtype == np.float32 and state["v"]["w"].dtype == np.float32
    with pytest.raises(TypeError, match="float32"):
        adam_update({"w": np.zeros(4)}, state, params, AdamConfig(lrs={"*": 0.1}))


def test_gradient_errors():
    params = {"w": np.zeros(3)}
    state = adam_init(params)
    config = AdamConfig(lrs={"*": 0.1})
    with pytest.raises(ValueError, match=r"grads\['w'\] must have shape \(3,\)"):
        adam_update({"w": np.zeros(4)}, state, params, config)
    with pytest.raises(ValueError, match="NaN or inf"):
        adam_update({"w": np.array([0.0, np.nan, 0.0])}, state, params, config)
    with pytest.raises(ValueError, match="params does not have"):
        adam_update({"x": np.zeros(3)}, state, params, config)
    with pytest.raises(TypeError, match="AdamConfig"):
        adam_update({"w": np.zeros(3)}, state, params, {"lr": 0.1})


def test_row_sparse_update_leaves_other_rows_and_their_moments_alone():
    from d2gs_np.optim.adam import adam_update_rows

    rng = np.random.default_rng(3)
    p0 = {"camera.xi_start": rng.normal(size=(5, 6))}
    cfg = AdamConfig(lrs={"camera.xi_start": 1e-2})
    state = adam_init(p0)
    g = {"camera.xi_start": rng.normal(size=(5, 6))}
    p1, s1 = adam_update_rows(g, {"camera.xi_start": [2]}, state, p0, cfg)
    changed = np.any(p1["camera.xi_start"] != p0["camera.xi_start"], axis=1)
    np.testing.assert_array_equal(changed, [False, False, True, False, False])
    # A first step of Adam moves by lr * sign(g) (up to eps).
    np.testing.assert_allclose(p1["camera.xi_start"][2] - p0["camera.xi_start"][2],
                               -1e-2 * np.sign(g["camera.xi_start"][2]), rtol=1e-12)
    # Row 4's first update later is again a bias-corrected first step (its own count is 0),
    # and row 2 does not move on stale momentum meanwhile.
    g2 = {"camera.xi_start": rng.normal(size=(5, 6))}
    p2, s2 = adam_update_rows(g2, {"camera.xi_start": [4]}, s1, p1, cfg)
    np.testing.assert_array_equal(p2["camera.xi_start"][2], p1["camera.xi_start"][2])
    np.testing.assert_allclose(p2["camera.xi_start"][4] - p1["camera.xi_start"][4],
                               -1e-2 * np.sign(g2["camera.xi_start"][4]), rtol=1e-12)
    np.testing.assert_array_equal(s2["row_step"]["camera.xi_start"], [0, 0, 1, 0, 1])
    # Dense updates and pruning keep the row counts.
    p3, s3 = adam_update({}, s2, p2, cfg)
    assert "row_step" in s3
    with pytest.raises(ValueError, match="rows"):
        adam_update_rows(g2, {}, s2, p2, cfg)


# ------------------------------------------------------------- lr_step_scale (time-budgeted runs)
def _decay_setup():
    rng = np.random.default_rng(3)
    params = {"a.x": rng.normal(size=(5, 3)), "cam.r": rng.normal(size=(4, 2))}
    grads = [{"a.x": rng.normal(size=(5, 3))} for _ in range(6)]
    return params, grads


def test_lr_step_scale_one_is_bitwise_the_default():
    params, grads = _decay_setup()
    cfg = adam.AdamConfig(lrs={"a.x": adam.exponential_decay(1e-2, 1e-4, 10)})
    p1, s1 = params, adam.adam_init(params)
    p2, s2 = params, adam.adam_init(params)
    for g in grads:
        p1, s1 = adam.adam_update(g, s1, p1, cfg)
        p2, s2 = adam.adam_update(g, s2, p2, cfg, lr_step_scale=1.0)
    assert np.array_equal(p1["a.x"], p2["a.x"])


def test_lr_step_scale_reads_the_schedule_further_along():
    # scale 2 on a decay over 10 steps reads lr(2 k): the same as a decay over 5 steps read at k
    # (the log-linear decay depends on step / max_steps only), while the bias correction is unchanged.
    params, grads = _decay_setup()
    fast = adam.AdamConfig(lrs={"a.x": adam.exponential_decay(1e-2, 1e-4, 10)})
    short = adam.AdamConfig(lrs={"a.x": adam.exponential_decay(1e-2, 1e-4, 5)})
    p1, s1 = params, adam.adam_init(params)
    p2, s2 = params, adam.adam_init(params)
    for g in grads:
        p1, s1 = adam.adam_update(g, s1, p1, fast, lr_step_scale=2.0)
        p2, s2 = adam.adam_update(g, s2, p2, short)
    np.testing.assert_allclose(p1["a.x"], p2["a.x"], rtol=0, atol=1e-15)
    p3, _ = adam.adam_update(grads[0], adam.adam_init(params), params, fast)
    assert not np.allclose(p1["a.x"], p3["a.x"])
    # row-sparse updates read their rows' visit counts the same way
    cfg_r = adam.AdamConfig(lrs={"cam.r": adam.exponential_decay(1e-2, 1e-4, 10)})
    short_r = adam.AdamConfig(lrs={"cam.r": adam.exponential_decay(1e-2, 1e-4, 5)})
    g = {"cam.r": np.ones((4, 2))}
    q1, t1 = params, adam.adam_init(params)
    q2, t2 = params, adam.adam_init(params)
    for _ in range(4):
        q1, t1 = adam.adam_update_rows(g, {"cam.r": [1]}, t1, q1, cfg_r, lr_step_scale=2.0)
        q2, t2 = adam.adam_update_rows(g, {"cam.r": [1]}, t2, q2, short_r)
    np.testing.assert_allclose(q1["cam.r"], q2["cam.r"], rtol=0, atol=1e-15)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), True])
def test_lr_step_scale_must_be_positive_and_finite(bad):
    params, grads = _decay_setup()
    cfg = adam.AdamConfig(lrs={"*": 1e-3})
    with pytest.raises(ValueError, match="lr_step_scale"):
        adam.adam_update(grads[0], adam.adam_init(params), params, cfg, lr_step_scale=bad)
