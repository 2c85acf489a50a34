"""Position steps by depth (LearningRates.means_depth = "near"): each Gaussian's factor is its depth
over the step frame's median static depth, clipped to [floor, 1], and Adam's step of a position row
is that factor times the plain step, the moments unchanged."""
import numpy as np
import pytest

from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.optim import adam
from d2gs_np.train.config import ExperimentConfig, LearningRates, TrainConfig
from d2gs_np.train.learning_rates import optimiser_step, position_row_factors
from d2gs_np.train.trainer import Trainer

from run_fixtures import tiny_dynamic_scene


def _reference_factors(means, T, z_med, floor):
    """The obvious loop: depth of each point in camera T, over z_med, clipped."""
    out = []
    for m in means:
        z = (T[:3, :3] @ m + T[:3, 3])[2]
        out.append(min(1.0, max(floor, z / z_med)))
    return np.array(out)


def test_factors_are_depth_over_the_static_median_clipped():
    rng = np.random.default_rng(0)
    T = se3_exp(np.array([0.1, -0.2, 0.3, 0.2, -0.1, 0.05]))
    cam = np.c_[rng.uniform(-1, 1, (41, 2)), rng.uniform(0.5, 6.0, 41)]
    cam[:3, 2] = [-1.0, 0.0, 1e-12]  # behind, at and just in front of the camera
    world = (cam - T[:3, 3]) @ T[:3, :3]  # camera points carried to the world
    dyn_cam = np.array([[0.0, 0.0, 0.3], [0.1, 0.2, 50.0]])
    dyn = (dyn_cam - T[:3, 3]) @ T[:3, :3]
    params = {"static.means": world, "dynamic.means": dyn, "dynamic.deform_means": np.zeros((2, 6, 3)),
              "static.colors": np.zeros((41, 3))}
    f = position_row_factors(params, T, 0.1)
    assert set(f) == {"static.means", "dynamic.means", "dynamic.deform_means"}
    z_med = np.median(cam[cam[:, 2] > 0, 2])
    np.testing.assert_allclose(f["static.means"], _reference_factors(world, T, z_med, 0.1), rtol=1e-12)
    np.testing.assert_allclose(f["dynamic.means"], _reference_factors(dyn, T, z_med, 0.1), rtol=1e-12)
    np.testing.assert_array_equal(f["dynamic.deform_means"], f["dynamic.means"])
    assert f["static.means"][0] == 0.1 and f["static.means"][1] == 0.1 and f["static.means"][2] == 0.1
    assert f["dynamic.means"][1] == 1.0  # far beyond the median: the plain step


@pytest.mark.parametrize("scale", [1e-8, 1e8])
def test_factors_do_not_depend_on_the_scene_scale(scale):
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-1, 1, (30, 2)), rng.uniform(1.0, 5.0, 30)]
    T = np.eye(4)
    f1 = position_row_factors({"static.means": pts}, T, 0.2)
    Ts = T.copy()
    Ts[:3, 3] *= scale
    fs = position_row_factors({"static.means": pts * scale}, Ts, 0.2)
    np.testing.assert_allclose(fs["static.means"], f1["static.means"], rtol=1e-12)
    assert np.all(np.isfinite(fs["static.means"]))


def test_no_static_gaussian_in_front_leaves_the_steps_alone():
    params = {"static.means": np.array([[0.0, 0.0, -2.0]]), "dynamic.means": np.array([[0.0, 0.0, 1.0]]),
              "dynamic.deform_means": np.zeros((1, 6, 3))}
    f = position_row_factors(params, np.eye(4), 0.1)
    assert all(np.array_equal(v, np.ones(len(v))) for v in f.values())
    assert position_row_factors({"static.means": np.zeros((0, 3))}, np.eye(4), 0.1)["static.means"].shape == (0,)


def test_a_row_steps_as_if_its_rate_were_its_factor_times_the_blocks():
    rng = np.random.default_rng(2)
    params = {"static.means": rng.normal(size=(5, 3)), "dynamic.deform_means": rng.normal(size=(5, 6, 3)),
              "static.colors": rng.normal(size=(5, 3))}
    grads = {k: rng.normal(size=v.shape) for k, v in params.items()}
    cfg = adam.AdamConfig(lrs={k: 0.01 for k in params})
    factors = {"static.means": np.array([1.0, 0.5, 0.1, 0.25, 1.0]),
               "dynamic.deform_means": np.array([0.3, 1.0, 0.1, 0.7, 0.2])}
    state = adam.adam_init(params)
    plain, s_plain = optimiser_step(grads, state, params, cfg, ("static.", "dynamic."), 0)
    scaled, s_scaled = optimiser_step(grads, state, params, cfg, ("static.", "dynamic."), 0,
                                      position_factors=factors)
    for name, f in factors.items():
        for i, fi in enumerate(f):
            # the same row under a rate of fi x 0.01
            one = adam.AdamConfig(lrs={name: 0.01 * fi})
            ref, _ = adam.adam_update({name: grads[name][i:i + 1]}, adam.adam_init({name: params[name][i:i + 1]}),
                                      {name: params[name][i:i + 1]}, one)
            np.testing.assert_allclose(scaled[name][i:i + 1], ref[name], rtol=1e-12, atol=1e-15)
        np.testing.assert_array_equal(s_scaled["m"][name], s_plain["m"][name])
        np.testing.assert_array_equal(s_scaled["v"][name], s_plain["v"][name])
    np.testing.assert_array_equal(scaled["static.colors"], plain["static.colors"])
    # a block the stage does not train is not moved by its factor
    frozen, _ = optimiser_step(grads, state, params, cfg, ("static.",), 0, position_factors=factors)
    np.testing.assert_array_equal(frozen["dynamic.deform_means"], params["dynamic.deform_means"])


def test_bad_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="LearningRates.means_depth"):
        LearningRates(means_depth="pixels")
    with pytest.raises(ValueError, match="LearningRates.means_depth_floor"):
        LearningRates(means_depth_floor=0.0)
    with pytest.raises(ValueError, match="LearningRates.means_depth_floor"):
        LearningRates(means_depth_floor=1.5)


def test_near_steps_move_near_gaussians_less_in_training(tmp_path):
    # The same two steps with and without the rule: the static Gaussians at or beyond the first
    # frame's median depth move as far; the nearest ones move less.
    scene = tiny_dynamic_scene(trusted=True)

    def moved(means_depth):
        lr = LearningRates(means_depth=means_depth)
        cfg = ExperimentConfig(train=TrainConfig(iters=2, quiet=True, eval_every=0, prune_every=0,
                                                 checkpoint_every=0, warmup_fraction=0.5, deform_fraction=0.0,
                                                 lr=lr, blur="off", dynamic="off"))
        tr = Trainer(scene, cfg, tmp_path / means_depth)
        before = tr.state.params["static.means"].copy()
        poses = tr.state.model.poses_ref
        k = tr.step(0).frame
        return before, np.linalg.norm(tr.state.params["static.means"] - before, axis=1), poses, k

    before, world, poses, k = moved("world")
    before2, near, _, k2 = moved("near")
    np.testing.assert_array_equal(before, before2)
    assert k == k2
    f = position_row_factors({"static.means": before}, poses[k], LearningRates().means_depth_floor)["static.means"]
    np.testing.assert_allclose(near, f * world, rtol=1e-9, atol=1e-15)
    assert np.any(f < 1.0) and np.any(f == 1.0)
