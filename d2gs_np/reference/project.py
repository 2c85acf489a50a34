"""EWA projection of 3D Gaussians, plain vectorised NumPy: forward and hand-derived backward.

Conventions are those of docs/conventions.md §1-4 (gsplat 1.5.3's reference renderer): wxyz quaternions
normalised inside, Sigma = R diag(s)^2 R^T with linear scales, world->camera pose with OpenCV
axes, depth = camera z, J with the x/z, y/z clamp, eps2d dilation, det clamp, per-axis 3.33 sigma
box, culling. Each ``dL_dX`` block in ``project_bwd`` sits under a comment quoting the forward
equation it differentiates, in reverse order of the forward pass.

These functions assume validated inputs (see ``d2gs_np.reference.render``); they compute in the
dtype of their inputs (float64, or float32 kept end to end).
"""
from __future__ import annotations

import numpy as np

from d2gs_np import constants as C


def quat_to_rotmat(q):
    """Rotation matrices (N, 3, 3) from unit wxyz quaternions q (N, 4) (docs/conventions.md §1)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    R = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )
    return R


def quat_to_rotmat_bwd(q, v_R):
    """Cotangent of the unit quaternion q (N, 4) given v_R (N, 3, 3) = dL/dR (no normalisation)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    v = v_R
    # dL_dq: each R_ij is a quadratic form in q; e.g. R_01 = 2(xy - wz) gives dR_01/dw = -2z.
    v_w = 2 * (-z * v[:, 0, 1] + y * v[:, 0, 2] + z * v[:, 1, 0] - x * v[:, 1, 2] - y * v[:, 2, 0]
               + x * v[:, 2, 1])
    v_x = 2 * (y * v[:, 0, 1] + z * v[:, 0, 2] + y * v[:, 1, 0] - 2 * x * v[:, 1, 1] - w * v[:, 1, 2]
               + z * v[:, 2, 0] + w * v[:, 2, 1] - 2 * x * v[:, 2, 2])
    v_y = 2 * (-2 * y * v[:, 0, 0] + x * v[:, 0, 1] + w * v[:, 0, 2] + x * v[:, 1, 0] + z * v[:, 1, 2]
               - w * v[:, 2, 0] + z * v[:, 2, 1] - 2 * y * v[:, 2, 2])
    v_z = 2 * (-2 * z * v[:, 0, 0] - w * v[:, 0, 1] + x * v[:, 0, 2] + w * v[:, 1, 0] - 2 * z * v[:, 1, 1]
               + y * v[:, 1, 2] + x * v[:, 2, 0] + y * v[:, 2, 1])
    return np.stack([v_w, v_x, v_y, v_z], axis=-1)


