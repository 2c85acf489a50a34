"""The trainer end to end on tiny synthetic scenes: it learns, leaves out what a scene does not
need (and never calls the skipped code), resumes exactly, respects the time budget, and
rejects bad input before doing any work."""
import csv
import dataclasses
import json

import numpy as np
import pytest

from d2gs_np.blur.render import _blur_render_fwd
from d2gs_np.blur.views import views_at_scale, views_for_length
from d2gs_np.data.synthetic import make_scene
from d2gs_np.scene import deformation
from d2gs_np.train.config import ExperimentConfig, LearningRates, PruneConfig, TrainConfig
from d2gs_np.render import RenderConfig
from d2gs_np.train.trainer import Trainer
from run_fixtures import copy_run_for_resume, step_and_checkpoint

TINY = dict(width=48, height=27, num_frames=6)


def _config(iters=12, **train):
    base = dict(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0, prune_every=0)
    base.update(train)
    return ExperimentConfig(train=TrainConfig(**base))


@pytest.fixture(scope="module")
def sharp_scene():
    return make_scene("sharp", 0, **TINY)


@pytest.fixture(scope="module")
def static_scene():
    return make_scene("static", 0, **TINY)


@pytest.fixture(scope="module")
def dynamic_scene():
    return make_scene("dynamic", 0, **TINY)


def test_training_reduces_the_loss(sharp_scene, tmp_path):
    cfg = _config(iters=60, progressive=False, warmup_fraction=0.0, deform_fraction=0.0)
    tr = Trainer(sharp_scene, cfg, tmp_path / "run")
    first = np.mean([tr.step(s).loss for s in range(6)])  # one epoch at the initial state
    tr.step_index = 6
    tr.run()
    last = np.mean([r["loss"] for r in tr.log.rows[-6:]])
    assert last < 0.8 * first, f"loss did not fall: first epoch {first:.4f}, last epoch {last:.4f}"


def test_sharp_scene_leaves_out_blur_and_never_calls_it(sharp_scene, tmp_path, monkeypatch):
    def forbidden(*a, **k):
        raise AssertionError("blur model called for a sharp scene")

    import d2gs_np.blur.render as blur_render
    import d2gs_np.train.model as train_model
    monkeypatch.setattr(blur_render, "blur_render_fwd", forbidden)
    monkeypatch.setattr(blur_render, "_blur_render_fwd", forbidden)
    monkeypatch.setattr(train_model, "_blur_render_fwd", forbidden)  # the name the training forward calls
    tr = Trainer(sharp_scene, _config(iters=4), tmp_path / "run")
    tr.run()
    assert not tr.components.blur
    assert not any(n.startswith(("camera.", "posenet.")) for n in tr.params)
    assert "blur_model" in tr.components.left_out()
    assert any("exposure_fraction = 0" in n for n in tr.log.notes)


def test_static_scene_leaves_out_dynamic_set_and_never_deforms(static_scene, tmp_path, monkeypatch):
    def forbidden(*a, **k):
        raise AssertionError("deformation evaluated for a scene with no moving pixels")

    monkeypatch.setattr(deformation, "deform_fwd", forbidden)
    monkeypatch.setattr(deformation, "_deform_fwd", forbidden)
    import d2gs_np.scene.render_inputs as model
    monkeypatch.setattr(model, "_deform_fwd", forbidden)  # the name render_inputs_fwd and the fast path call
    tr = Trainer(static_scene, _config(iters=20), tmp_path / "run")
    tr.run()
    assert not tr.components.dynamic
    assert not any(n.startswith("dynamic.") for n in tr.params)
    assert [s.name for s in tr.stages] == ["warmup", "joint"]
    assert {"dynamic_set", "deformation"} <= set(tr.components.left_out())


def test_dynamic_blurry_scene_uses_everything(dynamic_scene, tmp_path):
    tr = Trainer(dynamic_scene, _config(iters=10), tmp_path / "run")
    tr.run()
    assert tr.components.dynamic and tr.components.blur
    assert "camera.xi_start" in tr.params and "dynamic.deform_means" in tr.params
    assert [s.name for s in tr.stages] == ["warmup", "deform", "joint"]
    # The endpoints were trained: their spread moved away from the tiny initial one.
    meta = json.loads((tmp_path / "run" / "config.json").read_text())
    assert meta["blur"]["num_virtual"] == 8


@pytest.mark.parametrize("means_unit, backward_views", [("camera", 0), ("scene", 0), ("scene", 2)])
def test_resume_reproduces_an_uninterrupted_run(dynamic_scene, tmp_path, means_unit, backward_views):
    # "scene": the position rates' length comes from the initial points, which a resume no longer
    # has; it is read back from the checkpoint. backward_views = 2: the views each step's backward
    # runs through are drawn from (seed, step), so a resumed run draws the same ones. The camera
    # case runs the three-knot path: its middle knots and their moments resume too.
    cfg = _config(iters=10, lr=LearningRates(means_unit=means_unit))
    cfg = cfg.replace(blur=dataclasses.replace(cfg.blur, backward_views=backward_views))
    if means_unit == "camera":
        cfg = cfg.replace(trajectory=dataclasses.replace(cfg.trajectory, path="three_knot"))
    full = Trainer(dynamic_scene, cfg, tmp_path / "full")
    full.run()
    # Interrupted: stop after 6 steps (checkpoint), then resume in a new trainer.
    part_cfg = cfg.replace(train=dataclasses.replace(cfg.train, checkpoint_every=6, time_budget=None))
    part = Trainer(dynamic_scene, part_cfg, tmp_path / "part")
    step_and_checkpoint(part, 6)
    resumed = Trainer(dynamic_scene, part_cfg, tmp_path / "part", resume=True)
    assert resumed.step_index == 6
    resumed.run()
    for name in full.params:
        np.testing.assert_array_equal(resumed.params[name], full.params[name], err_msg=name)


