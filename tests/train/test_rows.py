"""resize_rows: parameters, Adam moments and per-row statistics change together, row for row."""
import numpy as np
import pytest

from d2gs_np.optim import adam
from d2gs_np.scene.gaussians import init_params
from d2gs_np.train.rows import resize_rows


def _setup(rng):
    p = init_params(rng.normal(size=(5, 3)), rng.uniform(size=(5, 3)), rng.normal(size=(3, 3)),
                    rng.uniform(size=(3, 3)), rng=rng)
    state = adam.adam_init(p)
    grads = {n: rng.normal(size=v.shape) for n, v in p.items()}
    p, state = adam.adam_update(grads, state, p, adam.AdamConfig(lrs={"*": 1e-2}))  # non-zero moments
    rows = {"stat/a": {"static": np.arange(5.0), "dynamic": np.arange(3.0) + 10}}
    return p, state, rows


def test_keep_selects_the_same_rows_everywhere_and_leaves_the_other_set():
    rng = np.random.default_rng(0)
    p, st, rows = _setup(rng)
    keep = np.array([True, False, True, True, False])
    p2, st2, rows2 = resize_rows(p, st, rows, "static", keep=keep)
    for name, v in p.items():
        if name.startswith("static."):
            np.testing.assert_array_equal(p2[name], v[keep])
            np.testing.assert_array_equal(st2["m"][name], st["m"][name][keep])
            np.testing.assert_array_equal(st2["v"][name], st["v"][name][keep])
        else:
            assert p2[name] is v and st2["m"][name] is st["m"][name]
    np.testing.assert_array_equal(rows2["stat/a"]["static"], [0.0, 2.0, 3.0])
    assert rows2["stat/a"]["dynamic"] is rows["stat/a"]["dynamic"]
    assert p["static.means"].shape[0] == 5  # inputs untouched


def test_new_rows_get_zero_moments_and_statistics_then_keep_applies_to_old_and_new():
    rng = np.random.default_rng(1)
    p, st, rows = _setup(rng)
    new = {n[len("dynamic."):]: v[:2].copy() for n, v in p.items() if n.startswith("dynamic.")}
    new = {f"dynamic.{f}": v for f, v in new.items()}
    keep = np.array([True, True, False, True, True])  # drop old row 2, keep both new rows
    p2, st2, rows2 = resize_rows(p, st, rows, "dynamic", keep=keep, new=new)
    assert p2["dynamic.means"].shape[0] == 4
    np.testing.assert_array_equal(p2["dynamic.means"][2:], p["dynamic.means"][:2])
    for name in (n for n in p2 if n.startswith("dynamic.")):
        assert st2["m"][name].shape == p2[name].shape
        assert not st2["m"][name][2:].any() and not st2["v"][name][2:].any()
    np.testing.assert_array_equal(rows2["stat/a"]["dynamic"], [10.0, 11.0, 0.0, 0.0])


def test_a_wrong_mask_is_an_error():
    rng = np.random.default_rng(2)
    p, st, rows = _setup(rng)
    with pytest.raises(ValueError, match="keep must have shape"):
        resize_rows(p, st, rows, "static", keep=np.ones(4, bool))
    with pytest.raises(ValueError, match="prefix"):
        resize_rows(p, st, rows, "camera", keep=np.ones(4, bool))
