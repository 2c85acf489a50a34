"""The random training background (train/background.py): the re-composite is exactly a render
over the drawn background, its alpha cotangent matches central differences, and a training step
with it computes the gradient of a step rendered over that background."""
import dataclasses

import numpy as np
import pytest

from d2gs_np.data.synthetic import make_scene
from d2gs_np.render import RenderConfig
from d2gs_np.render.api import render_fwd
from d2gs_np.train import trainer as trainer_module
from d2gs_np.train.background import background_rng, composite_bwd, composite_fwd
from d2gs_np.train.config import ExperimentConfig, TrainConfig
from d2gs_np.train.trainer import Trainer
from render_fixtures import random_scene


def test_composite_alpha_cotangent_matches_central_differences():
    rng = np.random.default_rng(0)
    image, alpha = rng.random((5, 7, 3)), rng.random((5, 7))
    bg, b0, w = rng.random(3), rng.random(3), rng.normal(size=(5, 7, 3))
    v_alpha = composite_bwd(w, bg, b0)
    h, fd = 1e-6, np.zeros_like(alpha)
    for idx in np.ndindex(alpha.shape):
        a_p, a_m = alpha.copy(), alpha.copy()
        a_p[idx] += h
        a_m[idx] -= h
        fd[idx] = (np.sum(w * composite_fwd(image, a_p, bg, b0)) - np.sum(w * composite_fwd(image, a_m, bg, b0))) / (2 * h)
    # the composite is linear in alpha, so the central difference is exact up to rounding:
    # |w| ~ 1, sums of 3 terms of size 1, divided by 2h = 2e-6 -> about 1e-16 / 1e-6 = 1e-10
    np.testing.assert_allclose(v_alpha, fd, rtol=0, atol=1e-8)


@pytest.mark.parametrize("raster_float32", [False, True])
def test_composite_equals_a_render_over_the_background(raster_float32):
    rng = np.random.default_rng(1)
    scene = random_scene(rng, 40, 32, 24)
    cfg = RenderConfig(raster_float32=raster_float32)
    b0, bg = np.array([0.2, 0.0, 0.7]), rng.random(3)
    over_b0, _ = render_fwd(**dict(scene, background=b0), config=cfg)
    over_bg, _ = render_fwd(**dict(scene, background=bg), config=cfg)
    assert 0.05 < over_b0["alpha"].mean() < 0.98, "the scene must leave the background partly visible"
    moved = composite_fwd(over_b0["image"], over_b0["alpha"], bg, b0)
    # float64: rounding of one multiply-add per pixel; float32 rasterisation: its own rounding of
    # the transmittance (~1e-7 relative, colours O(1)) enters both renders differently
    tol = 1e-5 if raster_float32 else 1e-12
    np.testing.assert_allclose(moved, over_bg["image"], rtol=0, atol=tol)


def test_a_step_with_a_random_background_is_a_step_rendered_over_it(tmp_path, monkeypatch):
    """The trainer's re-composite and its alpha cotangent: the gradient a step hands the optimiser
    equals that of the same step with the drawn colour as the model's fixed background. The
    dynamic blurry scene runs the blur model, the backward subset of views and the deformation."""
    scene = make_scene("dynamic", 0, width=48, height=27, num_frames=6)
    seen = []

    def record(grads, *args, **kwargs):
        seen.append({n: np.array(g) for n, g in grads.items()})
        return real(grads, *args, **kwargs)

    real = trainer_module.optimiser_step
    monkeypatch.setattr(trainer_module, "optimiser_step", record)
    base = dict(iters=12, quiet=True, eval_every=0, log_every=1, checkpoint_every=0, prune_every=0, seed=3,
                progressive=False, warmup_fraction=0.0, deform_fraction=0.0)
    step = 2
    bg = background_rng(3, step).random(3)
    render = RenderConfig(raster_float32=False)
    losses = []
    for train in (TrainConfig(random_background=True, **base), TrainConfig(background=tuple(bg), **base)):
        tr = Trainer(scene, ExperimentConfig(train=train, render=render), tmp_path / f"run{len(losses)}")
        losses.append(tr.step(step).loss)
    random_grads, fixed_grads = seen
    assert losses[0] == pytest.approx(losses[1], rel=1e-12, abs=1e-14)
    assert set(random_grads) == set(fixed_grads)
    top = max(np.abs(g).max() for g in fixed_grads.values())
    for name in fixed_grads:
        # one float64 re-composite per pixel against rendering over bg: rounding only (measured
        # <= 1e-14 of each block's largest entry). The quaternions' gradients are rounding noise
        # themselves (isotropic seeds: a rotation changes nothing), hence the floor at 1e-6 of the
        # largest gradient of any block.
        scale = max(np.abs(fixed_grads[name]).max(), 1e-6 * top)
        np.testing.assert_allclose(random_grads[name], fixed_grads[name], rtol=0, atol=1e-9 * scale, err_msg=name)
    assert np.abs(random_grads["static.opacity_logits"]).max() > 0


def test_the_background_draw_depends_only_on_seed_and_step():
    a, b = background_rng(0, 5).random(3), background_rng(0, 5).random(3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, background_rng(0, 6).random(3))
    assert not np.array_equal(a, background_rng(1, 5).random(3))


def test_random_background_must_be_a_bool():
    with pytest.raises((TypeError, ValueError), match="random_background"):
        TrainConfig(random_background="yes")
    assert dataclasses.replace(TrainConfig(), random_background=True).random_background is True


def test_composite_at_alpha_zero_and_one_is_the_background_and_the_render():
    """The extremes: where nothing is rendered (alpha 0) the pixel is the drawn background plus
    what the render put there, where the render is opaque (alpha 1) the background is gone and
    alpha's cotangent is still finite (the composite is linear in alpha)."""
    image = np.array([[[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]]])
    alpha = np.array([[0.0, 1.0]])
    bg, b0 = np.array([0.9, 0.5, 0.1]), np.zeros(3)
    out = composite_fwd(image, alpha, bg, b0)
    np.testing.assert_array_equal(out[0, 0], image[0, 0] + bg)
    np.testing.assert_array_equal(out[0, 1], image[0, 1])
    v = composite_bwd(np.ones_like(image), bg, b0)
    np.testing.assert_array_equal(v, np.full((1, 2), -bg.sum()))
