"""The L_iso loss term (train.terms.Isometry): entered by its weight and left out without a dynamic
set, its value and gradient those of losses/isometry.py on the dynamic blocks at the step frame's
time (checked against central differences through the term), 0 in the warm-up, its neighbour
lists found at mid-clip and checkpointed for an exact resume, and the term in a training run."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.losses.isometry import isometry_fwd, pair_floor
from d2gs_np.losses.smoothness import knn
from d2gs_np.scene.deformation import deform_basis
from d2gs_np.train.config import DensifyConfig, ExperimentConfig, LossConfig, TrainConfig
from d2gs_np.train.terms import TermInputs, loss_terms
from d2gs_np.train.trainer import Trainer
from run_fixtures import copy_run_for_resume



def _config(iters, weight, **train):
    base = dict(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0, prune_every=0)
    base.update(train)
    return ExperimentConfig(train=TrainConfig(**base), loss=LossConfig(lambda_iso=weight, lambda_freq=0.0))


class _Stage:
    def __init__(self, static_only):
        self.static_only = static_only


def test_entered_by_its_weight_and_left_out_without_a_dynamic_set(dynamic_scene, static_scene, tmp_path):
    notes = []
    terms = loss_terms(LossConfig(lambda_iso=0.1, lambda_freq=0.0), note=notes.append)
    assert [t.name for t in terms] == ["photometric", "iso"] and terms[1].weight == 0.1
    assert [p.name for p in terms[1].plugins] == ["iso_knn"]
    assert any(n.startswith("L_iso: weight 0.1") for n in notes)
    assert [t.name for t in loss_terms(LossConfig(lambda_freq=0.0))] == ["photometric"]
    tr = Trainer(static_scene, _config(1, 0.1), tmp_path / "static")
    assert [t.name for t in tr.terms] == ["photometric"] and "iso_knn" not in [p.name for p in tr.plugins]
    assert any("L_iso: left out" in n for n in tr.log.notes)
    # with L_ts as well each term keeps its own lists (L_ts's by base position, L_iso's at mid-clip)
    both = Trainer(dynamic_scene, _config(1, 0.1).replace(loss=LossConfig(lambda_iso=0.1, lambda_ts=1.0)),
                   tmp_path / "both")
    assert {"knn", "iso_knn"} <= {p.name for p in both.plugins}


def test_value_and_gradient_are_the_loss_at_the_step_frames_time(dynamic_scene, tmp_path):
    tr = Trainer(dynamic_scene, _config(1, 0.3), tmp_path / "run")
    term = next(t for t in tr.terms if t.name == "iso")
    model, k = tr.model, 2
    rng = np.random.default_rng(0)
    C = model.params["dynamic.deform_means"]
    params = dict(model.params, **{"dynamic.deform_means": C + 0.05 * rng.normal(size=C.shape)})
    m = model.replace(params=params)

    def value(p):
        return term.fwd(TermInputs({}, None, None, m.replace(params=p), k, _Stage(False)))

    v, saved = value(params)
    A0 = params["dynamic.means"]
    # the lists were built on the initial model, among its mid-clip positions (not its base ones)
    mid = A0 + np.einsum("k,nkd->nd", deform_basis(0.5, m.config.deform)[0], C)
    nb = knn(mid, 8)
    np.testing.assert_array_equal(term.knn.lists, nb)
    assert not np.array_equal(nb, knn(A0, 8))
    expect = isometry_fwd(A0, params["dynamic.deform_means"], nb, float(m.times[k]), 0.25, pair_floor(A0, nb),
                          m.config.deform)[0]
    assert v == expect and v > 0
    grads = term.bwd(saved).params
    assert set(grads) == {"dynamic.means", "dynamic.deform_means"}
    # central differences through the term, float64 (h = 1e-6 on coordinates ~0.1-1: relative error ~1e-8)
    for name, idxs in (("dynamic.means", [(0, 0), (3, 2)]), ("dynamic.deform_means", [(0, 0, 1), (5, 3, 0)])):
        x = params[name]
        for idx in idxs:
            d = np.zeros_like(x)
            d[idx] = 1e-6
            num = (value(dict(params, **{name: x + d}))[0] - value(dict(params, **{name: x - d}))[0]) / 2e-6
            assert term.weight * num == pytest.approx(grads[name][idx], rel=1e-5, abs=1e-10)
    # the warm-up renders the static set alone: nothing to hold
    assert term.fwd(TermInputs({}, None, None, m, k, _Stage(True))) == (0.0, None)


def test_training_logs_the_term_and_it_holds_the_distances(dynamic_scene, tmp_path):
    a = Trainer(dynamic_scene, _config(8, 1.0, warmup_fraction=0.0, deform_fraction=0.0), tmp_path / "a")
    a.run()
    rows = a.log.rows
    vals = [r["loss_iso"] for r in rows]
    assert all(np.isfinite(vals)) and max(vals) > 0
    r = rows[-1]
    assert r["loss"] == pytest.approx(r["loss_photometric"] + 1.0 * r["loss_iso"], rel=1e-12)
    b = Trainer(dynamic_scene, _config(8, 0.0, warmup_fraction=0.0, deform_fraction=0.0), tmp_path / "b")
    b.run()
    assert "loss_iso" not in b.log.rows[-1]
    assert not np.array_equal(a.params["dynamic.deform_means"], b.params["dynamic.deform_means"])


def test_resume_is_exact_with_the_term_and_densification(dynamic_scene, tmp_path):
    dens = DensifyConfig(enabled=True, every=3, start_fraction=0.0, stop_fraction=1.0, grad_threshold_ndc=1e-6)
    cfg = _config(10, 0.5, checkpoint_every=5).replace(densify=dens)
    cfg = cfg.replace(loss=dataclasses.replace(cfg.loss, ts_knn_every=4))
    full = Trainer(dynamic_scene, cfg, tmp_path / "full")
    full.run()
    copy_run_for_resume(tmp_path / "full", tmp_path / "part")
    resumed = Trainer(dynamic_scene, cfg, tmp_path / "part", resume=True)
    assert resumed.step_index == 5
    resumed.run()
    for name in full.params:
        np.testing.assert_array_equal(resumed.params[name], full.params[name], err_msg=name)
    lists = [next(p for p in t.plugins if p.name == "iso_knn").lists for t in (full, resumed)]
    np.testing.assert_array_equal(lists[0], lists[1])


def test_config_validates_the_term():
    with pytest.raises(ValueError, match="lambda_iso"):
        LossConfig(lambda_iso=-1.0)
    with pytest.raises(ValueError, match="iso_time_offset"):
        LossConfig(iso_time_offset=0.0)
    with pytest.raises(ValueError, match="iso_time_offset"):
        LossConfig(iso_time_offset=1.5)
