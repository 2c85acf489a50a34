"""Camera trajectories compared: Sim(3) alignment (Umeyama), ATE and RPE.

Definitions follow ``docs/dataset_format.md §6`` and ``docs/method.md §10``.

Trajectories
- Poses are ``cam_T_world`` (N, 4, 4), world-to-camera, OpenCV axes (see
  ``d2gs_np.data.scene``). Camera centres c_i = -R_i^T t_i.
- Sim(3) alignment (Umeyama 1991) maps *estimated* centres onto ground truth:
  (s, R, t) = argmin sum_i |c_gt_i - (s R c_est_i + t)|^2, with R a proper
  rotation (det +1).
- ATE = sqrt(mean_i |s R c_est_i + t - c_gt_i|^2), in ground-truth units.
- RPE between consecutive frames: with relative motions
  Delta_i = cam_T_world_i @ inv(cam_T_world_{i+1}) (the pose of camera i+1 in
  camera i), the estimated relative translation scaled by the alignment scale s
  (the alignment's rotation and translation cancel in relative motions),
  E_i = inv(Delta_gt_i) @ Delta_est_i;
  RPE_t = sqrt(mean_i |trans(E_i)|^2) (ground-truth units) and
  RPE_r = sqrt(mean_i angle(rot(E_i))^2) in degrees, both RMSE over the N-1
  consecutive pairs. The angle is |so3_log|, computed with atan2 (accurate at
  0 and near pi, unlike arccos).
- Degenerate inputs raise ValueError instead of returning NaN.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.constants import TRAJECTORY_SPREAD_MIN_REL
from d2gs_np.geometry.camera import camera_center
from d2gs_np.geometry.se3 import check_rigid, se3_inverse
from d2gs_np.geometry.so3 import so3_log

__all__ = ["umeyama", "align_trajectory", "sim3_inverse", "sim3_apply_to_poses", "frame_relative_poses", "ate", "rpe"]


def _check_points(x, name):
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.number) or np.issubdtype(x.dtype, np.complexfloating):
        raise TypeError(f"{name} must be a real numeric array of shape (N, 3); got dtype {x.dtype}")
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3); got {x.shape}")
    x = x.astype(np.float64, copy=False)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf values")
    return x


def _check_spread(x, name):
    """Raise if the points are all at one place (up to rounding)."""
    centred = x - x.mean(axis=0)
    var = float(np.mean(np.sum(centred * centred, axis=1)))
    mean_sq = float(np.mean(np.sum(x * x, axis=1)))
    if var <= TRAJECTORY_SPREAD_MIN_REL * mean_sq:
        raise ValueError(
            f"{name}: all points are at one place (spread variance {var:.3g}); a similarity "
            "alignment is undefined. The cameras must move (translate) for trajectory metrics."
        )
    return var


def _umeyama(src, dst, with_scale):
    """Umeyama on validated (N, 3) float64 arrays; needs N >= 2 and spread in both."""
    var_src = _check_spread(src, "src")
    _check_spread(dst, "dst")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    sigma = xd.T @ xs / src.shape[0]  # (3, 3) cross-covariance
    U, d, Vt = np.linalg.svd(sigma)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2] = -1.0  # best proper rotation, not a reflection
    R = (U * S) @ Vt
    s = float(np.sum(d * S) / var_src) if with_scale else 1.0
    t = mu_d - s * (R @ mu_s)
    return s, R, t


def umeyama(src, dst, with_scale=True):
    """Least-squares similarity transform: dst ~= s R src + t.

    src, dst: (N, 3) corresponding points, N >= 3. Minimises
    sum_i |dst_i - (s R src_i + t)|^2 over s > 0, R in SO(3) (never a
    reflection), t in R^3 (Umeyama 1991). with_scale=False fixes s = 1.
    Returns (s: float, R: (3, 3), t: (3,)). If the points are collinear the
    rotation about their line is not determined (any minimiser is returned;
    the residual is unique). Raises ValueError for N < 3, mismatched N, or
    points all at one place.
    """
    src = _check_points(src, "src")
    dst = _check_points(dst, "dst")
    if src.shape != dst.shape:
        raise ValueError(f"src and dst must have the same shape (N, 3); got {src.shape} and {dst.shape}")
    if src.shape[0] < 3:
        raise ValueError(f"umeyama needs at least 3 point pairs for a Sim(3) alignment; got {src.shape[0]}")
    return _umeyama(src, dst, with_scale)


def _check_poses(T, name):
    if not isinstance(T, np.ndarray):
        T = np.asarray(T)
    if not np.issubdtype(T.dtype, np.floating):
        raise TypeError(f"{name} must be a float array of shape (N, 4, 4); got dtype {T.dtype}")
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (N, 4, 4); got {T.shape}")
    T = T.astype(np.float64, copy=False)
    for i in range(T.shape[0]):
        check_rigid(T[i], f"{name}[{i}]")
    return T


def _check_pose_pair(est, gt, min_frames, what):
    est = _check_poses(est, "est_cam_T_world")
    gt = _check_poses(gt, "gt_cam_T_world")
    if est.shape[0] != gt.shape[0]:
        raise ValueError(
            f"est_cam_T_world and gt_cam_T_world must have the same number of poses; "
            f"got {est.shape[0]} and {gt.shape[0]}"
        )
    if est.shape[0] < min_frames:
        raise ValueError(f"{what} needs at least {min_frames} frames; got {est.shape[0]}")
    return est, gt


def align_trajectory(est_cam_T_world, gt_cam_T_world):
    """Sim(3) that maps estimated camera centres onto ground-truth centres.

    est_cam_T_world, gt_cam_T_world: (N, 4, 4) rigid world-to-camera poses,
    N >= 3. Returns (s, R (3, 3), t (3,)) with c_gt ~= s R c_est + t
    (``umeyama`` on the centres). Only positions are used, as in ATE.
    """
    est, gt = _check_pose_pair(est_cam_T_world, gt_cam_T_world, 3, "Sim(3) trajectory alignment")
    return _umeyama(camera_center(est), camera_center(gt), True)


def sim3_inverse(s, R, t):
    """Inverse of x -> s R x + t: returns (1/s, R^T, -R^T t / s)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if not (np.isfinite(s) and s > 0):
        raise ValueError(f"s must be a positive finite scale; got {s}")
    return 1.0 / s, R.T, -(R.T @ t) / s


