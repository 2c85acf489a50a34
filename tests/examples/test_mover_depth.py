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