def test_time_budget_stops_early_and_keeps_the_result(sharp_scene, tmp_path):
    cfg = _config(iters=10_000, time_budget=1e-9)
    tr = Trainer(sharp_scene, cfg, tmp_path / "run")
    result = tr.run()
    assert result.steps < 10_000
    assert (tmp_path / "run" / "final.npz").exists()
    assert any("time budget" in n for n in tr.log.notes)


def test_log_records_error_against_time(sharp_scene, tmp_path):
    tr = Trainer(sharp_scene, _config(iters=8, eval_every=4), tmp_path / "run")
    tr.run()
    rows = tr.log.rows
    secs = [r["seconds"] for r in rows]
    assert secs == sorted(secs) and secs[-1] > 0
    assert any(r["heldout_psnr"] is not None for r in rows), "held-out PSNR never logged"
    header = (tmp_path / "run" / "log.csv").read_text().splitlines()[0]
    assert header.startswith("step,seconds,stage,loss,train_psnr,heldout_psnr")


def test_bad_input_is_rejected_before_work(sharp_scene, tmp_path):
    one = dataclasses.replace(sharp_scene, frames=sharp_scene.frames[:1])
    with pytest.raises(ValueError, match="at least 2 frames"):
        Trainer(one, _config(), tmp_path / "a")
    bad_frames = [dataclasses.replace(f) for f in sharp_scene.frames]
    bad_frames[2] = dataclasses.replace(bad_frames[2], image=np.full_like(bad_frames[2].image, np.nan))
    with pytest.raises(ValueError, match="NaN"):
        Trainer(dataclasses.replace(sharp_scene, frames=bad_frames), _config(), tmp_path / "b")
    with pytest.raises(ValueError, match="TrainConfig.dynamic"):
        TrainConfig(dynamic="sometimes")
    with pytest.raises(ValueError, match="iters"):
        TrainConfig(iters=0)
    assert not (tmp_path / "a" / "final.npz").exists()


def test_config_round_trips_through_json_and_rejects_unknown_keys():
    cfg = ExperimentConfig(train=TrainConfig(iters=77, background=(0.1, 0.2, 0.3)))
    again = ExperimentConfig.from_json(cfg.to_json())
    assert again == cfg
    d = cfg.to_dict()
    d["train"]["itres"] = 5
    with pytest.raises(ValueError, match="itres"):
        ExperimentConfig.from_dict(d)


def test_pruning_keeps_optimizer_state_in_step(dynamic_scene, tmp_path):
    # A high threshold forces pruning of both sets; training must go on with consistent moments.
    cfg = _config(iters=12, prune_every=3, prune_opacity=0.1)
    tr = Trainer(dynamic_scene, cfg, tmp_path / "run")
    n0 = tr.num_gaussians()
    tr.run()
    assert tr.num_gaussians() < n0
    for name, p in tr.params.items():
        assert tr.adam_state["m"][name].shape == p.shape, name


def test_posenet_trajectory_and_learned_exposure_train(dynamic_scene, tmp_path):
    from d2gs_np.blur.config import TrajectoryConfig

    scene = dataclasses.replace(dynamic_scene, exposure_fraction=None)  # exposure unknown -> learned
    cfg = _config(iters=8).replace(trajectory=TrajectoryConfig(kind="posenet"))
    tr = Trainer(scene, cfg, tmp_path / "run")
    before = {n: v.copy() for n, v in tr.params.items() if n.startswith(("posenet.", "camera."))}
    assert "camera.exposure_logit" in before and "posenet.W0" in before
    tr.run()
    assert tr.components.learn_exposure
    for n, v in before.items():
        assert not np.array_equal(tr.params[n], v), f"{n} was not trained"
    assert any("exposure length learned" in n for n in tr.log.notes)
    assert any("trajectory model: posenet" in n for n in tr.log.notes)


def test_resume_after_a_time_budget_stop_continues_from_the_final_result(sharp_scene, tmp_path):
    cfg = _config(iters=8)
    first = Trainer(sharp_scene, cfg.replace(train=dataclasses.replace(cfg.train, time_budget=1e-9)), tmp_path / "r")
    first.run()
    stopped = first.step_index
    assert 0 < stopped < 8
    again = Trainer(sharp_scene, cfg, tmp_path / "r", resume=True)
    assert again.step_index == stopped
    again.run()
    steps = [int(line.split(",")[0]) for line in (tmp_path / "r" / "log.csv").read_text().splitlines()[1:]]
    assert steps == sorted(set(steps)), "log.csv has repeated or backwards steps after resume"


