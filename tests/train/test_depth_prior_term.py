"""The L_depth loss term (train.terms.DepthPrior): the prior at each render size, left out without
priors, its gradient through the render reaching the Gaussians downhill, and the term in a
training run (log column, weighted sum, the runs it changes)."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.data import suite
from d2gs_np.losses.depth_prior import depth_prior_fwd
from d2gs_np.blur.config import BlurConfig
from d2gs_np.render.config import RenderConfig
from d2gs_np.train.config import ExperimentConfig, LossConfig, PoseSolverConfig, TrainConfig
from d2gs_np.train.model import frame_render_fwd
from d2gs_np.train.terms import DepthPrior, TermInputs, loss_terms
from d2gs_np.train.trainer import Trainer
from run_fixtures import expected_depth_descent

TINY = dict(width=48, height=27, num_frames=4, num_test_views=2, subframes=4)


@pytest.fixture(scope="module")
def prior_scene():
    return suite.make_suite_scene("crossing", 0, depth_prior="video", **TINY)


def test_the_prior_at_a_render_size_is_the_area_mean_where_every_pixel_is_known():
    full = np.arange(1.0, 1.0 + 8 * 6).reshape(6, 8)
    full[0, 0] = np.nan
    term = DepthPrior(1.0, [full], "depth")
    assert term.prior(0, 8, 6) is not None and np.array_equal(term.prior(0, 8, 6), full, equal_nan=True)
    half = term.prior(0, 4, 3)
    assert np.isnan(half[0, 0])  # one unknown pixel under it
    np.testing.assert_allclose(half[1:, :], full[2:, :].reshape(2, 2, 4, 2).mean(axis=(1, 3)), rtol=1e-15)
    np.testing.assert_allclose(half[0, 1:], full[:2, 2:].reshape(1, 2, 3, 2).mean(axis=(1, 3))[0], rtol=1e-15)
    assert term.prior(0, 4, 3) is half  # kept per size


def test_left_out_without_depth_priors(prior_scene):
    notes = []
    bare = suite.make_suite_scene("crossing", 0, **TINY)
    terms = loss_terms(LossConfig(lambda_depth_prior=0.1, lambda_freq=0.0), note=notes.append, scene=bare)
    assert [t.name for t in terms] == ["photometric"]
    assert any("L_depth: left out" in n and "depth_prior_file_path" in n for n in notes)
    terms = loss_terms(LossConfig(lambda_depth_prior=0.1, lambda_freq=0.0), note=notes.append, scene=prior_scene,
                       prior_space="disparity")
    assert [t.name for t in terms] == ["photometric", "depth_prior"] and terms[1].space == "disparity"


def _config(iters, weight, **train):
    base = dict(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0, prune_every=0)
    base.update(train)
    return ExperimentConfig(train=TrainConfig(**base), loss=LossConfig(lambda_depth_prior=weight, lambda_freq=0.0),
                            pose_solver=PoseSolverConfig(mode="off"))


def test_its_gradient_through_the_render_is_downhill(prior_scene, tmp_path):
    # The term's cotangent on the expected depth, through the float64 render backward, onto the
    # static means: a step of the means against it lowers the term; central differences along
    # that direction agree with the gradient's squared norm to 1e-5. The step moves a mean by at
    # most 1e-7: larger ones (1e-6 .. 1e-4) cross a footprint's integer radius or tile on this
    # frame and miss by up to 30 %; at 1e-7 rounding leaves ~1e-9 (measured 8e-10).
    cfg = dataclasses.replace(_config(1, 1.0), render=RenderConfig(raster_float32=False),
                              blur=BlurConfig(backward_views=0))  # float64, every view's backward
    v, slope, g2, below = expected_depth_descent(Trainer(prior_scene, cfg, tmp_path / "r"), "depth_prior")
    assert 0.0 < v < 2.0
    assert slope == pytest.approx(g2, rel=1e-5) and below < v


def test_training_logs_the_term_and_it_reaches_the_gaussians(prior_scene, tmp_path):
    a = Trainer(prior_scene, _config(6, 0.5), tmp_path / "a")
    assert [t.name for t in a.terms] == ["photometric", "depth_prior"]
    a.run()
    assert any(n.startswith("L_depth: weight 0.5") for n in a.log.notes)
    rows = a.log.rows
    vals = [r["loss_depth_prior"] for r in rows]
    assert all(np.isfinite(vals)) and min(vals) > 0
    r = rows[-1]
    assert r["loss"] == pytest.approx(r["loss_photometric"] + 0.5 * r["loss_depth_prior"], rel=1e-12)
    b = Trainer(prior_scene, dataclasses.replace(_config(6, 0.5), loss=LossConfig(lambda_freq=0.0)), tmp_path / "b")
    b.run()
    assert not np.array_equal(a.params["static.means"], b.params["static.means"])


def test_the_value_is_the_loss_functions(prior_scene, tmp_path):
    # the term is depth_prior_fwd on the render and the frame's prior at its size, no more
    tr = Trainer(prior_scene, _config(1, 1.0), tmp_path / "v")
    term = next(t for t in tr.terms if t.name == "depth_prior")
    tgt = tr.cache.get(2, 0.5)
    out, _ = frame_render_fwd(tr.model, 2, tgt.K, tgt.width, tgt.height)
    v, _ = term.fwd(TermInputs(out, tgt.image, None, tr.model, 2, None))
    expect = depth_prior_fwd(out["expected_depth"], term.prior(2, tgt.width, tgt.height), out["alpha"],
                             tolerance=0.1)[0]
    assert term.tolerance == 0.1  # LossConfig.depth_prior_tolerance
    assert v == expect and out["expected_depth"].shape == (tgt.height, tgt.width)


def test_moving_pixels_take_their_own_tolerance(prior_scene, tmp_path):
    # LossConfig.depth_prior_tolerance_moving: the frame's motion mask picks each pixel's tau; the
    # value is depth_prior_fwd with that map, and differs from the one-tau value where movers are
    config = _config(1, 1.0)
    config = dataclasses.replace(config, loss=dataclasses.replace(config.loss, depth_prior_tolerance_moving=0.0))
    tr = Trainer(prior_scene, config, tmp_path / "m")
    term = next(t for t in tr.terms if t.name == "depth_prior")
    assert term.tolerance == 0.1 and term.tolerance_moving == 0.0
    k = next(i for i, f in enumerate(prior_scene.frames) if f.mask is not None and f.mask.any())
    tgt = tr.cache.get(k, 1.0)
    assert tgt.mask is not None and tgt.mask.any()
    out, _ = frame_render_fwd(tr.model, k, tgt.K, tgt.width, tgt.height)
    prior = term.prior(k, tgt.width, tgt.height)
    v, _ = term.fwd(TermInputs(out, tgt.image, None, tr.model, k, None, tgt.mask))
    expect = depth_prior_fwd(out["expected_depth"], prior, out["alpha"], tolerance=np.where(tgt.mask, 0.0, 0.1))[0]
    one = depth_prior_fwd(out["expected_depth"], prior, out["alpha"], tolerance=0.1)[0]
    assert v == expect and v > one  # moving pixels within 10 % of the prior now cost
    # without a mask (a frame with no moving pixels) the one tau holds
    assert term.fwd(TermInputs(out, tgt.image, None, tr.model, k, None, None))[0] == one


def test_a_bad_moving_tolerance_is_refused_by_name():
    with pytest.raises(ValueError, match="LossConfig.depth_prior_tolerance_moving"):
        LossConfig(depth_prior_tolerance_moving=-0.1)
    assert LossConfig(depth_prior_tolerance_moving=None).depth_prior_tolerance_moving is None