def project_fwd(means, quats, scales, opacities, cam_T_world, K, width, height, config):
    """Project N Gaussians to the image plane.

    means (N,3), quats (N,4) raw wxyz, scales (N,3) linear, opacities (N,), cam_T_world (4,4),
    K (3,3) zero skew, width/height ints, config a RenderConfig.

    Returns (proj, saved). proj: dict with
      "means2d" (N,2) (u, v), "conics" (N,3) (a, b, c), "opacities" (N,) effective opacities
      (times the antialiasing factor when config.antialiased), "depths" (N,) camera z (for every
      Gaussian), "radii" (N,2) int32, "visible" (N,) bool (= both radii > 0).
    means2d, conics and effective opacities are set to 0 for culled Gaussians (radii == 0).
    saved: dict of intermediates for ``project_bwd`` (also read by the test fixtures).
    """
    dtype = means.dtype
    n = means.shape[0]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    # Quaternion normalisation and rotation: q_n = q / |q|; R = R(q_n)
    q_norm = np.linalg.norm(quats, axis=1)  # (N,)
    qn = quats / q_norm[:, None]
    R = quat_to_rotmat(qn)  # (N,3,3)
    # Covariance: M = R diag(s); Sigma = M M^T
    M = R * scales[:, None, :]
    Sigma = M @ np.swapaxes(M, 1, 2)

    # World to camera: p_c = R_v p + t_v; Sigma_c = R_v Sigma R_v^T
    R_v = cam_T_world[:3, :3]
    t_v = cam_T_world[:3, 3]
    p_c = means @ R_v.T + t_v
    Sigma_c = R_v @ Sigma @ R_v.T
    x, y, z = p_c[:, 0], p_c[:, 1], p_c[:, 2]

    # Depth culling (exclusive bounds). Culled Gaussians are evaluated at z = 1 to keep every
    # intermediate finite (two-step where); they are masked out of every output and gradient.
    in_depth = (z > config.near_plane) & (z < config.far_plane)
    zs = np.where(in_depth, z, np.ones_like(z))

    # Pinhole mean (not clamped): u = fx x/z + cx, v = fy y/z + cy
    u = fx * x / zs + cx
    v = fy * y / zs + cy

    # Jacobian of the perspective map with x/z, y/z clamped to the widened field of view
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x = (-(cx / fx + C.FOV_CLAMP_MARGIN * tan_fovx), (width - cx) / fx + C.FOV_CLAMP_MARGIN * tan_fovx)
    lim_y = (-(cy / fy + C.FOV_CLAMP_MARGIN * tan_fovy), (height - cy) / fy + C.FOV_CLAMP_MARGIN * tan_fovy)
    x_over_z = x / zs
    y_over_z = y / zs
    cxz = np.clip(x_over_z, lim_x[0], lim_x[1])
    cyz = np.clip(y_over_z, lim_y[0], lim_y[1])
    tx = zs * cxz
    ty = zs * cyz
    J = np.zeros((n, 2, 3), dtype=dtype)
    J[:, 0, 0] = fx / zs
    J[:, 0, 2] = -fx * tx / (zs * zs)
    J[:, 1, 1] = fy / zs
    J[:, 1, 2] = -fy * ty / (zs * zs)

    # 2D covariance with low-pass dilation: cov = J Sigma_c J^T + eps2d I
    cov_raw = J @ Sigma_c @ np.swapaxes(J, 1, 2)  # (N,2,2)
    det_orig = cov_raw[:, 0, 0] * cov_raw[:, 1, 1] - cov_raw[:, 0, 1] * cov_raw[:, 1, 0]
    cov = cov_raw.copy()
    cov[:, 0, 0] += config.eps2d
    cov[:, 1, 1] += config.eps2d
    det_raw = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
    det_clamped = det_raw < C.DET_MIN
    det = np.maximum(det_raw, C.DET_MIN)

    # Conic = inverse of the dilated covariance, (a, b, c) for [[a, b], [b, c]]
    conics = np.stack(
        [cov[:, 1, 1] / det, -(cov[:, 0, 1] + cov[:, 1, 0]) / 2 / det, cov[:, 0, 0] / det], axis=-1
    )

    # Antialiasing factor: comp = sqrt(max(det_orig / det, 0))
    if config.antialiased:
        comp = np.sqrt(np.maximum(det_orig / det, 0))
        opac_eff = opacities * comp
    else:
        comp = np.ones_like(opacities)
        opac_eff = opacities.copy()

    # Per-axis 3.33 sigma box and culling
    rx = np.ceil(C.RADIUS_SIGMA * np.sqrt(cov[:, 0, 0]))
    ry = np.ceil(C.RADIUS_SIGMA * np.sqrt(cov[:, 1, 1]))
    valid = (det > 0) & in_depth
    inside = (u + rx > 0) & (u - rx < width) & (v + ry > 0) & (v - ry < height)
    visible = valid & inside
    radii = np.where(visible[:, None], np.stack([rx, ry], axis=-1), 0).astype(np.int32)

    zero = np.zeros((), dtype=dtype)
    proj = {
        "means2d": np.where(visible[:, None], np.stack([u, v], axis=-1), zero),
        "conics": np.where(visible[:, None], conics, zero),
        "opacities": np.where(visible, opac_eff, zero),
        "depths": z.copy(),
        "radii": radii,
        "visible": visible,
    }
    saved = {
        "means": means, "scales": scales, "opacities": opacities, "cam_T_world": cam_T_world, "K": K,
        "q_norm": q_norm, "qn": qn, "R": R, "M": M, "Sigma": Sigma, "Sigma_c": Sigma_c, "p_c": p_c,
        "zs": zs, "x_over_z": x_over_z, "y_over_z": y_over_z, "lim_x": lim_x, "lim_y": lim_y,
        "cxz": cxz, "cyz": cyz, "tx": tx, "ty": ty, "J": J, "cov": cov, "det_orig": det_orig,
        "det": det, "det_clamped": det_clamped, "conics": conics, "comp": comp,
        "antialiased": bool(config.antialiased), "eps2d": config.eps2d,
        "depths": proj["depths"], "radii": radii, "visible": visible,
    }
    return proj, saved


