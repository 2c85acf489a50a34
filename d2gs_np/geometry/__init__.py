"""Geometry: SO(3)/SE(3) Lie groups (left perturbations), quaternions (wxyz), pinhole cameras."""
from d2gs_np.geometry.camera import (
    camera_center, cam_T_world_to_opengl_c2w, check_intrinsics, look_at, make_intrinsics,
    opengl_c2w_to_cam_T_world, project_points, scale_intrinsics, scaled_size,
)
from d2gs_np.geometry.quaternion import quat_multiply, quat_normalize, quat_to_rotmat, rotmat_to_quat
from d2gs_np.geometry.se3 import (
    check_rigid, matrix_grad_to_left_tangent, se3_adjoint, se3_compose, se3_exp, se3_interpolate,
    se3_inverse, se3_left_jacobian, se3_left_jacobian_inv, se3_log, se3_right_jacobian,
    se3_right_jacobian_inv,
)
from d2gs_np.geometry.so3 import (
    hat, left_jacobian, left_jacobian_inv, right_jacobian, right_jacobian_inv, so3_exp, so3_log,
    so3_orthonormalize, vee,
)
