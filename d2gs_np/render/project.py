"""EWA projection of 3D Gaussians to screen space: Numba forward and backward kernels.

Conventions are those of docs/conventions.md §1-4 (gsplat 1.5.3's reference renderer):

* ``R`` from the L2-normalised wxyz quaternion, ``Sigma = R diag(s)^2 R^T`` with linear scales;
* ``p_c = R_v p + t_v`` and ``Sigma_c = R_v Sigma R_v^T`` with ``cam_T_world = [R_v | t_v]``
  (OpenCV axes; the bottom row is ignored), depth = camera z;
* ``u = fx x/z + cx``, ``v = fy y/z + cy`` (unclamped);
* ``J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]`` with ``tx = z clamp(x/z, -lim_neg,
  lim_pos)`` (the clamped value is held constant in the gradient, ``tx`` keeps its factor z);
* ``cov2d = J Sigma_c J^T + eps2d I``, ``det = max(det, DET_MIN)`` (no gradient through the
  clamp when active), ``conic = (cov11, -cov01, cov00) / det``;
* antialiased mode: opacity is multiplied by ``sqrt(max(det_orig / det, 0))``;
* culling (radius := 0) unless ``det > 0``, ``near < z < far`` and the per-axis
  ``ceil(3.33 sigma)`` box overlaps the image.

Implementation: the covariance is never formed. With ``B = R_v R diag(s)`` (3, 3) and
``A = J B`` (2, 3), ``cov2d = A A^T + eps2d I``; the backward pass differentiates this
factored form (mathematically the same function as ``J R_v R S S^T R^T R_v^T J^T``).

The kernels loop over Gaussians with ``prange``; each iteration writes only row ``i`` of its
outputs, so there are no write conflicts. The pose gradient is written per Gaussian into
``v_view_rows`` (N, 12) and summed by the caller in a fixed order (deterministic).

Kernels are generic in the float dtype: every float constant comes from the ``consts`` array
(built by :func:`make_consts` in the working dtype) so that the float32 specialisation performs
all arithmetic in float32 (a Python float literal would promote to float64 in Numba).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from d2gs_np import constants as C

# Indices into the ``consts`` array shared by the projection and rasterisation kernels.
K_ZERO = 0
K_ONE = 1
K_TWO = 2
K_HALF = 3
K_NEAR = 4
K_FAR = 5
K_EPS2D = 6
K_DET_MIN = 7
K_RADIUS_SIGMA = 8
K_FOV_MARGIN = 9
K_WIDTH = 10
K_HEIGHT = 11
K_TILE = 12
K_ALPHA_MAX = 13
K_ALPHA_THRESHOLD = 14
K_T_MIN = 15
N_CONSTS = 16

_SUM_BLOCK = 256  # rows per block of the two-level fixed-order sum (any fixed value is deterministic)


def make_consts(config, width, height, dtype):
    """The float constants of the kernels, in ``dtype`` (see the module docstring)."""
    c = np.zeros(N_CONSTS, dtype=dtype)
    c[K_ZERO] = 0.0
    c[K_ONE] = 1.0
    c[K_TWO] = 2.0
    c[K_HALF] = 0.5
    c[K_NEAR] = config.near_plane
    c[K_FAR] = config.far_plane
    c[K_EPS2D] = config.eps2d
    c[K_DET_MIN] = C.DET_MIN
    c[K_RADIUS_SIGMA] = C.RADIUS_SIGMA
    c[K_FOV_MARGIN] = C.FOV_CLAMP_MARGIN
    c[K_WIDTH] = width
    c[K_HEIGHT] = height
    c[K_TILE] = config.tile_size
    c[K_ALPHA_MAX] = C.ALPHA_MAX
    c[K_ALPHA_THRESHOLD] = C.ALPHA_THRESHOLD
    c[K_T_MIN] = C.TRANSMITTANCE_MIN
    return c


@njit(cache=True)
def _quat_to_rotmat(qw, qx, qy, qz, one, two):
    """Rotation matrix (row-major 9-tuple) of a UNIT wxyz quaternion (docs/conventions.md §1)."""
    r00 = one - two * (qy * qy + qz * qz)
    r01 = two * (qx * qy - qw * qz)
    r02 = two * (qx * qz + qw * qy)
    r10 = two * (qx * qy + qw * qz)
    r11 = one - two * (qx * qx + qz * qz)
    r12 = two * (qy * qz - qw * qx)
    r20 = two * (qx * qz - qw * qy)
    r21 = two * (qy * qz + qw * qx)
    r22 = one - two * (qx * qx + qy * qy)
    return r00, r01, r02, r10, r11, r12, r20, r21, r22


@njit(cache=True)
def _fov_limits(K, consts):
    """(lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos) of the x/z, y/z clamp in J (docs/conventions.md §3)."""
    half = consts[K_HALF]
    margin = consts[K_FOV_MARGIN]
    W = consts[K_WIDTH]
    H = consts[K_HEIGHT]
    fx = K[0, 0]
    fy = K[1, 1]
    cx = K[0, 2]
    cy = K[1, 2]
    tan_fovx = half * W / fx
    tan_fovy = half * H / fy
    lim_x_pos = (W - cx) / fx + margin * tan_fovx
    lim_x_neg = cx / fx + margin * tan_fovx
    lim_y_pos = (H - cy) / fy + margin * tan_fovy
    lim_y_neg = cy / fy + margin * tan_fovy
    return lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos


@njit(cache=True)
def _project_one(i, means, quats, scales, viewmat, consts):
    """Everything the forward and backward passes need about Gaussian ``i``.

    Returns a flat tuple (see the unpacking in the kernels); ``z`` first so callers can cull.
    """
    one = consts[K_ONE]
    two = consts[K_TWO]
    # camera-space mean
    px = means[i, 0]
    py = means[i, 1]
    pz = means[i, 2]
    x = viewmat[0, 0] * px + viewmat[0, 1] * py + viewmat[0, 2] * pz + viewmat[0, 3]
    y = viewmat[1, 0] * px + viewmat[1, 1] * py + viewmat[1, 2] * pz + viewmat[1, 3]
    z = viewmat[2, 0] * px + viewmat[2, 1] * py + viewmat[2, 2] * pz + viewmat[2, 3]
    # rotation of the normalised quaternion
    qw = quats[i, 0]
    qx = quats[i, 1]
    qy = quats[i, 2]
    qz = quats[i, 3]
    qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    qw = qw / qn
    qx = qx / qn
    qy = qy / qn
    qz = qz / qn
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _quat_to_rotmat(qw, qx, qy, qz, one, two)
    s0 = scales[i, 0]
    s1 = scales[i, 1]
    s2 = scales[i, 2]
    # M = R diag(s)
    m00 = r00 * s0
    m01 = r01 * s1
    m02 = r02 * s2
    m10 = r10 * s0
    m11 = r11 * s1
    m12 = r12 * s2
    m20 = r20 * s0
    m21 = r21 * s1
    m22 = r22 * s2
    # B = R_v M
    v00 = viewmat[0, 0]
    v01 = viewmat[0, 1]
    v02 = viewmat[0, 2]
    v10 = viewmat[1, 0]
    v11 = viewmat[1, 1]
    v12 = viewmat[1, 2]
    v20 = viewmat[2, 0]
    v21 = viewmat[2, 1]
    v22 = viewmat[2, 2]
    b00 = v00 * m00 + v01 * m10 + v02 * m20
    b01 = v00 * m01 + v01 * m11 + v02 * m21
    b02 = v00 * m02 + v01 * m12 + v02 * m22
    b10 = v10 * m00 + v11 * m10 + v12 * m20
    b11 = v10 * m01 + v11 * m11 + v12 * m21
    b12 = v10 * m02 + v11 * m12 + v12 * m22
    b20 = v20 * m00 + v21 * m10 + v22 * m20
    b21 = v20 * m01 + v21 * m11 + v22 * m21
    b22 = v20 * m02 + v21 * m12 + v22 * m22
    return (z, x, y, qn, qw, qx, qy, qz, r00, r01, r02, r10, r11, r12, r20, r21, r22,
            m00, m01, m02, m10, m11, m12, m20, m21, m22, b00, b01, b02, b10, b11, b12, b20, b21, b22)


@njit(cache=True)
def _jacobian(x, y, z, fx, fy, lims):
    """Entries of J and the clamp state: (j00, j02, j11, j12, tx, ty, cxz, cyz, clamped_x, clamped_y)."""
    lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos = lims
    xz = x / z
    yz = y / z
    clamped_x = False
    clamped_y = False
    if xz < -lim_x_neg:
        xz = -lim_x_neg
        clamped_x = True
    elif xz > lim_x_pos:
        xz = lim_x_pos
        clamped_x = True
    if yz < -lim_y_neg:
        yz = -lim_y_neg
        clamped_y = True
    elif yz > lim_y_pos:
        yz = lim_y_pos
        clamped_y = True
    tx = z * xz
    ty = z * yz
    z2 = z * z
    j00 = fx / z
    j02 = -fx * tx / z2
    j11 = fy / z
    j12 = -fy * ty / z2
    return j00, j02, j11, j12, tx, ty, xz, yz, clamped_x, clamped_y


@njit(cache=True, parallel=True)
def _project_fwd_kernel(means, quats, scales, opacities, viewmat, K, consts, antialiased,
                        means2d, depths, conics, radii, opac_eff, cov2d):
    """Project every Gaussian (prange over Gaussians; row i of each output written by iteration i).

    means (N,3), quats (N,4), scales (N,3), opacities (N,), viewmat (4,4), K (3,3), consts
    (N_CONSTS,); outputs means2d (N,2), depths (N,), conics (N,3), radii (N,2) float (0 = culled),
    opac_eff (N,) (opacity times the antialiasing compensation, or the opacity), cov2d (N,3) the
    dilated 2D covariance (c00, c01, c11) (used by the rasteriser to bound each row's footprint).
    Culled Gaussians get means2d = conics = opac_eff = cov2d = 0; depths is always the camera z.
    """
    n = means.shape[0]
    zero = consts[K_ZERO]
    eps2d = consts[K_EPS2D]
    det_min = consts[K_DET_MIN]
    near = consts[K_NEAR]
    far = consts[K_FAR]
    rsig = consts[K_RADIUS_SIGMA]
    W = consts[K_WIDTH]
    H = consts[K_HEIGHT]
    fx = K[0, 0]
    fy = K[1, 1]
    cx = K[0, 2]
    cy = K[1, 2]
    lims = _fov_limits(K, consts)
    for i in prange(n):
        (z, x, y, qn, qw, qx, qy, qz, r00, r01, r02, r10, r11, r12, r20, r21, r22,
         m00, m01, m02, m10, m11, m12, m20, m21, m22,
         b00, b01, b02, b10, b11, b12, b20, b21, b22) = _project_one(
            i, means, quats, scales, viewmat, consts)
        depths[i] = z
        means2d[i, 0] = zero
        means2d[i, 1] = zero
        conics[i, 0] = zero
        conics[i, 1] = zero
        conics[i, 2] = zero
        radii[i, 0] = zero
        radii[i, 1] = zero
        opac_eff[i] = zero
        cov2d[i, 0] = zero
        cov2d[i, 1] = zero
        cov2d[i, 2] = zero
        if not (z > near and z < far):
            continue
        u = fx * x / z + cx
        v = fy * y / z + cy
        j00, j02, j11, j12, tx, ty, xz, yz, clx, cly = _jacobian(x, y, z, fx, fy, lims)
        a00 = j00 * b00 + j02 * b20
        a01 = j00 * b01 + j02 * b21
        a02 = j00 * b02 + j02 * b22
        a10 = j11 * b10 + j12 * b20
        a11 = j11 * b11 + j12 * b21
        a12 = j11 * b12 + j12 * b22
        s00 = a00 * a00 + a01 * a01 + a02 * a02
        s01 = a00 * a10 + a01 * a11 + a02 * a12
        s11 = a10 * a10 + a11 * a11 + a12 * a12
        det_orig = s00 * s11 - s01 * s01
        c00 = s00 + eps2d
        c11 = s11 + eps2d
        det = c00 * c11 - s01 * s01
        if det < det_min:
            det = det_min
        if not det > zero:
            continue
        rx = np.ceil(rsig * math.sqrt(c00))
        ry = np.ceil(rsig * math.sqrt(c11))
        if not (u + rx > zero and u - rx < W and v + ry > zero and v - ry < H):
            continue
        means2d[i, 0] = u
        means2d[i, 1] = v
        conics[i, 0] = c11 / det
        conics[i, 1] = -s01 / det
        conics[i, 2] = c00 / det
        radii[i, 0] = rx
        radii[i, 1] = ry
        cov2d[i, 0] = c00
        cov2d[i, 1] = s01
        cov2d[i, 2] = c11
        o = opacities[i]
        if antialiased:
            r = det_orig / det
            if r < zero:
                r = zero
            o = o * math.sqrt(r)
        opac_eff[i] = o


@njit(cache=True, parallel=True)
def _project_bwd_kernel(means, quats, scales, opacities, viewmat, K, consts, antialiased, radii,
                        v_means2d, v_depths, v_conics, v_opac_eff,
                        v_means, v_quats, v_scales, v_opacities, v_view_rows):
    """Backward of :func:`_project_fwd_kernel` (prange over Gaussians, no write conflicts).

    Recomputes the forward quantities of Gaussian i from the inputs, then pulls the cotangents
    v_means2d (N,2), v_depths (N,), v_conics (N,3), v_opac_eff (N,) back to v_means (N,3),
    v_quats (N,4) (raw quaternion), v_scales (N,3), v_opacities (N,) and the per-Gaussian pose
    gradient v_view_rows (N,12) = (dL/dR_v row-major (9), dL/dt_v (3)). Culled Gaussians
    (radii == 0) get zero everywhere. Outputs must be zero-initialised.
    """
    n = means.shape[0]
    zero = consts[K_ZERO]
    two = consts[K_TWO]
    half = consts[K_HALF]
    eps2d = consts[K_EPS2D]
    det_min = consts[K_DET_MIN]
    fx = K[0, 0]
    fy = K[1, 1]
    lims = _fov_limits(K, consts)
    for i in prange(n):
        if radii[i, 0] == zero or radii[i, 1] == zero:
            continue
        (z, x, y, qn, qw, qx, qy, qz, r00, r01, r02, r10, r11, r12, r20, r21, r22,
         m00, m01, m02, m10, m11, m12, m20, m21, m22,
         b00, b01, b02, b10, b11, b12, b20, b21, b22) = _project_one(
            i, means, quats, scales, viewmat, consts)
        j00, j02, j11, j12, tx, ty, xz, yz, clx, cly = _jacobian(x, y, z, fx, fy, lims)
        a00 = j00 * b00 + j02 * b20
        a01 = j00 * b01 + j02 * b21
        a02 = j00 * b02 + j02 * b22
        a10 = j11 * b10 + j12 * b20
        a11 = j11 * b11 + j12 * b21
        a12 = j11 * b12 + j12 * b22
        s00 = a00 * a00 + a01 * a01 + a02 * a02
        s01 = a00 * a10 + a01 * a11 + a02 * a12
        s11 = a10 * a10 + a11 * a11 + a12 * a12
        det_orig = s00 * s11 - s01 * s01
        c00 = s00 + eps2d
        c11 = s11 + eps2d
        det = c00 * c11 - s01 * s01
        det_clamped = det < det_min
        if det_clamped:
            det = det_min
        ca = c11 / det
        cb = -s01 / det
        cc = c00 / det

        # ---- opacity (and the antialiasing compensation) ----
        v_oe = v_opac_eff[i]
        v_det = zero
        v_det_orig = zero
        if antialiased:
            r = det_orig / det
            if r > zero:
                comp = math.sqrt(r)
                v_opacities[i] = v_oe * comp
                v_r = v_oe * opacities[i] * half / comp
                v_det_orig = v_r / det
                v_det = -v_r * r / det
            else:
                v_opacities[i] = zero  # comp = 0: the effective opacity is 0 whatever o is
        else:
            v_opacities[i] = v_oe

        # ---- conic = (c11, -c01, c00) / det ----
        v_a = v_conics[i, 0]
        v_b = v_conics[i, 1]
        v_c = v_conics[i, 2]
        v_c00 = v_c / det
        v_c11 = v_a / det
        v_c01 = -v_b / det
        if not det_clamped:
            v_det = v_det - (v_a * ca + v_b * cb + v_c * cc) / det
            v_c00 += v_det * c11
            v_c11 += v_det * c00
            v_c01 += -two * s01 * v_det
        # det_orig = s00 s11 - s01^2 ; c00 = s00 + eps, c11 = s11 + eps, c01 = s01
        g00 = v_c00 + v_det_orig * s11
        g11 = v_c11 + v_det_orig * s00
        g01 = v_c01 - two * s01 * v_det_orig
        # s00 = |a0|^2, s11 = |a1|^2, s01 = a0.a1
        va00 = two * g00 * a00 + g01 * a10
        va01 = two * g00 * a01 + g01 * a11
        va02 = two * g00 * a02 + g01 * a12
        va10 = two * g11 * a10 + g01 * a00
        va11 = two * g11 * a11 + g01 * a01
        va12 = two * g11 * a12 + g01 * a02
        # A = J B
        v_j00 = va00 * b00 + va01 * b01 + va02 * b02
        v_j02 = va00 * b20 + va01 * b21 + va02 * b22
        v_j11 = va10 * b10 + va11 * b11 + va12 * b12
        v_j12 = va10 * b20 + va11 * b21 + va12 * b22
        vb00 = j00 * va00
        vb01 = j00 * va01
        vb02 = j00 * va02
        vb10 = j11 * va10
        vb11 = j11 * va11
        vb12 = j11 * va12
        vb20 = j02 * va00 + j12 * va10
        vb21 = j02 * va01 + j12 * va11
        vb22 = j02 * va02 + j12 * va12

        # ---- J -> camera point ----
        vx = zero
        vy = zero
        vz = v_depths[i]
        vz += -j00 / z * v_j00 - j11 / z * v_j11 - two * j02 / z * v_j02 - two * j12 / z * v_j12
        z2 = z * z
        v_tx = -fx / z2 * v_j02
        v_ty = -fy / z2 * v_j12
        if clx:
            vz += xz * v_tx  # tx = z * clamp value: the clamp value is constant
        else:
            vx += v_tx  # tx = z * (x / z) = x
        if cly:
            vz += yz * v_ty
        else:
            vy += v_ty
        # ---- mean2d ----
        v_u = v_means2d[i, 0]
        v_v = v_means2d[i, 1]
        vx += fx / z * v_u
        vy += fy / z * v_v
        vz += -fx * x / z2 * v_u - fy * y / z2 * v_v

        # ---- B = R_v M ----
        v00 = viewmat[0, 0]
        v01 = viewmat[0, 1]
        v02 = viewmat[0, 2]
        v10 = viewmat[1, 0]
        v11 = viewmat[1, 1]
        v12 = viewmat[1, 2]
        v20 = viewmat[2, 0]
        v21 = viewmat[2, 1]
        v22 = viewmat[2, 2]
        vm00 = v00 * vb00 + v10 * vb10 + v20 * vb20
        vm01 = v00 * vb01 + v10 * vb11 + v20 * vb21
        vm02 = v00 * vb02 + v10 * vb12 + v20 * vb22
        vm10 = v01 * vb00 + v11 * vb10 + v21 * vb20
        vm11 = v01 * vb01 + v11 * vb11 + v21 * vb21
        vm12 = v01 * vb02 + v11 * vb12 + v21 * vb22
        vm20 = v02 * vb00 + v12 * vb10 + v22 * vb20
        vm21 = v02 * vb01 + v12 * vb11 + v22 * vb21
        vm22 = v02 * vb02 + v12 * vb12 + v22 * vb22
        # dL/dR_v[r, k] = sum_j vB[r, j] M[k, j] + v_pc[r] p[k]
        px = means[i, 0]
        py = means[i, 1]
        pz = means[i, 2]
        v_view_rows[i, 0] = vb00 * m00 + vb01 * m01 + vb02 * m02 + vx * px
        v_view_rows[i, 1] = vb00 * m10 + vb01 * m11 + vb02 * m12 + vx * py
        v_view_rows[i, 2] = vb00 * m20 + vb01 * m21 + vb02 * m22 + vx * pz
        v_view_rows[i, 3] = vb10 * m00 + vb11 * m01 + vb12 * m02 + vy * px
        v_view_rows[i, 4] = vb10 * m10 + vb11 * m11 + vb12 * m12 + vy * py
        v_view_rows[i, 5] = vb10 * m20 + vb11 * m21 + vb12 * m22 + vy * pz
        v_view_rows[i, 6] = vb20 * m00 + vb21 * m01 + vb22 * m02 + vz * px
        v_view_rows[i, 7] = vb20 * m10 + vb21 * m11 + vb22 * m12 + vz * py
        v_view_rows[i, 8] = vb20 * m20 + vb21 * m21 + vb22 * m22 + vz * pz
        v_view_rows[i, 9] = vx
        v_view_rows[i, 10] = vy
        v_view_rows[i, 11] = vz
        # ---- p_c = R_v p + t ----
        v_means[i, 0] = v00 * vx + v10 * vy + v20 * vz
        v_means[i, 1] = v01 * vx + v11 * vy + v21 * vz
        v_means[i, 2] = v02 * vx + v12 * vy + v22 * vz

        # ---- M = R diag(s) ----
        s0 = scales[i, 0]
        s1 = scales[i, 1]
        s2 = scales[i, 2]
        v_scales[i, 0] = vm00 * r00 + vm10 * r10 + vm20 * r20
        v_scales[i, 1] = vm01 * r01 + vm11 * r11 + vm21 * r21
        v_scales[i, 2] = vm02 * r02 + vm12 * r12 + vm22 * r22
        g_00 = vm00 * s0
        g_01 = vm01 * s1
        g_02 = vm02 * s2
        g_10 = vm10 * s0
        g_11 = vm11 * s1
        g_12 = vm12 * s2
        g_20 = vm20 * s0
        g_21 = vm21 * s1
        g_22 = vm22 * s2
        # ---- R(q_unit) ----
        vqw = two * (-qz * g_01 + qy * g_02 + qz * g_10 - qx * g_12 - qy * g_20 + qx * g_21)
        vqx = two * (qy * g_01 + qz * g_02 + qy * g_10 - two * qx * g_11 - qw * g_12 + qz * g_20
                     + qw * g_21 - two * qx * g_22)
        vqy = two * (-two * qy * g_00 + qx * g_01 + qw * g_02 + qx * g_10 + qz * g_12 - qw * g_20
                     + qz * g_21 - two * qy * g_22)
        vqz = two * (-two * qz * g_00 - qw * g_01 + qx * g_02 + qw * g_10 - two * qz * g_11
                     + qy * g_12 + qx * g_20 + qy * g_21)
        # ---- normalisation q_unit = q / |q| ----
        dot = qw * vqw + qx * vqx + qy * vqy + qz * vqz
        v_quats[i, 0] = (vqw - qw * dot) / qn
        v_quats[i, 1] = (vqx - qx * dot) / qn
        v_quats[i, 2] = (vqy - qy * dot) / qn
        v_quats[i, 3] = (vqz - qz * dot) / qn


def project_fwd(means, quats, scales, opacities, cam_T_world, K, consts, antialiased):
    """Allocate and run the projection forward (inputs already validated by ``api.render_fwd``).

    Returns dict(means2d (N,2), depths (N,), conics (N,3), radii_f (N,2) float, opac_eff (N,),
    cov2d (N,3)).
    """
    n = means.shape[0]
    dtype = means.dtype
    means2d = np.empty((n, 2), dtype)
    depths = np.empty(n, dtype)
    conics = np.empty((n, 3), dtype)
    radii = np.empty((n, 2), dtype)
    opac_eff = np.empty(n, dtype)
    cov2d = np.empty((n, 3), dtype)
    _project_fwd_kernel(means, quats, scales, opacities, cam_T_world, K, consts, bool(antialiased),
                        means2d, depths, conics, radii, opac_eff, cov2d)
    return dict(means2d=means2d, depths=depths, conics=conics, radii_f=radii, opac_eff=opac_eff, cov2d=cov2d)


def project_bwd(means, quats, scales, opacities, cam_T_world, K, consts, antialiased, radii_f,
                v_means2d, v_depths, v_conics, v_opac_eff):
    """Allocate and run the projection backward; returns (v_means, v_quats, v_scales,
    v_opacities, v_cam_T_world (4,4) with a zero bottom row)."""
    n = means.shape[0]
    dtype = means.dtype
    v_means = np.zeros((n, 3), dtype)
    v_quats = np.zeros((n, 4), dtype)
    v_scales = np.zeros((n, 3), dtype)
    v_opacities = np.zeros(n, dtype)
    v_view_rows = np.zeros((n, 12), dtype)
    _project_bwd_kernel(means, quats, scales, opacities, cam_T_world, K, consts, bool(antialiased),
                        radii_f, v_means2d, v_depths, v_conics, v_opac_eff,
                        v_means, v_quats, v_scales, v_opacities, v_view_rows)
    v_view = np.zeros((4, 4), dtype)
    total = _sum_rows_kernel(v_view_rows)
    v_view[:3, :3] = total[:9].reshape(3, 3)
    v_view[:3, 3] = total[9:]
    return v_means, v_quats, v_scales, v_opacities, v_view


@njit(cache=True)
def _sum_rows_kernel(rows):
    """Sum of the rows of ``rows`` (N, M) in a fixed order (deterministic).

    Two levels: sequential sums over blocks of ``_SUM_BLOCK`` consecutive rows, then a sequential
    sum of the block totals; the rounding error grows like N / _SUM_BLOCK + _SUM_BLOCK instead of
    N, which matters for float32.
    """
    n = rows.shape[0]
    m = rows.shape[1]
    out = np.zeros(m, rows.dtype)
    block = np.zeros(m, rows.dtype)
    for start in range(0, n, _SUM_BLOCK):
        block[:] = 0
        for i in range(start, min(start + _SUM_BLOCK, n)):
            for j in range(m):
                block[j] += rows[i, j]
        for j in range(m):
            out[j] += block[j]
    return out

