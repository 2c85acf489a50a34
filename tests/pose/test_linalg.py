"""The solvers' small dense linear algebra (d2gs_np/pose/linalg.py)."""
import numpy as np

from d2gs_np.pose.linalg import cholesky_solve


def test_cholesky_solve_matches_numpy_and_flags_indefinite_matrices():
    # against np.linalg.solve on SPD matrices of the camera system's size (cond up to ~1e8: the relative
    # error of a backward-stable solve is ~cond x 1e-16 = 1e-8, so 1e-7 relative)
    rng = np.random.default_rng(30)
    for n, cond in ((1, 1.0), (7, 10.0), (145, 1e8)):
        Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
        S = (Q * np.geomspace(1.0, 1.0 / cond, n)) @ Q.T
        b = rng.standard_normal(n)
        x, ok = cholesky_solve(S, b)
        assert ok
        ref = np.linalg.solve(S, b)
        assert np.abs(x - ref).max() <= 1e-7 * np.abs(ref).max()
    S = np.diag([1.0, -1e-3, 2.0])
    assert not cholesky_solve(S, np.ones(3))[1]
    assert not cholesky_solve(np.diag([1.0, np.nan]), np.ones(2))[1]
    assert not cholesky_solve(np.diag([np.inf, 1.0]), np.ones(2))[1]  # an infinite pivot too