def test_resume_errors(sharp_scene, tmp_path):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        Trainer(sharp_scene, _config(), tmp_path / "empty", resume=True)
    Trainer(sharp_scene, _config(iters=2), tmp_path / "r").run()
    other = _config(iters=2, seed=5)
    with pytest.raises(ValueError, match="train.seed"):
        Trainer(sharp_scene, other, tmp_path / "r", resume=True)


def test_only_the_trained_frame_moves_its_camera_endpoints(dynamic_scene, tmp_path):
    tr = Trainer(dynamic_scene, _config(iters=20, warmup_fraction=0.0, deform_fraction=0.0), tmp_path / "r")
    before = tr.params["camera.xi_start"].copy()
    info = tr.step(0)
    moved = np.flatnonzero(np.any(tr.params["camera.xi_start"] != before, axis=1))
    np.testing.assert_array_equal(moved, [info.frame])


def test_warmup_survives_frames_whose_ssim_interior_is_all_moving(dynamic_scene, tmp_path):
    frames = []
    for f in dynamic_scene.frames:
        m = f.mask.copy()
        m[8:20, :] = True  # a band across the middle: at the smallest scale the SSIM interior is masked
        frames.append(dataclasses.replace(f, mask=m))
    scene = dataclasses.replace(dynamic_scene, frames=frames)
    tr = Trainer(scene, _config(iters=10, warmup_fraction=0.5), tmp_path / "r")
    tr.run()
    assert tr.step_index == 10


def test_a_partial_config_section_keeps_the_experiment_defaults():
    """A config JSON that names one key of a section takes the other keys from ExperimentConfig's
    own default for that section, not from the section class: training rasterises in float32
    (render.raster_float32) although RenderConfig() itself does not."""
    base = ExperimentConfig()
    cfg = ExperimentConfig.from_dict({"render": {"eps2d": 0.1}, "train": {"iters": 7}})
    assert cfg.render == dataclasses.replace(base.render, eps2d=0.1)
    assert cfg.render.raster_float32 != RenderConfig().raster_float32
    assert cfg.train == dataclasses.replace(base.train, iters=7)
    assert ExperimentConfig.from_dict(base.to_dict()) == base
    off = ExperimentConfig.from_dict({"render": {"raster_float32": False}})
    assert not off.render.raster_float32


def test_model_render_is_float64_while_steps_rasterise_in_float32(dynamic_scene, tmp_path):
    """Model.render (evaluation, reports) ignores render.raster_float32: the same params give
    bitwise the same image with the option on and off, and that image is the float64 render."""
    cfg = _config(iters=2)
    tr = Trainer(dynamic_scene, cfg, tmp_path / "run")
    assert tr.config.render.raster_float32
    tr.run()
    notes = json.loads((tmp_path / "run" / "log.json").read_text())["notes"]
    assert any("steps rasterise in float32" in n for n in notes), notes
    on = tr.model.render(1)
    off_model = tr.model.replace(config=cfg.replace(render=dataclasses.replace(cfg.render, raster_float32=False)))
    np.testing.assert_array_equal(on, off_model.render(1))


def test_float_and_bool_config_types_are_checked():
    with pytest.raises(ValueError, match="iters"):
        ExperimentConfig.from_dict({"train": {"iters": 3.0}})
    with pytest.raises(ValueError, match="progressive"):
        ExperimentConfig.from_dict({"train": {"progressive": "false"}})
    with pytest.raises(ValueError, match="log_every"):
        TrainConfig(log_every=0)
    from d2gs_np.train.config import LearningRates
    with pytest.raises(ValueError, match="LearningRates.means"):
        LearningRates(means=-1.0)


def test_densification_adds_gaussians_and_keeps_state_consistent(dynamic_scene, tmp_path):
    from d2gs_np.train.config import DensifyConfig

    cfg = _config(iters=12).replace(densify=DensifyConfig(enabled=True, every=4, start_fraction=0.0,
                                                          stop_fraction=1.0, grad_threshold_ndc=1e-9))
    tr = Trainer(dynamic_scene, cfg, tmp_path / "run")
    n0 = tr.num_gaussians()
    tr.run()
    assert tr.num_gaussians() > n0, "a tiny threshold must densify"
    assert any("densified" in n for n in tr.log.notes)
    for name, p in tr.params.items():
        assert tr.adam_state["m"][name].shape == p.shape, name
    from d2gs_np.train.densify import GRAD_COUNT, GRAD_SUM
    for name in (GRAD_SUM, GRAD_COUNT):
        for prefix in ("static", "dynamic"):
            assert tr.state.rows[name][prefix].shape[0] == tr.params[f"{prefix}.means"].shape[0], (name, prefix)


