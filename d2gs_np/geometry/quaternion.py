"""Quaternions in wxyz order (docs/conventions.md §1), vectorised over leading axes."""
from __future__ import annotations

import numpy as np

from d2gs_np.constants import QUAT_NORM_MIN
from d2gs_np.geometry.so3 import float_dtype


def _as_quat(q, name="q"):
    q = np.asarray(q, dtype=float_dtype(q))
    if q.shape[-1:] != (4,):
        raise ValueError(f"{name} must have shape (..., 4) in wxyz order; got {q.shape}")
    return q


def quat_normalize(q):
    """L2-normalise (..., 4) quaternions; raises ValueError on (near-)zero norm."""
    q = _as_quat(q)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < QUAT_NORM_MIN):
        raise ValueError(f"quaternion with norm < {QUAT_NORM_MIN:g} cannot be normalised")
    return q / n


def quat_to_rotmat(q):
    """(..., 4) wxyz (normalised first, as gsplat does) -> (..., 3, 3), the matrix of docs/conventions.md §1."""
    w, x, y, z = np.moveaxis(quat_normalize(q), -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(R.shape[:-1] + (3, 3))


def rotmat_to_quat(R):
    """(..., 3, 3) rotation -> (..., 4) unit wxyz with w >= 0 (Shepperd's method: stable at all angles)."""
    R = np.asarray(R, dtype=float_dtype(R))
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3); got {R.shape}")
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # Four candidate formulas, each well conditioned when its pivot (4 q_i^2) is large.
    cands = np.stack(
        [
            np.stack([1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            np.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            np.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1]], -1),
            np.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1),
        ],
        axis=-2,
    )  # (..., 4 candidates, 4 components); candidate k has component k = 4 q_k^2 / (2 q_k) scale
    pivots = np.stack([1 + tr, 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                       1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1)
    k = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(cands, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_multiply(a, b):
    """Hamilton product a * b of (..., 4) wxyz quaternions (rotation a after b)."""
    a, b = _as_quat(a, "a"), _as_quat(b, "b")
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )
