"""Exposure continuity L_cont (losses/continuity.py): zero on every constant-velocity path, its
hand-derived gradient against central differences in float64, the exposure-fraction ends (a
zero-length exposure, an exposure as long as the frame), tiny and large rotations, the neighbour
pairs, bad input, and that it moves a frame with noisy endpoints back onto its neighbours' path."""
import numpy as np
import pytest

from d2gs_np.geometry.se3 import se3_exp, se3_inverse, se3_log
from d2gs_np.losses.continuity import continuity_bwd, continuity_fwd, pixel_weights, time_pairs

W = pixel_weights(200.0, 3.0)


def _path(rng, N, times, vel_scale=0.3):
    """Reference poses on a constant-velocity path and the exact exposure offsets on it."""
    v = rng.normal(size=6) * vel_scale
    T0 = se3_exp(rng.normal(size=6))
    return v, np.stack([se3_exp(v * t) @ T0 for t in times])


def _fd(f, x, h):
    g = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        d = np.zeros_like(x)
        d[idx] = h
        g[idx] = (f(x + d) - f(x - d)) / (2 * h)
    return g


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_zero_on_every_constant_velocity_path(seed):
    # uneven frame times; the exposure offsets of each frame exactly on the path: r = 0 for every pair
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, 1, 6))
    v, P = _path(rng, 6, t)
    tau = 0.7 * np.diff(t).min()
    xs, xe = np.tile(-0.5 * tau * v, (6, 1)), np.tile(0.5 * tau * v, (6, 1))
    value, saved = continuity_fwd(xs, xe, P, t, tau, time_pairs(t), W)
    assert value < 1e-20
    gs, ge, gt = continuity_bwd(saved)
    assert np.abs(gs).max() < 1e-8 and np.abs(ge).max() < 1e-8 and abs(gt) < 1e-8


@pytest.mark.parametrize("scale", [1e-9, 1e-3, 0.1, 0.8])
def test_gradient_matches_central_differences(scale):
    # Offsets of size `scale` about reference poses 0.2-1 rad apart: the series branches of the
    # Jacobians (1e-9) through large angles. h = 1e-6 x max(scale, 1e-3): the truncation error is
    # O(h^2) ~ 1e-12 relative, rounding ~ 1e-16 x value / h; 1e-6 of the largest entry holds both
    # with room (measured 4e-11 .. 5e-8 relative).
    rng = np.random.default_rng(5)
    N = 5
    t = np.linspace(0.0, 1.0, N)
    P = np.stack([se3_exp(rng.normal(size=6) * 0.5) for _ in range(N)])
    xs, xe = rng.normal(size=(N, 6)) * scale, rng.normal(size=(N, 6)) * scale
    tau = 0.6 / (N - 1)
    pairs = time_pairs(t)
    value, saved = continuity_fwd(xs, xe, P, t, tau, pairs, W)
    assert np.isfinite(value) and value > 0
    gs, ge, gt = continuity_bwd(saved, 0.3)
    h = 1e-6 * max(scale, 1e-3)

    def f(a, b, c):
        return 0.3 * continuity_fwd(a, b, P, t, c, pairs, W)[0]

    for g, num in ((gs, _fd(lambda a: f(a, xe, tau), xs, h)), (ge, _fd(lambda b: f(xs, b, tau), xe, h))):
        np.testing.assert_allclose(g, num, rtol=0, atol=1e-6 * np.abs(num).max())
    num_t = (f(xs, xe, tau + 1e-7) - f(xs, xe, tau - 1e-7)) / 2e-7
    assert gt == pytest.approx(num_t, rel=1e-6)


def test_an_exposure_as_long_as_the_frame_ties_end_to_next_start():
    # e = 1: the residual is the gap log(S_j E_i^-1) alone, whatever the exposures' own motion
    rng = np.random.default_rng(3)
    t = np.array([0.0, 0.5])
    P = np.stack([se3_exp(rng.normal(size=6) * 0.3) for _ in t])
    xs, xe = rng.normal(size=(2, 6)) * 0.05, rng.normal(size=(2, 6)) * 0.05
    value, _ = continuity_fwd(xs, xe, P, t, 0.5, time_pairs(t), W)
    gap = se3_log(se3_exp(xs[1]) @ P[1] @ se3_inverse(se3_exp(xe[0]) @ P[0]))
    assert value == pytest.approx(float(np.sum((W * gap) ** 2)), rel=1e-12)


