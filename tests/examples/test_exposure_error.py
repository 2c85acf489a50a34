"""examples/exposure_error.py: zero spread error for a run whose endpoints are the true ones, zero
mid error for an exposure centred on the true mid pose, and a clear refusal of a scene without
true exposures."""
import numpy as np
import pytest

from d2gs_np.data.io import load_scene, write_scene
from d2gs_np.data.synthetic import make_scene
from d2gs_np.geometry import se3_exp, se3_inverse, se3_log
from d2gs_np.train.config import ExperimentConfig, TrainConfig
from d2gs_np.train.trainer import Trainer
from d2gs_np.blur.endpoints import XI_END, XI_START
from example_fixtures import load_example


def _module():
    return load_example("exposure_error.py")


def _run_holding_the_true_endpoints(scene, run):
    """A one-step run of ``scene`` in ``run`` whose final checkpoint holds the true exposure
    endpoints, as left perturbations of the reference (= true mid) poses; (trainer, xs, xe)."""
    tr = Trainer(scene, ExperimentConfig(train=TrainConfig(iters=1, quiet=True, eval_every=0, checkpoint_every=0)), run)
    P = tr.model.poses_ref
    xs = np.stack([se3_log(f.gt_exposure_start @ se3_inverse(p)) for f, p in zip(scene.frames, P)])
    xe = np.stack([se3_log(f.gt_exposure_end @ se3_inverse(p)) for f, p in zip(scene.frames, P)])
    tr.params = {**tr.params, XI_START: xs, XI_END: xe}
    tr.checkpoint(final=True)
    return tr, xs, xe


def test_true_endpoints_score_zero_and_a_centred_exposure_has_no_mid_error(tmp_path):
    mod = _module()
    scene = make_scene("dynamic", 0, width=48, height=27, num_frames=5, rot_noise_deg=0.0, trans_noise_fraction=0.0)
    scene_dir = tmp_path / "scene"
    write_scene(scene, scene_dir)
    run = tmp_path / "run"
    tr, xs, xe = _run_holding_the_true_endpoints(scene, run)
    e = mod.exposure_errors(run, scene_dir, windows=(1,))
    assert e["spread_learned_deg"] < 1e-9 and e["spread_learned_t"] < 1e-12
    assert np.isfinite(e["spread_start_h1_deg"]) and np.isfinite(e["spread_start_h1_t"])
    # a centred exposure about the true mid pose (the reference here): no mid error, and a spread
    # error that is not zero (0.2 rad exposures are not the true ones)
    d = np.tile([0.0, 0.0, 0.0, 0.1, 0.0, 0.0], (len(xs), 1))
    tr.params = {**tr.params, XI_START: -d, XI_END: d}
    tr.checkpoint(final=True)
    e = mod.exposure_errors(run, scene_dir, windows=(1,))
    assert e["mid_learned_deg"] < 1e-9 and e["mid_learned_t"] < 1e-12 and e["spread_learned_deg"] > 1.0


def test_rotation_and_translation_are_read_from_the_right_parts_of_the_pose():
    """se(3) tangents are (rho, phi), translation first: a pure rotation of 2 degrees reads as 2
    degrees and no translation, a pure translation as 0 degrees and its length."""
    mod = _module()
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    R = se3_exp(np.concatenate([np.zeros(3), np.deg2rad(2.0) * axis]))
    assert mod.rotation_deg(R) == pytest.approx(2.0, abs=1e-12)
    assert mod.translation(R) == pytest.approx(0.0, abs=1e-15)
    T = se3_exp(np.array([0.3, -0.4, 0.0, 0.0, 0.0, 0.0]))
    assert mod.rotation_deg(T) == pytest.approx(0.0, abs=1e-12)
    assert mod.translation(T) == pytest.approx(0.5, abs=1e-12)
    # the spread error of an exposure turning 1 degree more than the truth about the same axis
    I = np.eye(4)[None]
    rot = lambda deg: se3_exp(np.concatenate([np.zeros(3), np.deg2rad(deg) * axis]))[None]
    r, t = mod.spread_error(I, rot(3.0), I, rot(2.0))
    assert r[0] == pytest.approx(1.0, abs=1e-10) and t[0] == pytest.approx(0.0, abs=1e-15)


