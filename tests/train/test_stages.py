"""Tests of the step planner's frame order (d2gs_np/train/stages.py): the uniform permutation and
the sharpness-weighted draws of ``TrainConfig.frame_sampling``."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from d2gs_np.train.config import ExperimentConfig, TrainConfig
from d2gs_np.train.stages import Planner, frame_probabilities, make_stages, sharpness


def _planner(frame_p=None, num_frames=6, seed=0):
    cfg = ExperimentConfig(train=TrainConfig(iters=100, seed=seed))
    return Planner(cfg, [(32, 24)] * num_frames, make_stages(cfg.train, False), frame_p)


def _texture(seed, blur=0):
    img = np.random.default_rng(seed).random((40, 50, 3))
    return uniform_filter(img, size=(blur, blur, 1)) if blur else img


def test_uniform_order_visits_every_frame_once_per_epoch_and_depends_only_on_seed_and_step():
    p = _planner()
    for epoch in range(5):
        frames = [p.frame_for_step(epoch * 6 + i) for i in range(6)]
        assert sorted(frames) == list(range(6))
    assert [_planner().frame_for_step(s) for s in range(30)] == [p.frame_for_step(s) for s in range(30)]
    assert [_planner(seed=1).frame_for_step(s) for s in range(30)] != [p.frame_for_step(s) for s in range(30)]


def test_sharpness_falls_with_blur_and_is_zero_on_a_flat_image():
    sharp = _texture(0)
    values = [sharpness(_texture(0, b)) for b in (0, 3, 5, 9)]
    assert all(a > b for a, b in zip(values, values[1:])), values
    assert sharpness(np.full((8, 8, 3), 0.3)) == 0.0
    # luminance of forward differences, by hand on a 2 x 2 image
    img = np.zeros((2, 2, 3))
    img[0, 1] = 1.0  # luminance 1 at (0, 1): row differences [[0, -1]], column differences [[1], [0]]
    assert sharpness(img) == pytest.approx(0.5 * (0.5 + 0.5), rel=1e-15)
    with pytest.raises(ValueError, match="H, W >= 2"):
        sharpness(sharp[:1])


def test_frame_probabilities_mix_uniform_and_sharpness():
    images = [_texture(0), _texture(0, 5), _texture(0, 9)]
    s = np.array([sharpness(im) for im in images])
    for share in (0.0, 0.5, 1.0):
        p = frame_probabilities(images, share)
        np.testing.assert_allclose(p, (1 - share) / 3 + share * s / s.sum(), rtol=1e-14)
    assert frame_probabilities(images, 0.5)[0] > 1 / 3 > frame_probabilities(images, 0.5)[2]
    np.testing.assert_array_equal(frame_probabilities([np.zeros((4, 4, 3))] * 2, 1.0), [0.5, 0.5])
    with pytest.raises(ValueError, match="share"):
        frame_probabilities(images, 1.5)


def test_weighted_draws_follow_the_probabilities_and_are_reproducible():
    prob = np.array([0.4, 0.3, 0.1, 0.1, 0.05, 0.05])
    p = _planner(prob)
    frames = np.array([p.frame_for_step(s) for s in range(6 * 2000)])
    freq = np.bincount(frames, minlength=6) / frames.size
    # 12 000 draws: the standard error of a frequency is <= sqrt(0.25 / 12 000) = 0.0046; 0.02 is > 4 of them
    np.testing.assert_allclose(freq, prob, atol=0.02)
    again = _planner(prob)
    assert [again.frame_for_step(s) for s in range(500, 560)] == list(frames[500:560])


def test_planner_refuses_bad_probabilities():
    for bad in ([0.5, 0.5], [0.5, 0.5, 0, 0, 0, 0.1], [1.1, -0.1, 0, 0, 0, 0]):
        with pytest.raises(ValueError, match="frame_p"):
            _planner(np.array(bad))
    for bad in (dict(frame_sampling="sharp"), dict(sharpness_share=-0.1), dict(sharpness_share=True)):
        with pytest.raises(ValueError, match="frame_sampling|sharpness_share"):
            TrainConfig(**bad)
