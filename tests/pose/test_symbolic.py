"""The pose solver's CasADi functions (d2gs_np/pose/symbolic.py): the symbolic mid pose is the
geodesic midpoint of ``geometry/se3.py``, and its Jacobian matches central differences in every
branch of the symbolic exp and log."""
import numpy as np
import pytest

from d2gs_np.geometry.se3 import se3_exp, se3_interpolate
from d2gs_np.pose import symbolic as sym

# Central differences with h = 1e-6 in float64: truncation ~h^2 |third derivative| ~ 1e-12 and
# rounding ~1e-16 / h ~ 1e-10 for the O(1) entries of the mid pose: 1e-6 relative to max(1, |J|)
# leaves a margin of 100 over both.
FD_STEP = 1e-6
FD_REL_TOL = 1e-6


@pytest.mark.parametrize("rot", [0.0, 1e-8, 0.3, 0.49, 0.51, 1.0, 3.0])  # both sides of SERIES_ANGLE2, near pi
@pytest.mark.parametrize("spread", [0.0, 1e-8, 9e-4, 1.1e-3, 0.2, 0.8])  # both sides of sin^2 = 1e-6 and of SERIES_ANGLE2
def test_mid_pose_jacobian_in_every_branch(rot, spread):
    rng = np.random.default_rng(4)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    Ts = se3_exp(rng.normal(0, 0.5, 6))
    Te = se3_exp(np.r_[0.3 * spread, 0.0, 0.0, spread * axis]) @ Ts
    x = np.r_[rng.normal(0, 0.1, 3), rot * axis, rng.normal(0, 0.1, 3), rot * axis]
    f = sym.mid_function()
    fs, fe = sym.pose_to_flat(Ts), sym.pose_to_flat(Te)
    m0, dm, _, _ = f(x, fs, fe)
    dm = np.array(dm)
    assert np.all(np.isfinite(dm))
    fd = np.stack([(np.array(f(x + FD_STEP * e, fs, fe)[0]) - np.array(f(x - FD_STEP * e, fs, fe)[0])).ravel()
                   / (2 * FD_STEP) for e in np.eye(12)], axis=1)
    assert np.abs(dm - fd).max() <= FD_REL_TOL * max(1.0, np.abs(dm).max())
    S, E = se3_exp(x[:6]) @ Ts, se3_exp(x[6:]) @ Te
    assert np.abs(sym.flat_to_pose(np.array(m0).ravel()) - se3_interpolate(S, E, 0.5)).max() < 1e-12


def test_symbolic_mid_pose_is_the_geodesic_midpoint_and_exact_at_zero_spread():
    rng = np.random.default_rng(3)
    for spread in (0.0, 1e-9, 1e-4, 0.3):
        Ts = se3_exp(rng.normal(0, 0.5, 6))
        Te = se3_exp(rng.normal(0, spread, 6)) @ Ts if spread else Ts.copy()
        x = rng.normal(0, 0.05, 12)
        mid, dmid, s, e = sym.mid_function()(x, sym.pose_to_flat(Ts), sym.pose_to_flat(Te))
        S, E = se3_exp(x[:6]) @ Ts, se3_exp(x[6:]) @ Te
        assert np.allclose(sym.flat_to_pose(np.array(s).ravel()), S, atol=1e-14)
        assert np.abs(sym.flat_to_pose(np.array(mid).ravel()) - se3_interpolate(S, E, 0.5)).max() < 1e-13
        assert np.all(np.isfinite(np.array(dmid)))


def test_flat_poses_round_trip():
    T = se3_exp(np.random.default_rng(0).normal(0, 0.5, (5, 6)))
    assert np.array_equal(sym.flat_to_pose(sym.pose_to_flat(T)), T)
    assert np.array_equal(sym.pose_to_flat(T)[1, :9], T[1, :3, :3].ravel())  # R row-major, then t
