"""The L_var loss term (train.terms.DepthVariance): its value is the loss function on a render of the
(z, z^2, 0) features, its gradient through that render reaches the static and dynamic Gaussians
downhill, and the term in a training run (log column, weighted sum, the runs it changes)."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.data import suite
from d2gs_np.geometry.camera import scale_intrinsics
from d2gs_np.losses.depth_variance import depth_variance_fwd, z_features_fwd
from d2gs_np.blur.config import BlurConfig
from d2gs_np.render import render_fwd
from d2gs_np.render.config import RenderConfig
from d2gs_np.scene.render_inputs import render_inputs_fwd
from d2gs_np.train.config import ExperimentConfig, LossConfig, PoseSolverConfig, TrainConfig
from d2gs_np.train.model import frame_render_fwd
from d2gs_np.train.terms import TermInputs, loss_terms
from d2gs_np.train.trainer import Trainer

TINY = dict(width=48, height=27, num_frames=4, num_test_views=2, subframes=4)


@pytest.fixture(scope="module")
def scene():
    return suite.make_suite_scene("crossing", 0, **TINY)


def _config(iters, weight):
    return ExperimentConfig(train=TrainConfig(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0,
                                              prune_every=0),
                            loss=LossConfig(lambda_depth_var=weight, lambda_freq=0.0),
                            pose_solver=PoseSolverConfig(mode="off"),
                            render=RenderConfig(raster_float32=False), blur=BlurConfig(backward_views=0))


def test_built_only_with_a_weight():
    assert [t.name for t in loss_terms(LossConfig(lambda_freq=0.0))] == ["photometric"]
    notes = []
    terms = loss_terms(LossConfig(lambda_depth_var=0.5, lambda_freq=0.0), note=notes.append)
    assert [t.name for t in terms] == ["photometric", "depth_var"] and terms[1].weight == 0.5
    assert any(n.startswith("L_var: weight 0.5") for n in notes)
    with pytest.raises(ValueError, match="LossConfig.lambda_depth_var"):
        LossConfig(lambda_depth_var=-1.0)


def test_the_value_is_the_loss_function_on_the_feature_render(scene, tmp_path):
    tr = Trainer(scene, _config(1, 1.0), tmp_path / "v")
    term = next(t for t in tr.terms if t.name == "depth_var")
    m, k = tr.model, 2
    tgt = tr.cache.get(k, 0.5)
    out, _ = frame_render_fwd(m, k, tgt.K, tgt.width, tgt.height)
    v, _ = term.fwd(TermInputs(out, tgt.image, None, m, k, None))
    # the same with the public functions: scene at the frame's time, features, a float64 render
    ri, _ = render_inputs_fwd({n: p for n, p in m.params.items() if n.startswith(("static.", "dynamic."))},
                              float(m.times[k]), m.config.deform)
    pose = m.mid_pose(k)
    feats, _ = z_features_fwd(ri["means"], pose)
    K = scale_intrinsics(m.Ks[k], tgt.width / m.widths[k], tgt.height / m.heights[k])
    o, _ = render_fwd(ri["means"], ri["quats"], ri["scales"], ri["opacities"], feats, pose, K, tgt.width, tgt.height,
                      np.zeros(3), m.config.render)
    expect = depth_variance_fwd(o["image"][..., 0], o["image"][..., 1], o["alpha"])[0]
    assert v == pytest.approx(expect, rel=1e-12) and v > 0
    # D of the feature render is the render's own depth sum
    np.testing.assert_allclose(o["image"][..., 0], o["depth"], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("block", ["static.means", "dynamic.means", "static.opacity_logits", "dynamic.deform_means"])
def test_its_gradient_is_downhill(scene, tmp_path, block):
    # a step of the block against the term's gradient lowers it; central differences along it agree
    # with the gradient's squared norm to 1e-5 (a step of at most 1e-7 per entry: larger ones cross
    # a footprint's integer radius or tile, as in test_depth_prior_term)
    tr = Trainer(scene, _config(1, 1.0), tmp_path / "g")
    term = next(t for t in tr.terms if t.name == "depth_var")
    m, k = tr.model, 1
    tgt = tr.cache.get(k, 1.0)
    out, _ = frame_render_fwd(m, k, tgt.K, tgt.width, tgt.height)

    def value(params):
        return term.fwd(TermInputs(out, tgt.image, None, m.replace(params=params), k, None))

    v, saved = value(m.params)
    g = term.bwd(saved).params[block]
    assert not any(n.endswith("colors") for n in term.bwd(saved).params)
    assert np.abs(g).max() > 0
    h = 1e-7 / np.abs(g).max()
    plus = dict(m.params, **{block: m.params[block] + h * g})
    minus = dict(m.params, **{block: m.params[block] - h * g})
    slope = (value(plus)[0] - value(minus)[0]) / (2 * h)
    assert slope == pytest.approx(float(np.sum(g * g)), rel=1e-5)
    assert value(minus)[0] < v


def test_training_logs_the_term_and_it_changes_the_run(scene, tmp_path):
    a = Trainer(scene, _config(6, 2.0), tmp_path / "a")
    a.run()
    rows = a.log.rows
    vals = [r["loss_depth_var"] for r in rows]
    assert all(np.isfinite(vals)) and min(vals) > 0
    r = rows[-1]
    assert r["loss"] == pytest.approx(r["loss_photometric"] + 2.0 * r["loss_depth_var"], rel=1e-12)
    b = Trainer(scene, _config(6, 0.0), tmp_path / "b")
    b.run()
    assert not np.array_equal(a.params["static.means"], b.params["static.means"])
