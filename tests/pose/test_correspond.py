"""Correspondences of a video (d2gs_np/pose/correspond.py): pairs, masks, the cache, the report, ORB/AKAZE."""
import numpy as np
import pytest

from d2gs_np.pose import correspond as cs
from d2gs_np.pose.config import CorrespondConfig, FeatureConfig


def _texture(seed=0, H=120, W=200):
    import cv2
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((H, W)), (0, 0), 1.5)
    img = (img - img.min()) / (img.max() - img.min())
    return np.repeat(img[:, :, None], 3, axis=2)


def _video(n=4, shift=3):
    """n crops of one texture, each `shift` px to the right of the previous: frame j's pixel x
    shows what frame k shows at x + (j - k) shift."""
    big = _texture(W=100 + n * shift + 40)
    return [np.ascontiguousarray(big[10:90, k * shift:k * shift + 100]) for k in range(n)]


def test_pairs_of_consecutive_and_two_apart_frames_follow_the_shift():
    frames = _video()
    c = cs.correspondences(frames)
    assert [(p.k, p.j) for p in c.pairs] == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)]
    for p in c.used:
        assert p.num_matches >= 12 and 0 < p.inlier_ratio <= 1
        d = p.pts_k - p.pts_j - np.array([(p.j - p.k) * 3.0, 0.0])
        assert np.median(np.abs(d)) < 0.3
    assert len(c.used) == 5
    assert len(c.report()) == 5 and "matches of" in c.report()[0]


def test_masked_pixels_carry_no_match():
    frames = _video(3)
    masks = [np.zeros(f.shape[:2], dtype=bool) for f in frames]
    for m in masks:
        m[:, :50] = True
    c = cs.correspondences(frames, masks)
    for p in c.pairs:
        assert np.all(p.pts_k[:, 0] > 50) and np.all(p.pts_j[:, 0] > 50)
    free = cs.correspondences(frames)
    assert sum(p.num_matches for p in free.pairs) > sum(p.num_matches for p in c.pairs)


def test_a_pair_with_too_few_matches_is_reported_and_skipped():
    frames = _video(3)
    frames[2] = np.full_like(frames[2], 0.5)  # a featureless frame (lens cap, fog)
    c = cs.correspondences(frames, config=CorrespondConfig(min_pair_matches=12))
    by = {(p.k, p.j): p for p in c.pairs}
    assert by[(0, 1)].used
    assert not by[(1, 2)].used and not by[(0, 2)].used
    assert any("skipped" in line for line in c.report())


def test_cache_is_read_back_and_keyed_by_config_and_frames(tmp_path):
    frames = _video(3)
    a = cs.correspondences(frames, cache_dir=tmp_path)
    assert not a.from_cache and len(list(tmp_path.glob("correspondences_*.npz"))) == 1
    b = cs.correspondences(frames, cache_dir=tmp_path)
    assert b.from_cache and b.key == a.key
    for p, q in zip(a.pairs, b.pairs):
        assert (p.k, p.j, p.used, p.num_tentative) == (q.k, q.j, q.used, q.num_tentative)
        assert np.array_equal(p.pts_k, q.pts_k) and np.array_equal(p.pts_j, q.pts_j)
    c = cs.correspondences(frames, config=CorrespondConfig(gaps=(1,)), cache_dir=tmp_path)
    assert not c.from_cache and c.key != a.key
    frames[1] = frames[1] * 0.9
    assert cs.cache_key(frames, [None] * 3, CorrespondConfig()) != a.key


@pytest.mark.parametrize("detector", ["orb", "akaze"])
def test_binary_detectors_are_selectable(detector):
    big = _texture(W=400, H=300)
    frames = [np.ascontiguousarray(big[20:260, k * 4:k * 4 + 320]) for k in range(2)]
    fc = FeatureConfig(detector=detector, ratio=0.85)
    c = cs.correspondences(frames, config=CorrespondConfig(features=fc, gaps=(1,), min_pair_matches=8))
    p = c.pairs[0]
    assert p.used, c.report()
    assert np.median(np.abs(p.pts_k[:, 0] - p.pts_j[:, 0] - 4.0)) < 1.0


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="images"):
        cs.correspondences([np.zeros((8, 8, 3))])
    with pytest.raises(ValueError, match=r"masks\[0\]"):
        cs.correspondences([np.zeros((8, 8, 3))] * 2, [np.zeros((4, 4), bool)] * 2)
