"""Pinhole cameras: intrinsics, projection, resolution scaling, axis conventions.

Internal convention (docs/conventions.md §2): poses are ``cam_T_world``
(world -> camera), OpenCV axes (x right, y down, z forward), depth = camera z,
pixel (row i, col j) has its centre at (j + 0.5, i + 0.5) so pixel j covers
[j, j + 1) in continuous coordinates. Scene files (docs/dataset_format.md §2) store
OpenGL/Nerfstudio camera-to-world matrices (x right, y up, looking down -z).
"""
from __future__ import annotations

import numpy as np

from d2gs_np.geometry.se3 import check_rigid, se3_inverse

# Flips y and z: OpenGL camera axes <-> OpenCV camera axes (its own inverse).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def make_intrinsics(fx, fy, cx, cy):
    """3x3 zero-skew pinhole matrix; focal lengths must be positive."""
    if not (fx > 0 and fy > 0):
        raise ValueError(f"focal lengths must be positive; got fx={fx}, fy={fy}")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def check_intrinsics(K, name="K"):
    K = np.asarray(K)
    if K.shape != (3, 3):
        raise ValueError(f"{name} must have shape (3, 3); got {K.shape}")
    if not np.all(np.isfinite(K)):
        raise ValueError(f"{name} contains NaN or inf")
    if K[0, 1] != 0.0:
        raise ValueError(f"{name} must have zero skew (K[0, 1] = 0); got {K[0, 1]}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"{name} must have positive focal lengths; got fx={K[0, 0]}, fy={K[1, 1]}")


def scale_intrinsics(K, sx, sy=None):
    """Intrinsics for an image resampled by factors (sx, sy) (new_size = sx * old_size).

    Continuous pixel coordinates scale linearly (pixel edges map to edges), so
    fx, cx scale by sx and fy, cy by sy. With area downsampling by an integer
    factor f (sx = 1/f) the new pixel j covers old pixels [f j, f j + f), whose
    centre f j + f/2 maps to j + 1/2: centres at +0.5 stay consistent.
    """
    sy = sx if sy is None else sy
    K = np.array(K, dtype=np.float64, copy=True)
    K[0, :] *= sx
    K[1, :] *= sy
    K[2, :] = (0.0, 0.0, 1.0)
    return K


def scaled_size(width, height, scale):
    """Image size at render scale r: (max(1, round(W r)), max(1, round(H r)))."""
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))


def project_points(points, cam_T_world, K):
    """Project (N, 3) world points: returns (uv (N, 2) in continuous pixel coords, z (N,) camera depth).

    Points with z <= 0 get non-finite-safe but meaningless uv; callers mask by z.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3); got {points.shape}")
    T = np.asarray(cam_T_world, dtype=np.float64)
    pc = points @ T[:3, :3].T + T[:3, 3]
    z = pc[:, 2]
    zs = np.where(np.abs(z) > 0, z, 1.0)
    uv = np.stack([K[0, 0] * pc[:, 0] / zs + K[0, 2], K[1, 1] * pc[:, 1] / zs + K[1, 2]], axis=1)
    return uv, z


def unproject_points(pix, depth, cam_T_world, K):
    """World points on the rays through continuous pixels pix (M, 2) at camera depths depth (M,):
    the inverse of project_points for points in front of the camera."""
    pix = np.asarray(pix, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    pc = np.stack([(pix[:, 0] - K[0, 2]) / K[0, 0] * depth, (pix[:, 1] - K[1, 2]) / K[1, 1] * depth, depth], axis=1)
    T = np.asarray(cam_T_world, dtype=np.float64)
    return (pc - T[:3, 3]) @ T[:3, :3]  # R^T (p_cam - t), row-wise


def camera_center(cam_T_world):
    """World position of the camera centre, (..., 4, 4) -> (..., 3): -R^T t."""
    T = np.asarray(cam_T_world, dtype=np.float64)
    return -np.einsum("...ji,...j->...i", T[..., :3, :3], T[..., :3, 3])


def opengl_c2w_to_cam_T_world(c2w):
    """OpenGL camera-to-world (..., 4, 4) -> internal OpenCV world-to-camera (..., 4, 4)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return se3_inverse(c2w @ _GL_TO_CV)


def cam_T_world_to_opengl_c2w(cam_T_world):
    """Internal OpenCV world-to-camera (..., 4, 4) -> OpenGL camera-to-world (..., 4, 4)."""
    return se3_inverse(np.asarray(cam_T_world, dtype=np.float64)) @ _GL_TO_CV


def look_at(eye, target, up=(0.0, -1.0, 0.0)):
    """cam_T_world of an OpenCV camera at ``eye`` looking at ``target``; ``up`` is the world
    direction that should appear upwards in the image (camera -y)."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(-up, z)  # image x (right) = down x forward
    if np.linalg.norm(x) < 1e-12:
        raise ValueError("look_at: up is parallel to the viewing direction; pick another up vector")
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


__all__ = [
    "make_intrinsics", "check_intrinsics", "scale_intrinsics", "scaled_size", "project_points", "unproject_points",
    "camera_center", "opengl_c2w_to_cam_T_world", "cam_T_world_to_opengl_c2w", "look_at", "check_rigid",
]
