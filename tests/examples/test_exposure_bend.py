"""examples/exposure_bend.py: its bend estimates are ``exposure_bend_px`` of the scene's true and given
poses, its true bend the geodesic midpoint's distance from the true mid pose (zero for a path that
does not bend, below the blur's length otherwise), its "auto" line the run's decision; a scene
without true exposures is refused."""
import numpy as np
import pytest

from d2gs_np.blur.endpoints import exposure_bend_px
from d2gs_np.data.io import load_scene, write_scene
from d2gs_np.data.suite import write_suite_scene
from example_fixtures import load_example

KW = dict(width=96, height=54, num_frames=8, subframes=4, num_test_views=0)


@pytest.fixture(scope="module")
def crossing(tmp_path_factory):
    return write_suite_scene(tmp_path_factory.mktemp("bend") / "crossing", "crossing", seed=0, **KW)


def test_the_table_is_the_library_s_bend_of_each_set_of_poses(crossing):
    mod = load_example("exposure_bend.py")
    r = mod.bend_table(crossing)
    scene = load_scene(crossing)
    f = scene.frames
    depth = float(np.median(np.concatenate([x.depth[np.isfinite(x.depth)] for x in f])))
    times = np.array([x.time for x in f])
    for key, poses in (("from_true", [x.gt_cam_T_world for x in f]), ("from_given", [x.cam_T_world for x in f])):
        expect = np.median(exposure_bend_px(np.stack(poses), times, scene.exposure_fraction, f[0].K[0, 0], depth))
        assert r[key] == pytest.approx(float(expect), rel=1e-12), key
    assert 0.0 < r["true_bend"] < r["blur"]  # a shaken camera bends, by less than it moves
    assert r["auto"].startswith("exposure path: ")


def test_a_straight_exposure_has_no_true_bend_and_a_scene_without_exposures_is_refused(tmp_path):
    mod = load_example("exposure_bend.py")
    steady = write_suite_scene(tmp_path / "steady", "wall_disk", seed=0, shake=0.0, **KW)
    r = mod.bend_table(steady)
    # no shake: a smooth pan and sway, bending far less than a pixel within an exposure
    assert r["true_bend"] < 0.05 and r["blur"] > 1.0
    scene = load_scene(steady)
    for fr in scene.frames:
        fr.gt_exposure_start = None
    write_scene(scene, tmp_path / "no_exposures")
    with pytest.raises(ValueError, match="gt_exposure_start"):
        mod.bend_table(tmp_path / "no_exposures")
