"""Our ATE and RPE (Sim(3)-aligned, d2gs_np/geometry/trajectory.py) against evo's, on TUM files
written by d2gs_np.importers.tum: the same numbers from an independent implementation (evo's
Umeyama alignment, association and metrics)."""
import numpy as np
import pytest

from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.geometry.trajectory import ate, rpe
from d2gs_np.importers.tum import write_tum

REL = 1e-9  # both are float64 closed forms over the same poses: only rounding differs


def _paths(n=40, seed=0):
    """A smooth turning path (cam_T_world) and an estimate of it: a similarity away, with noise."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n)
    xi_gt = np.stack([np.cos(2 * s), 0.3 * np.sin(3 * s), 2 * s, 0.2 * s, 0.8 * s, 0.1 * np.sin(5 * s)], axis=1)
    gt = se3_exp(xi_gt)
    world = se3_exp(np.array([0.5, -1.0, 2.0, 0.3, -0.2, 0.9]))  # the estimate's world, rigidly moved ...
    est = gt @ world
    est[:, :3, 3] *= 2.7  # ... and scaled
    noise = se3_exp(np.c_[0.02 * rng.standard_normal((n, 3)), 0.01 * rng.standard_normal((n, 3))])
    return gt, noise @ est


def test_ate_and_rpe_agree_with_evo(tmp_path):
    pytest.importorskip("evo", reason="evo (pip install evo, in the dev extra) is the independent implementation")
    from evo.core import metrics, sync
    from evo.tools import file_interface

    gt, est = _paths()
    t = np.arange(len(gt)) / 30.0
    write_tum(tmp_path / "gt.txt", t, gt)
    write_tum(tmp_path / "est.txt", t + 1e-4, est)  # stamps within evo's max_diff: association pairs them
    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.txt"))
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "est.txt"))
    ref, traj = sync.associate_trajectories(ref, traj, max_diff=0.01)
    assert ref.num_poses == traj.num_poses == len(gt)
    traj.align(ref, correct_scale=True)  # Sim(3), Umeyama on the positions

    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    assert ate(est, gt) == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=REL)

    rpe_t, rpe_r = rpe(est, gt, align=True)
    for relation, ours in ((metrics.PoseRelation.translation_part, rpe_t),
                           (metrics.PoseRelation.rotation_angle_deg, rpe_r)):
        m = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        m.process_data((ref, traj))
        assert ours == pytest.approx(m.get_statistic(metrics.StatisticsType.rmse), rel=REL)
    # and the check can fail: the noise-free path scores far lower in both
    assert ate(gt, gt) < 1e-3 * ate(est, gt)
