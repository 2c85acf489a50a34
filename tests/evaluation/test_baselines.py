"""The classical two-stage baseline: motion kernels, kernels predicted from poses, deconvolution."""
import math

import numpy as np
import pytest

from d2gs_np.evaluation.baselines import deblur_scene, frame_blur_kernel, motion_kernel, richardson_lucy
from d2gs_np.geometry.camera import make_intrinsics


@pytest.mark.parametrize("d", [(0.0, 0.0), (0.3, 0.0), (5.0, 0.0), (0.0, -7.5), (4.0, 3.0), (-9.2, 2.7)])
def test_motion_kernel_is_a_centred_normalised_segment(d):
    ker = motion_kernel(*d)
    k = ker.shape[0]
    assert ker.shape == (k, k) and k % 2 == 1 and np.all(ker >= 0)
    assert math.isclose(ker.sum(), 1.0, rel_tol=1e-12)
    ys, xs = np.mgrid[:k, :k] - k // 2
    # centred: its first moment is zero; its second moment along the segment is length^2 / 12 (+ splat spread)
    assert abs((ker * xs).sum()) < 1e-9 and abs((ker * ys).sum()) < 1e-9
    length2 = d[0] ** 2 + d[1] ** 2
    second = (ker * (xs ** 2 + ys ** 2)).sum()
    # evenly spaced samples including both ends add a factor (m + 1)/(m - 1) <= 1 + 1/(4 L) (m >= 8 L + 1
    # samples), and bilinear splats add at most 1/2 px^2
    assert length2 / 12 - 1e-9 <= second <= length2 / 12 * (1 + 0.25 / max(math.sqrt(length2), 1e-9)) + 0.5


def test_motion_kernel_rejects_nan():
    with pytest.raises(ValueError, match="finite"):
        motion_kernel(float("nan"), 1.0)


def test_kernel_from_a_sideways_camera_has_the_predicted_length():
    # camera translating along x at speed v (world units per unit time); over tau the image centre's
    # point at depth d moves by f v tau / d pixels
    n, f, d, v, frac = 5, 100.0, 4.0, 0.5, 0.6
    times = np.linspace(0, 1, n)
    poses = np.stack([np.eye(4) for _ in range(n)])
    poses[:, 0, 3] = -v * times  # cam_T_world of a camera at x = v t
    K = make_intrinsics(f, f, 32.0, 24.0)
    ker, (dx, dy) = frame_blur_kernel(poses, times, 2, K, 64, 48, frac, d)
    tau = frac / (n - 1)
    assert math.isclose(abs(dx), f * v * tau / d, rel_tol=1e-9) and abs(dy) < 1e-12
    # zero motion: the identity kernel; zero exposure likewise
    still = np.stack([np.eye(4)] * n)
    ker0, d0 = frame_blur_kernel(still, times, 0, K, 64, 48, frac, d)
    assert d0 == (0.0, 0.0) and ker0[ker0.shape[0] // 2, ker0.shape[1] // 2] == pytest.approx(1.0)
    _, dz = frame_blur_kernel(poses, times, 1, K, 64, 48, 0.0, d)
    assert dz == (0.0, 0.0)
    with pytest.raises(ValueError, match="depth"):
        frame_blur_kernel(poses, times, 1, K, 64, 48, frac, 0.0)


def test_richardson_lucy_undoes_a_known_motion_blur():
    import cv2
    rng = np.random.default_rng(0)
    sharp = cv2.GaussianBlur(rng.uniform(size=(48, 64, 3)), (0, 0), 1.2)
    sharp = (sharp - sharp.min()) / (sharp.max() - sharp.min()) * 0.8 + 0.1
    ker = motion_kernel(6.0, 2.0)
    blurry = np.stack([cv2.filter2D(sharp[..., c], -1, ker[::-1, ::-1], borderType=cv2.BORDER_REFLECT)
                       for c in range(3)], axis=-1)
    err = lambda a: float(np.sqrt(np.mean((a - sharp)[6:-6, 6:-6] ** 2)))  # noqa: E731
    out = richardson_lucy(blurry, ker, 30)
    assert out.shape == sharp.shape and np.all(np.isfinite(out)) and 0 <= out.min() and out.max() <= 1
    assert err(out) < 0.9 * err(blurry)
    wrong = richardson_lucy(blurry, motion_kernel(-2.0, 6.0), 30)  # the perpendicular blur
    assert err(out) < err(wrong)
    with pytest.raises(ValueError, match="NaN"):
        richardson_lucy(np.full((8, 8, 3), np.nan), ker)


def test_deblur_scene_writes_a_sharp_input_copy(tmp_path):
    from d2gs_np.data.io import load_scene
    from d2gs_np.data.synthetic import write_synthetic_scene

    src = write_synthetic_scene(tmp_path / "s", "dynamic", 0, width=40, height=24, num_frames=4)
    rep = deblur_scene(src, tmp_path / "d", iterations=3)
    a, b = load_scene(src), load_scene(tmp_path / "d")
    assert b.exposure_fraction == 0.0 and len(rep["blur_length_px"]) == 4
    assert all(np.allclose(fa.gt_cam_T_world, fb.gt_cam_T_world, atol=1e-12) for fa, fb in zip(a.frames, b.frames))
    assert any(not np.array_equal(fa.image, fb.image) for fa, fb in zip(a.frames, b.frames))
    assert np.isfinite(rep["deblurred_psnr"]) and np.isfinite(rep["input_psnr"])
