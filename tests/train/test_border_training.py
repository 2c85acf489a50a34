"""The finished model's static world past the frames' borders (BorderConfig, scene/border.py): the
run adds it after its last step and says so, the training views render exactly as trained, the
saved model holds it, and margin 0 leaves it out."""
import dataclasses

import numpy as np

from d2gs_np.evaluation.runs import load_run
from d2gs_np.scene.config import BorderConfig
from d2gs_np.scene.gaussians import num_static
from d2gs_np.train.config import DensifyConfig, ExperimentConfig, LossConfig, PoseSolverConfig, TrainConfig
from d2gs_np.train.trainer import Trainer
from run_fixtures import tiny_dynamic_scene


def _config(margin):
    return ExperimentConfig(train=TrainConfig(iters=6, quiet=True, eval_every=0, log_every=1, checkpoint_every=0),
                            loss=LossConfig(lambda_freq=0.0), pose_solver=PoseSolverConfig(mode="off"),
                            densify=DensifyConfig(enabled=False), border=BorderConfig(margin=margin))


def test_a_finished_run_holds_the_world_past_the_borders(tmp_path):
    scene = tiny_dynamic_scene(trusted=True)
    off = Trainer(scene, _config(0.0), tmp_path / "off")
    off.run()
    on = Trainer(scene, _config(0.3), tmp_path / "on")
    on.run()
    added = num_static(on.params) - num_static(off.params)
    assert added > 0
    note = [n for n in on.log.notes if n.startswith("past the frames' borders")]
    assert note and f"{added} static Gaussians added" in note[0]
    assert not any(n.startswith("past the frames' borders") for n in off.log.notes)
    # the same steps trained the same model; the copies change no training view
    n = num_static(off.params)
    for k, v in off.params.items():
        got = on.params[k][:n] if k.startswith("static.") else on.params[k]
        np.testing.assert_array_equal(got, v, err_msg=k)
    for view in range(scene.num_frames):
        np.testing.assert_array_equal(on.model.render(view), off.model.render(view))
    loaded = load_run(tmp_path / "on").model
    assert num_static(loaded.params) == num_static(on.params)
