"""examples/nvs_ceiling.py and examples/border_effect.py: the unseen pixels' ceilings on views whose
answer is known, and the border copies added to a finished run change no training view and lift
its novel views' end strip."""
import json

import numpy as np
import pytest

from example_fixtures import load_example

nc = load_example("nvs_ceiling.py")


def test_ceilings_of_a_view_with_a_known_unseen_strip():
    rng = np.random.default_rng(0)
    img = np.full((20, 40, 3), 0.5)
    img[:, :4] = rng.uniform(0.2, 0.8, (20, 4, 3))  # the unseen strip: 10 % of the pixels, uniform noise
    seen = np.ones((20, 40), bool)
    seen[:, :4] = False
    share, c_mean, c_low = nc.view_ceilings(img, seen, sigma=2.0)
    assert share == pytest.approx(0.1)
    px = img[:, :4].reshape(-1, 3)
    assert c_mean == pytest.approx(-10 * np.log10(0.1 * ((px - px.mean(0)) ** 2).mean()), rel=1e-12)
    # noise keeps little of itself under a blur: the low-pass oracle is near the mean colour's
    assert abs(c_low - c_mean) < 3.0
    # a smooth strip: the low-pass oracle knows it almost exactly, the mean colour does not
    img[:, :4] = np.linspace(0.2, 0.8, 20)[:, None, None]
    _, c_mean, c_low = nc.view_ceilings(img, seen, sigma=2.0)
    assert c_low > c_mean + 10
    assert nc.view_ceilings(img, np.ones((20, 40), bool), 2.0) == (0.0, float("inf"), float("inf"))


def test_bad_sigma_is_refused(capsys):
    with pytest.raises(SystemExit):
        nc.main(["somewhere", "--sigma", "0"])
    assert "--sigma must be a positive number" in capsys.readouterr().err


def test_border_effect_on_a_finished_run(tmp_path):
    from d2gs_np.data.suite import write_suite_scene
    from d2gs_np.data.io import load_scene
    from d2gs_np.train.config import ExperimentConfig
    from d2gs_np.train.trainer import Trainer

    be = load_example("border_effect.py")
    scene_dir = write_suite_scene(tmp_path / "scene", "wall_disk", seed=0, width=48, height=27, num_frames=4,
                                  num_test_views=2)
    cfg = ExperimentConfig.from_dict({"train": {"iters": 4, "quiet": True, "eval_every": 0},
                                      "pose_solver": {"mode": "off"}, "border": {"margin": 0.0}})
    Trainer(load_scene(scene_dir), cfg, tmp_path / "run").run()
    from d2gs_np.scene.config import BorderConfig
    r = be.border_effect(tmp_path / "run", BorderConfig(margin=0.4))  # 19 px past this 48 px image
    assert r["added"] > 0 and r["training_views_max_change"] == 0.0
    assert r["dvs_after"] == r["dvs_before"]
    # the end views see what no frame saw: they gain, the mean with them
    assert r["views_after"][0] > r["views_before"][0] and r["nvs_after"] > r["nvs_before"]
    out = tmp_path / "b.csv"
    assert be.main([str(tmp_path / "run"), "--margin", "0.4", "--out", str(out)]) == 0
    assert out.read_text().splitlines()[0].startswith("run,added")
