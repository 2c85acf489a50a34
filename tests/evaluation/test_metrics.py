"""Tests for d2gs_np.evaluation.metrics: PSNR/SSIM against scikit-image, trajectory metrics
against constructions with known answers."""
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from d2gs_np.geometry.camera import camera_center, look_at
from d2gs_np.evaluation.metrics import (
    align_trajectory,
    ate,
    flip,
    lpips,
    psnr,
    rpe,
    sim3_apply_to_poses,
    sim3_inverse,
    ssim,
    umeyama,
)

# Agreement with scikit-image: both compute the same float64 formulas; 1e-6 is
# the brief's bound and leaves room for a differently ordered separable filter.
SKIMAGE_TOL = 1e-6
# Direct recomputation of a masked mean of the same numbers: only summation order differs.
DIRECT_TOL = 1e-12
# Exact similarity transforms / constructions: a few float64 roundings of
# O(10)-sized coordinates through inverses and SVDs.
EXACT_TOL = 1e-10
# Umeyama vs a generic iterative least-squares solver (xtol/ftol 1e-15): the
# optimiser's own convergence limits the agreement.
OPTIMIZER_TOL = 1e-7


# --------------------------------------------------------------------------- images
def _random_pair(rng, h=32, w=32, c=3):
    a = rng.random((h, w, c))
    b = np.clip(a + 0.1 * rng.standard_normal((h, w, c)), 0.0, 1.0)
    return a, b


