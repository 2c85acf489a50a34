"""Evaluation helpers: the NVS alignment uses orientations, so collinear camera paths align."""
import numpy as np

from d2gs_np import metrics
from d2gs_np.evaluate import align_with_orientations
from d2gs_np.geometry import look_at, se3_exp


def _similarity(s, R, t, T):
    return metrics.sim3_apply_to_poses(s, R, t, T)


def test_orientation_alignment_recovers_the_similarity_of_a_collinear_path():
    rng = np.random.default_rng(0)
    # Cameras on a straight dolly line, each looking forward with some pan: centres are collinear.
    est = np.stack([look_at([0.3 * i, 0.0, 0.0], [0.3 * i + rng.normal(0, 0.2), 0.1, 5.0]) for i in range(8)])
    R_true = se3_exp(np.array([0, 0, 0, 0.3, -1.1, 0.7]))[:3, :3]
    s_true, t_true = 2.5, np.array([1.0, -2.0, 0.5])
    gt = _similarity(s_true, R_true, t_true, est)
    s, R, t = align_with_orientations(est, gt)
    assert abs(s - s_true) < 1e-10
    np.testing.assert_allclose(R, R_true, atol=1e-10)
    np.testing.assert_allclose(t, t_true, atol=1e-10)
    # Centres alone cannot fix the rotation about the line: the centre-only fit misses it.
    s2, R2, t2 = metrics.align_trajectory(est, gt)
    mapped = _similarity(s2, R2, t2, est)
    angle = np.degrees(np.arccos(np.clip((np.trace(mapped[0, :3, :3].T @ gt[0, :3, :3]) - 1) / 2, -1, 1)))
    assert angle > 1.0
