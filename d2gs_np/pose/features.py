"""Feature correspondences between two images (docs/method.md §5): SIFT, ratio test, RANSAC on F.

Pipeline: 8-bit greyscale -> OpenCV SIFT (``cv2.SIFT_create``) restricted to static pixels by
a detector mask -> brute-force L2 2-nearest-neighbour matching with Lowe's ratio test ->
RANSAC on the fundamental matrix (``cv2.findFundamentalMat``, ``FM_RANSAC``). The paper's DIFT
needs network weights; features are a replaceable component behind ``match_images``.

Pixel convention. OpenCV keypoint coordinates put pixel centres at INTEGER positions (pixel
(i, j) is at (j, i)); this project puts them at (j + 0.5, i + 0.5) (docs/conventions.md §2). Every
point leaving this module is converted: ``pts_ours = pts_opencv + 0.5``. SIFT is created with
``enable_precise_upscale=True``: OpenCV's default up-sampling of the first octave biases every
keypoint by +0.25 px in x and y, which the +0.5 conversion would otherwise carry along. The fundamental matrix
is returned in our convention too: with S = [[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]] mapping
ours -> OpenCV, ``F_ours = S^T F_opencv S`` so that ``x1_ours^T F_ours x0_ours = 0``.

Motion masks (True = dynamic pixel) are dilated by ``mask_dilation_px`` (a disc of that radius)
and their complement is passed to SIFT as the detector mask, so no keypoint is detected on or
near a moving object (descriptors near the border still see a few dynamic pixels; the dilation
keeps that small).

RANSAC uses OpenCV's global RNG; ``match_keypoints`` reseeds it with ``FeatureConfig.seed``
before every call, so results are deterministic.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from d2gs_np.constants import PIXEL_CENTER_OFFSET
from d2gs_np.pose.config import FeatureConfig

__all__ = [
    "Keypoints",
    "Matches",
    "to_gray_u8",
    "static_detector_mask",
    "detect_features",
    "match_keypoints",
    "match_images",
]

@dataclass
class Keypoints:
    """Detected keypoints of one image."""

    pts: np.ndarray  # (K, 2) float64, continuous pixel coords, OUR convention (centres at +0.5)
    descriptors: np.ndarray  # (K, 128) float32 SIFT descriptors (OpenCV's dtype); (K, B) uint8 for ORB/AKAZE
    image_shape: tuple  # (H, W) of the image they came from

    def __len__(self):
        return self.pts.shape[0]


@dataclass
class Matches:
    """Verified correspondences between image 0 and image 1 (RANSAC inliers on F)."""

    pts0: np.ndarray  # (M, 2) float64, our pixel convention
    pts1: np.ndarray  # (M, 2) float64, our pixel convention
    idx0: np.ndarray  # (M,) int64 indices into the keypoints of image 0
    idx1: np.ndarray  # (M,) int64 indices into the keypoints of image 1
    num_keypoints0: int
    num_keypoints1: int
    num_tentative: int  # matches that passed the ratio test (before RANSAC)
    F: Optional[np.ndarray] = None  # (3, 3) fundamental matrix, our convention; None if not estimated

    @property
    def num_inliers(self) -> int:
        return int(self.pts0.shape[0])

    def __len__(self):
        return self.num_inliers


def _check_config(config):
    if config is None:
        return FeatureConfig()
    if not isinstance(config, FeatureConfig):
        raise TypeError(f"config must be a FeatureConfig; got {type(config).__name__}")
    return config


def to_gray_u8(image, name="image"):
    """(H, W, 3) RGB or (H, W) grey, float in [0, 1] or uint8 -> (H, W) uint8 grey.

    Floats are clipped to [0, 1] and rounded: round(255 x). RGB -> grey uses OpenCV's
    0.299 R + 0.587 G + 0.114 B.
    """
    img = np.asarray(image)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ValueError(f"{name} must have shape (H, W, 3) or (H, W); got {img.shape}")
    if img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"{name} must be non-empty; got shape {img.shape}")
    if img.dtype == np.uint8:
        u8 = img
    elif np.issubdtype(img.dtype, np.floating):
        if not np.all(np.isfinite(img)):
            raise ValueError(f"{name} contains NaN or inf")
        u8 = np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)
    else:
        raise TypeError(f"{name} must be float in [0, 1] or uint8; got dtype {img.dtype}")
    if u8.ndim == 3:
        u8 = cv2.cvtColor(np.ascontiguousarray(u8), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(u8)


def static_detector_mask(motion_mask, dilation_px):
    """Detector mask from a motion mask: (H, W) bool, True = dynamic -> (H, W) uint8, 255 = usable.

    The dynamic region is dilated by a disc of radius ``dilation_px`` pixels first.
    """
    m = np.asarray(motion_mask)
    if m.ndim != 2:
        raise ValueError(f"motion mask must have shape (H, W); got {m.shape}")
    if m.dtype != np.bool_:
        raise TypeError(f"motion mask must be bool (True = dynamic); got dtype {m.dtype}")
    dyn = m.astype(np.uint8)
    if dilation_px > 0 and dyn.any():
        r = int(dilation_px)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        dyn = cv2.dilate(dyn, kernel)
    return np.where(dyn > 0, 0, 255).astype(np.uint8)


def detect_features(image, config: FeatureConfig = None, mask=None) -> Keypoints:
    """SIFT keypoints and descriptors of one image, away from dynamic pixels.

    image: (H, W, 3) or (H, W), float in [0, 1] or uint8. mask: optional (H, W) bool motion
    mask, True = dynamic (excluded after dilation). Returns Keypoints in our pixel convention.
    An image without features gives 0 keypoints.
    """
    config = _check_config(config)
    gray = to_gray_u8(image)
    det_mask = None
    if mask is not None:
        if np.shape(mask) != gray.shape:
            raise ValueError(f"mask must have the image's shape {gray.shape}; got {np.shape(mask)}")
        det_mask = static_detector_mask(mask, config.mask_dilation_px)
    if config.detector == "sift":
        # enable_precise_upscale: without it OpenCV's doubled first octave shifts every keypoint by
        # +0.25 px in x and y (docs/results.md §12).
        det = cv2.SIFT_create(
            config.max_features, config.octave_layers, config.contrast_threshold, config.edge_threshold,
            config.sigma, True,
        )
        empty = np.zeros((0, 128), dtype=np.float32)
    elif config.detector == "orb":
        det = cv2.ORB_create(nfeatures=config.max_features or 2000)
        empty = np.zeros((0, 32), dtype=np.uint8)
    else:
        det = cv2.AKAZE_create()
        empty = np.zeros((0, 61), dtype=np.uint8)
    kps, desc = det.detectAndCompute(gray, det_mask)
    if not kps or desc is None:
        return Keypoints(np.zeros((0, 2)), empty, gray.shape)
    pts = np.array([kp.pt for kp in kps], dtype=np.float64) + PIXEL_CENTER_OFFSET  # OpenCV -> ours
    return Keypoints(pts, np.ascontiguousarray(desc, dtype=empty.dtype), gray.shape)


def _empty_matches(kp0, kp1, num_tentative=0):
    z2, zi = np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    return Matches(z2, z2.copy(), zi, zi.copy(), len(kp0), len(kp1), num_tentative, None)


def match_keypoints(kp0: Keypoints, kp1: Keypoints, config: FeatureConfig = None) -> Matches:
    """Ratio-test matches of kp0 -> kp1, verified by RANSAC on the fundamental matrix.

    Returns zero matches (no error) when either side has fewer than 2 keypoints, when fewer
    than ``config.min_matches`` pass the ratio test, or when RANSAC finds no model.
    """
    config = _check_config(config)
    for name, kp in (("kp0", kp0), ("kp1", kp1)):
        if not isinstance(kp, Keypoints):
            raise TypeError(f"{name} must be Keypoints (from detect_features); got {type(kp).__name__}")
    if len(kp0) < 1 or len(kp1) < 2:
        return _empty_matches(kp0, kp1)
    if kp0.descriptors.dtype != kp1.descriptors.dtype:
        raise TypeError(f"kp0 and kp1 come from different detectors (descriptor dtypes {kp0.descriptors.dtype} and "
                        f"{kp1.descriptors.dtype}); detect both with the same FeatureConfig.detector")
    norm = cv2.NORM_L2 if kp0.descriptors.dtype == np.float32 else cv2.NORM_HAMMING
    if config.max_displacement_px > 0:
        near = np.linalg.norm(kp0.pts[:, None, :] - kp1.pts[None, :, :], axis=-1) <= config.max_displacement_px
        knn = cv2.BFMatcher(norm).knnMatch(kp0.descriptors, kp1.descriptors, k=2, mask=near.astype(np.uint8))
        # a keypoint with a single candidate in reach has no second neighbour: the ratio test
        # cannot vouch for it, and it is dropped below (len(m) == 2)
    else:
        knn = cv2.BFMatcher(norm).knnMatch(kp0.descriptors, kp1.descriptors, k=2)
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in knn
             if len(m) == 2 and m[0].distance < config.ratio * m[1].distance]
    if len(pairs) < config.min_matches:
        return _empty_matches(kp0, kp1, len(pairs))
    idx0, idx1 = (np.array(a, dtype=np.int64) for a in zip(*pairs))
    p0, p1 = kp0.pts[idx0], kp1.pts[idx1]
    cv2.setRNGSeed(config.seed)
    F_cv, inl = cv2.findFundamentalMat(
        p0 - PIXEL_CENTER_OFFSET, p1 - PIXEL_CENTER_OFFSET, cv2.FM_RANSAC,
        config.ransac_threshold_px, config.ransac_confidence, config.ransac_max_iters,
    )
    if F_cv is None or inl is None or F_cv.shape != (3, 3):
        return _empty_matches(kp0, kp1, len(pairs))
    keep = inl.ravel().astype(bool)
    S = np.array([[1.0, 0.0, -PIXEL_CENTER_OFFSET], [0.0, 1.0, -PIXEL_CENTER_OFFSET], [0.0, 0.0, 1.0]])
    return Matches(
        pts0=p0[keep], pts1=p1[keep], idx0=idx0[keep], idx1=idx1[keep], num_keypoints0=len(kp0),
        num_keypoints1=len(kp1), num_tentative=len(pairs), F=S.T @ F_cv @ S,
    )


def match_images(image0, image1, config: FeatureConfig = None, mask0=None, mask1=None) -> Matches:
    """Correspondences between two images on static pixels (docs/method.md §5).

    image0, image1: (H, W, 3) or (H, W), float in [0, 1] or uint8 (sizes may differ).
    mask0, mask1: optional (H, W) bool motion masks, True = dynamic (dilated, then excluded).
    Returns Matches with pts0[m] in image 0 <-> pts1[m] in image 1, our pixel convention.
    """
    config = _check_config(config)
    kp0 = detect_features(image0, config, mask0)
    kp1 = detect_features(image1, config, mask1)
    return match_keypoints(kp0, kp1, config)