def test_the_clips_pixel_count_caps_densification_and_the_log_says_so(dynamic_scene, tmp_path):
    from d2gs_np.train.config import DensifyConfig

    pixels = sum(f.width * f.height for f in dynamic_scene.frames)
    probe = Trainer(dynamic_scene, _config(iters=1), tmp_path / "probe")
    n0 = probe.num_gaussians()
    # room for 6 more Gaussians by the clip's pixels (ceil of n0 + 5.5), far more by max_gaussians:
    # the pixels bind (the tiny threshold below would otherwise double the model)
    ppg = pixels / (n0 + 5.5)
    cfg = _config(iters=12).replace(densify=DensifyConfig(enabled=True, every=4, start_fraction=0.0, stop_fraction=1.0,
                                                          grad_threshold_ndc=1e-9, pixels_per_gaussian=ppg))
    tr = Trainer(dynamic_scene, cfg, tmp_path / "run")
    tr.run()
    assert any("densified" in n for n in tr.log.notes)
    assert tr.num_gaussians() <= n0 + 6
    assert any(f"densification: up to {n0 + 6} Gaussians ({pixels} observed pixels" in n for n in tr.log.notes)


def test_the_moving_pixels_cap_the_dynamic_set_and_the_log_says_so(dynamic_scene, tmp_path):
    from d2gs_np.train.config import DensifyConfig

    moving = sum(int(np.count_nonzero(f.mask)) for f in dynamic_scene.frames)
    dens = dict(enabled=True, every=4, start_fraction=0.0, stop_fraction=1.0, grad_threshold_ndc=1e-9)
    free = Trainer(dynamic_scene, _config(iters=12).replace(
        densify=DensifyConfig(**dens, dynamic_pixels_per_gaussian=0.0)), tmp_path / "free")
    d0 = free.params["dynamic.means"].shape[0]
    free.run()
    assert free.params["dynamic.means"].shape[0] > d0 + 2, "without the cap the tiny threshold grows the dynamic set"
    # room for 2 more dynamic Gaussians by the moving pixels (ceil of d0 + 1.5)
    ppg = moving / (d0 + 1.5)
    capped = Trainer(dynamic_scene, _config(iters=12).replace(
        densify=DensifyConfig(**dens, dynamic_pixels_per_gaussian=ppg)), tmp_path / "capped")
    capped.run()
    assert d0 < capped.params["dynamic.means"].shape[0] <= d0 + 2
    # the static set grows as it does without the cap (same candidates, same seeded children)
    assert capped.params["static.means"].shape[0] == free.params["static.means"].shape[0]
    assert any(f"the dynamic set up to {d0 + 2} ({moving} moving pixels" in n for n in capped.log.notes)


def test_opacity_reset_fires_inside_the_densification_window_only_and_resumes_exactly(dynamic_scene, tmp_path):
    from d2gs_np.train.config import DensifyConfig

    # schedule steps 1..12, densification from 3 to 9: resets at 4 and 8 (not 12, past the window)
    dens = DensifyConfig(enabled=True, every=3, start_fraction=0.25, stop_fraction=0.75, grad_threshold_ndc=1e-6,
                         opacity_reset_every=4, opacity_reset_value=0.02)
    cfg = _config(iters=12, checkpoint_every=6).replace(densify=dens)
    full = Trainer(dynamic_scene, cfg, tmp_path / "full")
    full.run()
    resets = [n for n in full.log.notes if "opacity reset to 0.02" in n]
    assert [n.split(":")[0] for n in resets] == ["step 4", "step 8"], resets
    assert all(int(n.split("(")[1].split(" ")[0]) > 0 for n in resets), "the trained opacities rise above 0.02"
    copy_run_for_resume(tmp_path / "full", tmp_path / "part")
    resumed = Trainer(dynamic_scene, cfg, tmp_path / "part", resume=True)
    resumed.run()
    for name in full.params:
        np.testing.assert_array_equal(resumed.params[name], full.params[name], err_msg=name)
    off = Trainer(dynamic_scene, _config(iters=12).replace(densify=dataclasses.replace(dens, opacity_reset_every=0)),
                  tmp_path / "off")
    off.run()
    assert not any("opacity reset" in n for n in off.log.notes)
    a, b = off.params["static.opacity_logits"], full.params["static.opacity_logits"]
    assert a.shape != b.shape or not np.array_equal(a, b), "the resets changed nothing"


def test_resume_is_exact_with_densification(dynamic_scene, tmp_path):
    from d2gs_np.train.config import DensifyConfig

    dens = DensifyConfig(enabled=True, every=3, start_fraction=0.0, stop_fraction=1.0, grad_threshold_ndc=1e-6)
    cfg = _config(iters=10, checkpoint_every=5).replace(densify=dens)
    full = Trainer(dynamic_scene, cfg, tmp_path / "full")
    full.run()
    # The run as it was after step 5 (densified at step 3; statistics of step 4 accumulated since),
    # resumed in another folder.
    copy_run_for_resume(tmp_path / "full", tmp_path / "part")
    resumed = Trainer(dynamic_scene, cfg, tmp_path / "part", resume=True)
    assert resumed.step_index == 5
    assert any(v.any() for v in resumed.state.rows["densify/count"].values()), "statistics were not restored"
    resumed.run()
    assert full.num_gaussians() > 0
    for name in full.params:
        np.testing.assert_array_equal(resumed.params[name], full.params[name], err_msg=name)


