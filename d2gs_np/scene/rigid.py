"""Rigid motion of tracked movers: one SE(3) path per cluster of dynamic Gaussians (issue #44).

A dynamic Gaussian of cluster c >= 0 (``dynamic.cluster``, a float block holding the integer id)
lives in its cluster's frame. Its deformed position x_l(t) and unit rotation q_l(t)
(``scene/deformation.py``: the residual motion) are carried to the world by its cluster's pose at t,

    x(t) = R(q_c(t)) x_l(t) + p_c(t),        q(t) = q_c(t) ⊗ q_l(t),

where p_c(t), q_c(t) follow the same polynomial + Fourier model (same basis, same K) as a
Gaussian's position and rotation, on the C-row blocks

    rigid.means (C, 3)   rigid.quats (C, 4) raw wxyz   rigid.deform_means (C, K, 3)   rigid.deform_quats (C, K, 4)

(docs/method.md §2). A cluster is one object: its Gaussians share one shape over the clip, so a
monocular camera sees one scale of it for the whole clip, not one per frame. Cluster -1: no rigid
motion (the residual deformation is the world motion, as in a scene without clusters). A scene
without ``rigid.*`` blocks does none of this work.

Conventions: R(q) is the rotation matrix of docs/conventions.md §1 evaluated at the deformation's
unit output; the backward goes through the deformation's normalisation Jacobian (``_deform_bwd``).
Vectorised NumPy over Gaussians; arrays keep their dtype. The loop-per-Gaussian reference is
``d2gs_np.reference.rigid.rigid_transform``.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.scene.deformation import _deform_bwd, _deform_fwd
from d2gs_np.scene.gaussians import CLUSTER, DYNAMIC, RIGID, has_rigid

__all__ = ["quat_rotmat_unit", "cluster_poses", "rigid_fwd", "rigid_bwd", "dynamic_positions", "hold_rigid_residuals"]


def quat_rotmat_unit(q):
    """(N, 4) unit wxyz -> (N, 3, 3), the matrix of docs/conventions.md §1 without normalising
    (its backward is ``_rotmat_vjp``)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    R = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1)
    return R.reshape(-1, 3, 3)


def _rotmat_vjp(q, v_R):
    """v_q (N, 4) of ``quat_rotmat_unit`` at q (N, 4) for the cotangent v_R (N, 3, 3)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    g = v_R.reshape(-1, 9)
    # d R_ab / d(w, x, y, z), row-major over (a, b)
    dw = 2 * np.stack([0 * w, -z, y, z, 0 * w, -x, -y, x, 0 * w], -1)
    dx = 2 * np.stack([0 * w, y, z, y, -2 * x, -w, z, w, -2 * x], -1)
    dy = 2 * np.stack([-2 * y, x, w, x, 0 * w, z, -w, z, -2 * y], -1)
    dz = 2 * np.stack([-2 * z, -w, x, w, -2 * z, y, x, y, 0 * w], -1)
    return np.stack([np.sum(g * d, axis=1) for d in (dw, dx, dy, dz)], axis=1)


def _left_matrix(a):
    """(N, 4, 4) L(a) with a ⊗ b = L(a) b (Hamilton product, wxyz)."""
    w, x, y, z = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    return np.stack([w, -x, -y, -z,
                     x, w, -z, y,
                     y, z, w, -x,
                     z, -y, x, w], -1).reshape(-1, 4, 4)


def _right_matrix(b):
    """(N, 4, 4) Q(b) with a ⊗ b = Q(b) a."""
    w, x, y, z = b[:, 0], b[:, 1], b[:, 2], b[:, 3]
    return np.stack([w, -x, -y, -z,
                     x, w, z, -y,
                     y, -z, w, x,
                     z, y, -x, w], -1).reshape(-1, 4, 4)


def _cluster_path(rigid_blocks, t, deform_config, dtype):
    """Each cluster's position (C, 3) and unit rotation (C, 4) at time t, and what the backward needs."""
    C = rigid_blocks[f"{RIGID}.means"].shape[0]
    (p, qc, _), csaved = _deform_fwd(rigid_blocks[f"{RIGID}.means"], rigid_blocks[f"{RIGID}.quats"],
                                     np.zeros((C, 3), dtype=dtype), rigid_blocks[f"{RIGID}.deform_means"],
                                     rigid_blocks[f"{RIGID}.deform_quats"],
                                     np.zeros(rigid_blocks[f"{RIGID}.deform_means"].shape, dtype=dtype), t,
                                     deform_config)
    return p, qc, csaved


def cluster_poses(rigid_blocks, t, deform_config):
    """Each cluster's pose at time t, cluster -> world: (R (C, 3, 3), p (C, 3))."""
    p, qc, _ = _cluster_path(rigid_blocks, t, deform_config, np.asarray(rigid_blocks[f"{RIGID}.means"]).dtype)
    return quat_rotmat_unit(qc), p


