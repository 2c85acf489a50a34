"""Tests for d2gs_np.geometry.camera: OpenGL <-> OpenCV poses, pinhole projection, intrinsics scaling
with the +0.5 pixel-centre convention (docs/conventions.md §2), look_at and camera centres."""
from __future__ import annotations

import numpy as np
import pytest

from d2gs_np.geometry.camera import (
    cam_T_world_to_opengl_c2w, camera_center, check_intrinsics, look_at, make_intrinsics,
    opengl_c2w_to_cam_T_world, project_points, scale_intrinsics, scaled_size,
)
from d2gs_np.geometry.quaternion import quat_to_rotmat
from d2gs_np.geometry.se3 import check_rigid

EPS = np.finfo(np.float64).eps
# Poses and projections are a few rounded products of O(1)..O(10) numbers; pixel coordinates are
# O(100) so one ulp there is ~1.4e-14.
POSE_TOL = 1e-14
PIXEL_TOL = 1e-12
# Depths and camera centres: -R^T t and R p + t with |t|, |p| <= ~10, i.e. a few ulps of 10.
DEPTH_TOL = 1e-13

K_FULL = make_intrinsics(120.0, 110.0, 33.0, 21.5)  # a 64 x 40 image with an off-centre principal point


def random_c2w(rng, n):
    """OpenGL camera-to-world matrices (rotation from a random quaternion, translation ~ N(0, 2))."""
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = quat_to_rotmat(rng.normal(size=(n, 4)))
    T[:, :3, 3] = 2.0 * rng.normal(size=(n, 3))
    T[:, 3, 3] = 1.0
    return T


def points_in_front(rng, cam_T_world, n, K=K_FULL, size=(64, 40)):
    """World points that land inside the image at depths 1..5."""
    uv = rng.uniform(0.0, 1.0, size=(n, 2)) * np.array(size)
    z = rng.uniform(1.0, 5.0, size=n)
    pc = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], axis=1)
    R, t = cam_T_world[:3, :3], cam_T_world[:3, 3]
    return (pc - t) @ R, uv, z


# --- OpenGL <-> OpenCV -------------------------------------------------------------------------------


def test_opengl_round_trip():
    rng = np.random.default_rng(50)
    c2w = random_c2w(rng, 8)
    cam_T_world = opengl_c2w_to_cam_T_world(c2w)
    check_rigid(cam_T_world, "cam_T_world")
    np.testing.assert_allclose(cam_T_world_to_opengl_c2w(cam_T_world), c2w, rtol=0, atol=POSE_TOL)
    np.testing.assert_allclose(opengl_c2w_to_cam_T_world(cam_T_world_to_opengl_c2w(cam_T_world)), cam_T_world,
                               rtol=0, atol=POSE_TOL)
    # The camera centre is the translation of c2w in both conventions.
    np.testing.assert_allclose(camera_center(cam_T_world), c2w[:, :3, 3], rtol=0, atol=POSE_TOL)


def test_identity_opengl_camera_is_diag_1_m1_m1():
    """An OpenGL camera at the origin looking down -z, y up: in OpenCV axes its rotation is diag(1, -1, -1)."""
    cam_T_world = opengl_c2w_to_cam_T_world(np.eye(4))
    np.testing.assert_array_equal(cam_T_world[:3, :3], np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_array_equal(cam_T_world[:3, 3], 0.0)
    points = np.array([[0.0, 0.0, -5.0], [0.0, 1.0, -5.0], [1.0, 0.0, -5.0], [0.0, 0.0, 5.0]])
    uv, z = project_points(points, cam_T_world, K_FULL)
    assert z[0] == 5.0  # in front of the OpenGL camera: positive OpenCV depth
    assert z[3] < 0.0  # behind it
    np.testing.assert_allclose(uv[0], K_FULL[:2, 2], rtol=0, atol=PIXEL_TOL)
    assert uv[1, 1] < K_FULL[1, 2]  # world up (OpenGL +y) is up in the image (smaller row)
    assert uv[2, 0] > K_FULL[0, 2]  # world right (+x) is right in the image


def test_opengl_camera_looks_along_minus_z_axis():
    rng = np.random.default_rng(51)
    for c2w in random_c2w(rng, 8):
        forward = -c2w[:3, 2]  # OpenGL cameras look down their -z axis
        target = c2w[:3, 3] + 3.0 * forward
        uv, z = project_points(target[None], opengl_c2w_to_cam_T_world(c2w), K_FULL)
        assert z[0] == pytest.approx(3.0, abs=DEPTH_TOL)
        np.testing.assert_allclose(uv[0], K_FULL[:2, 2], rtol=0, atol=PIXEL_TOL)


# --- Projection --------------------------------------------------------------------------------------


def test_project_points_is_the_pinhole_formula():
    rng = np.random.default_rng(52)
    cam_T_world = opengl_c2w_to_cam_T_world(random_c2w(rng, 1)[0])
    points, uv_expected, z_expected = points_in_front(rng, cam_T_world, 32)
    uv, z = project_points(points, cam_T_world, K_FULL)
    np.testing.assert_allclose(z, z_expected, rtol=0, atol=DEPTH_TOL)
    np.testing.assert_allclose(uv, uv_expected, rtol=0, atol=PIXEL_TOL)


def test_point_on_optical_axis_lands_on_principal_point():
    rng = np.random.default_rng(53)
    for cam_T_world in opengl_c2w_to_cam_T_world(random_c2w(rng, 8)):
        axis = cam_T_world[2, :3]  # camera +z in world coordinates (third row of R)
        points = camera_center(cam_T_world) + np.array([0.5, 2.0, 9.0])[:, None] * axis
        uv, z = project_points(points, cam_T_world, K_FULL)
        np.testing.assert_allclose(z, [0.5, 2.0, 9.0], rtol=0, atol=DEPTH_TOL)
        np.testing.assert_allclose(uv, np.broadcast_to(K_FULL[:2, 2], uv.shape), rtol=0, atol=PIXEL_TOL)


def test_project_points_rejects_wrong_shape():
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\)"):
        project_points(np.zeros((4, 2)), np.eye(4), K_FULL)


# --- Intrinsics ----------------------------------------------------------------------------------


@pytest.mark.parametrize("sx, sy", [(0.5, 0.5), (0.25, 0.25), (1 / 3, 1 / 3), (2.0, 2.0), (0.5, 0.25)])
def test_scaled_projection_is_the_scaled_full_projection(sx, sy):
    rng = np.random.default_rng(54)
    cam_T_world = opengl_c2w_to_cam_T_world(random_c2w(rng, 1)[0])
    points, _, _ = points_in_front(rng, cam_T_world, 32)
    uv_full, z_full = project_points(points, cam_T_world, K_FULL)
    uv_s, z_s = project_points(points, cam_T_world, scale_intrinsics(K_FULL, sx, sy))
    np.testing.assert_array_equal(z_s, z_full)
    np.testing.assert_allclose(uv_s, uv_full * np.array([sx, sy]), rtol=0, atol=PIXEL_TOL)


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_downsampled_pixel_centres_are_block_centres(factor):
    """Area downsampling by f: full-res pixels f j .. f j + f - 1 form low-res pixel j. The point
    that projects to the centre of that block, f j + f/2 (in continuous coordinates where pixel j
    covers [j, j + 1)), must land on the low-res pixel centre j + 0.5."""
    cam_T_world = opengl_c2w_to_cam_T_world(np.eye(4))
    K_small = scale_intrinsics(K_FULL, 1.0 / factor)
    j = np.arange(5)
    i = np.arange(5)[::-1]
    uv_block_centres = np.stack([factor * j + factor / 2, factor * i + factor / 2], axis=1)
    # Back-project those full-res positions at depth 2 (OpenCV camera = world with y, z flipped).
    z = 2.0
    pc = np.stack([(uv_block_centres[:, 0] - K_FULL[0, 2]) / K_FULL[0, 0] * z,
                   (uv_block_centres[:, 1] - K_FULL[1, 2]) / K_FULL[1, 1] * z, np.full(5, z)], axis=1)
    points = pc * np.array([1.0, -1.0, -1.0])
    uv_full, _ = project_points(points, cam_T_world, K_FULL)
    np.testing.assert_allclose(uv_full, uv_block_centres, rtol=0, atol=PIXEL_TOL)
    uv_small, _ = project_points(points, cam_T_world, K_small)
    np.testing.assert_allclose(uv_small, np.stack([j + 0.5, i + 0.5], axis=1), rtol=0, atol=PIXEL_TOL)


def test_scale_intrinsics_keeps_zero_skew_and_last_row():
    K = scale_intrinsics(K_FULL, 0.5, 0.25)
    check_intrinsics(K)
    np.testing.assert_array_equal(K, [[60.0, 0.0, 16.5], [0.0, 27.5, 5.375], [0.0, 0.0, 1.0]])