def test_heldout_is_evaluated_before_pruning_and_densification(dynamic_scene, tmp_path, monkeypatch):
    # The logged held-out PSNR must describe the model the Adam step produced: a split moves its
    # children apart and costs dB for a while, and eval_every shares multiples with the densify
    # period, so evaluating after densification would log only those transients.
    from d2gs_np.train.config import DensifyConfig
    from d2gs_np.train.plugins import Plugin

    dens = DensifyConfig(enabled=True, every=4, start_fraction=0.0, stop_fraction=1.0, grad_threshold_ndc=1e-9)
    cfg = _config(iters=9, eval_every=4).replace(densify=dens)

    class Count(Plugin):  # the number of Gaussians after all other plugins of the step
        name = "count"

        def on_step(self, state):
            counts.append(state.model.num_gaussians())
            return state

    counts, seen = [], []
    tr = Trainer(dynamic_scene, cfg, tmp_path / "run", plugins=[Count()])
    heldout = next(p for p in tr.plugins if p.name == "heldout_psnr")
    monkeypatch.setattr(heldout, "heldout", lambda model: seen.append(model.num_gaussians()) or {"psnr": 20.0,
                                                                                                  "depth_absrel": None})
    after_adam, step = [], tr.step

    def step_then_count(*args):  # the number of Gaussians the Adam step left
        record = step(*args)
        after_adam.append(tr.num_gaussians())
        return record

    monkeypatch.setattr(tr, "step", step_then_count)
    tr.run()
    assert any("densified" in n for n in tr.log.notes)
    assert seen == [after_adam[0], after_adam[4], after_adam[8]], (seen, after_adam)
    assert after_adam[4] < counts[4], "the test needs a densification at step 4"


def test_plugins_run_in_order_and_their_state_is_checkpointed_for_an_exact_resume(dynamic_scene, tmp_path):
    # A plugin that changes the model with its own random state (as a pose solver or a new
    # densification rule would): resuming from a checkpoint must continue it exactly.
    from d2gs_np.train.plugins import Plugin

    class Jitter(Plugin):
        name = "jitter"

        def __init__(self):
            self.rng = np.random.default_rng(7)
            self.calls = 0

        def on_step(self, state):
            self.calls += 1
            if state.step % 2:
                return state
            p = dict(state.params)
            p["static.colors"] = p["static.colors"] + 1e-3 * self.rng.normal(size=p["static.colors"].shape)
            return state.with_params(p)

        def state_dict(self):
            return {"rng": json.dumps(self.rng.bit_generator.state), "calls": self.calls,
                    "seen": np.arange(self.calls)}

        def load_state_dict(self, d):
            self.rng.bit_generator.state = json.loads(d["rng"])
            self.calls = d["calls"]
            assert np.array_equal(d["seen"], np.arange(self.calls))

    cfg = _config(iters=8, checkpoint_every=3)
    full = Trainer(dynamic_scene, cfg, tmp_path / "full", plugins=[Jitter()])
    assert [p.name for p in full.plugins][-1] == "jitter"
    full.run()
    copy_run_for_resume(tmp_path / "full", tmp_path / "part")
    jitter = Jitter()
    resumed = Trainer(dynamic_scene, cfg, tmp_path / "part", plugins=[jitter], resume=True)
    assert resumed.step_index == 6 and jitter.calls == 6
    resumed.run()
    for name in full.params:
        np.testing.assert_array_equal(resumed.params[name], full.params[name], err_msg=name)


def test_a_loss_term_added_to_the_list_enters_the_total_the_gradient_and_the_log(sharp_scene, tmp_path):
    from d2gs_np.train.terms import TermGrads

    class OpacityPull:  # a toy regulariser on parameters: weight * mean(opacity_logits)
        name, weight = "pull", 0.5

        def fwd(self, x):
            logits = x.model.params["static.opacity_logits"]
            return float(np.mean(logits)), logits.shape[0]

        def bwd(self, n):
            return TermGrads(render={}, params={"static.opacity_logits": np.full(n, self.weight / n)})

    cfg = _config(iters=3, progressive=False, warmup_fraction=0.0, deform_fraction=0.0)
    plain, pulled = Trainer(sharp_scene, cfg, tmp_path / "a"), Trainer(sharp_scene, cfg, tmp_path / "b")
    pulled.terms.append(OpacityPull())
    before = pulled.params["static.opacity_logits"].copy()
    a, b = plain.step(0), pulled.step(0)
    assert b.loss == a.loss + 0.5 * b.losses["pull"] and b.losses["pull"] == float(np.mean(before))
    assert not np.array_equal(plain.params["static.opacity_logits"], pulled.params["static.opacity_logits"])
    np.testing.assert_array_equal(plain.params["static.colors"], pulled.params["static.colors"])


