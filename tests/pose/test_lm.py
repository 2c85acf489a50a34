"""The Levenberg-Marquardt pieces of the pose solvers (d2gs_np/pose/lm.py): SciPy's robust losses, the
pose solver's robust cost and IRLS weights, the damping schedules and their limits."""
import numpy as np
import pytest
from scipy.optimize import least_squares

from d2gs_np.constants import LM_DAMPING_MAX, LM_DAMPING_MIN
from d2gs_np.pose.config import ROBUST_LOSSES
from d2gs_np.pose.lm import (LOSSES, SCIPY_LOSS, Damping, FixedFactors, Nielsen, accept_step, at_damping_limit,
                             damping_start, finite_or_inf, robust_cost, robust_loss)


@pytest.mark.parametrize("loss", LOSSES)
def test_robust_loss_is_scipys(loss):
    # rho against SciPy's own cost (least_squares with a constant residual stops at once and reports
    # 0.5 f^2 sum rho(z) there); rho' against central differences (h = 1e-6 on z in [0, 9]: truncation
    # ~h^2 |rho'''| < 1e-11, rounding ~1e-16 / 1e-6 = 1e-10, so 1e-8 absolute)
    r = np.array([0.0, 0.3, -0.9, 1.0, 1.7, -4.0, 25.0])
    fs = 1.3
    res = least_squares(lambda x: r + 0.0 * x[0], x0=[0.0], loss=loss, f_scale=fs, max_nfev=1)
    z = (r / fs) ** 2
    rho, drho = robust_loss(z, loss)
    assert 0.5 * fs ** 2 * np.sum(rho) == pytest.approx(res.cost, rel=1e-12)
    zz = np.linspace(0.05, 9.0, 40)
    h = 1e-6
    num = (robust_loss(zz + h, loss)[0] - robust_loss(zz - h, loss)[0]) / (2 * h)
    np.testing.assert_allclose(robust_loss(zz, loss)[1], num, atol=1e-8)


@pytest.mark.parametrize("kind", ROBUST_LOSSES)
def test_robust_cost_is_scipys_loss_and_its_weights_are_the_irls_weights(kind):
    # the cost against SciPy's form 0.5 d^2 sum rho((r / d)^2) of the same loss ("none": d = 1; the
    # Huber written on |r| rounds differently, so 1e-12 relative); the weight against rho_r'(r) / r by
    # central differences of the elementwise cost (h = 1e-6 on |r| >= 0.3: 1e-7 relative is ~100x the
    # truncation and rounding)
    r = np.array([0.3, -0.9, 1.0001, 1.7, -4.0, 25.0])
    d = 1.0 if kind == "none" else 1.3
    cost, w = robust_cost(r, kind, d)
    assert cost == pytest.approx(0.5 * d * d * np.sum(robust_loss((r / d) ** 2, SCIPY_LOSS[kind])[0]), rel=1e-12)
    h = 1e-6
    elementwise = lambda x: np.array([robust_cost(np.array([v]), kind, d)[0] for v in x])  # noqa: E731
    np.testing.assert_allclose(w, (elementwise(r + h) - elementwise(r - h)) / (2 * h) / r, rtol=1e-7)
    with pytest.raises(ValueError, match="robust loss must be one of"):
        robust_cost(r, "l1", d)


def test_the_damping_stays_within_its_limits():
    assert damping_start(1e300).lam == LM_DAMPING_MAX and damping_start(0.0).lam == LM_DAMPING_MIN
    fixed = FixedFactors(up=10.0, down=0.3)
    assert fixed.accepted(Damping(1.0)).lam == 0.3 and fixed.rejected(Damping(1.0)).lam == 10.0
    assert fixed.accepted(Damping(LM_DAMPING_MIN)).lam == LM_DAMPING_MIN
    top = fixed.rejected(Damping(0.5 * LM_DAMPING_MAX))
    assert top.lam == LM_DAMPING_MAX and at_damping_limit(top) and not at_damping_limit(Damping(0.5 * LM_DAMPING_MAX))


def test_nielsens_schedule():
    nielsen = Nielsen()
    # gain 1 (the model was exact): lambda / 3; gain 1/2: unchanged; gain 0 or no predicted decrease
    assert nielsen.accepted(Damping(3.0, nu=8.0), 2.0, 2.0) == Damping(1.0, 2.0)
    assert nielsen.accepted(Damping(3.0), 1.0, 2.0).lam == 3.0
    assert nielsen.accepted(Damping(3.0), 0.0, 2.0).lam == 6.0
    assert nielsen.accepted(Damping(3.0), 1.0, 0.0).lam == 1.0  # no decrease predicted: gain taken as 1
    # rejections: lambda x nu, nu doubled, lambda capped
    d = nielsen.rejected(nielsen.rejected(Damping(1.0)))
    assert d == Damping(8.0, 8.0)
    assert nielsen.rejected(Damping(LM_DAMPING_MAX, 4.0)).lam == LM_DAMPING_MAX


def test_a_step_is_taken_only_if_it_lowers_a_finite_cost():
    assert accept_step(2.0, 1.0) and not accept_step(1.0, 1.0) and not accept_step(1.0, 2.0)
    assert not accept_step(1.0, finite_or_inf(float("nan"))) and finite_or_inf(3.0) == 3.0
