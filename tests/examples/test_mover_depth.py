"""examples/mover_depth.py: the movers' depth ratios and where they land in a novel view, on cases
whose answer is known, including a point projected through two real cameras."""
import numpy as np
import pytest

from d2gs_np.geometry import look_at
from example_fixtures import load_example

md = load_example("mover_depth.py")


def test_depth_ratios_over_the_moving_pixels_only():
    true = np.full((4, 5), 2.0)
    expected = true.copy()
    mask = np.zeros((4, 5), bool)
    mask[1:3, 1:4] = True  # 6 moving pixels
    expected[mask] = 2.0 * np.array([0.9, 0.95, 1.0, 1.0, 1.05, 1.1])
    expected[~mask] = 100.0  # the static pixels must not count
    med, lo, hi = md.depth_ratios(expected, true, mask)
    assert med == pytest.approx(1.0)
    assert lo == pytest.approx(np.percentile([0.9, 0.95, 1.0, 1.0, 1.05, 1.1], 10))
    assert hi == pytest.approx(np.percentile([0.9, 0.95, 1.0, 1.0, 1.05, 1.1], 90))
    true[1, 1] = 0.0  # no true depth there: left out
    assert md.depth_ratios(expected, true, mask)[0] == pytest.approx(1.0)


def test_bad_input_is_refused_by_name():
    with pytest.raises(ValueError, match="share a shape"):
        md.depth_ratios(np.ones((2, 2)), np.ones((2, 3)), np.ones((2, 3), bool))
    with pytest.raises(ValueError, match="no moving pixel"):
        md.depth_ratios(np.ones((2, 2)), np.ones((2, 2)), np.zeros((2, 2), bool))
    with pytest.raises(ValueError, match="depth must be positive"):
        md.parallax_px(200.0, 0.1, 0.0)


def test_landing_matches_a_point_projected_through_two_cameras():
    # a point at depth z seen by a camera and one moved sideways by b; rendered at r x its depth
    # along the first camera's ray, it lands parallax x |1 - 1/r| from where it belongs
    f, b, z, r = 210.0, 0.12, 2.5, 0.93
    K = np.array([[f, 0, 120.0], [0, f, 67.5], [0, 0, 1]])
    cam0 = look_at(np.array([0.0, 0.0, 5.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    cam1 = cam0.copy()
    cam1[0, 3] -= b  # the camera moved +b along its own x axis
    x_cam0 = np.array([0.3, -0.2, z])
    world = np.linalg.solve(cam0, np.r_[x_cam0, 1.0])[:3]
    wrong = np.linalg.solve(cam0, np.r_[x_cam0 * r, 1.0])[:3]

    def project(T, X):
        p = K @ (T[:3, :3] @ X + T[:3, 3])
        return p[:2] / p[2]

    moved = np.linalg.norm(project(cam1, wrong) - project(cam1, world))
    par = md.parallax_px(f, b, z)
    assert par == pytest.approx(np.linalg.norm(project(cam1, world) - project(cam0, world)), rel=1e-12)
    shift, spread = md.landing(par, (r, r, r))
    assert shift == pytest.approx(moved, rel=1e-9) and spread == 0.0
    assert md.landing(par, (1.0, 0.9, 1.1))[1] == pytest.approx(par * (1 / 0.9 - 1 / 1.1))


def test_best_shift_finds_the_shift_that_made_the_render():
    rng = np.random.default_rng(3)
    truth = rng.random((30, 40, 3))
    mask = np.zeros((30, 40), bool)
    mask[8:20, 10:30] = True
    dy, dx = 2, -3  # the render is the truth moved by (-dy, -dx): shifting it back by (dy, dx) restores it
    render = np.roll(truth, (-dy, -dx), axis=(0, 1)) + 1e-3 * rng.standard_normal(truth.shape)
    at0, top, shift = md.best_shift(render, truth, mask, radius=4)
    assert shift == (dy, dx)
    # at the right shift only the added noise is left: PSNR = -10 log10(1e-6) = 60 dB within the
    # sample variance of 240 x 3 squared normals (a few per cent, well under 0.5 dB)
    assert top == pytest.approx(60.0, abs=0.5)
    assert at0 < 15.0  # uniform noise images apart by a shift: MSE ~ 1/6, about 7.8 dB
    # outside the search radius the true shift is not found, and the score at it is not claimed
    assert md.best_shift(render, truth, mask, radius=1)[2] != (dy, dx)


def test_best_shift_ignores_pixels_whose_source_leaves_the_image():
    truth = np.zeros((6, 6, 1))
    render = np.zeros((6, 6, 1))
    mask = np.zeros((6, 6), bool)
    mask[0, :] = True  # the top row: a shift down by 1 reads from row -1 for all of them
    render[0, :] = 1.0  # wrong everywhere at no shift
    at0, top, shift = md.best_shift(render, truth, mask, radius=1)
    assert at0 == 0.0  # MSE 1
    assert top == np.inf and shift[0] == -1  # read from row 1, which is right: the search takes it


def test_best_shift_refuses_bad_input_by_name():
    with pytest.raises(ValueError, match="render and truth"):
        md.best_shift(np.ones((4, 4, 3)), np.ones((4, 5, 3)), np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="radius"):
        md.best_shift(np.ones((4, 4, 3)), np.ones((4, 4, 3)), np.ones((4, 4), bool), radius=-1)
    with pytest.raises(ValueError, match="no moving pixel"):
        md.best_shift(np.ones((4, 4, 3)), np.ones((4, 4, 3)), np.zeros((4, 4), bool))
