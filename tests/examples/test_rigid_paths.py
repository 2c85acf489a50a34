"""examples/rigid_paths.py: the turn error of a rigid path in the camera, on rotations whose answer is
known, free of the world's gauge and of the cluster's own frame."""
import numpy as np
import pytest

from d2gs_np.geometry.so3 import so3_exp
from d2gs_np.train.config import ExperimentConfig
from example_fixtures import load_example

rp = load_example("rigid_paths.py")


def _path(rng, N=7):
    cams = so3_exp(rng.normal(0, 0.05, (N, 3)))
    objs = so3_exp(np.linspace(-0.6, 0.6, N)[:, None] * np.array([0.2, 1.0, 0.1]))  # a steady turn
    return cams, objs


def test_exact_path_scores_zero_in_any_gauge_and_cluster_frame():
    rng = np.random.default_rng(0)
    cams, objs = _path(rng)
    G = so3_exp(np.array([0.3, -1.2, 2.0]))  # the estimate's world = G x the truth's
    B = so3_exp(np.array([-2.5, 0.4, 0.7]))  # the cluster's own frame
    err = rp.turn_errors_deg(cams @ G.T, G @ objs @ B, cams, objs, ref=3)
    # float64 rotations composed five deep: arccos near 1 turns 1e-16 into ~1e-6 degrees
    assert np.all(err < 1e-5)


def test_a_known_extra_turn_is_measured():
    rng = np.random.default_rng(1)
    cams, objs = _path(rng)
    est = objs.copy()
    est[5] = so3_exp(np.array([0.0, 0.0, np.radians(10.0)])) @ objs[5]  # 10 deg off at frame 5 only
    err = rp.turn_errors_deg(cams, est, cams, objs, ref=3)
    assert err[5] == pytest.approx(10.0, abs=1e-9)
    assert np.all(np.delete(err, 5) < 1e-5)
    # an error at the reference frame itself shows at every other frame
    est = objs.copy()
    est[3] = so3_exp(np.array([np.radians(20.0), 0.0, 0.0])) @ objs[3]
    err = rp.turn_errors_deg(cams, est, cams, objs, ref=3)
    assert err[3] < 1e-5 and np.all(np.delete(err, 3) == pytest.approx(20.0, abs=1e-6))


def test_a_mirrored_turn_is_not_a_small_error():
    # the same turn angle the other way about the same axis: twice the angle off
    rng = np.random.default_rng(2)
    cams = np.broadcast_to(np.eye(3), (5, 3, 3))
    objs = so3_exp(np.linspace(-0.4, 0.4, 5)[:, None] * np.array([0.0, 1.0, 0.0]))
    err = rp.turn_errors_deg(cams, np.swapaxes(objs, 1, 2), cams, objs, ref=2)
    assert err == pytest.approx(np.degrees(2 * np.abs(np.linspace(-0.4, 0.4, 5))), abs=1e-9)


def test_near_pi_turns_stay_finite():
    cams = np.broadcast_to(np.eye(3), (3, 3, 3))
    objs = so3_exp(np.array([[0, 0, 0], [0, 0, np.pi - 1e-9], [0, 0, np.pi]]))
    err = rp.turn_errors_deg(cams, np.broadcast_to(np.eye(3), (3, 3, 3)), cams, objs, ref=0)
    assert np.all(np.isfinite(err)) and err[2] == pytest.approx(180.0, abs=1e-4)


def test_best_cluster_per_mover():
    errors = {(0, 0): np.array([1.0, 50.0, 60.0]), (1, 0): np.array([5.0, 5.0, 6.0]),
              (0, 1): np.array([2.0, 2.0, 2.0]), (1, 1): np.array([9.0, 9.0, 9.0])}
    assert rp.best_clusters(errors) == {0: (1, 5.0), 1: (0, 2.0)}


def test_bad_input_is_refused_by_name():
    eye = np.broadcast_to(np.eye(3), (4, 3, 3))
    with pytest.raises(ValueError, match="obj_R must be finite"):
        rp.turn_errors_deg(eye, eye[:3], eye, eye, ref=0)
    bad = eye.copy()
    bad[1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="cam_R_true must be finite"):
        rp.turn_errors_deg(eye, eye, bad, eye, ref=0)
    with pytest.raises(ValueError, match="ref must be a frame index"):
        rp.turn_errors_deg(eye, eye, eye, eye, ref=4)
    cfg = ExperimentConfig()
    with pytest.raises(ValueError, match="section.field=value"):
        rp._override(cfg, "motion_init.no_such_field=3")
    assert rp._override(cfg, "motion_init.bundle_window=8").motion_init.bundle_window == 8
    with pytest.raises(Exception, match="bundle_window"):
        rp._override(cfg, "motion_init.bundle_window=0")
    with pytest.raises(ValueError, match="unknown static-depth variant"):
        rp.measure("cube_sign", 0, "no_such_variant")
