"""Pixel rays and the images of a cast (d2gs_np/data/raycast.py), on an analytic textured plane."""
import numpy as np
import pytest

from d2gs_np.data.raycast import cast_depth, cast_view, check_view, pixel_rays, stratified_offsets
from d2gs_np.geometry.camera import look_at, make_intrinsics, project_points

# Rays and hits are a few float64 operations on O(1-10) values: ~1e-15 relative; 1e-12 leaves
# three orders of magnitude while a ray through the wrong sub-sample is off by >= 1e-2.
ATOL = 1e-12
PLANE_Z = -5.0  # the test world: the plane z = -5, seen from cameras near the origin


def plane_cast(origin, dirs):
    """A smooth texture on the plane z = PLANE_Z; "moving" where the hit has x > 0.3."""
    s = (PLANE_Z - origin[2]) / dirs[2]
    x, y = origin[0] + s * dirs[0], origin[1] + s * dirs[1]
    rgb = np.stack([np.sin(3.0 * x), np.cos(2.0 * y), x * y])
    return rgb, s, x > 0.3


def _camera():
    T = look_at([0.2, -0.1, 0.3], [0.5, 0.3, PLANE_Z], up=(0.0, 1.0, 0.0))
    return T, make_intrinsics(9.0, 9.5, 6.2, 4.9)


@pytest.mark.parametrize("s", [1, 2, 3])
def test_rays_pass_through_the_sub_sample_centres_with_unit_camera_z(s):
    T, K = _camera()
    W, H = 11, 7
    origin, dirs = pixel_rays(T, K, W, H, s)
    d = np.stack(dirs, axis=1)
    np.testing.assert_allclose((T[:3, :3] @ d.T)[2], 1.0, rtol=0, atol=ATOL)  # camera z of each direction
    uv, z = project_points(origin + 2.0 * d, T, K)
    np.testing.assert_allclose(z, 2.0, rtol=0, atol=ATOL)
    i, j = np.divmod(np.arange(H * s * W * s), W * s)  # row-major over the fine grid
    np.testing.assert_allclose(uv, np.stack([(j + 0.5) / s, (i + 0.5) / s], axis=1), rtol=0, atol=ATOL)


def test_supersampling_is_the_mean_of_shifted_single_samples():
    T, K = _camera()
    W, H = 10, 6
    img2, dyn2 = cast_view(plane_cast, T, K, W, H, supersample=2)
    acc = np.zeros_like(img2)
    any_dyn = np.zeros_like(dyn2)
    for ox in (0.25, 0.75):
        for oy in (0.25, 0.75):
            Ks = K.copy()
            Ks[0, 2] += 0.5 - ox  # a single sample at j + 0.5 with cx' sees what j + ox sees with cx
            Ks[1, 2] += 0.5 - oy
            img, d = cast_view(plane_cast, T, Ks, W, H, supersample=1)
            acc += img / 4
            any_dyn |= d
    np.testing.assert_allclose(img2, acc, rtol=0, atol=ATOL)
    assert np.array_equal(dyn2, any_dyn)
    assert dyn2.any() and not dyn2.all()  # the mask test can fail both ways


@pytest.mark.parametrize("offset", [(0.25, -0.125), (-0.5, 0.5)])
def test_an_offset_shifts_every_sub_sample_within_its_cell(offset):
    # an offset (ox, oy) moves sub-sample (a, b) of pixel (i, j) to (j + (a + 0.5 + ox)/s, ...): the
    # same as casting without offset through a principal point moved by -(ox, oy)/s
    T, K = _camera()
    W, H, s = 10, 6, 2
    img, dyn = cast_view(plane_cast, T, K, W, H, supersample=s, offset=offset)
    Ks = K.copy()
    Ks[0, 2] -= offset[0] / s
    Ks[1, 2] -= offset[1] / s
    ref, ref_dyn = cast_view(plane_cast, T, Ks, W, H, supersample=s)
    np.testing.assert_allclose(img, ref, rtol=0, atol=ATOL)
    assert np.array_equal(dyn, ref_dyn)
    assert np.abs(img - cast_view(plane_cast, T, K, W, H, supersample=s)[0]).max() > 1e-3  # it moved


