"""Levenberg-Marquardt pieces shared by the two pose solvers, and their robust loss (docs/method.md §5).

Two solvers minimise a robust sum of squares by Levenberg-Marquardt on IRLS-weighted normal
equations: the pose solver (``pose/gauss_newton.py`` ``solve``: dense normal equations over the
frames' endpoint perturbations) and the bundle adjustment's Schur-complement solver
(``pose/bundle.py`` ``_schur_lm``: the points eliminated). What the two loops share lives here.

Robust loss. SciPy's losses (``scipy.optimize.least_squares``, ``LOSSES``), in SciPy's form:
``robust_loss(z)`` gives rho(z) and rho'(z) of z = (r / d)^2, the cost is 0.5 d^2 sum_i rho(z_i)
and the IRLS weight of residual i is rho'(z_i) (the weight rho_r'(r) / r of rho_r(r) = 0.5 d^2
rho((r / d)^2)), so the weighted normal equations H = J^T W J, g = J^T W r carry the exact
gradient of the robust cost. The pose solver names its losses ``ROBUST_LOSSES`` ("none", "huber",
"cauchy"; ``SCIPY_LOSS`` gives SciPy's name of each) and sums them over its data rows with
``robust_cost``: "none" and "cauchy" are ``robust_loss`` itself; its Huber is written on |r|
(``r^2/2 if |r| <= d else d|r| - d^2/2``, weight ``d / max(|r|, d)``), the same function as SciPy's
Huber but not the same floating-point operations, so it is kept in that form (the pose solver's
results stay bitwise what they were).

Damping. lambda (relative to the Marquardt diagonal of each solver) is kept in
[LM_DAMPING_MIN, LM_DAMPING_MAX]; a trial step is accepted only if it lowers the cost
(``accept_step``; a non-finite cost counts as +inf, ``finite_or_inf``), so the cost never rises,
and a solver stops when lambda has reached LM_DAMPING_MAX and a step is still refused
(``at_damping_limit``). ``Damping`` holds lambda and Nielsen's nu; two schedules update it:

- ``FixedFactors(up, down)`` (the pose solver): lambda x down after an accepted step, x up after a
  rejected one;
- ``Nielsen()`` (the bundle adjustment): after an accepted step lambda x max(1/3, 1 - (2 rho - 1)^3),
  rho = actual / predicted decrease (1 when the model predicts none), and nu = 2; after a
  rejected one lambda x nu, nu x 2.

What stays in each solver: the damped system and its solve (dense Cholesky with lambda scaled out
when it is large, or the Schur complement), the floor of the Marquardt diagonal, the budget
(linearisations or residual evaluations) and the stopping rules, which differ in form (the cost
decrease relative to the cost before or after the step, strict or not; the step relative to x
before or after it): one shared form would move either solver's decisions at the boundary.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from d2gs_np.constants import LM_DAMPING_MAX, LM_DAMPING_MIN
from d2gs_np.pose.config import ROBUST_LOSSES

__all__ = ["LOSSES", "SCIPY_LOSS", "robust_loss", "robust_cost", "Damping", "damping_start", "FixedFactors",
           "Nielsen", "at_damping_limit", "accept_step", "finite_or_inf"]

LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")  # SciPy's robust losses
SCIPY_LOSS = {"none": "linear", "huber": "huber", "cauchy": "cauchy"}  # the pose solver's losses by SciPy's names


# ---------------------------------------------------------------------------------------------
# Robust loss
# ---------------------------------------------------------------------------------------------


def robust_loss(z, loss):
    """SciPy's robust losses (``scipy.optimize.least_squares``): rho(z) and rho'(z) of z = (r / f_scale)^2,
    element-wise; the cost is 0.5 f_scale^2 sum rho(z) over residual elements.

    linear z; soft_l1 2 (sqrt(1 + z) - 1); huber z (z <= 1), 2 sqrt(z) - 1; cauchy ln(1 + z);
    arctan arctan(z).
    """
    z = np.asarray(z, dtype=np.float64)
    if loss == "linear":
        return z, np.ones_like(z)
    if loss == "soft_l1":
        t = np.sqrt(1.0 + z)
        return 2.0 * (t - 1.0), 1.0 / t
    if loss == "huber":
        small = z <= 1.0
        zs = np.sqrt(np.maximum(z, 1.0))
        return np.where(small, z, 2.0 * zs - 1.0), np.where(small, 1.0, 1.0 / zs)
    if loss == "cauchy":
        return np.log1p(z), 1.0 / (1.0 + z)
    if loss == "arctan":
        return np.arctan(z), 1.0 / (1.0 + z * z)
    raise ValueError(f"loss must be one of {LOSSES}; got {loss!r}")


def robust_cost(r, kind, scale):
    """The pose solver's robust cost sum_i rho(r_i) of residuals r and the IRLS weights rho'(r_i) / r_i
    (module docstring); kind in ``ROBUST_LOSSES``, scale = d in residual units ("none" has none)."""
    r = np.asarray(r, dtype=np.float64)
    if kind == "none":
        rho, w = robust_loss(r * r, SCIPY_LOSS[kind])
        return 0.5 * float(np.sum(rho)), w
    if kind == "huber":
        a = np.abs(r)
        inside = a <= scale
        rho = np.where(inside, 0.5 * r * r, scale * a - 0.5 * scale * scale)
        w = np.where(inside, 1.0, scale / np.maximum(a, scale))
        return float(np.sum(rho)), w
    if kind == "cauchy":
        rho, w = robust_loss((r / scale) ** 2, SCIPY_LOSS[kind])
        return float(np.sum(0.5 * scale * scale * rho)), w
    raise ValueError(f"robust loss must be one of {ROBUST_LOSSES}; got {kind!r}")


# ---------------------------------------------------------------------------------------------
# Damping and the acceptance of a step
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Damping:
    """Levenberg-Marquardt state: lambda and Nielsen's nu (the fixed-factor schedule leaves nu alone)."""

    lam: float
    nu: float = 2.0


