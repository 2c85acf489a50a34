"""The trained model: one render and one mid pose for training, evaluation and the command line;
a checkpoint round trip; validation once, with errors that say what to do; and a training step
that runs no validation."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.data.synthetic import make_scene
from d2gs_np.geometry.se3 import se3_exp, se3_interpolate
from d2gs_np.train.checkpoint import load_checkpoint, save_checkpoint
from d2gs_np.train.components import Components, composition_notes, decide_components
from d2gs_np.train.config import ExperimentConfig, LearningRates, TrainConfig
from d2gs_np.train.model import Model
from d2gs_np.train.learning_rates import block_learning_rate
from d2gs_np.train.trainer import Trainer

TINY = dict(width=40, height=24, num_frames=5)


@pytest.fixture(scope="module")
def scene():
    return make_scene("dynamic", 1, **TINY)


@pytest.fixture(scope="module")
def model(scene):
    cfg = ExperimentConfig(train=TrainConfig(iters=4, quiet=True))
    return Model.from_scene(scene, cfg, decide_components(scene, cfg))


def test_render_of_a_frame_is_the_render_at_its_mid_pose_time_and_camera(model, scene):
    k = 3
    f = scene.frames[k]
    np.testing.assert_array_equal(model.render(k), model.render(model.mid_pose(k), f.time, f.K, f.width, f.height))
    assert model.render(k).shape == (f.height, f.width, 3)
    with pytest.raises(ValueError, match="a pose needs the time"):
        model.render(model.mid_pose(k))
    with pytest.raises(ValueError, match="frame index"):
        model.render(len(scene.frames))


def test_mid_pose_is_the_geodesic_midpoint_of_the_endpoints_around_the_reference_pose(model):
    k = 2
    T = model.poses_ref[k]
    Ts, Te = se3_exp(model.params["camera.xi_start"][k]) @ T, se3_exp(model.params["camera.xi_end"][k]) @ T
    np.testing.assert_array_equal(model.mid_pose(k), se3_interpolate(Ts, Te, 0.5))
    # A refined reference pose moves the mid pose with it (where a pose solver writes).
    moved = model.replace(poses_ref=np.ascontiguousarray(se3_exp(np.full(6, 1e-3)) @ model.poses_ref)).validate()
    assert not np.allclose(moved.mid_pose(k), model.mid_pose(k))
    np.testing.assert_array_equal(moved.poses_est, model.poses_est)


def test_checkpoint_round_trip_is_exact_and_old_checkpoints_load(model, tmp_path):
    arrays, meta = model.to_checkpoint()
    save_checkpoint(tmp_path / "m.npz", arrays, meta)
    again = Model.from_checkpoint(*load_checkpoint(tmp_path / "m.npz"))
    assert sorted(again.params) == sorted(model.params)
    for name, v in model.params.items():
        np.testing.assert_array_equal(again.params[name], v)
    for field in ("times", "poses_est", "poses_ref", "Ks"):
        np.testing.assert_array_equal(getattr(again, field), getattr(model, field))
    assert (again.components, again.widths, again.heights, again.config) == \
        (model.components, model.widths, model.heights, model.config)
    arrays.pop("camera/poses_ref")  # written before the camera state had refined poses
    old = Model.from_checkpoint(arrays, meta)
    np.testing.assert_array_equal(old.poses_ref, model.poses_est)


def test_validation_names_the_problem(model):
    p = dict(model.params)
    p["static.foo"] = np.zeros(3)
    with pytest.raises(ValueError, match="unexpected"):
        model.replace(params=p).validate()
    p = {n: v for n, v in model.params.items() if n != "camera.xi_end"}
    with pytest.raises(ValueError, match="camera.xi_end"):
        model.replace(params=p).validate()
    bent = model.poses_ref.copy()
    bent[1, 0, 0] += 0.1
    with pytest.raises(ValueError, match="poses_ref"):
        model.replace(poses_ref=bent).validate()
    with pytest.raises(ValueError, match="components.dynamic"):
        model.replace(components=dataclasses.replace(model.components, dynamic=False)).validate()


def test_a_new_block_kind_gets_an_error_that_says_where_its_learning_rate_goes():
    lr = LearningRates()
    assert block_learning_rate("static.colors", lr, 2.0, 100, 5) == lr.colors
    with pytest.raises(ValueError, match="add a field 'sh_rest' to LearningRates"):
        block_learning_rate("static.sh_rest", lr, 2.0, 100, 5)


def test_final_ratio_decays_the_constant_rate_blocks_only():
    lr = LearningRates(final_ratio=0.1)
    for name, rate in (("static.colors", lr.colors), ("dynamic.log_scales", lr.log_scales),
                       ("static.opacity_logits", lr.opacity_logits), ("dynamic.deform_quats", lr.deform_other)):
        sched = block_learning_rate(name, lr, 2.0, 100, 5)
        assert sched(0) == pytest.approx(rate, rel=1e-12)
        assert sched(50) == pytest.approx(rate * 0.1 ** 0.5, rel=1e-12)  # log-linear: the geometric mean halfway
        assert sched(100) == pytest.approx(rate * 0.1, rel=1e-12) and sched(10_000) == sched(100)
    # positions keep their own decay, unchanged by the ratio
    assert block_learning_rate("static.means", lr, 2.0, 100, 5)(100) == pytest.approx(lr.means_final * 2.0)
    # the camera's rates are not Gaussian blocks
    assert block_learning_rate("camera.exposure_logit", lr, 2.0, 100, 5) == lr.exposure
    with pytest.raises(ValueError, match=r"final_ratio must be a finite number in \(0, 1\]"):
        LearningRates(final_ratio=0.0)
    with pytest.raises(ValueError, match=r"final_ratio must be a finite number in \(0, 1\]"):
        LearningRates(final_ratio=1.5)


def test_left_out_follows_what_the_run_has():
    c = Components(dynamic=True, blur=True, learn_exposure=False, exposure_fraction=0.5)
    assert c.left_out() == ["pose_refinement", "loss_ts", "loss_gs", "loss_reproj", "loss_freq"]
    assert c.left_out(terms=["photometric", "gs"], plugins=["pose_solver"]) == ["loss_ts", "loss_reproj",
                                                                                 "loss_freq"]
    assert Components(False, False, False, 0.0).left_out()[:4] == ["dynamic_set", "deformation", "blur_model",
                                                                   "trajectory_model"]
    assert composition_notes(["photometric", "ts", "gs", "reproj", "freq"], ["pose_solver"]) == \
        ["loss = L_render + L_ts + L_gs + L_reproj + L_freq"]


def test_a_training_step_runs_no_validation(scene, tmp_path, monkeypatch):
    # Validation happens once (Model.validate); the step's forward and backward use the private
    # paths. Make every public validator fail after construction: the step must not notice.
    cfg = ExperimentConfig(train=TrainConfig(iters=4, quiet=True, eval_every=0, prune_every=0, checkpoint_every=0,
                                             warmup_fraction=0.0, deform_fraction=0.0))
    tr = Trainer(scene, cfg, tmp_path / "run")

    def forbidden(*a, **k):
        raise AssertionError("validation inside the training step")

    import d2gs_np.render.api as api
    import d2gs_np.scene.deformation as deformation
    import d2gs_np.scene.render_inputs as scene_model
    import d2gs_np.blur.endpoints as trajectory
    import d2gs_np.blur.virtual_poses as virtual_poses

    for module, name in ((api, "_validate_inputs"), (api, "_check_cotangent"), (scene_model, "validate_params"),
                         (deformation, "_check_block"), (virtual_poses, "check_rigid"), (trajectory, "check_rigid"),
                         (trajectory, "_check_params")):
        monkeypatch.setattr(module, name, forbidden)
    info = tr.step(0)
    assert np.isfinite(info.loss)
