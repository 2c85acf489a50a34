"""A synthetic pose problem with a known answer, for trying the pose solver (``pose/gauss_newton.py``).

Used by notebooks/05_pose_refinement.ipynb and examples/gn_vs_scipy.py: the matches are exact
projections of known points (plus optional pixel noise and outliers), the depths exact, so the
true mid poses are the solution of the noise-free problem.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.pose.gauss_newton import PoseProblem, pair_observations

__all__ = ["toy_problem"]


def toy_problem(num_frames=4, num_points=150, pixel_noise=0.0, outlier_fraction=0.0, rot_error=0.01,
                trans_error=0.03, spread=1e-3, gaps=(1, 2), seed=0, width=160, height=90):
    """(problem, true mid poses (N, 4, 4)): a camera sliding sideways past points 4-7 units away,
    matches of pairs (k, k + g) with exact depths, ``pixel_noise`` px of noise on p, a fraction of
    p replaced by uniform outliers, and every free frame's endpoints moved by one random left
    perturbation (rotation std ``rot_error`` rad, translation std ``trans_error``)."""
    rng = np.random.default_rng(seed)
    f = 0.75 * width
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    mids = np.stack([se3_exp(np.r_[0.15 * k, 0.02 * k, 0.0, 0.0, 0.03 * k, 0.01 * k]) for k in range(num_frames)])
    d = rng.normal(0, spread, (num_frames, 6))
    starts, ends = se3_exp(-d) @ mids, se3_exp(d) @ mids
    X = np.c_[rng.uniform(-2.5, 2.5, (num_points, 2)), rng.uniform(4.0, 7.0, num_points)]

    def project(T):
        Xc = X @ T[:3, :3].T + T[:3, 3]
        p = Xc @ K.T
        return p[:, :2] / p[:, 2:], Xc[:, 2]

    pairs = []
    for k in range(num_frames):
        for g in gaps:
            j = k + g
            if j >= num_frames:
                continue
            pk, dk = project(mids[k])
            pj, dj = project(mids[j])
            pk = pk + rng.normal(0, pixel_noise, pk.shape) if pixel_noise else pk
            bad = rng.random(num_points) < outlier_fraction
            pk[bad] = rng.uniform([0, 0], [width, height], (int(bad.sum()), 2))
            pairs.append(pair_observations(k, j, pk, pj, dk, dj))
    P = np.stack([np.eye(4) if k == 0 else se3_exp(np.r_[rng.normal(0, trans_error, 3), rng.normal(0, rot_error, 3)])
                  for k in range(num_frames)])
    return PoseProblem(P @ starts, P @ ends, np.stack([K] * num_frames), pairs), mids
