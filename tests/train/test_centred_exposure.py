"""A centred exposure (docs/method.md §4, ``TrajectoryConfig.centre``): with trusted poses only the
spread of the exposure is learned, xi_start = -xi_end holds to the last bit through training, and
the mid-exposure pose stays the given one; with untrusted poses both endpoints stay free."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.geometry.se3 import se3_exp, se3_interpolate, se3_log
from d2gs_np.train.components import decide_components
from d2gs_np.train.config import ExperimentConfig, LearningRates, TrainConfig
from d2gs_np.train.learning_rates import block_learning_rate, centre_endpoint_grads
from d2gs_np.train.trainer import Trainer
from d2gs_np.blur.config import TrajectoryConfig
from d2gs_np.blur.endpoints import XI_END, XI_START



def _config(iters=16, centre="auto"):
    # the geodesic named: "auto" takes the three-knot path on this clip (bend over bend_px), whose
    # centred form frees the endpoints about a middle knot held at 0
    return ExperimentConfig(train=TrainConfig(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0,
                                              prune_every=0, warmup_fraction=0.0, deform_fraction=0.0),
                            trajectory=TrajectoryConfig(centre=centre, path="geodesic"))


def test_components_centre_the_exposure_for_trusted_poses_only(trusted_scene, noisy_scene):
    notes = []
    assert decide_components(trusted_scene, _config(), notes.append).centred
    assert any("centred on the given poses" in n for n in notes)
    assert not decide_components(noisy_scene, _config()).centred
    assert not decide_components(trusted_scene, _config(centre="off")).centred
    assert decide_components(noisy_scene, _config(centre="on")).centred
    posenet = ExperimentConfig(trajectory=TrajectoryConfig(kind="posenet"))
    assert not decide_components(trusted_scene, posenet).centred  # auto never ties a PoseNet
    with pytest.raises(ValueError, match="centre = 'on' needs kind 'direct'"):
        TrajectoryConfig(kind="posenet", centre="on")
    with pytest.raises(ValueError, match="centre must be"):
        TrajectoryConfig(centre="yes")


def test_centred_training_keeps_the_mid_pose_and_learns_the_spread(trusted_scene, tmp_path):
    tr = Trainer(trusted_scene, _config(), tmp_path / "run")
    assert tr.components.centred
    start = {n: tr.params[n].copy() for n in (XI_START, XI_END)}
    np.testing.assert_array_equal(start[XI_START], -start[XI_END])  # the velocity start is centred
    tr.run()
    xs, xe = tr.params[XI_START], tr.params[XI_END]
    np.testing.assert_array_equal(xs, -xe)  # exact: Adam's updates are exact negations
    assert np.abs(xe - start[XI_END]).max() > 1e-6  # the spread did train
    m = tr.model
    for k in range(m.num_frames):
        mid = se3_interpolate(se3_exp(xs[k]) @ m.poses_ref[k], se3_exp(xe[k]) @ m.poses_ref[k], 0.5)
        # the geodesic midpoint of exp(-h) T and exp(h) T is T; 1e-12: a few exp/log roundings
        assert np.abs(se3_log(mid @ np.linalg.inv(m.poses_ref[k]))).max() < 1e-12
        np.testing.assert_allclose(m.mid_pose(k), m.poses_ref[k], atol=1e-12)
    np.testing.assert_array_equal(m.poses_ref, np.stack([f.cam_T_world for f in trusted_scene.frames]))


def test_free_endpoints_move_the_mid_pose(trusted_scene, tmp_path):
    """The same run with centre = off: the tie is what keeps the mid pose (this test's contrast)."""
    tr = Trainer(trusted_scene, _config(centre="off"), tmp_path / "run")
    tr.run()
    assert not np.array_equal(tr.params[XI_START], -tr.params[XI_END])


def test_centred_grads_are_the_derivative_along_the_spread():
    """L(h) = f(xi_start = -h, xi_end = h) for a smooth f with known gradients: dL/dh = g_e - g_s,
    checked by central differences (float64, step 1e-6: truncation ~1e-13 from the sine's third
    derivative, rounding ~1e-10; hence 1e-8 relative)."""
    rng = np.random.default_rng(0)
    A, B = rng.standard_normal((6, 6)), rng.standard_normal((6, 6))

    def f(xs, xe):
        return 0.5 * xs @ A @ xs + xe @ B @ xs + np.sin(xe).sum()

    h0 = rng.standard_normal(6) * 0.1
    xs, xe = -h0, h0
    g_s = 0.5 * (A + A.T) @ xs + B.T @ xe
    g_e = B @ xs + np.cos(xe)
    grads = centre_endpoint_grads({XI_START: g_s[None], XI_END: g_e[None], "other": np.ones(2)})
    fd = np.array([(f(-(h0 + e), h0 + e) - f(-(h0 - e), h0 - e)) / 2e-6 for e in np.eye(6) * 1e-6])
    np.testing.assert_allclose(grads[XI_END][0], fd, rtol=1e-8, atol=1e-9)
    np.testing.assert_array_equal(grads[XI_START], -grads[XI_END])
    np.testing.assert_array_equal(grads["other"], np.ones(2))


def test_centred_endpoints_learn_at_the_spread_rate():
    lr = LearningRates(camera=1e-3, camera_final=1e-5, camera_spread=2e-4, camera_spread_final=2e-6)
    free = block_learning_rate(XI_END, lr, 1.0, 100, 5)
    tied = block_learning_rate(XI_END, lr, 1.0, 100, 5, centred=True)
    assert free.lr_init == 1e-3 and free.lr_final == 1e-5
    assert tied.lr_init == 2e-4 and tied.lr_final == 2e-6



def test_the_rows_a_kept_adjustment_moved_learn_slower():
    """camera_row_scales: Adam alone after a kept adjustment (then = adam) scales the rows of the
    frames it moved by camera_adjusted_scale, and keeps the full rate for those it held; an Adam
    step's size on a row follows the scale (Adam's first step is lr x sign(g), bias-corrected)."""
    from d2gs_np.optim import adam
    from d2gs_np.train.components import Components
    from d2gs_np.train.learning_rates import camera_row_scales, optimiser_step

    lr = LearningRates(camera_adjusted_scale=0.25)
    base = dict(dynamic=False, blur=True, learn_exposure=False, exposure_fraction=0.5)
    np.testing.assert_array_equal(camera_row_scales(Components(**base), lr, 4), 1.0)
    np.testing.assert_array_equal(camera_row_scales(Components(**base, adjusted_then="solver", held_frames=(1,)), lr, 4), 1.0)
    np.testing.assert_array_equal(camera_row_scales(Components(**base, adjusted_then="adam", held_frames=(1,)), lr, 4),
                                  [0.25, 1.0, 0.25, 0.25])
    # the "uncertainty" rule: each moved row at its rotation uncertainty over the prior's, clipped to
    # [camera_adjusted_scale, 1]; held rows at 1; without uncertainties (an old checkpoint) the constant
    unc = Components(**base, adjusted_then="adam", held_frames=(1,), rotation_uncertainty=(0.05, 0.3, 0.5, 3.0))
    np.testing.assert_array_equal(camera_row_scales(unc, lr, 4, "uncertainty"), [0.25, 1.0, 0.5, 1.0])
    np.testing.assert_array_equal(camera_row_scales(unc, lr, 4, "constant"), [0.25, 1.0, 0.25, 0.25])
    np.testing.assert_array_equal(camera_row_scales(Components(**base, adjusted_then="adam"), lr, 4, "uncertainty"),
                                  0.25)
    np.testing.assert_array_equal(camera_row_scales(Components(**base, adjusted_then="solver",
                                                               rotation_uncertainty=(0.5,) * 4), lr, 4, "uncertainty"),
                                  1.0)
    # a checkpoint's JSON gives lists: the Components it builds equals the one saved
    import dataclasses
    import json
    assert Components(**json.loads(json.dumps(dataclasses.asdict(unc)))) == unc
    params = {XI_START: np.zeros((4, 6)), XI_END: np.zeros((4, 6))}
    cfg = adam.AdamConfig(lrs={XI_START: 1e-3, XI_END: 1e-3})
    grads = {XI_START: np.ones((4, 6)), XI_END: -np.ones((4, 6))}
    for frame, scale in ((0, 0.25), (1, 1.0)):
        p, _ = optimiser_step(grads, adam.adam_init(params), params, cfg, ("camera",), frame, 1.0, scale)
        np.testing.assert_allclose(p[XI_END][frame], 1e-3 * scale, rtol=1e-6)
        assert not np.any(p[XI_END][np.arange(4) != frame])  # other rows untouched


def test_a_centred_three_knot_path_bends_through_the_trusted_pose(trusted_scene, tmp_path):
    from d2gs_np.blur.endpoints import XI_MID

    cfg = _config()
    cfg = cfg.replace(trajectory=TrajectoryConfig(path="three_knot"))
    tr = Trainer(trusted_scene, cfg, tmp_path / "run")
    assert tr.components.centred
    tr.run()
    xs, xe = tr.params[XI_START], tr.params[XI_END]
    np.testing.assert_array_equal(tr.params[XI_MID], 0.0)  # the deblurred view stays the trusted pose
    assert not np.array_equal(xs, -xe)  # the endpoints trained freely: the path bends
    m = tr.model
    np.testing.assert_array_equal(m.poses_ref, np.stack([f.cam_T_world for f in trusted_scene.frames]))
    for k in range(m.num_frames):
        np.testing.assert_allclose(m.mid_pose(k), m.poses_ref[k], atol=1e-15)


@pytest.fixture(scope="module")
def room_160():
    """A noisy-pose suite scene whose bundle adjustment is kept (tests/pose/test_given.py)."""
    from d2gs_np.data.suite import make_suite_scene

    return make_suite_scene("photo_room", seed=0, width=160, height=90, num_frames=12, num_test_views=0)


def test_held_adjusted_poses_train_as_trusted_ones(room_160, tmp_path):
    """pose_init.then = hold: the kept adjustment's poses are the run's, held as a trusted scene's
    are (a centred exposure, no pose solver), through a resume too."""
    from d2gs_np.pose.config import PoseInitConfig
    from d2gs_np.pose.given import initial_poses

    adjusted = initial_poses(room_160, ExperimentConfig())
    assert adjusted is not None  # kept: the premise
    cfg = _config(iters=4).replace(pose_init=PoseInitConfig(then="hold"))
    tr = Trainer(room_160, cfg, tmp_path / "run")
    assert tr.components.centred and tr.components.poses_held and tr.components.adjusted_then == "hold"
    assert any("held as exact" in n for n in tr.log.notes)
    np.testing.assert_array_equal(tr.model.poses_ref, adjusted)  # the adjustment is deterministic
    tr.run()
    m = tr.model
    np.testing.assert_array_equal(tr.params[XI_START], -tr.params[XI_END])
    for k in range(m.num_frames):
        np.testing.assert_allclose(m.mid_pose(k), adjusted[k], atol=1e-12)  # as in the trusted test above
    resumed = Trainer(room_160, cfg.replace(train=dataclasses.replace(cfg.train, iters=6)), tmp_path / "run",
                      resume=True)
    assert resumed.components.poses_held and resumed.components.centred
    assert "pose_solver" not in [p.name for p in resumed.plugins]


def test_adjusted_poses_refined_by_adam_alone(room_160, tmp_path):
    """pose_init.then = adam: free endpoints from the adjusted poses, no pose solver; "solver" keeps
    it (for a run long enough to call it)."""
    from d2gs_np.pose.config import PoseInitConfig
    from d2gs_np.train.pose_solver import use_pose_solver

    cfg = _config(iters=4).replace(pose_init=PoseInitConfig(then="adam"))
    tr = Trainer(room_160, cfg, tmp_path / "run")
    assert tr.components.adjusted_then == "adam" and tr.components.solver_left_out
    assert not tr.components.centred and not tr.components.poses_held
    assert any("refined by Adam alone" in n for n in tr.log.notes)
    # no frame held here: every row at its rotation uncertainty over the prior's, at least the floor
    u = np.asarray(tr.components.rotation_uncertainty)
    assert u.shape == (len(room_160.frames),) and not tr.components.held_frames
    np.testing.assert_array_equal(tr.camera_row_scales, np.clip(u, cfg.train.lr.camera_adjusted_scale, 1.0))
    assert any("its rotation's uncertainty" in n for n in tr.log.notes)
    tr_c = Trainer(room_160, cfg.replace(pose_init=PoseInitConfig(then="adam", adam_rows="constant")), tmp_path / "c")
    np.testing.assert_array_equal(tr_c.camera_row_scales, cfg.train.lr.camera_adjusted_scale)
    tr.run()
    assert not np.array_equal(tr.params[XI_START], -tr.params[XI_END])  # free endpoints
    long = cfg.replace(train=dataclasses.replace(cfg.train, iters=5000))
    for then, runs in (("solver", True), ("adam", False), ("hold", False), ("", True)):
        assert use_pose_solver(room_160, long, adjusted_then=then) is runs, then
    assert not decide_components(room_160, long, adjusted=False).centred
    assert decide_components(room_160, long, adjusted=False).adjusted_then == ""


def test_an_adjustment_that_was_not_kept_is_left_to_the_solver(room_160, tmp_path):
    from d2gs_np.pose.config import PoseInitConfig

    cfg = _config(iters=2).replace(pose_init=PoseInitConfig(then="hold", min_points=10 ** 6, fallback_min_points=0))
    tr = Trainer(room_160, cfg, tmp_path / "run")
    assert tr.components.adjusted_then == "" and not tr.components.centred
    assert any("given poses kept" in n for n in tr.log.notes)
    np.testing.assert_array_equal(tr.model.poses_ref, np.stack([f.cam_T_world for f in room_160.frames]))
    with pytest.raises(ValueError, match="then must be"):
        PoseInitConfig(then="yes")
