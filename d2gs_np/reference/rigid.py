"""Reference rigid cluster motion (``d2gs_np.scene.rigid``): the obvious per-Gaussian loop, float64.

Each clustered Gaussian's world position is its cluster's rotation times its local position plus
the cluster's position, and its rotation the cluster's quaternion times its own,

    x(t) = R(q_c(t)) x_l(t) + p_c(t),    q(t) = q_c(t) q_l(t),

with the cluster's p_c, q_c from the reference deformation. It does not import the fast path.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.geometry.quaternion import quat_multiply, quat_to_rotmat
from d2gs_np.reference.deformation import deform


def rigid_transform(local_means, local_quats, cluster, rigid_blocks, t, config):
    """World (means (N, 3), quats (N, 4)) of ``scene.rigid.rigid_fwd``, one Gaussian at a time."""
    C = len(rigid_blocks["rigid.means"])
    p, qc, _ = deform(rigid_blocks["rigid.means"], rigid_blocks["rigid.quats"], np.zeros((C, 3)),
                      rigid_blocks["rigid.deform_means"], rigid_blocks["rigid.deform_quats"],
                      np.zeros(rigid_blocks["rigid.deform_means"].shape), t, config)
    means = np.array(local_means, dtype=np.float64, copy=True)
    quats = np.array(local_quats, dtype=np.float64, copy=True)
    for i, c in enumerate(np.asarray(cluster)):
        c = int(c)
        if c < 0:
            continue
        means[i] = quat_to_rotmat(qc[c]) @ np.asarray(local_means[i], np.float64) + p[c]
        quats[i] = quat_multiply(qc[c], np.asarray(local_quats[i], np.float64))
    return means, quats
