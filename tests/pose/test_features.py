"""Feature matching: pixel convention, known homography and pose, masks, degenerate inputs."""
import cv2
import numpy as np
import pytest

from d2gs_np.pose import features as ft
from d2gs_np.pose.config import FeatureConfig
from d2gs_np.data import synthetic as syn
from d2gs_np.geometry.camera import look_at, make_intrinsics, project_points

# SIFT localises an isolated Gaussian blob to ~0.02 px (measured std 0.004-0.06 px for blob
# sigmas 1.5-4 px). A missing +0.5 conversion would show up as 0.5 px, OpenCV's imprecise
# first-octave upscaling as 0.25 px; 0.1 px separates these cleanly.
BLOB_MEAN_OFFSET_TOL_PX = 0.1
BLOB_MAX_OFFSET_TOL_PX = 0.3
# Matched points against a known mapping, after bilinear warping (homography) or nearest-pixel
# depth look-ups (pose): most agree to a fraction of a pixel; a few sit on edges or depth
# discontinuities, hence a median and a 90th-percentile bound ("to ~1 px").
MAP_MEDIAN_TOL_PX = 0.3
MAP_P90_TOL_PX = 1.0
# Keypoints are refined to sub-pixel positions after the detector mask is applied; the refinement
# moves a point by < 1 px from the (unmasked) pixel where it was detected.
MASK_REFINE_SLACK_PX = 1.0


def textured_image(width=160, height=120, t=0.0):
    """A sharp ray-cast image of the static synthetic room (float64 (H, W, 3))."""
    world = syn.build_world(syn.SyntheticConfig(moving_objects=False))
    K = make_intrinsics(0.9 * width, 0.9 * width, width / 2, height / 2)
    T = look_at([0.3, 1.4, 2.5], [0.0, 0.8, -1.0], up=(0.0, 1.0, 0.0))
    img, _ = syn.render_view(world, T, t, K, width, height, supersample=2)
    return img, world, K, T


def blob_image(height=96, width=128, sigma=2.5, seed=0):
    rng = np.random.default_rng(seed)
    centres = np.array([(16 + 24 * j + rng.uniform(-3, 3), 14 + 22 * i + rng.uniform(-3, 3))
                        for i in range(4) for j in range(5)])
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)  # our pixel centres
    img = np.full((height, width), 0.2)
    for cx, cy in centres:
        img += 0.6 * np.exp(-((jj - cx) ** 2 + (ii - cy) ** 2) / (2 * sigma**2))
    return img, centres


@pytest.mark.parametrize("sigma", [1.5, 2.5, 4.0])
def test_keypoints_use_our_pixel_convention(sigma):
    img, centres = blob_image(sigma=sigma)
    kp = ft.detect_features(img)
    d = np.linalg.norm(kp.pts[:, None, :] - centres[None], axis=-1)
    nearest = d.argmin(axis=1)
    on_blob = d.min(axis=1) < 2.0  # keypoints at blob centres (others fire on blob-pair saddles)
    assert len(np.unique(nearest[on_blob])) >= 15  # most of the 20 blobs are found
    offset = kp.pts[on_blob] - centres[nearest[on_blob]]
    assert np.all(np.abs(offset.mean(axis=0)) < BLOB_MEAN_OFFSET_TOL_PX), offset.mean(axis=0)
    assert np.abs(offset).max() < BLOB_MAX_OFFSET_TOL_PX


def test_matches_follow_a_known_homography():
    img, *_ = textured_image()
    H, W = img.shape[:2]
    a, s = np.deg2rad(6.0), 1.08
    H_ours = np.array([[s * np.cos(a), -s * np.sin(a), 4.0], [s * np.sin(a), s * np.cos(a), -9.0], [2e-4, -1e-4, 1.0]])
    S = np.array([[1.0, 0, -0.5], [0, 1.0, -0.5], [0, 0, 1.0]])  # ours -> OpenCV pixel coords
    H_cv = S @ H_ours @ np.linalg.inv(S)
    warped = cv2.warpPerspective(img, H_cv, (W, H), flags=cv2.INTER_LINEAR)
    m = ft.match_images(img, warped)
    assert m.num_inliers >= 50
    p = np.c_[m.pts0, np.ones(len(m.pts0))] @ H_ours.T
    err = np.linalg.norm(p[:, :2] / p[:, 2:] - m.pts1, axis=1)
    assert np.median(err) < MAP_MEDIAN_TOL_PX and np.percentile(err, 90) < MAP_P90_TOL_PX, np.percentile(err, [50, 90])