def test_a_zero_length_exposure_asks_the_exposures_not_to_move():
    # e = 0: r = -(m_i + m_j) / 2, finite, and zero once the endpoints coincide (any reference poses)
    rng = np.random.default_rng(4)
    t = np.array([0.0, 0.5, 1.0])
    P = np.stack([se3_exp(rng.normal(size=6)) for _ in t])
    xs = rng.normal(size=(3, 6)) * 0.05
    value, saved = continuity_fwd(xs, xs + 0.01, P, t, 0.0, time_pairs(t), W)
    assert np.isfinite(value) and value > 0
    assert all(np.all(np.isfinite(g)) for g in continuity_bwd(saved)[:2])
    assert continuity_fwd(xs, xs.copy(), P, t, 0.0, time_pairs(t), W)[0] < 1e-24


def test_reference_motion_near_a_half_turn_stays_finite():
    # neighbouring reference poses 179.9 degrees apart (far beyond a camera's frame-to-frame turn)
    t = np.array([0.0, 1.0])
    turn = np.r_[0.1, 0.0, 0.0, 0.0, 0.0, np.deg2rad(179.9)]
    P = np.stack([np.eye(4), se3_exp(turn)])
    xs, xe = np.full((2, 6), 1e-3), np.full((2, 6), -1e-3)
    value, saved = continuity_fwd(xs, xe, P, t, 0.5, time_pairs(t), W)
    assert np.isfinite(value) and all(np.all(np.isfinite(g)) for g in continuity_bwd(saved)[:2])


def test_pairs_follow_time_not_index():
    t = np.array([0.5, 0.0, 1.0, 0.25])
    assert time_pairs(t).tolist() == [[1, 3], [3, 0], [0, 2]]
    assert time_pairs(t, [0]).tolist() == [[3, 0], [0, 2]]
    assert time_pairs(t, [1]).tolist() == [[1, 3]]
    assert time_pairs(np.array([0.3])).shape == (0, 2)
    with pytest.raises(ValueError, match="share a time"):
        time_pairs(np.array([0.0, 0.5, 0.5]))


def test_bad_input_is_refused():
    t = np.array([0.0, 0.5, 1.0])
    P = np.stack([np.eye(4)] * 3)
    z = np.zeros((3, 6))
    with pytest.raises(ValueError, match="tau must lie"):
        continuity_fwd(z, z, P, t, 0.6, time_pairs(t), W)
    with pytest.raises(ValueError, match="tau must lie"):
        continuity_fwd(z, z, P, t, -0.1, time_pairs(t), W)
    bad = z.copy()
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="xi_start holds NaN"):
        continuity_fwd(bad, z, P, t, 0.2, time_pairs(t), W)
    with pytest.raises(ValueError, match=r"\(N, 6\)"):
        continuity_fwd(z[:, :5], z, P, t, 0.2, time_pairs(t), W)
    with pytest.raises(ValueError, match="t_i < t_j"):
        continuity_fwd(z, z, P, t, 0.2, np.array([[2, 1]]), W)
    with pytest.raises(ValueError, match="focal"):
        pixel_weights(0.0)
    assert continuity_fwd(z, z, P, t, 0.2, np.zeros((0, 2)), W)[0] == 0.0
    np.testing.assert_array_equal(pixel_weights(100.0, None), [100.0] * 6)


def test_descent_moves_a_noisy_frame_back_onto_its_neighbours_path():
    # Five frames on a constant-velocity path; frame 2's reference pose is off by 0.5 degree and a
    # sideways shift (a streaked frame held at a noisy given pose). Its neighbours' exposures sit on
    # the true path; gradient descent on frame 2's endpoints alone brings its mid-exposure pose to
    # the true one, from 0.5 deg to < 0.01 deg, the term's value down 1000-fold.
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 1.0, 5)
    v, true = _path(rng, 5, t, 0.4)
    tau = 0.6 * 0.25
    noise = se3_exp(np.r_[0.02, -0.01, 0.0, 0.0, np.deg2rad(0.5), 0.0])
    P = true.copy()
    P[2] = noise @ true[2]
    xs, xe = np.tile(-0.5 * tau * v, (5, 1)), np.tile(0.5 * tau * v, (5, 1))
    w = pixel_weights(200.0, 3.0)

    def mid_error(xs, xe):
        mid = se3_exp(0.5 * (xs[2] + xe[2])) @ P[2]
        return np.rad2deg(np.linalg.norm(se3_log(mid @ se3_inverse(true[2]))[3:]))

    before = mid_error(xs, xe)
    pairs = time_pairs(t, [2])
    start = continuity_fwd(xs, xe, P, t, tau, pairs, w)[0]
    lr = 0.2 / (w.max() ** 2)
    for _ in range(1000):
        value, saved = continuity_fwd(xs, xe, P, t, tau, pairs, w)
        gs, ge, _ = continuity_bwd(saved)
        xs[2] -= lr * gs[2]
        xe[2] -= lr * ge[2]
    assert before == pytest.approx(0.5, rel=0.05)
    assert mid_error(xs, xe) < 0.01 and value < 1e-3 * start
