"""Pruning rules: transparent, oversized, and dynamic Gaussians that escaped their motion masks."""
import numpy as np
import pytest

from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.deformation import deform_fwd
from d2gs_np.train import prune
from d2gs_np.train.config import PruneConfig

K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
W, H = 64, 48
# deform_fwd and dynamic_centres evaluate the same basis product; only summation order differs.
CENTRE_ATOL = 1e-12


def test_transparent_is_exact_at_the_threshold_and_finite_at_the_extremes():
    thr = 0.005
    at = np.log(thr) - np.log1p(-thr)
    logits = np.array([-np.inf, at - 1e-9, at, at + 1e-9, 0.0, 40.0, np.inf])
    np.testing.assert_array_equal(prune.transparent(logits, thr), [True, True, True, False, False, False, False])
    assert not prune.transparent(logits, 0.0).any()  # floor 0: off


def test_oversized_removes_only_axes_above_the_share_of_the_extent():
    extent = 5.0
    log_scales = np.log(np.array([[0.1, 0.1, 0.1], [0.49, 0.01, 0.01], [0.01, 0.51, 0.01], [1e-12, 1e-12, 1e-12],
                                  [1e6, 1.0, 1.0]]))
    np.testing.assert_array_equal(prune.oversized(log_scales, extent, 0.1), [False, False, True, False, True])
    assert not prune.oversized(log_scales, extent, 0.0).any()


def test_dynamic_centres_match_the_deformation_model():
    rng = np.random.default_rng(0)
    cfg = DeformConfig()
    n, k = 7, cfg.num_coefs
    base = rng.normal(size=(n, 3))
    coef = rng.normal(size=(n, k, 3)) * 0.1
    times = np.array([0.0, 0.3, 1.0])
    got = prune.dynamic_centres(base, coef, times, cfg)
    for i, t in enumerate(times):
        (means, _, _), _ = deform_fwd(base, np.tile([1.0, 0, 0, 0], (n, 1)), np.zeros((n, 3)), coef,
                                       np.zeros((n, k, 4)), np.zeros((n, k, 3)), t, cfg)
        np.testing.assert_allclose(got[i], means, atol=CENTRE_ATOL)


def _point_at_pixel(u, v, z):
    return np.array([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])


def test_outside_share_counts_in_view_frames_only():
    masks = []
    for k in range(4):
        m = np.zeros((H, W), dtype=bool)
        m[10:20, 10 + 10 * k:20 + 10 * k] = True  # a mover sliding right by 10 px a frame
        masks.append(m)
    poses = np.tile(np.eye(4), (4, 1, 1))
    Ks = np.tile(K, (4, 1, 1))
    follow = np.stack([_point_at_pixel(15.5 + 10 * k, 15.5, 3.0) for k in range(4)])  # with the mover
    stay = np.stack([_point_at_pixel(15.5, 15.5, 3.0)] * 4)  # on the mover only in frame 0
    behind = np.stack([-_point_at_pixel(15.5, 15.5, 3.0)] * 4)  # behind the camera in every frame
    at_centre = np.zeros((4, 3))  # at the camera centre: z = 0, never in view, no NaN
    centres = np.stack([follow, stay, behind, at_centre], axis=1)  # (T, N, 3)
    share, seen = prune.outside_share(centres, poses, Ks, masks, 0)
    np.testing.assert_array_equal(seen, [4, 4, 0, 0])
    np.testing.assert_allclose(share, [0.0, 0.75, 0.0, 0.0])
    # dilation by 3 px does not reach 10 px away; frames without a mask are skipped
    share, seen = prune.outside_share(centres, poses, Ks, [masks[0], None, None, masks[3]], 3)
    np.testing.assert_array_equal(seen, [2, 2, 0, 0])
    np.testing.assert_allclose(share[:2], [0.0, 0.5])


def test_escaped_removes_a_dynamic_gaussian_that_lives_on_static_pixels():
    cfg = DeformConfig()
    k = cfg.num_coefs
    times = np.linspace(0, 1, 4)
    masks = []
    for i in range(4):
        m = np.zeros((H, W), dtype=bool)
        m[20:30, 20:30] = True
        masks.append(m)
    base = np.stack([_point_at_pixel(25.5, 25.5, 3.0), _point_at_pixel(50.5, 40.5, 3.0)])
    coef = np.zeros((2, k, 3))
    poses, Ks = np.tile(np.eye(4), (4, 1, 1)), np.tile(K, (4, 1, 1))
    out = prune.escaped(base, coef, times, poses, Ks, masks, cfg, PruneConfig())
    np.testing.assert_array_equal(out, [False, True])
    off = prune.escaped(base, coef, times, poses, Ks, masks, cfg, PruneConfig(max_outside_share=0.0))
    assert not off.any()


@pytest.mark.parametrize("bad", [dict(max_scale_fraction=-1.0), dict(max_outside_share=1.5),
                                 dict(mask_dilation_px=-1), dict(max_scale_fraction=float("nan")),
                                 dict(past_schedule="yes")])
def test_bad_prune_config_is_rejected(bad):
    with pytest.raises(ValueError, match="PruneConfig"):
        PruneConfig(**bad)