def test_a_scene_without_true_exposures_is_refused(tmp_path):
    mod = _module()
    with pytest.raises(SystemExit, match="gt_exposure_start"):
        scene = make_scene("sharp", 0, width=48, height=27, num_frames=4)
        for f in scene.frames:
            f.gt_exposure_start = None
        write_scene(scene, tmp_path / "s")
        mod.exposure_errors(tmp_path / "missing_run", tmp_path / "s")


def test_the_blur_vector_error_is_zero_for_the_truth_and_f_alpha_for_a_turn(tmp_path):
    """On a suite scene (its true world rebuilt from suite_config.json): the true exposures' blur
    vectors have zero error; turning both endpoints by alpha/2 more about the camera's y axis
    (a pure rotation, so every depth moves alike) changes a blur vector by f alpha (1 + x^2) at
    normalised image abscissa x: between f alpha and f alpha (1 + tan^2(fov_x / 2)) = 1.33 f alpha
    for the suite's 60 degree field of view."""
    from d2gs_np.data.suite import write_suite_scene

    mod = _module()
    scene_dir = write_suite_scene(tmp_path / "s", "cube_sign", 0, num_frames=4, width=48, height=27)
    scene = load_scene(scene_dir, load_images=False)
    ts = np.stack([f.gt_exposure_start for f in scene.frames])
    te = np.stack([f.gt_exposure_end for f in scene.frames])
    pts = mod.mid_camera_points(scene_dir, ts, te, step=2)
    assert pts is not None and all(len(p) > 100 for p in pts)
    K = scene.frames[0].K
    assert mod.blur_error_px(pts, K, ts, te, ts, te) == 0.0
    alpha = np.deg2rad(0.5)
    turn = lambda a: se3_exp(np.array([0.0, 0.0, 0.0, 0.0, a, 0.0]))
    # left perturbations act in the camera frame: exp(d) T turns the camera about its own y axis
    e = mod.blur_error_px(pts, K, np.einsum("ij,njk->nik", turn(-alpha / 2), ts),
                          np.einsum("ij,njk->nik", turn(alpha / 2), te), ts, te)
    f_alpha = K[0, 0] * alpha
    assert f_alpha * 0.99 <= e <= f_alpha * 1.34, (e, f_alpha)
    # the length ratio: 1 for the truth, 0.5 for blur vectors half as long
    bt = mod.blur_vectors(pts, K, ts, te)
    assert mod.blur_length_ratio(bt, bt) == pytest.approx(1.0, abs=1e-12)
    assert mod.blur_length_ratio([0.5 * v for v in bt], bt) == pytest.approx(0.5, abs=1e-12)
    zero = [np.zeros_like(v) for v in bt]
    assert np.isnan(mod.blur_length_ratio(bt, zero))  # no true blur: no ratio, not a division by 0
    # a scene folder without a world has no pixel metric
    assert mod.mid_camera_points(tmp_path / "nowhere", ts, te) is None


def test_a_run_with_the_true_endpoints_has_blur_ratio_one_and_half_the_spread_about_half(tmp_path):
    """exposure_errors on a suite scene reports blur_ratio_learned: 1 (and no blur error) for a
    run holding the true endpoints; endpoints at half their tangents blur about half as far (the
    exposures are short, so halving the tangent halves the motion to first order)."""
    from d2gs_np.data.suite import write_suite_scene

    mod = _module()
    scene_dir = write_suite_scene(tmp_path / "s", "cube_sign", 0, num_frames=4, width=48, height=27)
    scene = load_scene(scene_dir)
    run = tmp_path / "run"
    tr, xs, xe = _run_holding_the_true_endpoints(scene, run)
    e = mod.exposure_errors(run, scene_dir, windows=(1,))
    assert e["blur_ratio_learned"] == pytest.approx(1.0, abs=1e-9) and e["blur_learned_px"] < 1e-9
    tr.params = {**tr.params, XI_START: 0.5 * xs, XI_END: 0.5 * xe}
    tr.checkpoint(final=True)
    e = mod.exposure_errors(run, scene_dir, windows=(1,))
    assert 0.45 <= e["blur_ratio_learned"] <= 0.55, e["blur_ratio_learned"]
