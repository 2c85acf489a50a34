"""Training with rigid movers (MotionInitConfig.rigid, scene/rigid.py): the run says so, the
clusters' pose paths train, densification and pruning keep every row's cluster, the finished
model loads and renders as trained, and a resumed run reproduces an uninterrupted one."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.data import suite
from d2gs_np.evaluation.runs import load_run
from d2gs_np.scene.config import MotionInitConfig
from d2gs_np.scene.gaussians import CLUSTER, num_clusters
from d2gs_np.train.config import DensifyConfig, ExperimentConfig, LossConfig, PoseSolverConfig, TrainConfig
from d2gs_np.train.trainer import Trainer
from run_fixtures import step_and_checkpoint

TINY = dict(width=48, height=27, num_frames=4, num_test_views=1, subframes=4)


@pytest.fixture(scope="module")
def mover_scene():
    return suite.make_suite_scene("cube_sign", 0, **TINY)


def _config(iters, rigid=True, grow=True, **train):
    """``grow``: densify every 3 steps at a low threshold and prune every 4 (the rows change)."""
    base = dict(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0, prune_every=4 if grow else 0)
    base.update(train)
    densify = DensifyConfig(start_fraction=0.0, stop_fraction=1.0, every=3, grad_threshold_ndc=1e-6) if grow \
        else DensifyConfig(enabled=False)
    return ExperimentConfig(train=TrainConfig(**base), loss=LossConfig(lambda_freq=0.0),
                            pose_solver=PoseSolverConfig(mode="off"), motion_init=MotionInitConfig(rigid=rigid),
                            densify=densify)


def test_rigid_run_trains_its_clusters_and_keeps_their_rows(mover_scene, tmp_path):
    tr = Trainer(mover_scene, _config(16), tmp_path / "r")
    start = {k: v.copy() for k, v in tr.params.items() if k.startswith("rigid.")}
    ids0 = tr.params[CLUSTER].copy()
    C = num_clusters(tr.params)
    assert C >= 1 and (ids0 >= 0).any()
    assert any(n.startswith("rigid movers (motion_init.rigid)") for n in tr.log.notes)
    tr.run()
    p = tr.params
    assert num_clusters(p) == C
    assert len(p[CLUSTER]) != len(ids0)  # densification and pruning changed the dynamic rows ...
    assert set(np.unique(p[CLUSTER])) <= set(np.unique(ids0))  # ... and every row kept a cluster it had
    for k, v in start.items():
        assert not np.array_equal(p[k], v), f"{k} did not train"
    loaded = load_run(tmp_path / "r").model
    for k in p:
        np.testing.assert_array_equal(loaded.params[k], p[k], err_msg=k)
    view = 1
    np.testing.assert_array_equal(loaded.render(view), tr.model.render(view))


def test_clones_and_splits_stay_in_their_parents_cluster():
    from d2gs_np.train.densify import GRAD_COUNT, GRAD_SUM, densify, init_grad_stats

    rng = np.random.default_rng(0)
    nd = 6
    params = {"static.means": rng.normal(size=(2, 3)), "static.log_scales": np.full((2, 3), -3.0),
              "static.quats": np.tile([1.0, 0, 0, 0], (2, 1)), "static.opacity_logits": np.zeros(2),
              "static.colors": np.zeros((2, 3)), "dynamic.means": rng.normal(size=(nd, 3)),
              "dynamic.log_scales": np.log(np.r_[[0.001] * 3, [0.5] * 3])[:, None].repeat(3, 1),
              "dynamic.quats": np.tile([1.0, 0, 0, 0], (nd, 1)), "dynamic.opacity_logits": np.zeros(nd),
              "dynamic.colors": np.zeros((nd, 3)), "dynamic.deform_means": np.zeros((nd, 6, 3)),
              "dynamic.deform_quats": np.zeros((nd, 6, 4)), "dynamic.deform_colors": np.zeros((nd, 6, 3)),
              CLUSTER: np.array([0.0, 1.0, -1.0, 1.0, 0.0, -1.0]), "rigid.means": np.zeros((2, 3)),
              "rigid.quats": np.tile([1.0, 0, 0, 0], (2, 1)), "rigid.deform_means": np.zeros((2, 6, 3)),
              "rigid.deform_quats": np.zeros((2, 6, 4))}
    rows = init_grad_stats(params)
    rows[GRAD_SUM]["dynamic"][:] = 1.0  # every dynamic row hot: the small ones clone, the large ones split
    rows[GRAD_COUNT]["dynamic"][:] = 1.0
    out, _, _, info = densify(params, {"m": {}, "v": {}}, rows, DensifyConfig(), 1.0, 48, rng)
    assert info["dynamic_cloned"] == 3 and info["dynamic_split"] == 3
    # originals of the clones, then the clones (rows 0-2), then two children per split row (3-5)
    np.testing.assert_array_equal(out[CLUSTER], [0.0, 1.0, -1.0, 0.0, 1.0, -1.0, 1.0, 0.0, -1.0, 1.0, 0.0, -1.0])


def test_without_rigid_the_run_has_no_clusters(mover_scene, tmp_path):
    tr = Trainer(mover_scene, _config(1, rigid=False), tmp_path / "r")
    assert not any(k.startswith("rigid.") or k == CLUSTER for k in tr.params)


def test_resume_reproduces_an_uninterrupted_rigid_run(mover_scene, tmp_path):
    # stepped by hand to the checkpoint, as tests/train/test_trainer.py's resume test: the schedule's
    # densification and pruning run in Trainer.run, so this run keeps its rows
    cfg = _config(8, grow=False)
    full = Trainer(mover_scene, cfg, tmp_path / "full")
    full.run()
    part_cfg = cfg.replace(train=dataclasses.replace(cfg.train, checkpoint_every=5))
    part = Trainer(mover_scene, part_cfg, tmp_path / "part")
    step_and_checkpoint(part, 5)
    resumed = Trainer(mover_scene, part_cfg, tmp_path / "part", resume=True)
    resumed.run()
    assert resumed.params.keys() == full.params.keys()
    for name in full.params:
        np.testing.assert_array_equal(resumed.params[name], full.params[name], err_msg=name)


def test_a_rigid_body_keeps_its_gaussians_residuals_at_zero(mover_scene, tmp_path):
    """``rigid_residual=False``: the clustered rows' position and rotation residuals stay exactly
    zero through training and densification, while their colours and the clusters' paths train."""
    cfg = _config(12)
    cfg = cfg.replace(motion_init=MotionInitConfig(rigid=True, rigid_residual=False))
    tr = Trainer(mover_scene, cfg, tmp_path / "r")
    colors0 = tr.params["dynamic.deform_colors"].copy()
    path0 = tr.params["rigid.deform_means"].copy()
    tr.run()
    p = tr.params
    on = p[CLUSTER] >= 0
    assert on.sum() > 0
    assert not p["dynamic.deform_means"][on].any() and not p["dynamic.deform_quats"][on].any()
    assert not np.array_equal(p["rigid.deform_means"], path0)
    assert len(p[CLUSTER]) != len(colors0) or not np.array_equal(p["dynamic.deform_colors"], colors0)
    free = Trainer(mover_scene, _config(12), tmp_path / "free")
    free.run()
    assert free.params["dynamic.deform_means"][free.params[CLUSTER] >= 0].any()  # the default trains them
