"""The toy pose problem (d2gs_np/pose/toy.py): its truth is the noise-free solution."""
import numpy as np

from d2gs_np.pose.config import GaussNewtonConfig
from d2gs_np.pose.gauss_newton import PoseProblem
from d2gs_np.pose.toy import toy_problem


def test_the_true_poses_explain_the_matches_and_the_perturbed_ones_do_not():
    cfg = GaussNewtonConfig()
    problem, truth = toy_problem(num_frames=3, num_points=30, seed=1)
    n = 3 * problem.num_matches
    assert problem.num_matches == 3 * 30  # pairs (0, 1), (1, 2), (0, 2), every point in view
    exact = PoseProblem(truth, truth, problem.Ks, problem.pairs)
    r_true = exact.residuals(np.zeros(exact.num_params), cfg.beta, cfg.spread_sigma, jacobian=False)[0]
    r_start = problem.residuals(np.zeros(problem.num_params), cfg.beta, cfg.spread_sigma, jacobian=False)[0]
    assert np.abs(r_true).max() < 1e-9  # exact projections and depths
    assert np.median(np.abs(r_start[:n])) > 0.1  # frames 1 and 2 moved by 0.01 rad / 0.03 units
