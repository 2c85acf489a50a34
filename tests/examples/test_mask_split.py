"""examples/mask_split.py: the input's PSNR over the moving / static pixels of all frames equals
metrics.psnr on the stacked frames with the stacked masks, and the render's lies where a direct
render-and-score says; a scene without sharp frames is refused."""
import json

import numpy as np
import pytest

from d2gs_np.evaluation import metrics
from d2gs_np.data.io import load_scene, write_scene
from d2gs_np.data.synthetic import make_scene
from d2gs_np.evaluation.runs import load_run
from d2gs_np.train.config import ExperimentConfig, TrainConfig
from d2gs_np.train.trainer import Trainer
from example_fixtures import load_example


def test_split_matches_psnr_over_the_stacked_masks(tmp_path):
    mod = load_example("mask_split.py")
    scene = make_scene("dynamic", 0, width=48, height=27, num_frames=4)
    scene_dir = tmp_path / "scene"
    write_scene(scene, scene_dir)
    run = tmp_path / "run"
    Trainer(scene, ExperimentConfig(train=TrainConfig(iters=2, quiet=True, eval_every=0, checkpoint_every=0)),
            run).run()
    m = mod.mask_split(run, scene_dir)
    scene = load_scene(scene_dir)  # as written (8-bit frames), as the script reads it
    masks = np.concatenate([f.mask for f in scene.frames])
    assert 0.0 < m["moving_share"] < 1.0 and masks.any()
    stack = lambda imgs: np.concatenate(imgs)  # noqa: E731  (frames one under the other)
    images, sharps = stack([f.image for f in scene.frames]), stack([f.sharp for f in scene.frames])
    # the sums are in a different order than metrics.psnr's mean: 1e-9 dB
    assert m["moving_input"] == pytest.approx(metrics.psnr(images, sharps, masks), abs=1e-9)
    assert m["static_input"] == pytest.approx(metrics.psnr(images, sharps, ~masks), abs=1e-9)
    model = load_run(run).model
    renders = stack([model.render(P, f.time, f.K, f.width, f.height) for P, f in zip(model.mid_poses(), scene.frames)])
    assert m["moving_render"] == pytest.approx(metrics.psnr(renders, sharps, masks), abs=1e-9)
    assert m["static_render"] == pytest.approx(metrics.psnr(renders, sharps, ~masks), abs=1e-9)


def test_a_scene_without_sharp_frames_is_refused(tmp_path):
    mod = load_example("mask_split.py")
    scene = make_scene("dynamic", 0, width=48, height=27, num_frames=4)
    write_scene(scene, tmp_path / "scene")
    run = tmp_path / "run"
    Trainer(scene, ExperimentConfig(train=TrainConfig(iters=1, quiet=True, eval_every=0, checkpoint_every=0)),
            run).run()
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    for f in meta["frames"]:
        f.pop("sharp_file_path")
    (tmp_path / "scene" / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(SystemExit, match="no sharp frames"):
        mod.mask_split(run, tmp_path / "scene")