def damping_start(lam) -> Damping:
    """The first lambda, clipped into [LM_DAMPING_MIN, LM_DAMPING_MAX]."""
    return Damping(min(max(float(lam), LM_DAMPING_MIN), LM_DAMPING_MAX))


def _clip(lam):
    return min(max(lam, LM_DAMPING_MIN), LM_DAMPING_MAX)


@dataclass(frozen=True)
class FixedFactors:
    """lambda x ``down`` after an accepted step, x ``up`` after a rejected one (up > 1 > down > 0)."""

    up: float
    down: float

    def accepted(self, d: Damping, decrease=None, predicted=None) -> Damping:
        return Damping(_clip(d.lam * self.down), d.nu)

    def rejected(self, d: Damping) -> Damping:
        return Damping(min(d.lam * self.up, LM_DAMPING_MAX), d.nu)


@dataclass(frozen=True)
class Nielsen:
    """Nielsen's schedule: the accepted step's gain ratio rho = decrease / predicted sets the new lambda."""

    def accepted(self, d: Damping, decrease, predicted) -> Damping:
        gain = decrease / predicted if predicted > 0 else 1.0
        return Damping(_clip(d.lam * max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)), 2.0)

    def rejected(self, d: Damping) -> Damping:
        return Damping(min(d.lam * d.nu, LM_DAMPING_MAX), 2.0 * d.nu)


def at_damping_limit(d: Damping) -> bool:
    """lambda has reached LM_DAMPING_MAX: a step refused now is refused for good."""
    return d.lam >= LM_DAMPING_MAX


def accept_step(cost, cost_new) -> bool:
    """A trial step is taken only if it lowers the cost (a non-finite cost is +inf: never taken)."""
    return cost_new < cost


def finite_or_inf(cost):
    """The cost, or +inf where it is not finite (a residual overflowed, a point left a camera)."""
    return cost if math.isfinite(cost) else math.inf
