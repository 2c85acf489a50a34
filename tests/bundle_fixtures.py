"""Shared checks of the bundle adjustment's two solvers (tests/pose)."""
import numpy as np

from d2gs_np.pose.bundle import BundleProblem, bundle_adjust


def schur_then_scipy(prob: BundleProblem, kw: dict):
    """The Schur solver run to convergence, then SciPy started at its optimum: SciPy must find no
    lower cost (1e-10 relative) and not move it (1e-5 in every unknown; the bounds are justified in
    tests/pose/test_bundle_schur.py). Returns the Schur solver's (cams, points, focal, info)."""
    c1, p1, f1, i1 = bundle_adjust(prob, solver="schur", max_nfev=200, **kw)
    assert i1["status"] == 2
    start = BundleProblem(c1, p1, f1, prob.cx, prob.cy, prob.cam_idx, prob.pt_idx, prob.uv)
    c3, p3, _, i3 = bundle_adjust(start, solver="scipy", max_nfev=100, **kw)
    assert i3["cost"] >= i1["cost"] * (1 - 1e-10)
    np.testing.assert_allclose(c3, c1, atol=1e-5)
    np.testing.assert_allclose(p3, p1, atol=1e-5)
    return c1, p1, f1, i1
