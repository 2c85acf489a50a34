"""Test views carried onto an estimated trajectory by their pose relative to their frame's camera
(geometry.trajectory.frame_relative_poses; the ``nvs_rig`` protocol of docs/method.md §10).

Tolerances: every case is a handful of 4x4 products in float64 on poses of unit size, so 1e-12
absolute (a few hundred ulps) holds unless the composition itself is wrong; the scale cases
scale the tolerance with the translation's size."""
import numpy as np
import pytest

from d2gs_np.geometry import look_at, se3_exp, se3_inverse
from d2gs_np.geometry.trajectory import frame_relative_poses, sim3_apply_to_poses


def _path(n=6, seed=0):
    rng = np.random.default_rng(seed)
    return np.stack([look_at([0.2 * i, 0.05 * rng.normal(), 0.0], [0.2 * i + rng.normal(0, 0.3), 0.1, 5.0])
                     for i in range(n)])


def _rig(offset=0.25):
    """The second camera of a rig: moved ``offset`` along the first camera's x axis, turned 2 deg."""
    return se3_exp(np.array([-offset, 0.0, 0.0, 0.0, np.radians(2.0), 0.0]))


def test_an_estimate_equal_to_the_reference_up_to_a_similarity_gives_the_aligned_views():
    ref = _path()
    views = _rig() @ ref
    s, R, t = 0.37, se3_exp(np.array([0, 0, 0, 0.4, -0.9, 1.3]))[:3, :3], np.array([2.0, -1.0, 0.5])
    est = sim3_apply_to_poses(s, R, t, ref)  # the reference's world moved by a similarity
    # est ~= s R ref + t, so the reference has 1 / s of its units per estimated unit
    out = frame_relative_poses(views, ref, est, scale=1.0 / s)
    np.testing.assert_allclose(out, sim3_apply_to_poses(s, R, t, views), atol=1e-12)


def test_a_locally_wrong_camera_takes_its_view_along():
    # each estimated camera is off the reference by its own turn and shift (a bent trajectory):
    # the view keeps its pose relative to that camera, which a global alignment cannot give
    rng = np.random.default_rng(3)
    ref = _path()
    errors = np.stack([se3_exp(np.concatenate([rng.normal(0, 0.05, 3), rng.normal(0, 0.02, 3)])) for _ in ref])
    est = errors @ ref
    views = _rig() @ ref
    out = frame_relative_poses(views, ref, est)
    for o, e in zip(out, est):
        np.testing.assert_allclose(o @ se3_inverse(e), _rig(), atol=1e-12)
    # and it is not what the views were: the errors moved them
    assert np.abs(out - views).max() > 1e-3


@pytest.mark.parametrize("scale", [1e-8, 2.5, 1e8])
def test_the_offset_is_carried_into_the_estimates_units(scale):
    ref = _path()
    est = ref.copy()
    est[:, :3, 3] /= scale  # the same cameras in a world 1 / scale the size
    out = frame_relative_poses(_rig() @ ref, ref, est, scale=scale)
    rel = out @ se3_inverse(est)
    np.testing.assert_allclose(rel[:, :3, :3], np.broadcast_to(_rig()[:3, :3], (len(ref), 3, 3)), atol=1e-12)
    np.testing.assert_allclose(rel[:, :3, 3] * scale, np.broadcast_to(_rig()[:3, 3], (len(ref), 3)),
                               rtol=1e-9, atol=1e-12)
    assert np.isfinite(out).all()


def test_a_view_turned_near_pi_from_its_camera():
    ref = _path(3)
    rig = se3_exp(np.array([0.1, 0.0, 0.0, 0.0, np.pi - 1e-7, 0.0]))  # looking back, near pi
    out = frame_relative_poses(rig @ ref, ref, ref)
    np.testing.assert_allclose(out, rig @ ref, atol=1e-12)
    np.testing.assert_allclose(out[:, :3, :3] @ np.swapaxes(out[:, :3, :3], 1, 2),
                               np.broadcast_to(np.eye(3), (3, 3, 3)), atol=1e-12)


def test_bad_input_is_refused_with_its_name():
    ref = _path(3)
    with pytest.raises(ValueError, match=r"\(M, 4, 4\)"):
        frame_relative_poses(ref[:2], ref, ref)
    bad = ref.copy()
    bad[1, 0, 0] = 2.0
    with pytest.raises(ValueError, match="est_cam_T_world is not rigid"):
        frame_relative_poses(ref, ref, bad)
    nan = ref.copy()
    nan[0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="view_cam_T_world contains NaN"):
        frame_relative_poses(nan, ref, ref)
    for scale in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="scale must be a positive finite number"):
            frame_relative_poses(ref, ref, ref, scale=scale)