@pytest.mark.parametrize("count", [1, 4, 9, 16, 5, 20])
def test_stratified_offsets_put_one_cast_in_each_cell_of_the_finer_grid(count):
    off = stratified_offsets(count)
    m = int(np.ceil(np.sqrt(count)))
    assert off.shape == (count, 2) and np.all(np.abs(off) < 0.5)
    cells = np.round((off + 0.5) * m - 0.5).astype(int)  # cell (column, row) of each cast
    np.testing.assert_allclose((cells + 0.5) / m - 0.5, off, rtol=0, atol=1e-15)  # cell centres
    ids = cells[:, 1] * m + cells[:, 0]
    first = ids[: min(count, m * m)]
    assert len(set(first.tolist())) == len(first)  # no cell twice before every cell is used
    if count == m * m and count > 1:
        # shuffled: the first half of the casts (early in an exposure) is not one half of the pixel
        assert 0 < np.sum(off[: count // 2, 1] < 0) < count // 2
    np.testing.assert_array_equal(off, stratified_offsets(count))  # fixed, not random per call


def test_a_stratified_blur_samples_the_pixel_area_as_finely_as_its_casts_together():
    # 16 casts of 1 sample each, stratified, give exactly the 4 x 4 supersampled image
    T, K = _camera()
    W, H = 10, 6
    acc = sum(cast_view(plane_cast, T, K, W, H, supersample=1, offset=o)[0] for o in stratified_offsets(16))
    np.testing.assert_allclose(acc / 16, cast_view(plane_cast, T, K, W, H, supersample=4)[0], rtol=0, atol=ATOL)


def test_depth_is_the_camera_z_of_the_hit_through_each_pixel_centre():
    T, K = _camera()
    depth = cast_depth(plane_cast, T, K, 9, 5)
    assert depth.shape == (5, 9)
    i, j = np.mgrid[0:5, 0:9]
    ray_cam = np.stack([(j + 0.5 - K[0, 2]) / K[0, 0], (i + 0.5 - K[1, 2]) / K[1, 1], np.ones((5, 9))], -1)
    hit_cam = depth[..., None] * ray_cam
    hit_world = (hit_cam - T[:3, 3]) @ T[:3, :3]  # R^T (p_cam - t)
    np.testing.assert_allclose(hit_world[..., 2], PLANE_Z, rtol=0, atol=ATOL)


@pytest.mark.parametrize("args, exc, match", [
    (dict(cam_T_world=np.eye(4)[:3]), ValueError, r"cam_T_world must have shape \(4, 4\)"),
    (dict(cam_T_world=np.diag([2.0, 1.0, 1.0, 1.0])), ValueError, "not rigid"),
    (dict(K=np.eye(3)[:2]), ValueError, r"K must have shape \(3, 3\)"),
    (dict(width=0), ValueError, "width must be an integer >= 1"),
    (dict(height=True), ValueError, "height must be an integer >= 1"),
    (dict(supersample=0), ValueError, "supersample must be an integer >= 1"),
    (dict(supersample=1.5), ValueError, "supersample must be an integer >= 1"),
    (dict(offset=(0.6, 0.0)), ValueError, r"offset must be two finite numbers in \[-0.5, 0.5\]"),
    (dict(offset=(np.nan, 0.0)), ValueError, "offset must be two finite numbers"),
    (dict(offset=(0.1,)), ValueError, "offset must be two finite numbers"),
])
def test_bad_views_are_rejected_before_any_ray_is_cast(args, exc, match):
    T, K = _camera()
    view = dict(cam_T_world=T, K=K, width=4, height=3, supersample=2) | args

    def no_cast(origin, dirs):
        raise AssertionError("cast before the checks")

    with pytest.raises(exc, match=match):
        cast_view(no_cast, **view)
    if "supersample" not in args and "offset" not in args:
        with pytest.raises(exc, match=match):
            check_view(view["cam_T_world"], view["K"], view["width"], view["height"])