# ------------------------------------------------------------- time budget: a finished schedule
def test_a_time_budget_buys_a_finished_schedule(dynamic_scene, tmp_path):
    # 10 000 steps can never run in 4 s here: the budget ends the run, and every schedule reads the
    # budget's progress, so the run still reaches full resolution and passes through every stage.
    cfg = _config(iters=10000, time_budget=4.0, progressive=True, log_every=1)
    cfg = cfg.replace(blur=dataclasses.replace(cfg.blur, n_schedule="fixed"))
    tr = Trainer(dynamic_scene, cfg, tmp_path / "run")
    out = tr.run()
    assert out.steps < 10000
    rows = tr.log.rows
    assert rows[-1]["scale"] == 1.0, rows[-1]
    assert rows[0]["scale"] < 1.0
    stages_seen = {r["stage"] for r in rows}
    assert stages_seen == {"warmup", "deform", "joint"}, stages_seen
    assert any("schedule complete" in str(n) for n in tr.log.notes)
    # the log states the progress the budget bought at each row: ahead of step/iters, never back
    progress = [r["progress"] for r in rows]
    assert all(b >= a for a, b in zip(progress, progress[1:]))
    assert progress[-1] == 1.0 and progress[0] > rows[0]["step"] / 10000
    assert {r["views"] for r in rows} == {8}  # blur model on, n_schedule fixed


def test_a_budget_is_spent_after_the_schedule_ends(sharp_scene, tmp_path):
    # 6 steps take well under the 3 s budget here: with stretch_to_budget (the default) the run
    # finishes its schedule by the step, then trains on at the schedule's end until the budget is
    # spent; without it, it ends after its 6 steps
    cfg = _config(iters=6, time_budget=3.0, progressive=True, log_every=1)
    tr = Trainer(sharp_scene, cfg, tmp_path / "stretched")
    out = tr.run()
    assert out.steps > 6 and out.train_seconds >= 3.0
    rows = tr.log.rows
    for r in rows:  # the schedule by the step while it lasts, then its end: the last stage, full scale
        sched = min(r["step"], 6)
        assert r["stage"] == tr.planner.stage_at(sched).name and r["scale"] == round(tr.planner.scale_at(sched), 4)
    assert rows[0]["scale"] < 1.0 and rows[-1]["progress"] == 1.0
    assert any("time budget of 3s reached" in str(n) for n in tr.log.notes)
    fixed = Trainer(sharp_scene, cfg.replace(train=dataclasses.replace(cfg.train, stretch_to_budget=False)),
                    tmp_path / "fixed")
    assert fixed.run().steps == 6


def test_without_a_budget_the_schedule_reads_the_step(dynamic_scene, tmp_path):
    cfg = _config(iters=20, progressive=True)
    tr = Trainer(dynamic_scene, cfg, tmp_path / "run")
    tr.run()
    for r in tr.log.rows:
        assert r["scale"] == round(tr.planner.scale_at(r["step"]), 4)
        assert r["stage"] == tr.planner.stage_at(r["step"]).name


# ------------------------------------------------------------- pruning rules in the trainer
def test_prune_removes_oversized_and_escaped_gaussians_and_keeps_state_in_step(dynamic_scene, tmp_path):
    tr = Trainer(dynamic_scene, _config(iters=4), tmp_path / "run")
    ns, nd = tr.params["static.means"].shape[0], tr.params["dynamic.means"].shape[0]
    p = dict(tr.params)
    big = np.array(p["static.log_scales"])
    from d2gs_np.train.plugins import Prune
    prune = Prune(tr.config, tr.extent, [f.mask for f in tr.frames])
    prune.on_init(tr.model)  # measures the scene's size from the initial points
    assert prune.extent >= tr.extent
    resumed = Prune(tr.config, 1.0, [])
    resumed.load_state_dict(prune.state_dict())  # a resumed run keeps the measured size
    assert resumed.extent == prune.extent
    big[0] = np.log(0.5 * prune.extent)  # over the 0.1 x extent rule
    p["static.log_scales"] = big
    # move dynamic Gaussian 0 far from every mask: the top-left corner region of frame 0's view,
    # at the depth of its seed
    d = np.array(p["dynamic.means"])
    coef = np.zeros_like(p["dynamic.deform_means"])
    f = tr.frames[0]
    from d2gs_np.geometry.camera import unproject_points

    free = np.argwhere(~tr.frames[0].mask)
    corner = free[np.argmin(free.sum(axis=1))]
    d[0] = unproject_points(np.array([[corner[1] + 0.5, corner[0] + 0.5]]), np.array([1.0]), f.cam_T_world, f.K)[0]
    p["dynamic.means"] = d
    p["dynamic.deform_means"] = coef
    tr.params = p
    tr.state, removed = prune.prune(tr.state)
    assert removed >= 2
    assert tr.params["static.means"].shape[0] <= ns - 1 and tr.params["dynamic.means"].shape[0] <= nd - 1
    assert not np.any(np.all(tr.params["static.log_scales"] == big[0], axis=1))
    for name, v in tr.params.items():
        if name.startswith(("static.", "dynamic.")):
            assert tr.adam_state["m"][name].shape == v.shape, name