def rigid_fwd(local_means, local_quats, cluster, rigid_blocks, t, deform_config):
    """World positions and unit rotations of the dynamic Gaussians at time t.

    local_means (N, 3), local_quats (N, 4) unit wxyz: the deformed attributes in each Gaussian's
    cluster frame (world for cluster -1). cluster (N,): ids, -1 or 0..C-1 (any real dtype holding
    integers). rigid_blocks: dict with the four ``rigid.*`` blocks (module docstring). t: scalar.
    Returns ((means (N, 3), quats (N, 4)), saved). Trusts its inputs (validated with the params).
    """
    C = rigid_blocks[f"{RIGID}.means"].shape[0]
    p, qc, csaved = _cluster_path(rigid_blocks, t, deform_config, local_means.dtype)
    ids = np.asarray(cluster).astype(np.int64)
    on = np.flatnonzero(ids >= 0)
    c = ids[on]
    Rc = quat_rotmat_unit(qc)  # (C, 3, 3)
    means, quats = local_means.copy(), local_quats.copy()
    means[on] = np.einsum("nij,nj->ni", Rc[c], local_means[on]) + p[c]
    quats[on] = np.einsum("nij,nj->ni", _left_matrix(qc[c]), local_quats[on])
    saved = dict(csaved=csaved, on=on, c=c, Rc=Rc, qc=qc, num_clusters=C,
                 local_means=local_means[on], local_quats=local_quats[on])
    return (means, quats), saved


def rigid_bwd(saved, v_means, v_quats):
    """Vector-Jacobian product of ``rigid_fwd``.

    v_means (N, 3), v_quats (N, 4): cotangents of the world outputs.
    Returns (v_local_means (N, 3), v_local_quats (N, 4), v_rigid dict of the four blocks, v_t scalar).
    """
    on, c, Rc, qc, C = saved["on"], saved["c"], saved["Rc"], saved["qc"], saved["num_clusters"]
    xl, ql = saved["local_means"], saved["local_quats"]
    dtype = v_means.dtype
    v_xl, v_ql = v_means.copy(), v_quats.copy()
    vm, vq = v_means[on], v_quats[on]
    # x = R_c x_l + p_c: v_x_l = R_c^T v_x, v_R_c = sum v_x x_l^T, v_p_c = sum v_x
    v_xl[on] = np.einsum("nji,nj->ni", Rc[c], vm)
    v_R = np.zeros((C, 9), dtype=dtype)
    np.add.at(v_R, c, (vm[:, :, None] * xl[:, None, :]).reshape(-1, 9))
    v_p = np.zeros((C, 3), dtype=dtype)
    np.add.at(v_p, c, vm)
    # q = q_c ⊗ q_l = L(q_c) q_l = Q(q_l) q_c
    v_ql[on] = np.einsum("nji,nj->ni", _left_matrix(qc[c]), vq)
    v_qc = _rotmat_vjp(qc, v_R.reshape(C, 3, 3))
    np.add.at(v_qc, c, np.einsum("nji,nj->ni", _right_matrix(ql), vq))
    g = _deform_bwd(saved["csaved"], v_p, v_qc.astype(dtype), None)
    v_rigid = {f"{RIGID}.means": g["base_means"], f"{RIGID}.quats": g["base_quats"],
               f"{RIGID}.deform_means": g["coef_means"], f"{RIGID}.deform_quats": g["coef_quats"]}
    return v_xl, v_ql, v_rigid, g["t"]


def dynamic_positions(params, times, deform_config):
    """World centres (T, Nd, 3) of the dynamic set at each of ``times``: the deformation, then each
    cluster's rigid motion where the scene has clusters. For the rules that read where the movers
    are (pruning the escaped, the blur's length, neighbour lists)."""
    fields = ("means", "quats", "colors", "deform_means", "deform_quats", "deform_colors")
    out = []
    for t in times:
        (m, q, _), _ = _deform_fwd(*(params[f"{DYNAMIC}.{f}"] for f in fields), float(t), deform_config)
        if has_rigid(params):
            (m, _), _ = rigid_fwd(m, q, params[CLUSTER], params, float(t), deform_config)
        out.append(m)
    return np.stack(out) if out else np.zeros((0, params[f"{DYNAMIC}.means"].shape[0], 3))


def hold_rigid_residuals(grads, params):
    """``grads`` with the clustered rows of the dynamic position and rotation coefficients zeroed
    (``MotionInitConfig.rigid_residual = False``): from zero coefficients and zero Adam moments those
    rows then stay at zero, and each cluster moves as one body. Other blocks unchanged."""
    on = np.asarray(params[CLUSTER]) >= 0
    out = dict(grads)
    for name in (f"{DYNAMIC}.deform_means", f"{DYNAMIC}.deform_quats"):
        if name in out:
            g = out[name].copy()
            g[on] = 0.0
            out[name] = g
    return out
