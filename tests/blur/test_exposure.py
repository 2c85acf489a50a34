"""Tests of the exposure length (d2gs_np.blur.exposure): known from the scene, and learned through
a sigmoid that keeps it inside the frame interval, its gradient against central finite
differences."""
from __future__ import annotations

import numpy as np
import pytest

import render_fixtures as rf
from d2gs_np.blur.exposure import EXPOSURE_BLOCK, exposure_bwd, exposure_from_scene, exposure_fwd, init_exposure


def test_exposure_from_scene():
    assert exposure_from_scene(0.5, 11) == pytest.approx(0.05, rel=1e-15)
    assert exposure_from_scene(1.0, 2) == 1.0
    assert exposure_from_scene(0.7, 1) == 0.0
    with pytest.raises(ValueError, match="exposure_fraction must be in"):
        exposure_from_scene(1.5, 10)


def test_learned_exposure_init_range_and_gradient():
    params = init_exposure()
    np.testing.assert_array_equal(params[EXPOSURE_BLOCK], [0.0])
    tau, _ = exposure_fwd(params, 21)
    assert tau == pytest.approx(0.5 / 20, rel=1e-15)
    for logit_value in (-30.0, -2.0, 0.3, 4.0, 30.0):  # always inside (0, 1) of the frame interval
        p = {EXPOSURE_BLOCK: np.array([logit_value])}
        tau, saved = exposure_fwd(p, 21)
        assert 0.0 <= tau * 20 <= 1.0
        g = exposure_bwd(saved, 1.0)[EXPOSURE_BLOCK]
        fd = rf.central_fd(lambda x: exposure_fwd({EXPOSURE_BLOCK: x}, 21)[0], p[EXPOSURE_BLOCK], 1e-6)
        # tau ~ 0.05: FD round-off ~1e-16 * 0.05 / 1e-6 ~ 1e-11, truncation ~h^2 ~ 1e-12
        np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-10)
    assert exposure_fwd(init_exposure(0.25), 5)[0] == pytest.approx(0.25 / 4, rel=1e-14)

