"""geometry/depth.py: the per-pixel terms of AbsRel and delta1, on values worked out by hand."""
import numpy as np
import pytest

from d2gs_np.evaluation.metrics import depth_errors
from d2gs_np.geometry.depth import depth_error_terms


def test_relative_error_and_ratio_by_hand():
    true = np.array([[2.0, 4.0], [1.0, np.inf]])  # inf: no surface, not scored
    pred = np.array([[2.2, 3.0], [1.0, 7.0]])
    rel, ratio = depth_error_terms(pred, true)
    np.testing.assert_allclose(rel, [0.1, 0.25, 0.0], rtol=1e-15)
    np.testing.assert_allclose(ratio, [1.1, 4.0 / 3.0, 1.0], rtol=1e-15)
    m = depth_errors(pred, true)
    np.testing.assert_allclose(m["absrel"], (0.1 + 0.25 + 0.0) / 3, rtol=1e-15)
    assert m["delta1"] == 2 / 3 and m["num_pixels"] == 3  # 4/3 > 1.25 fails the threshold


@pytest.mark.parametrize("bad", [0.0, np.nan, np.inf, -3.0])
def test_a_pixel_where_nothing_was_rendered_scores_as_depth_zero(bad):
    # expected depth of an empty pixel is 0 (or inf/NaN from a division); it must count as a miss,
    # not vanish from the average or poison it
    rel, ratio = depth_error_terms(np.array([[bad, 2.0]]), np.array([[5.0, 2.0]]))
    np.testing.assert_array_equal(rel, [1.0, 0.0])
    assert np.isposinf(ratio[0]) and ratio[1] == 1.0
    m = depth_errors(np.array([[bad, 2.0]]), np.array([[5.0, 2.0]]))
    assert m["absrel"] == 0.5 and m["delta1"] == 0.5


def test_a_mask_scores_only_its_pixels_and_an_empty_one_gives_none():
    true = np.full((2, 3), 2.0)
    pred = np.array([[2.0, 2.0, 2.0], [4.0, 4.0, 4.0]])
    mask = np.array([[False] * 3, [True] * 3])
    assert depth_errors(pred, true, mask)["absrel"] == 1.0
    assert depth_errors(pred, true, ~mask)["absrel"] == 0.0
    assert depth_errors(pred, true, np.zeros((2, 3), bool)) == {"absrel": None, "delta1": None, "num_pixels": 0}


def test_shapes_and_masks_are_checked():
    with pytest.raises(ValueError, match=r"one shape; got \(2, 2\) and \(2, 3\)"):
        depth_error_terms(np.ones((2, 2)), np.ones((2, 3)))
    with pytest.raises(ValueError, match="mask must be a bool array"):
        depth_error_terms(np.ones((2, 2)), np.ones((2, 2)), np.ones((2, 2)))
    with pytest.raises(TypeError, match="mask must be a bool"):
        depth_errors(np.ones((2, 2)), np.ones((2, 2)), np.ones((2, 2)))