def test_prune_runs_past_the_schedule_end_until_90_percent_of_the_budget(dynamic_scene, tmp_path):
    """With PruneConfig.past_schedule a run that trains on past its schedule keeps pruning (an oversized
    Gaussian grown there is removed) until 90 % of the budget; inside the schedule the window is
    90 % of the steps, as before, and without a budget there is no stretched phase."""
    from d2gs_np.train.plugins import Prune

    tr = Trainer(dynamic_scene, _config(iters=10, prune_every=5), tmp_path / "run")
    off = Prune(tr.config, tr.extent, [f.mask for f in tr.frames])  # the default: the schedule's window only
    assert off.active(tr.state.replace(sched=5, budget_fraction=None))
    assert not off.active(tr.state.replace(sched=40, budget_fraction=0.5))
    prune = Prune(tr.config.replace(prune=PruneConfig(past_schedule=True)), tr.extent, [f.mask for f in tr.frames])
    prune.on_init(tr.model)
    big = np.array(tr.params["static.log_scales"])
    big[0] = np.log(0.5 * prune.extent)  # over the 0.1 x extent rule
    tr.params = {**tr.params, "static.log_scales": big}
    n = tr.params["static.means"].shape[0]

    def at(sched, fraction):
        return tr.state.replace(sched=sched, prev_sched=sched - 1, budget_fraction=fraction)

    assert prune.active(at(5, None)) and not prune.active(at(9, None))  # 90 % of 10 steps
    assert not prune.active(at(10, None))  # no budget: the run ends at its schedule's end
    assert prune.active(at(40, 0.5)) and not prune.active(at(40, 0.95))
    assert not prune.active(at(9, 0.5))  # the schedule's own last 10 % stays unpruned
    kept = prune.on_step(at(40, 0.95))
    assert kept.params["static.means"].shape[0] == n  # past 90 % of the budget: left alone
    pruned = prune.on_step(at(40, 0.5))
    assert pruned.params["static.means"].shape[0] < n
    assert not np.any(np.all(pruned.params["static.log_scales"] == big[0], axis=1))


def test_the_loop_tells_plugins_how_much_of_the_budget_is_spent(sharp_scene, tmp_path):
    from d2gs_np.train.plugins import Plugin

    class Spy(Plugin):
        name = "spy"
        timed = False

        def __init__(self):
            self.seen = []

        def on_step(self, state):
            self.seen.append((state.sched, state.budget_fraction))
            return state

    for budget in (None, 1.0):
        tr = Trainer(sharp_scene, _config(iters=4, time_budget=budget), tmp_path / f"b{budget}")
        spy = Spy()
        tr.plugins = [*tr.plugins, spy]
        tr.run()
        fractions = [f for _, f in spy.seen]
        if budget is None:
            assert fractions == [None] * 4
        else:  # rises with the clock, and the last step spent the budget
            assert len(fractions) > 4 and all(b >= a > 0 for a, b in zip(fractions, fractions[1:]))
            assert fractions[-1] >= 1.0 and fractions[-2] < 1.0
            assert max(s for s, _ in spy.seen) > 4  # the stretched phase: schedule steps past iters


def test_a_timed_plugin_that_spends_the_budget_does_not_end_the_run_unmarked(sharp_scene, tmp_path):
    # The clock passes the 1 s budget inside a timed plugin of step 0. The run must go on to a step
    # that sees the budget spent and is marked last (plugins finalise on it); it used to stop at
    # the top of the loop with no step marked last (a race the test above met now and then).
    import time

    from d2gs_np.train.plugins import Plugin

    class Slow(Plugin):
        name = "slow"
        timed = True

        def __init__(self):
            self.seen = []

        def on_step(self, state):
            self.seen.append((state.step, state.last, state.budget_fraction))
            if state.step == 0:
                time.sleep(1.2)
            return state

    tr = Trainer(sharp_scene, _config(iters=4, time_budget=1.0), tmp_path / "run")
    slow = Slow()
    tr.plugins = [*tr.plugins, slow]
    tr.run()
    assert slow.seen[0][1] is False and slow.seen[0][2] < 1.0  # step 0 itself was within the budget
    assert len(slow.seen) == 2 and slow.seen[-1][1] is True and slow.seen[-1][2] >= 1.0


def test_position_rates_take_the_scene_size_as_their_unit(dynamic_scene, tmp_path):
    from d2gs_np.train.learning_rates import scene_extent, size_extent

    camera = Trainer(dynamic_scene, _config(iters=2, lr=LearningRates(means_unit="camera")), tmp_path / "camera")
    scene = Trainer(dynamic_scene, _config(iters=2), tmp_path / "scene")  # the default
    poses = np.stack([f.cam_T_world for f in dynamic_scene.frames])
    cam = scene_extent(poses, dynamic_scene.scene_scale)
    size = size_extent(poses, scene.params["static.means"], cam)
    assert camera.position_extent == cam and scene.position_extent == size
    assert size > 2 * cam  # the fixture's camera moves little against its depth, as a hand-held one does
    lr = LearningRates()
    for name, rate in (("static.means", lr.means), ("dynamic.deform_means", lr.deform)):
        assert scene.adam_config.lr(name, 0) == pytest.approx(rate * size, rel=1e-12)
        assert camera.adam_config.lr(name, 0) == pytest.approx(rate * cam, rel=1e-12)
    # other blocks do not depend on the unit
    assert scene.adam_config.lr("static.colors", 0) == camera.adam_config.lr("static.colors", 0)
    assert any("units of the scene's size" in n for n in scene.log.notes)
    with pytest.raises(ValueError, match=r"means_unit must be one of \('camera', 'scene'\)"):
        LearningRates(means_unit="extent")


