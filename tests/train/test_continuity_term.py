"""The L_cont loss term (train.terms.ExposureContinuity): entered by its weight and left out without
the blur model, its value and gradient those of losses/continuity.py on the step frame's pairs
(the learned exposure's logit included, checked against central differences), and the term in a
training run (log column, weighted sum, the endpoints it changes)."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.blur.endpoints import XI_END, XI_START
from d2gs_np.blur.exposure import EXPOSURE_BLOCK
from d2gs_np.losses.continuity import continuity_fwd, pixel_weights, time_pairs
from d2gs_np.train.components import decide_components
from d2gs_np.train.config import ExperimentConfig, LossConfig, PoseSolverConfig, TrainConfig
from d2gs_np.train.terms import TermInputs, loss_terms
from d2gs_np.train.trainer import Trainer


def _config(iters, weight, **train):
    base = dict(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0, prune_every=0,
                warmup_fraction=0.0, deform_fraction=0.0)
    base.update(train)
    return ExperimentConfig(train=TrainConfig(**base), loss=LossConfig(lambda_continuity=weight, lambda_freq=0.0),
                            pose_solver=PoseSolverConfig(mode="off"))


def test_entered_by_its_weight_and_left_out_without_the_blur_model(noisy_scene):
    notes = []
    terms = loss_terms(LossConfig(lambda_continuity=0.01, lambda_freq=0.0), note=notes.append, scene=noisy_scene)
    assert [t.name for t in terms] == ["photometric", "continuity"]
    f = noisy_scene.frames[0].K[0, 0]
    np.testing.assert_array_equal(terms[1].weights, pixel_weights(f, noisy_scene.scene_scale))
    assert any(n.startswith("L_cont: weight 0.01") for n in notes)
    sharp = decide_components(noisy_scene, _config(1, 0.01, blur="off"))
    notes = []
    terms = loss_terms(LossConfig(lambda_continuity=0.01, lambda_freq=0.0), sharp, notes.append, scene=noisy_scene)
    assert [t.name for t in terms] == ["photometric"] and any("L_cont: left out" in n for n in notes)
    assert [t.name for t in loss_terms(LossConfig(lambda_freq=0.0), scene=noisy_scene)] == ["photometric"]


@pytest.mark.parametrize("learn", ["off", "on"])
def test_value_and_gradient_are_the_step_frames_pairs(noisy_scene, tmp_path, learn):
    tr = Trainer(noisy_scene, _config(1, 1.0, learn_exposure=learn), tmp_path / learn)
    term = next(t for t in tr.terms if t.name == "continuity")
    model, k = tr.model, 2
    rng = np.random.default_rng(0)
    params = dict(model.params, **{XI_START: model.params[XI_START] + rng.normal(size=model.params[XI_START].shape)
                                   * 1e-3})
    m = model.replace(params=params)

    def value(p):
        return term.fwd(TermInputs({}, None, None, m.replace(params=p), k, None))

    v, saved = value(params)
    expect = continuity_fwd(params[XI_START], params[XI_END], m.poses_ref, m.times, m.exposure_tau(),
                            time_pairs(m.times, [k]), term.weights)[0]
    assert v == expect and v > 0
    grads = term.bwd(saved).params
    assert set(grads) == ({XI_START, XI_END, EXPOSURE_BLOCK} if learn == "on" else {XI_START, XI_END})
    # rows of frames in no pair with k are zero; the step frame's row and its neighbours' are not
    near = set(time_pairs(m.times, [k]).ravel().tolist())
    for r in range(m.num_frames):
        assert (np.abs(grads[XI_START][r]).max() > 0) == (r in near)
    # central differences in float64 (h = 1e-7 on offsets of 1e-3: relative error ~1e-7 measured)
    for name in grads:
        x = params[name]
        for idx in [(k, 0), (k, 4), (k - 1, 5)] if x.ndim == 2 else [(0,)]:
            d = np.zeros_like(x)
            d[idx] = 1e-7
            num = (value(dict(params, **{name: x + d}))[0] - value(dict(params, **{name: x - d}))[0]) / 2e-7
            assert term.weight * num == pytest.approx(grads[name][idx], rel=1e-5, abs=1e-9)


def test_training_logs_the_term_and_it_moves_the_endpoints(noisy_scene, tmp_path):
    a = Trainer(noisy_scene, _config(6, 0.05), tmp_path / "a")
    a.run()
    rows = a.log.rows
    vals = [r["loss_continuity"] for r in rows]
    assert all(np.isfinite(vals)) and max(vals) > 0
    r = rows[-1]
    assert r["loss"] == pytest.approx(r["loss_photometric"] + 0.05 * r["loss_continuity"], rel=1e-12)
    b = Trainer(noisy_scene, dataclasses.replace(_config(6, 0.0)), tmp_path / "b")
    b.run()
    assert "loss_continuity" not in b.log.rows[-1]
    assert not np.array_equal(a.params[XI_START], b.params[XI_START])
