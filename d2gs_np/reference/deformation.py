"""Reference DDDM deformation (docs/method.md §2): the obvious per-Gaussian loop, float64.

Same conventions as ``d2gs_np.scene.deformation`` (coefficient axis
[a_1..a_P, f_sin_1..f_sin_L, f_cos_1..f_cos_L], quaternion residual added to the raw wxyz base
and renormalised, identity quaternion where the sum has norm < QUAT_NORM_MIN), written
term by term from the equation

    A(t) = A0 + sum_{n=1..P} a_n t^n + sum_{l=1..L} (f_sin,l sin(l w t) + f_cos,l cos(l w t)).

It does not import the fast path; tests compare the two.
"""
from __future__ import annotations

import math

import numpy as np

from d2gs_np.constants import QUAT_NORM_MIN


def _residual(coef, t, degree, order, omega):
    """D(t) for one Gaussian's coefficient matrix ``coef`` (K, D)."""
    out = np.zeros(coef.shape[1])
    for n in range(1, degree + 1):
        out += coef[n - 1] * t**n
    for l in range(1, order + 1):
        out += coef[degree + l - 1] * math.sin(l * omega * t)
        out += coef[degree + order + l - 1] * math.cos(l * omega * t)
    return out


def deform(base_means, base_quats, base_colors, coef_means, coef_quats, coef_colors, t, config):
    """Deformed (means (N, 3), quats (N, 4) unit wxyz, colors (N, 3)) at time ``t``, float64.

    Arguments as ``d2gs_np.scene.deformation.deform_fwd``; ``config`` is a DeformConfig.
    """
    P, L, w = int(config.degree), int(config.order), float(config.omega)
    t = float(t)
    N = len(base_means)
    means = np.zeros((N, 3))
    quats = np.zeros((N, 4))
    colors = np.zeros((N, 3))
    for i in range(N):
        means[i] = np.asarray(base_means[i], np.float64) + _residual(np.asarray(coef_means[i], np.float64), t, P, L, w)
        colors[i] = np.asarray(base_colors[i], np.float64) + _residual(
            np.asarray(coef_colors[i], np.float64), t, P, L, w
        )
        r = np.asarray(base_quats[i], np.float64) + _residual(np.asarray(coef_quats[i], np.float64), t, P, L, w)
        norm = math.sqrt(float(r @ r))
        quats[i] = np.array([1.0, 0.0, 0.0, 0.0]) if norm < QUAT_NORM_MIN else r / norm
    return means, quats, colors
