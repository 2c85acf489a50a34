"""The exposure path chosen by measured need (``TrajectoryConfig.path = "auto"``, docs/method.md §4):
the three-knot path where reliable start poses bend within an exposure by more than
``trajectory.bend_px``, the geodesic otherwise; the decision is said in the run log, carried by
the model and its checkpoints, and a resume with the run's own ("auto") config keeps it."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.blur.config import TrajectoryConfig
from d2gs_np.blur.endpoints import XI_MID, exposure_bend_px
from d2gs_np.train.components import decide_components, resolved_config
from d2gs_np.train.config import ExperimentConfig, TrainConfig
from d2gs_np.train.trainer import Trainer
from run_fixtures import tiny_dynamic_scene



def _config(iters=4, **trajectory):
    return ExperimentConfig(train=TrainConfig(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0,
                                              prune_every=0, warmup_fraction=0.0, deform_fraction=0.0),
                            trajectory=TrajectoryConfig(**trajectory))


def _median_bend(scene, poses=None, depth=None):
    P = np.stack([f.cam_T_world for f in scene.frames]) if poses is None else poses
    t = np.array([f.time for f in scene.frames])
    return float(np.median(exposure_bend_px(P, t, scene.exposure_fraction, scene.frames[0].K[0, 0],
                                            depth or scene.scene_scale)))


def test_auto_takes_the_three_knot_path_only_beyond_the_measured_bend(trusted_scene):
    bend = _median_bend(trusted_scene)
    assert 0.5 < bend < 2.0  # the premise: a shake that bends by about a pixel
    notes = []
    c = decide_components(trusted_scene, _config(bend_px=0.9 * bend), notes.append)
    assert c.exposure_path == "three_knot"
    assert any(f"bends {bend:.2f} px on the trusted poses" in n and "three-knot" in n for n in notes)
    assert decide_components(trusted_scene, _config(bend_px=1.1 * bend)).exposure_path == "geodesic"
    # a path the config names is not decided
    assert decide_components(trusted_scene, _config(path="geodesic", bend_px=0.01)).exposure_path == ""
    assert decide_components(trusted_scene, _config(path="three_knot")).exposure_path == ""


def test_auto_keeps_the_geodesic_where_the_bend_cannot_be_read_or_used(trusted_scene, noisy_scene):
    notes = []
    # unadjusted noisy poses: their error would read as a bend
    assert decide_components(noisy_scene, _config(bend_px=1e-6), notes.append).exposure_path == "geodesic"
    assert any("not adjusted" in n for n in notes)
    assert decide_components(trusted_scene, _config(kind="posenet", bend_px=1e-6)).exposure_path == "geodesic"
    no_blur = _config(bend_px=1e-6).replace(train=TrainConfig(blur="off"))
    assert decide_components(trusted_scene, no_blur).exposure_path == ""


def test_adjusted_start_poses_and_their_depth_decide(noisy_scene, trusted_scene):
    """With a kept adjustment, its poses (here: the true ones, as a perfect adjustment) and its
    point depth measure the bend, not the noisy given poses."""
    true = np.stack([f.cam_T_world for f in trusted_scene.frames])
    bend = _median_bend(noisy_scene, poses=true, depth=3.0)
    assert abs(bend - _median_bend(noisy_scene)) > 0.05  # the premise: the given poses read otherwise
    for factor, path in ((0.95, "three_knot"), (1.05, "geodesic")):
        c = decide_components(noisy_scene, _config(bend_px=factor * bend), adjusted=True, start_poses=true, depth=3.0)
        assert c.exposure_path == path, factor


def test_resolved_config_names_the_decided_path():
    cfg = _config()
    c = dataclasses.replace(decide_components(tiny_dynamic_scene(trusted=True, seed=1), cfg),
                            exposure_path="three_knot")
    assert resolved_config(cfg, c).trajectory.path == "three_knot"
    assert resolved_config(cfg, dataclasses.replace(c, exposure_path="")).trajectory.path == "geodesic"
    named = _config(path="geodesic")
    assert resolved_config(named, c) is named
    with pytest.raises(ValueError, match="bend_px"):
        TrajectoryConfig(bend_px=0.0)
    with pytest.raises(ValueError, match="path must be"):
        TrajectoryConfig(path="spline")


def test_a_run_that_chose_the_three_knot_path_trains_it_and_resumes_with_it(trusted_scene, tmp_path):
    cfg = _config(iters=4, bend_px=0.1)
    tr = Trainer(trusted_scene, cfg, tmp_path / "run")
    assert tr.components.exposure_path == "three_knot"
    assert XI_MID in tr.params and tr.model.config.trajectory.path == "three_knot"
    tr.run()
    assert '"path": "auto"' in (tmp_path / "run" / "config.json").read_text()  # the user's config, as given
    longer = cfg.replace(train=dataclasses.replace(cfg.train, iters=6))
    resumed = Trainer(trusted_scene, longer, tmp_path / "run", resume=True)
    assert resumed.components.exposure_path == "three_knot"
    assert resumed.model.config.trajectory.path == "three_knot" and XI_MID in resumed.params
    resumed.run()
    # the geodesic named outright is another experiment: refused
    with pytest.raises(ValueError, match="differs from the saved run"):
        Trainer(trusted_scene, longer.replace(trajectory=TrajectoryConfig(path="geodesic", bend_px=0.1)),
                tmp_path / "run", resume=True)
