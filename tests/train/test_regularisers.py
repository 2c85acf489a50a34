"""The regularisers in training: loss terms entered by their LossConfig weights, their gradients on
the parameter blocks (central FD through the term API), the neighbour-list plugin (rebuilt after
any change of the dynamic rows, checkpointed for an exact resume), L_ts left out without a
dynamic set, the log columns and the config's validation."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.losses.smoothness import knn
from d2gs_np.train.config import METHOD_REGULARISER_WEIGHTS, ExperimentConfig, LossConfig, TrainConfig
from d2gs_np.train.plugins import NeighbourRefresh
from d2gs_np.train.terms import TermInputs, loss_terms
from d2gs_np.train.trainer import Trainer
from run_fixtures import copy_run_for_resume

# Central FD of a term's weighted value, h = 1e-6, on model parameters of size ~0.1-1: the terms
# are smooth there (no coincident neighbours, opacities away from the clamp), rounding of values
# ~1 gives ~1e-10; 1e-8 still catches a wrong factor or a missing weight on gradients ~1e-3..1.
FD_H = 1e-6
FD_TOL = 1e-8


def _config(iters=12, loss=None, **train):
    base = dict(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0, prune_every=0)
    base.update(train)
    return ExperimentConfig(train=TrainConfig(**base), loss=loss or LossConfig())


ALL_ON = LossConfig(**METHOD_REGULARISER_WEIGHTS)


def test_terms_enter_by_their_weights():
    # the default: L_freq at the method's weight, on the static pixels only; the other terms off
    default = loss_terms(LossConfig())
    assert [t.name for t in default] == ["photometric", "freq"] and default[1].weight == 0.002
    assert LossConfig().freq_static_only
    assert [t.name for t in loss_terms(LossConfig(lambda_freq=0.0))] == ["photometric"]
    assert [t.name for t in loss_terms(ALL_ON)] == ["photometric", "ts", "gs", "freq"]
    assert [t.name for t in loss_terms(LossConfig(lambda_gs=0.5, lambda_freq=0.0))] == ["photometric", "gs"]
    weights = {t.name: t.weight for t in loss_terms(ALL_ON)}
    assert weights == {"photometric": 1.0, "ts": 1.0, "gs": 0.01, "freq": 0.002}


def test_l_ts_is_left_out_without_a_dynamic_set(static_scene, tmp_path):
    tr = Trainer(static_scene, _config(iters=2, loss=ALL_ON), tmp_path / "run")
    assert [t.name for t in tr.terms] == ["photometric", "gs", "freq", "reproj"]
    assert "knn" not in [p.name for p in tr.plugins]
    assert any("L_ts: left out (no dynamic set" in n for n in tr.log.notes)
    assert "loss_ts" in tr.left_out() and "loss_gs" not in tr.left_out()
    tr.run()


def _joint_inputs(tr):
    stage = tr.stages[-1]
    assert stage.name == "joint" and not stage.static_only
    f = tr.frames[1]
    out = {"image": np.full((f.height, f.width, 3), 0.5)}
    return TermInputs(out, f.image, None, tr.model, 1, stage)


def _fd_term(term, tr, block, entries):
    inputs = _joint_inputs(tr)
    _, saved = term.fwd(inputs)
    grad = term.bwd(saved).params[block]
    p0 = tr.model.params
    for idx in entries:
        vals = []
        for s in (1.0, -1.0):
            p = dict(p0)
            p[block] = p0[block].copy()
            p[block][idx] += s * FD_H
            x = inputs._replace(model=tr.model.replace(params=p))
            vals.append(term.weight * term.fwd(x)[0])
        fd = (vals[0] - vals[1]) / (2 * FD_H)
        assert abs(grad[idx] - fd) <= FD_TOL, (block, idx, grad[idx], fd)


def test_term_gradients_on_blocks_match_central_fd(dynamic_scene, tmp_path):
    tr = Trainer(dynamic_scene, _config(iters=20, loss=ALL_ON), tmp_path / "run")
    rng = np.random.default_rng(0)
    p = dict(tr.model.params)
    for f in ("deform_means", "deform_quats", "deform_colors"):  # a non-trivial deformation everywhere
        p[f"dynamic.{f}"] = 0.2 * rng.standard_normal(p[f"dynamic.{f}"].shape)
    tr.state = tr.state.with_params(p)
    terms = {t.name: t for t in tr.terms}
    n = p["dynamic.deform_means"].shape[0]
    for block in ("dynamic.deform_means", "dynamic.deform_quats", "dynamic.deform_colors"):
        shape = p[block].shape
        entries = [tuple(int(rng.integers(s)) for s in shape) for _ in range(6)]
        _fd_term(terms["ts"], tr, block, entries)
    for block in ("static.opacity_logits", "dynamic.opacity_logits"):
        entries = [(int(i),) for i in rng.integers(p[block].shape[0], size=5)]
        _fd_term(terms["gs"], tr, block, entries)
    assert n > 8  # the spatial term had a full K = 8 neighbours


def test_l_freq_term_reuses_a_frames_target_spectrum_only_while_target_and_mask_are_the_same(
        dynamic_scene, tmp_path):
    from d2gs_np.losses.frequency import frequency_fwd

    tr = Trainer(dynamic_scene, _config(iters=2, loss=LossConfig(lambda_freq=0.5)), tmp_path / "run")
    term = next(t for t in tr.terms if t.name == "freq")
    x = _joint_inputs(tr)
    rng = np.random.default_rng(3)
    render = rng.uniform(0.2, 0.8, x.target.shape)
    x = x._replace(out={"image": render})
    other = np.clip(x.target + 0.1 * rng.standard_normal(x.target.shape), 0.0, 1.0)
    mask = (rng.uniform(size=x.target.shape[:2]) > 0.4).astype(np.float64)
    # each call is the direct value of its own target and mask: a stale spectrum would give the
    # first target's value for the second (they differ by far more than rounding)
    for tgt, m in ((x.target, None), (x.target, None), (other, None), (other, mask), (other, mask * 0.5),
                   (x.target, None)):
        expected = frequency_fwd(render, tgt, m, term.cutoff)[0]
        assert term.fwd(x._replace(target=tgt, loss_mask=m))[0] == pytest.approx(expected, rel=1e-13)
    assert frequency_fwd(render, other)[0] != pytest.approx(frequency_fwd(render, x.target)[0], rel=1e-3)
    assert list(term._spectra) == [1]  # one entry for the one frame, refreshed in place


def test_l_freq_on_static_pixels_only_masks_the_moving_ones_out(dynamic_scene, tmp_path):
    from d2gs_np.losses.frequency import frequency_fwd

    cfg = _config(iters=2, loss=LossConfig(lambda_freq=0.5, freq_static_only=True))
    term = next(t for t in Trainer(dynamic_scene, cfg, tmp_path / "run").terms if t.name == "freq")
    rng = np.random.default_rng(4)
    x = _joint_inputs(Trainer(dynamic_scene, _config(iters=2), tmp_path / "run2"))
    x = x._replace(out={"image": rng.uniform(0.2, 0.8, x.target.shape)})
    moving = np.zeros(x.target.shape[:2], bool)
    moving[3:9, 5:20] = True
    static = (~moving).astype(np.float64)
    got = term.fwd(x._replace(motion_mask=moving))[0]
    assert got == pytest.approx(frequency_fwd(x.out["image"], x.target, static, term.cutoff)[0], rel=1e-13)
    assert got != pytest.approx(frequency_fwd(x.out["image"], x.target, None, term.cutoff)[0], rel=1e-3)
    assert term.fwd(x)[0] == pytest.approx(frequency_fwd(x.out["image"], x.target)[0], rel=1e-13)  # no mask
    with pytest.raises(ValueError, match="freq_static_only must be true or false"):
        LossConfig(freq_static_only=1)


def test_l_freq_on_static_pixels_gives_moving_pixels_no_gradient_and_an_all_moving_frame_zero(dynamic_scene, tmp_path):
    # The default term (LossConfig()) in the joint stage, where no loss mask is set: the mask is the
    # motion mask alone. Moving pixels must get exactly zero gradient (an unmasked render would give
    # them the FFT's global coupling), and a frame whose every pixel moves gives value 0 and a zero,
    # finite gradient (all bins at amplitude 0: the phase gate's stiff end).
    term = next(t for t in Trainer(dynamic_scene, _config(iters=2), tmp_path / "run").terms if t.name == "freq")
    x = _joint_inputs(Trainer(dynamic_scene, _config(iters=2), tmp_path / "run2"))
    x = x._replace(out={"image": np.random.default_rng(6).uniform(0.2, 0.8, x.target.shape)})
    moving = np.zeros(x.target.shape[:2], bool)
    moving[3:9, 5:20] = True
    value, saved = term.fwd(x._replace(motion_mask=moving))
    v_image = term.bwd(saved).render["image"]
    assert value > 0 and np.all(np.isfinite(v_image))
    assert np.all(v_image[moving] == 0.0) and np.any(v_image[~moving] != 0.0)
    value, saved = term.fwd(x._replace(motion_mask=np.ones_like(moving)))
    v_image = term.bwd(saved).render["image"]
    assert value == 0.0 and np.all(v_image == 0.0)


def test_the_trainer_warms_l_freqs_kernel_up_before_its_clock(dynamic_scene, tmp_path, monkeypatch):
    import d2gs_np.train.terms as terms_module

    calls = []
    monkeypatch.setattr(terms_module, "_frequency_warm_up", lambda: calls.append("warm"))
    tr = Trainer(dynamic_scene, _config(iters=1, loss=LossConfig(lambda_freq=0.01)), tmp_path / "run")
    tr.run()
    assert calls == ["warm"]
    assert any("JIT warm-up" in n for n in tr.log.notes)


def test_l_ts_uses_the_frames_time_and_is_off_in_warmup(dynamic_scene, tmp_path):
    tr = Trainer(dynamic_scene, _config(iters=20, loss=LossConfig(lambda_ts=1.0)), tmp_path / "run")
    term = tr.terms[1]
    x = _joint_inputs(tr)
    p = dict(tr.model.params)
    p["dynamic.deform_means"] = np.random.default_rng(1).standard_normal(p["dynamic.deform_means"].shape)
    x = x._replace(model=tr.model.replace(params=p))
    v1 = term.fwd(x)[0]
    v3 = term.fwd(x._replace(frame=3))[0]
    assert v1 > 0 and v3 > 0 and v1 != v3  # evaluated at the frame's own time
    warm = tr.stages[0]
    assert warm.static_only
    value, saved = term.fwd(x._replace(stage=warm))
    assert value == 0.0 and term.bwd(saved).params == {}


def test_training_with_every_regulariser_logs_each_term(dynamic_scene, tmp_path):
    tr = Trainer(dynamic_scene, _config(iters=10, loss=ALL_ON), tmp_path / "run")
    assert [p.name for p in tr.plugins][-2:] == ["knn", "reproj_depths"]
    tr.run()
    rows = tr.log.rows
    for name in ("loss_ts", "loss_gs", "loss_freq", "loss_reproj"):
        assert all(np.isfinite(r[name]) for r in rows), name
    joint = [r for r in rows if r["stage"] == "joint"]
    assert all(r["loss_ts"] > 0 and r["loss_gs"] > 0 and r["loss_freq"] > 0 for r in joint)
    # the step's loss is the weighted sum of the terms
    r = joint[-1]
    total = (r["loss_photometric"] + 1.0 * r["loss_ts"] + 0.01 * r["loss_gs"] + 0.002 * r["loss_freq"]
             + 0.001 * r["loss_reproj"])
    assert r["loss"] == pytest.approx(total, rel=1e-12)
    assert "loss_ts" not in tr.left_out() and "loss_reproj" not in tr.left_out()
    header = (tmp_path / "run" / "log.csv").read_text().splitlines()[0]
    assert header.endswith("loss_photometric,loss_ts,loss_gs,loss_freq,loss_reproj")


def test_default_run_has_only_the_static_frequency_term(dynamic_scene, tmp_path):
    tr = Trainer(dynamic_scene, _config(iters=2), tmp_path / "run")
    assert [t.name for t in tr.terms] == ["photometric", "freq"] and "knn" not in [p.name for p in tr.plugins]
    assert tr.terms[1].static_only
    assert any("L_ts, L_gs, L_reproj: off" in n and "loss = L_render + L_freq" in n for n in tr.log.notes)
    assert any(n.startswith("L_freq: weight 0.002, on the static pixels only") for n in tr.log.notes)
    off = Trainer(dynamic_scene, _config(iters=2, loss=LossConfig(lambda_freq=0.0)), tmp_path / "off")
    assert [t.name for t in off.terms] == ["photometric"]
    assert any("L_ts, L_gs, L_reproj, L_freq: off" in n for n in off.log.notes)
    assert not any(n.startswith("L_freq: weight") for n in off.log.notes)
    whole = Trainer(dynamic_scene, _config(iters=2, loss=LossConfig(freq_static_only=False)), tmp_path / "whole")
    assert any(n.startswith("L_freq: weight 0.002, on the whole image") for n in whole.log.notes)


def test_neighbour_lists_follow_every_change_of_the_dynamic_rows(dynamic_scene, tmp_path):
    tr = Trainer(dynamic_scene, _config(iters=4, loss=LossConfig(lambda_ts=1.0, ts_knn_every=1000)),
                 tmp_path / "run")
    tr.run()
    plugin = next(p for p in tr.plugins if isinstance(p, NeighbourRefresh))
    state = tr.state.replace(step=10, sched=10, prev_sched=10)  # no period entered
    built = plugin.lists  # built after step 0 (the marker was 0), not since: the means moved a little
    assert built.shape == (state.params["dynamic.means"].shape[0], 8)
    assert plugin.on_step(state) is state and plugin.lists is built  # nothing changed: no rebuild
    # prune row 0 and append a far-away copy of row 1: the same count, different rows
    n = state.params["dynamic.means"].shape[0]
    new = {k: v[1:2].copy() for k, v in state.params.items() if k.startswith("dynamic.")}
    new["dynamic.means"] = new["dynamic.means"] + 100.0
    keep = np.ones(n + 1, dtype=bool)
    keep[0] = False
    changed = state.resize_rows("dynamic", keep=keep, new=new)
    assert changed.params["dynamic.means"].shape[0] == n
    after = plugin.on_step(changed)
    assert plugin.lists is not built
    np.testing.assert_array_equal(plugin.lists, knn(changed.params["dynamic.means"], 8))
    assert np.all(after.rows[NeighbourRefresh.MARK]["dynamic"] == 1.0)
    # a removal alone changes the count
    fewer = after.resize_rows("dynamic", keep=np.arange(n) > 2)
    plugin.on_step(fewer)
    assert plugin.lists.shape == (n - 3, 8)


def test_resume_is_exact_with_l_ts_and_densification(dynamic_scene, tmp_path):
    from d2gs_np.train.config import DensifyConfig

    dens = DensifyConfig(enabled=True, every=3, start_fraction=0.0, stop_fraction=1.0, grad_threshold_ndc=1e-6)
    cfg = _config(iters=10, checkpoint_every=5, loss=dataclasses.replace(ALL_ON, ts_knn_every=4)).replace(
        densify=dens)
    full = Trainer(dynamic_scene, cfg, tmp_path / "full")
    knn_full = next(p for p in full.plugins if p.name == "knn")
    seen = {}

    class Spy:  # records the lists each step ends with
        name, timed = "spy", True

        def rows(self, params):
            return {}

        def on_init(self, model):
            pass

        def on_step(self, state):
            seen[state.step] = knn_full.lists.copy()
            return state

        def state_dict(self):
            return {}

        def load_state_dict(self, d):
            pass

    full.plugins.append(Spy())
    full.run()
    copy_run_for_resume(tmp_path / "full", tmp_path / "part")
    resumed = Trainer(dynamic_scene, cfg, tmp_path / "part", resume=True)
    assert resumed.step_index == 5
    knn_resumed = next(p for p in resumed.plugins if p.name == "knn")
    np.testing.assert_array_equal(knn_resumed.lists, seen[4])  # the lists the run had, not rebuilt ones
    assert np.all(resumed.state.rows[NeighbourRefresh.MARK]["dynamic"] == 1.0)
    resumed.run()
    for name in full.params:
        np.testing.assert_array_equal(resumed.params[name], full.params[name], err_msg=name)
    np.testing.assert_array_equal(knn_resumed.lists, knn_full.lists)


def test_loss_config_validates_and_round_trips():
    cfg = ExperimentConfig(loss=LossConfig(lambda_ts=1.0, ts_neighbours=4, lambda_freq=0.01, freq_cutoff=0.2))
    assert ExperimentConfig.from_json(cfg.to_json()) == cfg
    for bad, match in ((dict(lambda_gs=-1.0), "lambda_gs must be a finite number >= 0"),
                       (dict(lambda_ts=float("nan")), "lambda_ts"),
                       (dict(ts_time_offset=0.0), "ts_time_offset must be a finite number > 0"),
                       (dict(ts_neighbours=0), "ts_neighbours must be an integer >= 1"),
                       (dict(ts_knn_every=2.5), "ts_knn_every must be an integer"),
                       (dict(freq_cutoff=1.5), r"freq_cutoff must be a finite number in \(0, 1.41421\)"),
                       (dict(lambda_freq=True), "lambda_freq")):
        with pytest.raises(ValueError, match=match):
            LossConfig(**bad)


def test_l_ts_with_every_dynamic_gaussian_pruned(dynamic_scene, tmp_path):
    tr = Trainer(dynamic_scene, _config(iters=20, loss=LossConfig(lambda_ts=1.0)), tmp_path / "run")
    empty = tr.state.resize_rows("dynamic", keep=np.zeros(tr.params["dynamic.means"].shape[0], dtype=bool))
    term, plugin = tr.terms[1], tr.terms[1].knn
    plugin.on_step(empty.replace(step=1, sched=1, prev_sched=1))
    assert plugin.lists.shape == (0, 0)
    value, saved = term.fwd(_joint_inputs(tr)._replace(model=empty.model))
    grads = term.bwd(saved).params
    assert value == 0.0 and all(g.shape[0] == 0 for g in grads.values())