def sim3_apply_to_poses(s, R, t, cam_T_world):
    """Move cameras by the world similarity x -> s R x + t.

    cam_T_world: (..., 4, 4) rigid. Returns (..., 4, 4) rigid poses whose
    centres are s R c + t and whose camera axes are rotated by R (images of a
    scene transformed by the same similarity are unchanged, up to the scale
    of depth). Use with ``sim3_inverse(*align_trajectory(est, gt))`` to map
    ground-truth test views into the reconstruction frame.
    """
    T = np.asarray(cam_T_world, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"cam_T_world must have shape (..., 4, 4); got {T.shape}")
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"R must have shape (3, 3) and t shape (3,); got {R.shape} and {t.shape}")
    c_new = s * (camera_center(T) @ R.T) + t  # (..., 3)
    R_cw_new = T[..., :3, :3] @ R.T  # camera-from-world rotation after moving the world
    out = np.zeros_like(T)
    out[..., :3, :3] = R_cw_new
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R_cw_new, c_new)
    out[..., 3, 3] = 1.0
    return out


def frame_relative_poses(view_cam_T_world, ref_cam_T_world, est_cam_T_world, scale=1.0):
    """Views carried onto an estimated trajectory as they sit beside a reference one.

    view_cam_T_world (M, 4, 4): views in the reference frame; ref_cam_T_world, est_cam_T_world
    (M, 4, 4): for each view, the reference and the estimated pose of the camera it sits beside;
    scale: reference units per estimated unit (ref ~= scale R est + t, e.g. ``align_trajectory``'s
    s). Returns (M, 4, 4) rigid poses Delta' est, Delta = view inv(ref) (the view in its camera's
    coordinates) with its translation divided by ``scale``: a stereo rig's second camera follows
    the first wherever the estimate put it (docs/method.md §10, ``nvs_rig``). Any similarity of
    the estimate's world cancels, so no global alignment enters."""
    view, ref, est = (np.asarray(T, dtype=np.float64) for T in (view_cam_T_world, ref_cam_T_world, est_cam_T_world))
    if not (view.shape == ref.shape == est.shape and view.ndim == 3):
        raise ValueError(f"view, ref and est poses must all have shape (M, 4, 4); got {view.shape}, {ref.shape} "
                         f"and {est.shape}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive finite number; got {scale}")
    for T, name in ((view, "view_cam_T_world"), (ref, "ref_cam_T_world"), (est, "est_cam_T_world")):
        check_rigid(T, name)
    delta = view @ se3_inverse(ref)
    delta[:, :3, 3] /= scale
    return delta @ est


