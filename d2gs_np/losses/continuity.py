"""Exposure continuity L_cont: neighbouring exposures lie on one smooth camera path (docs/method.md §6).

Frame i's exposure runs from S_i = exp(a_i) T̂_i to E_i = exp(b_i) T̂_i over tau; the next frame j
starts tau / 2 before its time t_j. On a camera moving at a constant velocity the motion within an
exposure and the motion across the gap to the next exposure are the same twist scaled by their
durations (tau and Δ − tau, Δ = t_j − t_i). With

    m_i = log(E_i S_i^-1) = log(exp(b_i) exp(-a_i))          (frame i's exposure; T̂_i cancels)
    g   = log(S_j E_i^-1) = log(exp(a_j) T̂_j T̂_i^-1 exp(-b_i))  (the gap)
    e   = tau / Δ                                             (the exposure fraction)

the residual of the pair is r = e g − (1 − e) (m_i + m_j) / 2, zero on any constant-velocity path
(g = (Δ − tau) v, m = tau v), and the term is the mean over pairs of |w ∘ r|², w the per-component
pixel weights (translation x focal / depth, rotation x focal: ``pixel_weights``), so its value is in
squared pixels. At e = 1 (exposure as long as the frame) it ties the end of one exposure to the
start of the next (DyBluRF's tie); at e = 0 it asks each exposure not to move. It relates only the
endpoints' offsets and the reference poses' relative motion, so a frame whose images carry little
(a streaked frame without tracks) is pulled onto the path its neighbours' exposures show.

Backward: a left perturbation of a tangent, exp(p + d) = exp(J_l(p) d) exp(p), and
log(exp(eps) X) = log X + J_l(log X)^-1 eps, log(X exp(eps)) = log X + J_r(log X)^-1 eps give, for
X = exp(p) D exp(-q): d log X / dp = J_l(x)^-1 J_l(p), d log X / dq = -J_r(x)^-1 J_l(q), x = log X.
d r / d tau = (g + (m_i + m_j) / 2) / Δ.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.geometry.se3 import (se3_exp, se3_inverse, se3_left_jacobian, se3_left_jacobian_inv, se3_log,
                                  se3_right_jacobian_inv)

__all__ = ["continuity_fwd", "continuity_bwd", "time_pairs", "pixel_weights"]


def time_pairs(times, frames=None):
    """(P, 2) int64 pairs (i, j) of frames next to each other in time (t_i < t_j); with ``frames``
    only the pairs that hold one of them. Times must be distinct."""
    t = np.asarray(times, dtype=np.float64)
    order = np.argsort(t, kind="stable")
    if t.size > 1 and not np.all(np.diff(t[order]) > 0):
        raise ValueError("time_pairs: two frames share a time; exposure continuity needs distinct frame times")
    pairs = np.stack([order[:-1], order[1:]], axis=1).astype(np.int64)
    if frames is not None:
        keep = np.isin(pairs, np.atleast_1d(np.asarray(frames, dtype=np.int64))).any(axis=1)
        pairs = pairs[keep]
    return pairs


def pixel_weights(focal, depth=None):
    """(6,) weights taking a tangent (rho, phi) to pixels: focal / depth on the translation, focal on
    the rotation (``blur.endpoints.tangent_px``'s scales). ``depth`` None or not positive: the
    translation is weighted as at depth 1."""
    f = float(focal)
    if not np.isfinite(f) or f <= 0:
        raise ValueError(f"pixel_weights: focal must be a positive number of pixels; got {focal}")
    d = float(depth) if depth is not None and np.isfinite(depth) and depth > 0 else 1.0
    return np.array([f / d] * 3 + [f] * 3, dtype=np.float64)


def _sandwich(p, D, q):
    """x = log(exp(p) D exp(-q)) (P, 6) and its Jacobians (P, 6, 6) in p and q (module docstring)."""
    X = se3_exp(p) @ D @ se3_exp(-q)
    x = se3_log(X)
    jp = se3_left_jacobian_inv(x) @ se3_left_jacobian(p)
    jq = -se3_right_jacobian_inv(x) @ se3_left_jacobian(q)
    return x, jp, jq


def continuity_fwd(xi_start, xi_end, poses_ref, times, tau, pairs, weights):
    """Mean over ``pairs`` of |weights ∘ r|² (module docstring).

    xi_start, xi_end: (N, 6) left tangents of every frame's exposure endpoints about ``poses_ref``
    (N, 4, 4, cam_T_world). times: (N,). tau: the exposure length in the units of ``times``, in
    [0, min Δ]. pairs: (P, 2) frames (i, j) with t_i < t_j (``time_pairs``); P = 0 gives 0.
    weights: (6,). Returns (value, a float, saved).
    """
    xs = np.asarray(xi_start, dtype=np.float64)
    xe = np.asarray(xi_end, dtype=np.float64)
    P = np.asarray(poses_ref, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    w = np.asarray(weights, dtype=np.float64)
    N = xs.shape[0]
    if xs.shape != (N, 6) or xe.shape != (N, 6) or P.shape != (N, 4, 4) or t.shape != (N,) or w.shape != (6,):
        raise ValueError(f"continuity_fwd: xi_start, xi_end (N, 6), poses_ref (N, 4, 4), times (N,) and weights (6,) "
                         f"expected; got {xs.shape}, {xe.shape}, {P.shape}, {t.shape}, {w.shape}")
    for name, a in (("xi_start", xs), ("xi_end", xe), ("poses_ref", P), ("times", t), ("weights", w)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"continuity_fwd: {name} holds NaN or inf")
    if pairs.shape[0]:
        delta = t[pairs[:, 1]] - t[pairs[:, 0]]
        if not np.all(delta > 0):
            raise ValueError("continuity_fwd: every pair (i, j) needs t_i < t_j")
        tau = float(tau)
        if not (np.isfinite(tau) and 0.0 <= tau <= float(delta.min()) * (1.0 + 1e-12)):
            raise ValueError(f"continuity_fwd: tau must lie in [0, the shortest frame interval {delta.min():.6g}]; "
                             f"got {tau}")
    return _continuity_fwd(xi_start, xi_end, P, t, tau, pairs, w)


def _continuity_fwd(xi_start, xi_end, P, t, tau, pairs, w):
    """``continuity_fwd`` without validation (the training step's path: a validated model, pairs from
    ``time_pairs``, tau within the frame interval)."""
    xs = np.asarray(xi_start, dtype=np.float64)
    xe = np.asarray(xi_end, dtype=np.float64)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    saved = {"P": 0, "N": xs.shape[0], "dtypes": (np.asarray(xi_start).dtype, np.asarray(xi_end).dtype)}
    if pairs.shape[0] == 0:
        return 0.0, saved
    i, j = pairs[:, 0], pairs[:, 1]
    delta = t[j] - t[i]
    e = np.minimum(float(tau) / delta, 1.0)[:, None]
    eye = np.broadcast_to(np.eye(4), (len(i), 4, 4))
    g, ga, gb = _sandwich(xs[j], P[j] @ se3_inverse(P[i]), xe[i])  # gap: da_j, db_i
    mi, mib, mia = _sandwich(xe[i], eye, xs[i])  # exposure i: db_i, da_i
    mj, mjb, mja = _sandwich(xe[j], eye, xs[j])
    mbar = 0.5 * (mi + mj)
    r = e * g - (1.0 - e) * mbar
    wr = w * r
    value = float(np.mean(np.sum(wr * wr, axis=1)))
    saved.update(P=len(i), i=i, j=j, e=e, delta=delta, r=r, w=w, g=g, mbar=mbar,
                 jac=(ga, gb, mib, mia, mjb, mja), clipped=(float(tau) / delta > 1.0))
    return value, saved


def continuity_bwd(saved, v_value=1.0):
    """Gradients of ``v_value * continuity_fwd(...)[0]``: (g_xi_start (N, 6), g_xi_end (N, 6), g_tau)
    (rows of frames in no pair are zero; g_tau a float)."""
    N, dts = saved["N"], saved["dtypes"]
    gs, ge = np.zeros((N, 6)), np.zeros((N, 6))
    if saved["P"] == 0:
        return gs.astype(dts[0]), ge.astype(dts[1]), 0.0
    i, j, e, w, r = saved["i"], saved["j"], saved["e"], saved["w"], saved["r"]
    v_r = (2.0 * float(v_value) / saved["P"]) * (w * w) * r  # (P, 6)
    ga, gb, mib, mia, mjb, mja = saved["jac"]

    def pull(J, v):  # J^T v per pair
        return np.einsum("pki,pk->pi", J, v)

    v_g = e * v_r
    v_m = -0.5 * (1.0 - e) * v_r  # on m_i and on m_j
    np.add.at(gs, j, pull(ga, v_g))
    np.add.at(ge, i, pull(gb, v_g))
    np.add.at(ge, i, pull(mib, v_m))
    np.add.at(gs, i, pull(mia, v_m))
    np.add.at(ge, j, pull(mjb, v_m))
    np.add.at(gs, j, pull(mja, v_m))
    dr_dtau = np.where(saved["clipped"][:, None], 0.0, (saved["g"] + saved["mbar"]) / saved["delta"][:, None])
    g_tau = float(np.sum(v_r * dr_dtau))
    return gs.astype(dts[0]), ge.astype(dts[1]), g_tau