def project_bwd(saved, v_means2d, v_conics, v_opacities, v_depths):
    """Backward of ``project_fwd``.

    v_means2d (N,2), v_conics (N,3), v_opacities (N,) (w.r.t. the effective opacities), v_depths
    (N,). Returns dict of cotangents: "means" (N,3), "quats" (N,4) (raw quats, orthogonal to q),
    "scales" (N,3), "opacities" (N,), "cam_T_world" (4,4) (bottom row zero). Culled Gaussians get
    zero gradient.
    """
    s = saved
    vis = s["visible"]
    dtype = s["means"].dtype
    zero = np.zeros((), dtype=dtype)
    K = s["K"]
    fx, fy = K[0, 0], K[1, 1]
    zs, J, cov, det = s["zs"], s["J"], s["cov"], s["det"]
    x, y = s["p_c"][:, 0], s["p_c"][:, 1]
    a, b, c = s["conics"][:, 0], s["conics"][:, 1], s["conics"][:, 2]
    v_a, v_b, v_c = v_conics[:, 0], v_conics[:, 1], v_conics[:, 2]
    # Culled Gaussians get nothing: zero their incoming cotangents first.
    v_means2d = np.where(vis[:, None], v_means2d, zero)
    v_a, v_b, v_c = (np.where(vis, t, zero) for t in (v_a, v_b, v_c))
    v_opacities = np.where(vis, v_opacities, zero)
    v_depths = np.where(vis, v_depths, zero)

    # opac_eff = opacity * comp,  comp = sqrt(max(det_orig / det, 0))   (antialiased only)
    # dL_dopacity = v_eff * comp; dL_dcomp = v_eff * opacity;
    # dcomp/dratio = 1 / (2 comp) where ratio > 0 (zero gradient where the max clamps);
    # ratio = det_orig / det: dratio/ddet_orig = 1/det, dratio/ddet = -ratio/det.
    v_opac_in = v_opacities * s["comp"]
    if s["antialiased"]:
        comp = s["comp"]
        ratio = s["det_orig"] / det
        pos = ratio > 0
        v_comp = v_opacities * s["opacities"]
        v_ratio = np.where(pos, v_comp * 0.5 / np.where(pos, comp, 1), zero)
        v_det_orig = v_ratio / det
        v_det_from_comp = -v_ratio * ratio / det
    else:
        v_det_orig = np.zeros_like(det)
        v_det_from_comp = np.zeros_like(det)

    # conic = (C/det, -B/det, A/det) with cov = [[A, B], [B, C]], det = max(A C - B^2, DET_MIN)
    # dL_ddet = -(v_a a + v_b b + v_c c) / det (+ the antialiasing term), zero when clamped.
    A, B, Cc = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    v_det = -(v_a * a + v_b * b + v_c * c) / det + v_det_from_comp
    v_det = np.where(s["det_clamped"], zero, v_det)
    # dL_dA, dL_dC, dL_dB (B = the shared off-diagonal entry)
    v_A = v_c / det + v_det * Cc
    v_C = v_a / det + v_det * A
    v_B = -v_b / det - 2 * B * v_det
    # det_orig = (A - eps)(C - eps) - B^2 (the undilated covariance)
    eps = s["eps2d"]
    v_A = v_A + v_det_orig * (Cc - eps)
    v_C = v_C + v_det_orig * (A - eps)
    v_B = v_B - 2 * B * v_det_orig
    # As a gradient w.r.t. the full (symmetric) 2x2 matrix, the off-diagonal is split in two.
    v_cov = np.stack([np.stack([v_A, 0.5 * v_B], -1), np.stack([0.5 * v_B, v_C], -1)], -2)  # (N,2,2)

    # cov = J Sigma_c J^T + eps2d I
    # dL_dSigma_c = J^T v_cov J;  dL_dJ = 2 v_cov J Sigma_c  (v_cov and Sigma_c symmetric)
    Sigma_c = s["Sigma_c"]
    v_Sigma_c = np.swapaxes(J, 1, 2) @ v_cov @ J
    v_J = 2 * v_cov @ J @ Sigma_c

    # J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]
    z2 = zs * zs
    z3 = z2 * zs
    v_z = (-fx / z2 * v_J[:, 0, 0] + 2 * fx * s["tx"] / z3 * v_J[:, 0, 2]
           - fy / z2 * v_J[:, 1, 1] + 2 * fy * s["ty"] / z3 * v_J[:, 1, 2])
    v_tx = -fx / z2 * v_J[:, 0, 2]
    v_ty = -fy / z2 * v_J[:, 1, 2]
    # tx = z * clamp(x/z, lo, hi): inside the clamp tx = x (dtx/dx = 1, dtx/dz = 0); when the
    # clamp is active the clamped value c is a constant and tx = z c (dtx/dz = c).
    lo_x, hi_x = s["lim_x"]
    lo_y, hi_y = s["lim_y"]
    free_x = (s["x_over_z"] >= lo_x) & (s["x_over_z"] <= hi_x)
    free_y = (s["y_over_z"] >= lo_y) & (s["y_over_z"] <= hi_y)
    v_x = np.where(free_x, v_tx, zero)
    v_y = np.where(free_y, v_ty, zero)
    v_z = v_z + np.where(free_x, zero, v_tx * s["cxz"]) + np.where(free_y, zero, v_ty * s["cyz"])

    # u = fx x/z + cx, v = fy y/z + cy
    v_u, v_v = v_means2d[:, 0], v_means2d[:, 1]
    v_x = v_x + fx / zs * v_u
    v_y = v_y + fy / zs * v_v
    v_z = v_z - fx * x / z2 * v_u - fy * y / z2 * v_v
    # depth = z
    v_z = v_z + v_depths
    v_p_c = np.stack([v_x, v_y, v_z], axis=-1)
    v_p_c = np.where(vis[:, None], v_p_c, zero)
    v_Sigma_c = np.where(vis[:, None, None], v_Sigma_c, zero)

    # p_c = R_v p + t_v:  dL_dp = R_v^T v_p_c;  dL_dR_v += sum_n v_p_c p^T;  dL_dt_v = sum_n v_p_c
    T = s["cam_T_world"]
    R_v = T[:3, :3]
    v_means = v_p_c @ R_v
    v_R_v = v_p_c.T @ s["means"]
    v_t_v = v_p_c.sum(axis=0)
    # Sigma_c = R_v Sigma R_v^T:  dL_dSigma = R_v^T v_Sigma_c R_v;  dL_dR_v += sum_n 2 v_Sigma_c R_v Sigma
    Sigma = s["Sigma"]
    v_Sigma = R_v.T @ v_Sigma_c @ R_v
    v_R_v = v_R_v + 2 * np.sum(v_Sigma_c @ R_v @ Sigma, axis=0)
    v_T = np.zeros((4, 4), dtype=dtype)
    v_T[:3, :3] = v_R_v
    v_T[:3, 3] = v_t_v

    # Sigma = M M^T, M = R diag(s):  dL_dM = 2 v_Sigma M;  dL_dR = v_M diag(s);
    # dL_ds_j = sum_i v_M_ij R_ij
    M, R = s["M"], s["R"]
    v_M = 2 * v_Sigma @ M
    v_R = v_M * s["scales"][:, None, :]
    v_scales = np.sum(v_M * R, axis=1)
    # R = R(q_n), q_n = q/|q|:  dL_dq = (v_qn - q_n (q_n . v_qn)) / |q|
    qn = s["qn"]
    v_qn = quat_to_rotmat_bwd(qn, v_R)
    v_quats = (v_qn - qn * np.sum(qn * v_qn, axis=1, keepdims=True)) / s["q_norm"][:, None]

    return {
        "means": v_means,
        "quats": v_quats,
        "scales": v_scales,
        "opacities": v_opac_in,
        "cam_T_world": v_T,
    }
