"""The L_dgrad loss term (train.terms.DepthGradient): left out without priors or with disparity
priors, its value the loss function's on the frame's moving pixels (or every pixel), nothing on a
frame without movers, its gradient through the render downhill, and the term in a training run."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.blur.config import BlurConfig
from d2gs_np.data import suite
from d2gs_np.losses.depth_gradient import depth_gradient_fwd
from d2gs_np.render.config import RenderConfig
from d2gs_np.train.config import ExperimentConfig, LossConfig, PoseSolverConfig, TrainConfig
from d2gs_np.train.model import frame_render_fwd
from d2gs_np.train.terms import TermInputs, loss_terms
from d2gs_np.train.trainer import Trainer
from run_fixtures import expected_depth_descent

TINY = dict(width=48, height=27, num_frames=4, num_test_views=2, subframes=4)


@pytest.fixture(scope="module")
def prior_scene():
    return suite.make_suite_scene("crossing", 0, depth_prior="video", **TINY)


def _config(iters, weight, region="moving", **train):
    base = dict(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0, prune_every=0)
    base.update(train)
    return ExperimentConfig(train=TrainConfig(**base),
                            loss=LossConfig(lambda_depth_grad=weight, depth_grad_region=region, lambda_freq=0.0),
                            pose_solver=PoseSolverConfig(mode="off"))


def test_left_out_without_depth_priors_or_with_disparities(prior_scene):
    notes = []
    bare = suite.make_suite_scene("crossing", 0, **TINY)
    cfg = LossConfig(lambda_depth_grad=0.3, lambda_freq=0.0)
    assert [t.name for t in loss_terms(cfg, note=notes.append, scene=bare)] == ["photometric"]
    assert any("L_dgrad: left out" in n and "depth_prior_file_path" in n for n in notes)
    assert [t.name for t in loss_terms(cfg, note=notes.append, scene=prior_scene, prior_space="disparity")] == \
        ["photometric"]
    assert any("L_dgrad: left out" in n and "disparities" in n for n in notes)
    terms = loss_terms(cfg, note=notes.append, scene=prior_scene)
    assert [t.name for t in terms] == ["photometric", "depth_grad"] and terms[1].weight == 0.3
    assert any(n.startswith("L_dgrad: weight 0.3") and "moving pixels" in n for n in notes)


def test_a_bad_region_is_refused_by_name():
    with pytest.raises(ValueError, match="LossConfig.depth_grad_region"):
        LossConfig(depth_grad_region="movers")
    with pytest.raises(ValueError, match="LossConfig.lambda_depth_grad"):
        LossConfig(lambda_depth_grad=-1.0)


@pytest.mark.parametrize("region", ["moving", "all"])
def test_the_value_is_the_loss_functions_on_its_region(prior_scene, tmp_path, region):
    tr = Trainer(prior_scene, _config(1, 1.0, region), tmp_path / region)
    term = next(t for t in tr.terms if t.name == "depth_grad")
    k = next(i for i, f in enumerate(prior_scene.frames) if f.mask is not None and f.mask.any())
    tgt = tr.cache.get(k, 1.0)
    out, _ = frame_render_fwd(tr.model, k, tgt.K, tgt.width, tgt.height)
    prior = term.prior(k, tgt.width, tgt.height)
    loss_mask = np.ones((tgt.height, tgt.width))
    loss_mask[:, :3] = 0.0
    v, _ = term.fwd(TermInputs(out, tgt.image, loss_mask, tr.model, k, None, tgt.mask))
    region_mask = (loss_mask > 0) & tgt.mask if region == "moving" else loss_mask
    expect = depth_gradient_fwd(out["expected_depth"], prior, out["alpha"], mask=region_mask)[0]
    assert v == expect and v > 0
    # without a motion mask (a frame with no moving pixels) "moving" adds nothing, "all" the whole loss mask
    v0, s0 = term.fwd(TermInputs(out, tgt.image, loss_mask, tr.model, k, None, None))
    if region == "moving":
        assert (v0, s0) == (0.0, None) and term.bwd(s0).render == {}
    else:
        assert v0 == expect


def test_its_gradient_through_the_render_is_downhill(prior_scene, tmp_path):
    # As L_depth's test (tests/train/test_depth_prior_term.py): the cotangent on the expected depth,
    # through the float64 render backward, onto the static means; central differences along that
    # direction match the gradient's squared norm to 1e-5 at a mean step of at most 1e-7 (larger
    # steps cross a footprint's integer radius on this frame). Every pixel, so the static set
    # carries it.
    cfg = dataclasses.replace(_config(1, 1.0, "all"), render=RenderConfig(raster_float32=False),
                              blur=BlurConfig(backward_views=0))
    v, slope, g2, below = expected_depth_descent(Trainer(prior_scene, cfg, tmp_path / "r"), "depth_grad")
    assert v > 0
    assert slope == pytest.approx(g2, rel=1e-5) and below < v


def test_training_logs_the_term_and_it_moves_the_dynamic_set(prior_scene, tmp_path):
    # The warm-up (a tenth of the schedule) renders the static set alone with the moving pixels
    # out of the loss, so the "moving" term starts with the deform stage; 20 steps reach it.
    a = Trainer(prior_scene, _config(20, 2.0), tmp_path / "a")
    a.run()
    vals = [r["loss_depth_grad"] for r in a.log.rows]
    assert all(np.isfinite(vals)) and max(vals) > 0
    r = next(r for r in a.log.rows[::-1] if r["loss_depth_grad"] > 0)
    assert r["loss"] == pytest.approx(r["loss_photometric"] + 2.0 * r["loss_depth_grad"], rel=1e-12)
    b = Trainer(prior_scene, dataclasses.replace(_config(20, 2.0), loss=LossConfig(lambda_freq=0.0)), tmp_path / "b")
    b.run()
    assert not np.array_equal(a.params["dynamic.means"], b.params["dynamic.means"])
