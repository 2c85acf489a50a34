"""examples/nvs_registration.py: the shift between a render and its view, and the baselines'
errors, on cases whose answer is known."""
import numpy as np
import pytest

from d2gs_np.geometry import look_at, se3_exp
from d2gs_np.geometry.trajectory import sim3_apply_to_poses
from example_fixtures import load_example

reg = load_example("nvs_registration.py")


def _texture(h=90, w=160, seed=0):
    import cv2

    rng = np.random.default_rng(seed)
    return np.clip(cv2.GaussianBlur(rng.random((h, w, 3)), (0, 0), 1.5) * 2.5 - 0.75, 0, 1)


def test_view_shift_finds_a_uniform_translation():
    # the truth is the render moved 2 px right and 1 px down; DIS on a smooth random texture
    # recovers integer shifts to a tenth of a pixel (0.25 px allowed), with a small spread
    img = _texture()
    truth = np.roll(img, (1, 2), axis=(0, 1))
    mu, spread = reg.view_shift(img, truth)
    np.testing.assert_allclose(mu, [2.0, 1.0], atol=0.25)
    assert spread < 0.25
    # moving pixels left out: a mask over everything but a window still measures it
    mask = np.ones(img.shape[:2], bool)
    mask[20:70, 30:130] = False
    np.testing.assert_allclose(reg.view_shift(img, truth, mask)[0], [2.0, 1.0], atol=0.25)
    with pytest.raises(ValueError, match="no pixel left"):
        reg.view_shift(img, truth, np.ones(img.shape[:2], bool))


def _path(n=10):
    rng = np.random.default_rng(2)
    return np.stack([look_at([0.05 * i + 0.01 * rng.normal(), 0.01 * rng.normal(), 0.0], [0.0, 0.0, 5.0])
                     for i in range(n)])


def test_baselines_of_a_similar_trajectory_are_exact():
    gt = _path()
    est = sim3_apply_to_poses(0.3, se3_exp(np.array([0, 0, 0, 0.2, 0.5, -0.4]))[:3, :3], np.ones(3), gt)
    for ratio, angle in reg.baseline_errors(est, gt, depth=5.0).values():
        assert ratio == pytest.approx(1.0, abs=1e-9) and angle == pytest.approx(0.0, abs=1e-5)


def test_baselines_turned_are_measured():
    gt = _path()
    # every centre moved so each baseline is turned 30 deg about the optical axis, orientations
    # kept: the measured angle is that (a uniform stretch would be a similarity, which the
    # alignment's scale takes off)
    from d2gs_np.geometry.camera import camera_center

    c = camera_center(gt)
    turn = se3_exp(np.array([0, 0, 0, 0, 0, np.radians(30.0)]))[:3, :3]
    c_new = c[0] + (c - c[0]) @ (gt[0, :3, :3].T @ turn @ gt[0, :3, :3]).T
    est = gt.copy()
    est[:, :3, 3] = -np.einsum("nij,nj->ni", gt[:, :3, :3], c_new)
    # all cameras share (nearly) one orientation here, so a baseline turned in camera 0's axes is
    # turned alike in each camera's; the alignment leans on the orientations at depth 1000, so it
    # does not turn the centres back
    err = reg.baseline_errors(est, gt, depth=1000.0, gaps=(1, 4))
    for ratio, angle in err.values():
        assert ratio == pytest.approx(1.0, rel=0.05) and angle == pytest.approx(30.0, abs=3.0)
    assert set(reg.baseline_errors(est, gt, gaps=(1, 20))) == {1}  # a gap longer than the clip is left out


def test_the_sharp_tracks_adjustment_leaves_the_scene_as_it_was():
    from d2gs_np.geometry.se3 import check_rigid
    from run_fixtures import tiny_dynamic_scene

    scene = tiny_dynamic_scene(trusted=False)
    before = [f.image.copy() for f in scene.frames]
    P = reg._adjusted_on_sharp(scene)
    assert P is None or (P.shape == (len(scene.frames), 4, 4) and check_rigid(P, "P") is None)
    for f, b in zip(scene.frames, before):
        assert np.array_equal(f.image, b) and not np.array_equal(f.image, f.sharp)  # still the blurry inputs
    for f in scene.frames:
        f.sharp = None
    with pytest.raises(SystemExit, match="sharp frames"):
        reg._adjusted_on_sharp(scene)