def _structured_pair(h=32, w=40):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = 0.5 + 0.5 * np.sin(x / 3.0) * np.cos(y / 5.0)
    g = ((x // 4 + y // 4) % 2).astype(np.float64)  # checkerboard with hard edges
    b = x / (w - 1)  # ramp
    a = np.stack([r, g, b], axis=-1)
    # Reference: shifted and contrast-changed copy (a plausible "render")
    b_img = np.roll(a, 1, axis=1) * 0.8 + 0.1
    return a, b_img


@pytest.mark.parametrize("kind", ["random", "structured"])
def test_psnr_matches_skimage(kind):
    rng = np.random.default_rng(0)
    a, b = _random_pair(rng) if kind == "random" else _structured_pair()
    expected = peak_signal_noise_ratio(b, a, data_range=1.0)
    assert abs(psnr(a, b) - expected) < SKIMAGE_TOL


@pytest.mark.parametrize("kind", ["random", "structured"])
def test_ssim_matches_skimage(kind):
    rng = np.random.default_rng(1)
    a, b = _random_pair(rng) if kind == "random" else _structured_pair()
    expected = structural_similarity(a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5)
    assert abs(ssim(a, b) - expected) < SKIMAGE_TOL


def test_ssim_non_square_and_float32_matches_skimage_float64():
    rng = np.random.default_rng(2)
    a, b = _random_pair(rng, h=17, w=29)
    expected = structural_similarity(a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5)
    assert abs(ssim(a, b) - expected) < SKIMAGE_TOL
    # float32 inputs are accumulated in float64: differences only from input rounding (~1e-7).
    assert abs(ssim(a.astype(np.float32), b.astype(np.float32)) - expected) < 1e-5


def test_identical_images():
    rng = np.random.default_rng(3)
    a, _ = _random_pair(rng)
    assert psnr(a, a) == float("inf")
    assert abs(ssim(a, a) - 1.0) < DIRECT_TOL


def test_psnr_masked_direct():
    rng = np.random.default_rng(4)
    a, b = _random_pair(rng)
    mask = rng.random(a.shape[:2]) < 0.3
    mse = np.mean((a[mask] - b[mask]) ** 2)
    assert abs(psnr(a, b, mask=mask) - 10 * np.log10(1.0 / mse)) < DIRECT_TOL
    # data_range enters as data_range^2 / MSE
    assert abs(psnr(a, b, mask=mask, data_range=2.0) - 10 * np.log10(4.0 / mse)) < DIRECT_TOL
    # A mask that differs from the full image changes the value (the mask is used)
    assert abs(psnr(a, b, mask=mask) - psnr(a, b)) > 1e-6


def test_ssim_masked_direct():
    rng = np.random.default_rng(5)
    a, b = _structured_pair()
    mask = np.zeros(a.shape[:2], dtype=bool)
    mask[3:20, 8:30] = True  # straddles the 5-pixel border on top
    _, full = structural_similarity(
        a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5, full=True
    )
    interior = full[5:-5, 5:-5]
    expected = interior[mask[5:-5, 5:-5]].mean()
    assert abs(ssim(a, b, mask=mask) - expected) < SKIMAGE_TOL
    # All-True mask equals the unmasked value
    assert abs(ssim(a, b, mask=np.ones(a.shape[:2], bool)) - ssim(a, b)) < DIRECT_TOL


def test_image_metric_errors():
    rng = np.random.default_rng(6)
    a, b = _random_pair(rng)
    with pytest.raises(ValueError, match="same shape"):
        psnr(a, b[:-1])
    with pytest.raises(TypeError, match="floating-point"):
        psnr((a * 255).astype(np.uint8), b)
    with pytest.raises(ValueError, match=r"shape \(H, W, C\)"):
        ssim(a[..., 0], b[..., 0])
    bad = a.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ssim(bad, b)
    with pytest.raises(ValueError, match="mask must have shape"):
        psnr(a, b, mask=np.ones((4, 4), bool))
    with pytest.raises(TypeError, match="mask must be a bool"):
        psnr(a, b, mask=np.ones(a.shape[:2]))
    with pytest.raises(ValueError, match="no pixels"):
        psnr(a, b, mask=np.zeros(a.shape[:2], bool))
    border_only = np.zeros(a.shape[:2], bool)
    border_only[:5, :] = True
    with pytest.raises(ValueError, match="interior"):
        ssim(a, b, mask=border_only)
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(a[:10], b[:10])
    with pytest.raises(ValueError, match="data_range"):
        psnr(a, b, data_range=0.0)


# ----------------------------------------------------------------------------- FLIP
# metrics.flip wraps NVIDIA's reference implementation (flip-evaluator); these tests check what
# the wrapper owns (clipping, dtype, argument passing, errors) and the properties any perceptual
# difference must have. Its arithmetic is float32 inside the package: 1e-6 bounds rounding when
# only the input's dtype changes.
FLIP_DTYPE_TOL = 1e-6


def test_flip_is_zero_for_identical_images_and_positive_otherwise():
    rng = np.random.default_rng(0)
    a, b = _random_pair(rng, 40, 48)
    assert flip(a, a) == 0.0
    assert 0.0 < flip(b, a) < 1.0


def test_flip_grows_with_the_noise_level():
    rng = np.random.default_rng(1)
    ref = rng.random((48, 64, 3))
    noise = rng.standard_normal(ref.shape)
    errs = [flip(np.clip(ref + s * noise, 0, 1), ref) for s in (0.005, 0.02, 0.05, 0.2)]
    assert all(e1 < e2 for e1, e2 in zip(errs, errs[1:])), errs


def test_flip_sees_blur_less_from_farther_away():
    """Blur removes fine detail; at more pixels per degree (viewed from farther) that detail is
    less visible, so FLIP's contrast-sensitivity filtering must rate the blur lower."""
    import cv2
    ref = np.random.default_rng(2).random((64, 64, 3))
    blurred = cv2.GaussianBlur(ref, (0, 0), 1.5)
    near, default, far = (flip(blurred, ref, ppd=p) for p in (20.0, 67.0, 200.0))
    assert near > default > far > 0.0


def test_flip_clips_to_the_ldr_range_and_accepts_float32():
    rng = np.random.default_rng(3)
    a, b = _random_pair(rng, 32, 40)
    over = a.copy()
    over[:4] += 0.3  # overshoot above 1, as a render may
    over[-4:] -= 0.3
    assert flip(over, b) == flip(np.clip(over, 0, 1), b)
    assert abs(flip(a.astype(np.float32), b.astype(np.float32)) - flip(a, b)) < FLIP_DTYPE_TOL


def test_flip_errors():
    a = np.zeros((16, 16, 3))
    with pytest.raises(ValueError, match="RGB"):
        flip(np.zeros((16, 16, 1)), np.zeros((16, 16, 1)))
    with pytest.raises(ValueError, match="NaN"):
        flip(np.full((16, 16, 3), np.nan), a)
    with pytest.raises(ValueError, match="same shape"):
        flip(a, np.zeros((16, 17, 3)))
    with pytest.raises(ValueError, match="ppd"):
        flip(a, a, ppd=0.0)
    with pytest.raises(TypeError, match="floating-point"):
        flip(np.zeros((16, 16, 3), np.uint8), a)


def test_lpips_raises_not_implemented():
    rng = np.random.default_rng(7)
    a, b = _random_pair(rng)
    with pytest.raises(NotImplementedError, match="weights"):
        lpips(a, b)


# ----------------------------------------------------------------------- trajectory
def _curved_trajectory(n, rng=None):
    """(n, 4, 4) cam_T_world on a helix, cameras looking at points near the origin."""
    s = np.linspace(0.0, 1.0, n)
    centres = np.stack([3 * np.cos(2.5 * s), 3 * np.sin(2.5 * s), 1.0 + 2.0 * s**2], axis=1)
    poses = []
    for i, c in enumerate(centres):
        target = np.array([0.3 * np.sin(7 * s[i]), 0.2, 0.5 * s[i]])
        poses.append(look_at(c, target, up=(0.0, 0.0, 1.0)))
    return np.stack(poses)


def _random_sim3(rng):
    R = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    return 2.7, R, rng.standard_normal(3) * 5


def test_umeyama_recovers_exact_similarity():
    rng = np.random.default_rng(10)
    src = rng.standard_normal((10, 3))
    s, R, t = _random_sim3(rng)
    dst = s * src @ R.T + t
    s2, R2, t2 = umeyama(src, dst)
    assert abs(s2 - s) < EXACT_TOL
    np.testing.assert_allclose(R2, R, atol=EXACT_TOL)
    np.testing.assert_allclose(t2, t, atol=EXACT_TOL)
    s3, R3, _ = umeyama(src, dst, with_scale=False)
    assert s3 == 1.0
    np.testing.assert_allclose(R3, R, atol=EXACT_TOL)  # rotation does not depend on scale


def _sim3_lsq(src, dst):
    def resid(p):
        R = Rotation.from_rotvec(p[1:4]).as_matrix()
        return (np.exp(p[0]) * src @ R.T + p[4:] - dst).ravel()

    # Start from a poor guess so the optimizer does real work
    sol = least_squares(resid, np.zeros(7), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return np.exp(sol.x[0]), Rotation.from_rotvec(sol.x[1:4]).as_matrix(), sol.x[4:]


@pytest.mark.parametrize("mirror", [False, True])
def test_umeyama_matches_generic_least_squares(mirror):
    """Noisy data, and mirrored data where the best orthogonal map is a reflection:
    Umeyama must still return the best *rotation*."""
    rng = np.random.default_rng(11 + mirror)
    src = rng.standard_normal((15, 3))
    dst = 1.3 * src @ Rotation.from_rotvec([0.2, -0.4, 0.3]).as_matrix().T + [1.0, 2.0, -1.0]
    if mirror:
        dst[:, 0] *= -1.0
    dst += 0.05 * rng.standard_normal(dst.shape)
    s, R, t = umeyama(src, dst)
    assert abs(np.linalg.det(R) - 1.0) < EXACT_TOL
    s_ref, R_ref, t_ref = _sim3_lsq(src, dst)
    cost = np.sum((s * src @ R.T + t - dst) ** 2)
    cost_ref = np.sum((s_ref * src @ R_ref.T + t_ref - dst) ** 2)
    assert cost <= cost_ref * (1 + OPTIMIZER_TOL)
    if not mirror:  # unique minimiser: parameters agree too
        assert abs(s - s_ref) < OPTIMIZER_TOL
        np.testing.assert_allclose(R, R_ref, atol=OPTIMIZER_TOL)


def test_similarity_transformed_trajectory_has_zero_errors():
    rng = np.random.default_rng(12)
    gt = _curved_trajectory(20)
    s, R, t = _random_sim3(rng)
    est = sim3_apply_to_poses(*sim3_inverse(s, R, t), gt)  # est world = gt world mapped by S^-1
    # The alignment recovers S (est -> gt)
    s2, R2, t2 = align_trajectory(est, gt)
    assert abs(s2 - s) < EXACT_TOL
    np.testing.assert_allclose(R2, R, atol=EXACT_TOL)
    assert ate(est, gt) < EXACT_TOL
    rpe_t, rpe_r = rpe(est, gt)
    assert rpe_t < EXACT_TOL and rpe_r < EXACT_TOL
    # Without alignment the scale mismatch shows up in RPE_t but not RPE_r
    rpe_t_raw, rpe_r_raw = rpe(est, gt, align=False)
    assert rpe_t_raw > 0.1 and rpe_r_raw < EXACT_TOL


def test_sim3_apply_moves_centres_and_keeps_rigidity():
    rng = np.random.default_rng(13)
    gt = _curved_trajectory(6)
    s, R, t = _random_sim3(rng)
    moved = sim3_apply_to_poses(s, R, t, gt)
    np.testing.assert_allclose(camera_center(moved), s * camera_center(gt) @ R.T + t, atol=EXACT_TOL)
    np.testing.assert_allclose(moved[:, :3, :3] @ np.swapaxes(moved[:, :3, :3], 1, 2), np.broadcast_to(np.eye(3), (6, 3, 3)), atol=EXACT_TOL)
    back = sim3_apply_to_poses(*sim3_inverse(s, R, t), moved)
    np.testing.assert_allclose(back, gt, atol=EXACT_TOL)


@pytest.mark.parametrize("k, n_pairs_touched", [(0, 1), (7, 2), (14, 1)])
def test_known_translation_offset_gives_known_rpe(k, n_pairs_touched):
    """Moving camera k by d (rotation kept) changes the relative translation of
    each pair it belongs to by exactly |d|; no rotation error. Without alignment
    (s = 1) RPE_t = |d| sqrt(pairs / (N - 1))."""
    gt = _curved_trajectory(15)
    n = gt.shape[0]
    d = np.array([0.03, -0.04, 0.12])  # |d| = 0.13
    est = gt.copy()
    c = camera_center(gt[k]) + d
    est[k, :3, 3] = -gt[k, :3, :3] @ c
    rpe_t, rpe_r = rpe(est, gt, align=False)
    assert abs(rpe_t - 0.13 * np.sqrt(n_pairs_touched / (n - 1))) < EXACT_TOL
    assert rpe_r < EXACT_TOL


@pytest.mark.parametrize("alpha", [1e-9, 0.3, np.pi - 1e-7])
def test_known_rotation_offset_gives_known_rpe(alpha):
    """Rotating camera k about its own centre leaves every centre in place, so the
    Sim(3) alignment is the identity and the expected RPE is exact:
    RPE_r = alpha sqrt(2/(N-1)); RPE_t: only pair (k, k+1) changes: its
    translation v = R_k (c_{k+1} - c_k) is expressed in camera k and becomes
    dR v, which differs from v by 2 sin(alpha/2) |v_perp| (v_perp: the part of
    v perpendicular to the rotation axis).
    alpha near pi and tiny alpha exercise both ends of the angle computation."""
    gt = _curved_trajectory(12)
    n, k = gt.shape[0], 5
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    dR = Rotation.from_rotvec(alpha * axis).as_matrix()
    est = gt.copy()
    c = camera_center(gt[k])
    est[k, :3, :3] = dR @ gt[k, :3, :3]
    est[k, :3, 3] = -est[k, :3, :3] @ c
    rpe_t, rpe_r = rpe(est, gt)
    expected_r = np.degrees(alpha * np.sqrt(2.0 / (n - 1)))
    assert abs(rpe_r - expected_r) <= 1e-7 * expected_r  # relative: arccos would fail at 1e-9
    v = gt[k, :3, :3] @ (camera_center(gt[k + 1]) - c)
    v_perp = v - (v @ axis) * axis
    expected_t = 2 * np.sin(alpha / 2) * np.linalg.norm(v_perp) * np.sqrt(1.0 / (n - 1))
    assert abs(rpe_t - expected_t) < EXACT_TOL
    assert ate(est, gt) < EXACT_TOL


def test_noise_gives_ate_near_noise_level():
    """Isotropic position noise sigma per axis: after fitting the 7 Sim(3)
    parameters, E[ATE^2] = (3N - 7)/N sigma^2 (linearised)."""
    rng = np.random.default_rng(14)
    n, sigma = 400, 0.02
    gt = _curved_trajectory(n)
    est = gt.copy()
    c = camera_center(gt) + sigma * rng.standard_normal((n, 3))
    est[:, :3, 3] = -np.einsum("nij,nj->ni", gt[:, :3, :3], c)
    expected = sigma * np.sqrt((3 * n - 7) / n)
    # Chi-square with ~1200 dof: relative std of ATE ~ 1/sqrt(2 * 1200) = 2%; allow 5 std.
    assert abs(ate(est, gt) - expected) < 0.10 * expected


def test_trajectory_degenerate_inputs():
    gt = _curved_trajectory(8)
    with pytest.raises(ValueError, match="at least 3"):
        ate(gt[:2], gt[:2])
    with pytest.raises(ValueError, match="at least 3"):
        align_trajectory(gt[:2], gt[:2])
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(np.eye(3)[:2], np.eye(3)[:2])
    with pytest.raises(ValueError, match="at least 2"):
        rpe(gt[:1], gt[:1])
    # Two frames are enough for RPE (only the alignment scale is used)
    assert rpe(gt[:2], gt[:2]) == pytest.approx((0.0, 0.0), abs=EXACT_TOL)
    with pytest.raises(ValueError, match="same number"):
        ate(gt, gt[:-1])
    with pytest.raises(ValueError, match="same number"):
        rpe(gt, gt[:-1])
    # All estimated cameras at one place (rotations differ, centres equal)
    still = gt.copy()
    c0 = camera_center(gt[0])
    still[:, :3, 3] = -np.einsum("nij,j->ni", gt[:, :3, :3], c0)
    with pytest.raises(ValueError, match="one place"):
        ate(still, gt)
    with pytest.raises(ValueError, match="one place"):
        rpe(still, gt)
    with pytest.raises(ValueError, match="one place"):
        ate(gt, still)
    # Non-rigid and non-finite poses name the array and index
    bad = gt.copy()
    bad[3, :3, :3] *= 1.01
    with pytest.raises(ValueError, match=r"est_cam_T_world\[3\] is not rigid"):
        ate(bad, gt)
    bad = gt.copy()
    bad[2, 0, 3] = np.nan
    with pytest.raises(ValueError, match=r"gt_cam_T_world\[2\].*NaN"):
        rpe(gt, bad)
    with pytest.raises(ValueError, match=r"shape \(N, 4, 4\)"):
        ate(gt[:, :3], gt[:, :3])


def test_gradient_energy_matches_the_loop_and_falls_with_blur():
    from scipy.ndimage import uniform_filter

    from d2gs_np.evaluation.metrics import gradient_energy

    rng = np.random.default_rng(0)
    img = rng.uniform(size=(9, 13, 3))
    g = img.mean(axis=2)
    dx = [(g[y, x + 1] - g[y, x]) ** 2 for y in range(9) for x in range(12)]
    dy = [(g[y + 1, x] - g[y, x]) ** 2 for y in range(8) for x in range(13)]
    assert gradient_energy(img) == pytest.approx(np.mean(dx) + np.mean(dy), rel=1e-14)
    assert gradient_energy(g) == pytest.approx(gradient_energy(img), rel=1e-14)  # grey input: the same
    assert gradient_energy(uniform_filter(img, size=(1, 5, 1))) < 0.5 * gradient_energy(img)
    assert gradient_energy(np.full((4, 4, 3), 0.7)) == 0.0
    for bad in (np.zeros((1, 5, 3)), np.zeros(5)):
        with pytest.raises(ValueError, match="H, W >= 2"):
            gradient_energy(bad)
    img[2, 2, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        gradient_energy(img)
