"""examples/run_diagnosis.py: the classes of a view's pixels (moving, unseen by every training
frame, rendered depth in front / behind / right), checked on hand-made depths and on test views
that coincide with, or stand far beside, the training path; a scene without true depth is refused."""
import numpy as np
import pytest

from d2gs_np.data.io import load_scene
from d2gs_np.data.scene import Frame
from d2gs_np.data.suite import write_suite_scene
from d2gs_np.geometry.camera import look_at, make_intrinsics
from d2gs_np.train.config import ExperimentConfig, TrainConfig
from d2gs_np.train.trainer import Trainer
from example_fixtures import load_example

KW = dict(width=48, height=27, num_frames=4, subframes=2, num_test_views=2)


def _frame(T, depth):
    K = make_intrinsics(40.0, 40.0, 3.0, 2.0)
    return Frame(file_path="x.png", time=0.5, cam_T_world=T, K=K, width=6, height=4, gt_cam_T_world=T, depth=depth)


def test_classes_by_hand():
    mod = load_example("run_diagnosis.py")
    T = look_at([0.0, 0.0, 0.0], [0.0, 0.0, -4.0], up=(0.0, 1.0, 0.0))
    true = np.full((4, 6), 4.0)
    true[0, 0] = np.inf  # no surface: no class
    f = _frame(T, true)
    depth = np.full((4, 6), 4.0)
    depth[1, :] = 2.0  # in front
    depth[2, :3] = 5.0  # behind
    moving = np.zeros((4, 6), bool)
    moving[3, :2] = True
    cls = mod._classify(T, f, depth, moving, [f], check_seen=True)  # its own frame sees every point
    assert cls[0, 0] == -1
    assert (cls[1] == 2).all() and (cls[2, :3] == 3).all() and (cls[3, :2] == 0).all()
    assert (cls[0, 1:] == 4).all() and (cls[2, 3:] == 4).all() and (cls[3, 2:] == 4).all()
    behind = _frame(look_at([0.0, 0.0, -10.0], [0.0, 0.0, -20.0], up=(0.0, 1.0, 0.0)), true)  # looks away
    cls = mod._classify(T, f, depth, moving, [behind], check_seen=True)
    assert (cls[cls >= 1] == 1).all() and (cls == 0).sum() == 2  # nothing seen; moving stays moving


def test_depth_shift_by_hand():
    mod = load_example("run_diagnosis.py")
    K = make_intrinsics(40.0, 40.0, 3.0, 2.0)
    uv = np.array([[1.5, 0.5], [3.5, 2.5], [5.5, 3.5]])
    z = np.full(3, 4.0)
    side = np.eye(4)
    side[0, 3] = -0.2  # the second camera 0.2 to the right: a point at depth 4 moves f b / z = 2 px
    par, shift = mod.depth_shift(uv, z, z, K, side)
    np.testing.assert_allclose(par, 2.0, rtol=1e-12)
    assert np.all(shift == 0.0)  # the right depth lands where the truth does
    par, shift = mod.depth_shift(uv, z, 1.1 * z, K, side)  # 10 % too far: moves 2 / 1.1 px
    np.testing.assert_allclose(shift, 2.0 - 2.0 / 1.1, rtol=1e-12)
    turn = np.eye(4)
    turn[:3, :3] = np.array([[np.cos(0.05), 0.0, np.sin(0.05)], [0.0, 1.0, 0.0], [-np.sin(0.05), 0.0, np.cos(0.05)]])
    par, shift = mod.depth_shift(uv, z, 0.5 * z, K, turn)  # a turn alone: no parallax, depth does not matter
    assert np.all(par > 1.0) and np.abs(shift).max() < 1e-12


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("diag")
    out = {}
    for name, offset in (("on_path", 0.0), ("far", 0.4)):
        scene_dir = write_suite_scene(root / name / "scene", "cube_sign", seed=0, test_offset_fraction=offset, **KW)
        Trainer(load_scene(scene_dir),
                ExperimentConfig(train=TrainConfig(iters=2, quiet=True, eval_every=0, checkpoint_every=0)),
                root / name / "run").run()
        out[name] = root / name / "run"
    return out


def test_a_test_view_on_the_path_is_seen_and_one_far_beside_it_is_partly_unseen(runs):
    mod = load_example("run_diagnosis.py")
    on, far = mod.diagnose(runs["on_path"]), mod.diagnose(runs["far"])
    for r in (on, far):
        for part in ("nvs_classes", "dvs_classes"):
            assert sum(v["pixel_share"] for v in r[part].values()) == pytest.approx(1.0, abs=1e-12)
            assert sum(v["error_share"] for v in r[part].values()) == pytest.approx(1.0, abs=1e-9)
        assert r["dvs_classes"]["unseen"]["pixel_share"] == 0.0  # training frames are not tested for it
        assert 0.0 <= r["static_fills_movers"] <= 1.0 and 0.0 <= r["dynamic_on_static"] <= 1.0
    # a test view at a training frame's own pose and time sees only what that frame sees (up to the
    # 1 % depth tolerance at depth edges); 40 % of the scene depth beside it, part of it is new
    assert on["nvs_classes"]["unseen"]["pixel_share"] < 0.01
    assert far["nvs_classes"]["unseen"]["pixel_share"] > 0.05
    # on the path a test view is its frame's own camera: nothing moves, whatever the depth; beside it, it does
    for v in on["nvs_depth_shift"]:
        assert v["parallax_px"] < 1e-6 and v["shift_px"] < 1e-6
    assert all(v["parallax_px"] > 1.0 for v in far["nvs_depth_shift"])
    assert len(far["nvs_depth_shift"]) == KW["num_test_views"]


def test_a_run_on_a_scene_without_the_true_world_is_refused(tmp_path):
    mod = load_example("run_diagnosis.py")
    with pytest.raises(FileNotFoundError, match="suite_config.json is missing"):
        mod._world(tmp_path)
