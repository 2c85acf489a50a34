"""Deformation initialised from mask tracks puts dynamic seeds inside the masks at other times."""
import numpy as np
import pytest

from d2gs_np.data.synthetic import make_scene
from d2gs_np.geometry.camera import project_points
from d2gs_np.scene.deformation import DeformConfig, deform_fwd
from d2gs_np.scene.initialize import InitConfig, initialize_points
from d2gs_np.scene.motion_init import MotionInitConfig, initialize_deformation, mask_components, track_components


def _inside_fraction(scene, means, coefs, cfg):
    """Share of (seed, frame) pairs whose deformed mean projects inside that frame's mask."""
    n = means.shape[0]
    hits = []
    for f in scene.frames:
        q = np.tile([1.0, 0, 0, 0], (n, 1))
        (m, _, _), _ = deform_fwd(means, q, np.zeros((n, 3)), coefs, np.zeros(coefs.shape[:2] + (4,)),
                                  np.zeros(coefs.shape), f.time, cfg)
        uv, z = project_points(m, f.cam_T_world, f.K)
        j, i = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 0) & (j >= 0) & (j < f.width) & (i >= 0) & (i < f.height)
        inside = np.zeros(n, bool)
        inside[ok] = f.mask[i[ok], j[ok]]
        hits.append(inside)
    return float(np.mean(hits))


def test_tracked_deformation_follows_the_masks():
    scene = make_scene("sharp", 0, width=96, height=54, num_frames=10)
    rng = np.random.default_rng(0)
    _, _, d_pts, _, info = initialize_points(scene, InitConfig(dynamic_points=300), rng)
    cfg = DeformConfig()
    means, coefs, minfo = initialize_deformation(scene, d_pts, info["dynamic_source_frames"],
                                                 info["dynamic_source_pixels"], cfg, MotionInitConfig())
    assert minfo["num_tracks"] >= 1 and minfo["num_tracked_seeds"] > 0.8 * len(d_pts)
    zero = np.zeros_like(coefs)
    before = _inside_fraction(scene, d_pts, zero, cfg)
    after = _inside_fraction(scene, means, coefs, cfg)
    # Without motion a seed lies in the masks of the few frames where its object was; with the
    # tracked motion it should follow the object through most of the clip.
    assert after > 0.7, f"only {after:.2f} of seed/frame pairs inside the masks"
    assert after > before + 0.3, f"tracked {after:.2f} vs static {before:.2f}"


def test_disabled_or_maskless_gives_zero_coefficients():
    scene = make_scene("static", 0, width=48, height=27, num_frames=4)
    pts = np.zeros((5, 3)) + [0, 0, 3.0]
    means, coefs, info = initialize_deformation(scene, pts, np.zeros(5, int), np.full((5, 2), 10.0),
                                                DeformConfig(), MotionInitConfig())
    np.testing.assert_array_equal(means, pts)
    assert not coefs.any() and info["num_tracked_seeds"] == 0


def test_components_and_tracking():
    m0 = np.zeros((20, 30), bool)
    m0[2:6, 2:6] = True
    m0[10:15, 20:25] = True
    m1 = np.zeros_like(m0)
    m1[3:7, 4:8] = True
    m1[11:16, 18:23] = True
    m1[0, 29] = True  # one-pixel noise, dropped by min_area
    labs, cents = [], []
    for m in (m0, m1):
        lab, c, area = mask_components(m, min_area=4)
        labs.append(lab)
        cents.append(c)
    assert len(cents[0]) == 2 and len(cents[1]) == 2
    np.testing.assert_allclose(cents[0][0], [4.0, 4.0])  # pixels 2..5 -> centres 2.5..5.5 -> mean 4
    ids = track_components(cents, gate=10.0)
    # Each object keeps its id: nearest centroids are linked.
    for c in range(2):
        j = ids[1][c]
        prev = cents[0][list(ids[0]).index(j)]
        assert np.linalg.norm(cents[1][c] - prev) < 4.0
    assert track_components(cents, gate=0.1)[1].min() >= 2  # gated: all new tracks


@pytest.mark.parametrize("bad", [dict(min_area_fraction=1.5), dict(max_jump_fraction=0.0), dict(ridge=-1.0), dict(ridge=0.0)])
def test_config_validation(bad):
    with pytest.raises(ValueError, match="MotionInitConfig"):
        MotionInitConfig(**bad)
