"""examples/mover_crops.py: the largest mover cropped in a finished run's frames and novel views."""
import numpy as np
import pytest

from example_fixtures import load_example

mc = load_example("mover_crops.py")


def _tiny_run(tmp, seed):
    from d2gs_np.data.io import load_scene
    from d2gs_np.data.suite import write_suite_scene
    from d2gs_np.train.config import ExperimentConfig
    from d2gs_np.train.trainer import Trainer

    scene_dir = write_suite_scene(tmp / f"scene{seed}", "wall_disk", seed=seed, width=48, height=27, num_frames=4,
                                  num_test_views=2)
    cfg = ExperimentConfig.from_dict({"train": {"iters": 4, "quiet": True, "eval_every": 0},
                                      "pose_solver": {"mode": "off"}, "border": {"margin": 0.0}})
    Trainer(load_scene(scene_dir), cfg, tmp / f"run{seed}").run()
    return tmp / f"run{seed}", load_scene(scene_dir)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    return _tiny_run(tmp_path_factory.mktemp("crops"), 0)


def test_crops_frame_the_largest_mover_of_frames_and_views(tiny_run, tmp_path):
    """Row one: blurry | each run | truth around the frame with most moving pixels; row two: each
    run | truth around the test view with most; the same crop box across a row."""
    run, scene = tiny_run
    r1, r2, lines = mc.scene_crops([str(run), str(run)], zoom=2)
    assert len(r1) == 4 and len(r2) == 3
    k = int(np.argmax([f.mask.sum() for f in scene.frames]))
    ys, xs = np.nonzero(scene.frames[k].mask)
    assert r1[0].shape[0] >= 2 * (ys.max() - ys.min() + 1) and r1[0].shape[1] >= 2 * (xs.max() - xs.min() + 1)
    assert len({c.shape for c in r1}) == 1 and len({c.shape for c in r2}) == 1
    assert r1[-1].shape == r1[0].shape
    # the truth's crop is the frame's sharp image around its movers, not the blurry input
    assert not np.array_equal(r1[0], r1[-1])
    assert "deblurred moving px" in lines[1] and lines[1] == lines[2]
    out = tmp_path / "c.png"
    assert mc.main([f"{run},{run}", "--out", str(out), "--height", "40"]) == 0
    import cv2

    img = cv2.imread(str(out))
    assert img.shape[0] == 2 * (40 + 6)


def test_runs_of_different_scenes_and_bad_height_are_refused(tiny_run, tmp_path, capsys):
    run, _ = tiny_run
    with pytest.raises(SystemExit):
        mc.main([str(run), "--out", str(tmp_path / "c.png"), "--height", "2"])
    assert "--height must be at least 8" in capsys.readouterr().err
    other, _ = _tiny_run(tmp_path, 1)
    with pytest.raises(SystemExit, match="must share a scene"):
        mc.scene_crops([str(run), str(other)])
