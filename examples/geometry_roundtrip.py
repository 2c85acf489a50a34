"""Maximal exp/log round-trip errors of SO(3) and SE(3) per angle regime, and the worst error of
the Lie coefficient functions against a 160-digit evaluation of their closed forms.

    python examples/geometry_roundtrip.py [--samples 2000]

Round trips (max over samples, random axes, translations ~ N(0, 1)):
- "log(exp)": |log(exp(xi)) - xi|_inf; at theta = pi exactly, min over the two logarithms +-pi a;
- "exp(log)": |exp(log(X)) - X|_inf with X = exp(xi).
"""
from __future__ import annotations

import argparse
import math
from decimal import Decimal, localcontext

import numpy as np

from d2gs_np.constants import LOG_SYMMETRIC_BRANCH_COS, SERIES_ANGLE2
from d2gs_np.geometry import se3, so3

REGIMES = {
    "0": 0.0,
    "1e-12": 1e-12,
    "1e-8": 1e-8,
    "1e-4": 1e-4,
    "th2 = SERIES_ANGLE2 - tiny": math.sqrt(SERIES_ANGLE2) * (1 - 1e-12),
    "th2 = SERIES_ANGLE2 + tiny": math.sqrt(SERIES_ANGLE2) * (1 + 1e-12),
    "cos = LOG_SYM_COS + 1e-12": math.acos(LOG_SYMMETRIC_BRANCH_COS + 1e-12),
    "cos = LOG_SYM_COS - 1e-12": math.acos(LOG_SYMMETRIC_BRANCH_COS - 1e-12),
    "random in (0, pi)": None,
    "pi - 1e-4": math.pi - 1e-4,
    "pi - 1e-9": math.pi - 1e-9,
    "pi": math.pi,
}


def round_trip_table(n, rng):
    rows = []
    for name, theta in REGIMES.items():
        axes = rng.normal(size=(n, 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        angles = rng.uniform(0, math.pi, n) if theta is None else np.full(n, theta)
        phi = axes * angles[:, None]
        xi = np.concatenate([rng.normal(size=(n, 3)), phi], axis=1)
        R, T = so3.so3_exp(phi), se3.se3_exp(xi)
        phi_back, xi_back = so3.so3_log(R), se3.se3_log(T)
        if name == "pi":  # both +-pi a are logarithms; compare the rotation part up to sign
            so3_le = np.minimum(np.abs(phi_back - phi).max(1), np.abs(phi_back + phi).max(1)).max()
            se3_le = np.minimum(np.abs(xi_back[:, 3:] - phi).max(1), np.abs(xi_back[:, 3:] + phi).max(1)).max()
        else:
            so3_le, se3_le = np.abs(phi_back - phi).max(), np.abs(xi_back - xi).max()
        so3_el = np.abs(so3.so3_exp(phi_back) - R).max()
        se3_el = np.abs(se3.se3_exp(xi_back) - T).max()
        rows.append((name, so3_le, so3_el, se3_le, se3_el))
    return rows


def _dec_sin_cos(t, digits):
    tiny = Decimal(10) ** -(digits + 5)
    x2, s, c, ts, tc, k = t * t, Decimal(0), Decimal(0), t, Decimal(1), 0
    while abs(ts) > tiny or abs(tc) > tiny:
        s, c = s + ts, c + tc
        ts, tc = -ts * x2 / ((2 * k + 2) * (2 * k + 3)), -tc * x2 / ((2 * k + 1) * (2 * k + 2))
        k += 1
    return s, c


def _closed_forms(x, digits):
    t = x.sqrt()
    s, c = _dec_sin_cos(t, digits)
    sh, ch = _dec_sin_cos(t / 2, digits)
    return {"coef_a": s / t, "coef_b": (1 - c) / x, "coef_c": (t - s) / (x * t),
            "coef_d": (1 - (t / 2) * ch / sh) / x, "_coef_q2": (x + 2 * c - 2) / (2 * x * x),
            "_coef_q3": (2 * t - 3 * s + t * c) / (2 * x * x * t)}


def coefficient_table(n_grid, digits=160):
    """Worst |f_hat - f| / (|f| + |x f'(x)|) (x = theta^2) over log-spaced theta in [1e-10, pi]."""
    funcs = {"coef_a": so3.coef_a, "coef_b": so3.coef_b, "coef_c": so3.coef_c, "coef_d": so3.coef_d,
             "_coef_q2": se3._coef_q2, "_coef_q3": se3._coef_q3}
    theta = np.logspace(-10, math.log10(math.pi), n_grid)
    xs = list(theta**2) + [np.nextafter(SERIES_ANGLE2, 0.0), SERIES_ANGLE2]
    worst = {k: (0.0, 0.0, 0.0) for k in funcs}
    with localcontext() as ctx:
        ctx.prec = digits
        for x in xs:
            xd = Decimal(float(x))
            dx = xd * Decimal(10) ** -50
            f0, fp, fm = _closed_forms(xd, digits), _closed_forms(xd + dx, digits), _closed_forms(xd - dx, digits)
            for k, func in funcs.items():
                err = abs(Decimal(float(func(np.array([x]))[0])) - f0[k])
                cond = float(err / (abs(f0[k]) + abs(xd * (fp[k] - fm[k]) / (2 * dx))))
                if cond > worst[k][0]:
                    worst[k] = (cond, float(err / abs(f0[k])), math.sqrt(x))
    return worst


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=2000, help="random axes per regime")
    parser.add_argument("--grid", type=int, default=400, help="theta grid points for the coefficients")
    args = parser.parse_args()
    rng = np.random.default_rng(0)

    print(f"max round-trip error over {args.samples} samples per regime (inf-norm)")
    print(f"{'theta':28s} {'SO3 log(exp)':>13s} {'SO3 exp(log)':>13s} {'SE3 log(exp)':>13s} {'SE3 exp(log)':>13s}")
    for name, *errs in round_trip_table(args.samples, rng):
        print(f"{name:28s} " + " ".join(f"{e:13.2e}" for e in errs))

    print(f"\ncoefficient functions vs 160-digit closed forms, {args.grid} log-spaced theta in [1e-10, pi]")
    print(f"{'function':10s} {'cond-rel err':>13s} {'rel err':>10s} {'at theta':>10s}")
    for k, (cond, rel, at) in coefficient_table(args.grid).items():
        print(f"{k:10s} {cond:13.2e} {rel:10.2e} {at:10.4f}")
    print("cond-rel err = |f_hat - f| / (|f| + |x f'(x)|), x = theta^2 (coef_a = sin t / t vanishes at pi)")


if __name__ == "__main__":
    main()
