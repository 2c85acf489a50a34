"""examples/pose_init_sweep.py: its settings are parsed against PoseInitConfig and a row reports the
poses' ATE and baselines."""
import numpy as np
import pytest

from d2gs_np.geometry import se3_exp
from example_fixtures import load_example

sweep = load_example("pose_init_sweep.py")


def test_settings_are_numeric_pose_init_fields():
    assert sweep.parse_setting("smooth_trans_rel=0.003") == ("smooth_trans_rel", 0.003)
    name, value = sweep.parse_setting("max_nfev=80")
    assert (name, value, type(value)) == ("max_nfev", 80, int)
    for bad in ("smooth_trans_rel", "nonsense=1", "solver=scipy", "smooth_trans_rel=abc"):
        with pytest.raises(SystemExit, match="--set"):
            sweep.parse_setting(bad)


def test_a_row_of_the_true_poses_has_no_error():
    rng = np.random.default_rng(0)
    gt = np.stack([se3_exp(np.r_[0.1 * k, 0.01 * rng.standard_normal(2), 0.01 * rng.standard_normal(3)])
                   for k in range(10)])
    line = sweep.row("truth", gt, gt, 5.0, 1.25)
    assert line.startswith("| truth | 0.0000 | x1.00, 0° | x1.00, 0° | x1.00, 0° | – | 1.2")
    noisy = np.stack([se3_exp(np.r_[0.05 * rng.standard_normal(3), np.zeros(3)]) @ T for T in gt])
    assert "| 0.0000 |" not in sweep.row("noisy", noisy, gt, 5.0)


class _Frame:
    def __init__(self, T, depth):
        self.gt_cam_T_world, self.depth = T, depth
        self.K = np.array([[50.0, 0, 20.0], [0, 50.0, 15.0], [0, 0, 1]])
        self.width, self.height = 40, 30


def test_structure_ratio_is_one_at_the_truth_and_follows_a_warp():
    # a fronto-parallel wall at depth 4 seen by cameras on a sideways line; points on the wall:
    # ratio 1 exactly; the same points 10 % deeper along the first camera's axis: 1.10 in that frame
    rng = np.random.default_rng(1)
    gt = np.stack([se3_exp(np.r_[-0.1 * k, 0, 0, 0, 0, 0]) for k in range(5)])
    frames = [_Frame(T, np.full((30, 40), 4.0)) for T in gt]
    pts = np.c_[rng.uniform(-0.5, 0.9, 40), rng.uniform(-0.5, 0.5, 40), np.full(40, 4.0)]
    med, lo, hi = sweep.structure_ratio(pts, gt, frames, 4.0)
    assert (med, lo, hi) == pytest.approx((1.0, 1.0, 1.0), abs=1e-12)
    med, _, _ = sweep.structure_ratio(pts * [1, 1, 1.1], gt, frames, 4.0)
    assert med == pytest.approx(1.1, rel=0.02)
    with pytest.raises(ValueError, match="no point lands"):
        sweep.structure_ratio(pts + [100.0, 0, 0], gt, frames, 4.0)