def ate(est_cam_T_world, gt_cam_T_world):
    """Absolute trajectory error: RMSE of camera centres after Sim(3) alignment.

    est_cam_T_world, gt_cam_T_world: (N, 4, 4), N >= 3. With (s, R, t) from
    ``align_trajectory``: ATE = sqrt(mean_i |s R c_est_i + t - c_gt_i|^2), in
    ground-truth world units.
    """
    est, gt = _check_pose_pair(est_cam_T_world, gt_cam_T_world, 3, "ATE (Sim(3) alignment)")
    c_est, c_gt = camera_center(est), camera_center(gt)
    s, R, t = _umeyama(c_est, c_gt, True)
    r = s * c_est @ R.T + t - c_gt
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def _rotation_angle(R):
    """(..., 3, 3) rotations -> (...,) angle in radians in [0, pi]."""
    return np.linalg.norm(so3_log(R), axis=-1)


def rpe(est_cam_T_world, gt_cam_T_world, align=True):
    """Relative pose error between consecutive frames -> (rpe_t, rpe_r_deg).

    est_cam_T_world, gt_cam_T_world: (N, 4, 4), N >= 2, in time order.
    Delta_i = T_i @ inv(T_{i+1}) (camera i+1 seen from camera i). With
    align=True the estimated relative translations are multiplied by the Sim(3)
    alignment scale s of the camera centres (Umeyama; the alignment's rotation
    and translation cancel in relative motions, so only s matters and N = 2 is
    enough); align=False uses s = 1. E_i = inv(Delta_gt_i) @ Delta_est_i,
    rpe_t = sqrt(mean_i |trans(E_i)|^2) (ground-truth units; equals
    |s t_est_i - t_gt_i|), rpe_r_deg = sqrt(mean_i angle(rot(E_i))^2) in degrees.
    """
    est, gt = _check_pose_pair(est_cam_T_world, gt_cam_T_world, 2, "RPE")
    s = _umeyama(camera_center(est), camera_center(gt), True)[0] if align else 1.0

    def relative(T):
        R, t = T[:, :3, :3], T[:, :3, 3]
        R_rel = R[:-1] @ np.swapaxes(R[1:], -1, -2)  # R_i R_{i+1}^T
        t_rel = t[:-1] - np.einsum("nij,nj->ni", R_rel, t[1:])  # t_i - R_rel t_{i+1}
        return R_rel, t_rel

    R_e, t_e = relative(est)
    R_g, t_g = relative(gt)
    # inv(Delta_gt) @ Delta_est = [R_g^T R_e, R_g^T (s t_e - t_g)]; |R_g^T v| = |v|.
    dt = s * t_e - t_g
    rpe_t = float(np.sqrt(np.mean(np.sum(dt * dt, axis=1))))
    ang = _rotation_angle(np.swapaxes(R_g, -1, -2) @ R_e)
    rpe_r = float(np.degrees(np.sqrt(np.mean(ang * ang))))
    return rpe_t, rpe_r