def test_matches_follow_a_known_pose():
    cfg = syn.SyntheticConfig(width=160, height=90, moving_objects=False)
    world = syn.build_world(cfg)
    K = syn.intrinsics(cfg)
    T0, T1 = syn.camera_pose(world, 0.3), syn.camera_pose(world, 0.4)
    img0, _ = syn.render_view(world, T0, 0.3, K, cfg.width, cfg.height)
    img1, _ = syn.render_view(world, T1, 0.4, K, cfg.width, cfg.height)
    m = ft.match_images(img0, img1)
    assert m.num_inliers >= 40
    D0 = syn.depth_map(world, T0, 0.3, K, cfg.width, cfg.height)
    z = D0[m.pts0[:, 1].astype(int), m.pts0[:, 0].astype(int)]
    pc = np.c_[(m.pts0[:, 0] - K[0, 2]) / K[0, 0] * z, (m.pts0[:, 1] - K[1, 2]) / K[1, 1] * z, z]
    pw = (pc - T0[:3, 3]) @ T0[:3, :3]  # camera 0 -> world
    uv1, _ = project_points(pw, T1, K)
    err = np.linalg.norm(uv1 - m.pts1, axis=1)
    assert np.median(err) < MAP_MEDIAN_TOL_PX and np.percentile(err, 90) < MAP_P90_TOL_PX, np.percentile(err, [50, 90])


def test_fundamental_matrix_is_in_our_convention():
    img, *_ = textured_image()
    cfg = syn.SyntheticConfig(width=160, height=90, moving_objects=False)
    world = syn.build_world(cfg)
    K = syn.intrinsics(cfg)
    img0, _ = syn.render_view(world, syn.camera_pose(world, 0.2), 0.2, K, cfg.width, cfg.height)
    img1, _ = syn.render_view(world, syn.camera_pose(world, 0.35), 0.35, K, cfg.width, cfg.height)
    config = FeatureConfig()
    m = ft.match_images(img0, img1, config)
    x0, x1 = np.c_[m.pts0, np.ones(len(m))], np.c_[m.pts1, np.ones(len(m))]
    l1 = x0 @ m.F.T  # epipolar lines in image 1
    d1 = np.abs(np.sum(l1 * x1, axis=1)) / np.linalg.norm(l1[:, :2], axis=1)
    # RANSAC inliers were selected with distance <= threshold; OpenCV then refits F on them
    assert np.median(d1) < 0.5 * config.ransac_threshold_px
    assert d1.max() < 3.0 * config.ransac_threshold_px


def test_masks_exclude_masked_regions():
    img, *_ = textured_image()
    H, W = img.shape[:2]
    config = FeatureConfig(mask_dilation_px=5)
    unmasked = ft.detect_features(img, config)
    assert np.sum(unmasked.pts[:, 0] < W / 2) > 20  # the left half has features to exclude
    mask = np.zeros((H, W), dtype=bool)
    mask[:, : W // 2] = True
    kp = ft.detect_features(img, config, mask)
    assert len(kp) > 20
    assert kp.pts[:, 0].min() > W // 2 + config.mask_dilation_px - MASK_REFINE_SLACK_PX
    mask1 = np.zeros((H, W), dtype=bool)
    mask1[: H // 3] = True
    m = ft.match_images(img, img, config, mask0=mask, mask1=mask1)
    assert m.num_inliers > 10
    assert m.pts0[:, 0].min() > W // 2 + config.mask_dilation_px - MASK_REFINE_SLACK_PX
    assert m.pts1[:, 1].min() > H // 3 + config.mask_dilation_px - MASK_REFINE_SLACK_PX


def test_static_detector_mask_dilates_by_a_disc():
    mask = np.zeros((21, 21), dtype=bool)
    mask[10, 10] = True
    det = ft.static_detector_mask(mask, 3)
    ii, jj = np.mgrid[:21, :21]
    r = np.hypot(ii - 10, jj - 10)
    assert np.all(det[r <= 2.9] == 0) and np.all(det[r >= 3.5] == 255)
    assert np.all(ft.static_detector_mask(mask, 0)[r > 0] == 255)


def test_blank_images_give_zero_matches():
    blank = np.full((60, 80, 3), 0.5)
    kp = ft.detect_features(blank)
    assert len(kp) == 0 and kp.pts.shape == (0, 2) and kp.descriptors.shape == (0, 128)
    m = ft.match_images(blank, blank)
    assert m.num_inliers == 0 and m.pts0.shape == (0, 2) and m.F is None
    img, *_ = textured_image(80, 60)
    for a, b in ((img, blank), (blank, img)):
        m = ft.match_images(a, b)
        assert m.num_inliers == 0 and m.pts1.shape == (0, 2)


def test_uint8_and_float_inputs_agree():
    img, *_ = textured_image(80, 60)
    u8 = np.round(img * 255).astype(np.uint8)
    a, b = ft.detect_features(img), ft.detect_features(u8)
    assert np.array_equal(a.pts, b.pts)


@pytest.mark.parametrize("image, exc, word", [
    (np.zeros((10, 10, 4)), ValueError, "shape"),
    (np.zeros((10, 10, 3), dtype=np.int32), TypeError, "dtype"),
    (np.full((10, 10), np.nan), ValueError, "NaN"),
])
def test_bad_images_are_rejected(image, exc, word):
    with pytest.raises(exc, match=word):
        ft.detect_features(image)


def test_bad_masks_and_config_are_rejected():
    img = np.zeros((10, 12, 3))
    with pytest.raises(ValueError, match="mask"):
        ft.detect_features(img, mask=np.zeros((12, 10), dtype=bool))
    with pytest.raises(TypeError, match="bool"):
        ft.detect_features(img, mask=np.zeros((10, 12), dtype=np.uint8))
    with pytest.raises(TypeError, match="config"):
        ft.match_images(img, img, config={"ratio": 0.8})
