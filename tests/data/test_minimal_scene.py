"""The minimal example scene of docs/dataset_format.md §7 loads, validates and round-trips."""
from pathlib import Path

import numpy as np

from d2gs_np.data.io import load_scene, write_scene
from d2gs_np.geometry.se3 import check_rigid

MINIMAL_SCENE = Path(__file__).resolve().parent / "minimal_scene"


def test_minimal_scene_loads_with_every_documented_field():
    scene = load_scene(MINIMAL_SCENE)
    assert scene.num_frames == 3 and len(scene.test_frames) == 1
    assert [f.time for f in scene.frames] == [0.0, 0.5, 1.0]
    assert (scene.exposure_fraction, scene.scene_scale, scene.blur_subframes) == (0.7, 4.0, 4)
    assert scene.has_masks and scene.has_moving_pixels and scene.has_sharp and scene.has_gt_poses
    for f in scene.frames:
        assert (f.width, f.height) == (16, 12)
        assert f.image.shape == (12, 16, 3) and f.image.dtype == np.float64
        assert 0.0 <= f.image.min() and f.image.max() <= 1.0
        assert f.mask.shape == (12, 16) and f.mask.dtype == np.bool_
        assert f.sharp.shape == (12, 16, 3)
        assert f.K[0, 1] == 0.0 and f.K[0, 0] > 0 and f.K[1, 1] > 0
        for T in (f.cam_T_world, f.gt_cam_T_world, f.gt_exposure_start, f.gt_exposure_end):
            check_rigid(T)
    test = scene.test_frames[0]
    assert test.file_path == "test/0000.png" and test.image.shape == (12, 16, 3)


def test_minimal_scene_round_trips_through_write_scene(tmp_path):
    scene = load_scene(MINIMAL_SCENE)
    write_scene(scene, tmp_path / "copy")
    again = load_scene(tmp_path / "copy")
    assert again.num_frames == scene.num_frames and len(again.test_frames) == 1
    for a, b in zip(scene.frames, again.frames):
        assert a.file_path == b.file_path and a.time == b.time
        np.testing.assert_allclose(b.cam_T_world, a.cam_T_world, atol=1e-12)
        np.testing.assert_array_equal(b.image, a.image)  # 8-bit PNG values survive exactly
        np.testing.assert_array_equal(b.mask, a.mask)
        np.testing.assert_allclose(b.K, a.K)