def test_scaled_size():
    assert scaled_size(64, 40, 0.5) == (32, 20)
    assert scaled_size(64, 40, 1.0) == (64, 40)
    assert scaled_size(64, 40, 1e-3) == (1, 1)  # never empty
    for r in np.linspace(0.2, 1.0, 17):  # nearest integer size (how halves round is not specified)
        w, h = scaled_size(65, 41, r)
        assert abs(w - 65 * r) <= 0.5 and abs(h - 41 * r) <= 0.5


@pytest.mark.parametrize("fx, fy", [(0.0, 100.0), (100.0, -1.0), (-5.0, -5.0), (np.nan, 100.0)])
def test_make_intrinsics_rejects_non_positive_focal(fx, fy):
    with pytest.raises(ValueError, match="focal"):
        make_intrinsics(fx, fy, 16.0, 16.0)


@pytest.mark.parametrize(
    "K, pattern",
    [
        (np.array([[100.0, 0.5, 16.0], [0.0, 100.0, 16.0], [0.0, 0.0, 1.0]]), "skew"),
        (np.eye(4), "shape"),
        (np.array([[100.0, 0.0, np.nan], [0.0, 100.0, 16.0], [0.0, 0.0, 1.0]]), "NaN"),
        (np.array([[-100.0, 0.0, 16.0], [0.0, 100.0, 16.0], [0.0, 0.0, 1.0]]), "focal"),
    ],
    ids=["skew", "shape", "nan", "negative_focal"],
)
def test_check_intrinsics_rejects(K, pattern):
    with pytest.raises(ValueError, match=pattern) as info:
        check_intrinsics(K, name="K_render")
    assert "K_render" in str(info.value)


def test_check_intrinsics_accepts_valid():
    check_intrinsics(K_FULL)


# --- look_at and camera centres ------------------------------------------------------------------


def test_look_at_puts_target_on_the_optical_axis():
    rng = np.random.default_rng(55)
    for _ in range(8):
        eye, target = rng.normal(size=3) * 3.0, rng.normal(size=3)
        cam_T_world = look_at(eye, target)
        check_rigid(cam_T_world, "cam_T_world")
        uv, z = project_points(target[None], cam_T_world, K_FULL)
        assert z[0] == pytest.approx(np.linalg.norm(target - eye), rel=1e-14)
        assert z[0] > 0.0
        np.testing.assert_allclose(uv[0], K_FULL[:2, 2], rtol=0, atol=PIXEL_TOL)
        np.testing.assert_allclose(camera_center(cam_T_world), eye, rtol=0, atol=DEPTH_TOL)


def test_look_at_up_vector_points_up_in_the_image():
    eye, target = np.array([0.0, 0.0, -4.0]), np.zeros(3)
    for up in ([0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.3]):
        cam_T_world = look_at(eye, target, up=up)
        uv, _ = project_points(np.stack([target, target + 0.1 * np.asarray(up)]), cam_T_world, K_FULL)
        assert uv[1, 1] < uv[0, 1]  # moving along up decreases the row
        assert uv[1, 0] == pytest.approx(uv[0, 0], abs=PIXEL_TOL)


def test_look_at_rejects_up_parallel_to_view():
    with pytest.raises(ValueError, match="parallel"):
        look_at([0.0, 0.0, 0.0], [0.0, 2.0, 0.0], up=[0.0, 1.0, 0.0])


def test_camera_center_maps_to_camera_origin():
    rng = np.random.default_rng(56)
    cam_T_world = opengl_c2w_to_cam_T_world(random_c2w(rng, 6)).reshape(2, 3, 4, 4)
    c = camera_center(cam_T_world)
    assert c.shape == (2, 3, 3)
    origin = np.einsum("...ij,...j->...i", cam_T_world[..., :3, :3], c) + cam_T_world[..., :3, 3]
    np.testing.assert_allclose(origin, 0.0, rtol=0, atol=DEPTH_TOL)


def test_unproject_inverts_project():
    from d2gs_np.geometry.camera import look_at, make_intrinsics, project_points, unproject_points

    rng = np.random.default_rng(5)
    T = look_at([0.5, -0.2, -3.0], [0.0, 0.0, 1.0])
    K = make_intrinsics(120.0, 110.0, 40.5, 30.25)
    pts = rng.normal(size=(20, 3))
    uv, z = project_points(pts, T, K)
    np.testing.assert_allclose(unproject_points(uv, z, T, K), pts, atol=1e-12)
