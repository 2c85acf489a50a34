"""Opacity entropy L_gs: value against the formula, backward vs central FD (both sides of the clamp),
and the stiff ends o -> 0, o = 1e-12, o = 1."""
import numpy as np
import pytest

from d2gs_np.constants import OPACITY_ENTROPY_MIN
from d2gs_np.losses.entropy import entropy_bwd, entropy_fwd
from render_fixtures import central_fd

# Central FD with h = 1e-6 on logits: the function is smooth on each side of the clamp and its
# third derivative is O(1), so the error is ~h^2 + rounding 1e-16 / h ~ 1e-10 against gradients
# ~1e-2; 1e-9 leaves margin while catching any wrong factor.
FD_H = 1e-6
FD_TOL = 1e-9


def _sigmoid(z):
    return 1.0 / (1.0 + np.exp(-z))


def test_value_is_the_mean_entropy():
    z = np.random.default_rng(0).normal(0.0, 2.0, size=50)
    o = _sigmoid(z)
    value, _ = entropy_fwd(z)
    assert value == pytest.approx(float(np.mean(-o * np.log(o))), rel=1e-13)


@pytest.mark.parametrize("low", [False, True])
def test_backward_matches_central_fd(low):
    rng = np.random.default_rng(1)
    # low: logits below logit(1e-6) ~ -13.8, where the clamp makes the term linear in o
    z = rng.uniform(-25.0, -15.0, size=12) if low else rng.uniform(-6.0, 6.0, size=12)
    _, saved = entropy_fwd(z)
    grad = entropy_bwd(saved, 0.7)
    fd = central_fd(lambda x: 0.7 * entropy_fwd(x)[0], z, FD_H)
    scale = 1.0 if not low else 1e-6  # gradients there are ~o ~ 1e-7: compare relative to that size
    np.testing.assert_allclose(grad, fd, rtol=0, atol=FD_TOL * scale)


def test_entropy_is_stationary_at_one_over_e_and_pushes_away_from_it():
    z = np.log(np.array([1.0 / np.e, 0.2, 0.6]) / (1.0 - np.array([1.0 / np.e, 0.2, 0.6])))
    grad = entropy_bwd(entropy_fwd(z)[1])
    assert abs(grad[0]) < 1e-15
    # gradient descent lowers a 0.2 opacity further and raises a 0.6 one (towards 0 or 1)
    assert grad[1] > 0 and grad[2] < 0


def test_stiff_ends_are_finite_and_correct():
    # o = 0 exactly (exp(-800) underflows), o = 1e-12 (below the clamp), o = 1 exactly (logit 40)
    z = np.array([-800.0, np.log(1e-12), 40.0])
    value, saved = entropy_fwd(z)
    grad = entropy_bwd(saved)
    assert np.all(np.isfinite(grad)) and np.isfinite(value)
    expected = (0.0 + 1e-12 * -np.log(OPACITY_ENTROPY_MIN) + 0.0) / 3
    assert value == pytest.approx(expected, rel=1e-9)
    assert grad[0] == 0.0
    assert grad[1] == pytest.approx(-np.log(OPACITY_ENTROPY_MIN) * 1e-12 / 3, rel=1e-9)
    assert -1e-17 < grad[2] <= 0.0  # -(log 1 + 1) o (1 - o) / 3 with 1 - o = sigmoid(-40) ~ 4e-18


def test_value_is_continuous_across_the_clamp():
    zc = np.log(OPACITY_ENTROPY_MIN / (1.0 - OPACITY_ENTROPY_MIN))
    below, _ = entropy_fwd(np.array([zc - 1e-9]))
    above, _ = entropy_fwd(np.array([zc + 1e-9]))
    assert abs(below - above) < 1e-13


def test_float32_keeps_its_dtype_and_empty_is_zero():
    z = np.array([0.3, -2.0], dtype=np.float32)
    assert entropy_bwd(entropy_fwd(z)[1]).dtype == np.float32
    value, saved = entropy_fwd(np.zeros(0))
    assert value == 0.0 and entropy_bwd(saved).shape == (0,)


def test_bad_input_names_the_argument():
    with pytest.raises(TypeError, match="opacity_logits must be a numpy array"):
        entropy_fwd([0.1, 0.2])
    with pytest.raises(ValueError, match=r"opacity_logits must have shape \(N,\)"):
        entropy_fwd(np.zeros((2, 1)))
    with pytest.raises(ValueError, match="NaN"):
        entropy_fwd(np.array([0.0, np.nan]))