def test_size_extent_follows_the_scene_when_the_camera_barely_moves():
    from d2gs_np.train.learning_rates import scene_extent, size_extent

    rng = np.random.default_rng(0)
    # forward-facing: camera centres within 0.1 of the origin, points on a wall 5 units away
    poses = []
    for c in rng.uniform(-0.1, 0.1, size=(6, 3)):
        T = np.eye(4)
        T[:3, 3] = -c  # identity rotation: centre = c
        poses.append(T)
    poses = np.stack(poses)
    pts = np.column_stack([rng.uniform(-2, 2, 500), rng.uniform(-1, 1, 500), np.full(500, 5.0)])
    cam = scene_extent(poses)
    centres = np.array([-T[:3, :3].T @ T[:3, 3] for T in poses])
    d = np.linalg.norm(pts - centres.mean(0), axis=1)
    assert cam < 0.25
    assert size_extent(poses, pts, cam) == 1.1 * np.percentile(d, 90)
    # a camera circling a small object: the camera extent is the larger and is kept
    assert size_extent(poses, 0.01 * pts, 10.0) == 10.0
    # no points: the camera extent
    assert size_extent(poses, np.zeros((0, 3)), cam) == cam


def test_n_schedule_renders_fewer_views_at_small_scales_and_n_at_full(dynamic_scene, tmp_path, monkeypatch):
    calls = []
    real = _blur_render_fwd

    def spy(*args, **kwargs):
        calls.append((args[7], args[10]))  # (render width, n)
        return real(*args, **kwargs)

    from d2gs_np.train import model as model_module
    monkeypatch.setattr(model_module, "_blur_render_fwd", spy)
    cfg = _config(iters=12, warmup_fraction=0.0, deform_fraction=0.0)
    cfg = cfg.replace(blur=dataclasses.replace(cfg.blur, n_schedule="scale"),
                      schedule=dataclasses.replace(cfg.schedule, r0=0.2, ramp_fraction=0.5))
    Trainer(dynamic_scene, cfg, tmp_path / "run").run()
    width = dynamic_scene.frames[0].width
    assert calls, "the blur model was never called"
    for w, n in calls:
        assert n == views_at_scale(8, min(1.0, w / width), "scale")
    assert min(n for _, n in calls) < 8 and calls[-1] == (width, 8)


def test_length_schedule_gives_each_frame_the_views_its_blur_length_needs(dynamic_scene, tmp_path, monkeypatch):
    calls = []
    real = _blur_render_fwd

    def spy(*args, **kwargs):
        calls.append(args[10])  # n
        return real(*args, **kwargs)

    from d2gs_np.train import model as model_module
    monkeypatch.setattr(model_module, "_blur_render_fwd", spy)
    lengths = []
    from d2gs_np.blur import views
    real_length = views.blur_length_px

    def length_spy(*args, **kwargs):
        lengths.append(real_length(*args, **kwargs))
        return lengths[-1]

    monkeypatch.setattr(views, "blur_length_px", length_spy)  # the name frame_views calls
    cfg = _config(iters=10, warmup_fraction=0.0, deform_fraction=0.0)
    cfg = cfg.replace(blur=dataclasses.replace(cfg.blur, n_schedule="length", view_spacing_px=1.0))
    run = tmp_path / "run"
    Trainer(dynamic_scene, cfg, run).run()
    assert len(calls) == 10
    # two lengths per step (static set, dynamic set at the sub-frame times); n from the longer
    per_step = [max(lengths[2 * i], lengths[2 * i + 1]) for i in range(10)]
    assert calls == [views_for_length(8, L, 1.0) for L in per_step]
    assert len(set(calls)) > 1 or 2 < calls[0] < 8, "the blur lengths of this scene should not all clip"
    with open(run / "log.csv") as fh:
        logged = {int(r["step"]): int(r["views"]) for r in csv.DictReader(fh)}
    assert logged and all(calls[step] == v for step, v in logged.items())


def test_backward_views_take_effect_only_below_the_forwards_views(dynamic_scene, tmp_path):
    # blur.backward_views >= n runs the exact backward (bitwise the default); m = 2 of n = 8 views
    # changes the gradients (a different estimate), and the trainer says it is on.
    def run(m, name):
        cfg = _config(iters=6, warmup_fraction=0.0, deform_fraction=0.0, progressive=False)
        cfg = cfg.replace(blur=dataclasses.replace(cfg.blur, n_schedule="fixed", backward_views=m))
        tr = Trainer(dynamic_scene, cfg, tmp_path / name)
        tr.run()
        return tr

    exact, every, two = run(0, "exact"), run(8, "every"), run(2, "two")
    for name in exact.params:
        np.testing.assert_array_equal(every.params[name], exact.params[name], err_msg=name)
    assert not np.array_equal(two.params["static.means"], exact.params["static.means"])
    assert any("backward through 2 of each step's virtual views" in n for n in two.log.notes)
    assert not any("backward through" in n for n in exact.log.notes)
