"""examples/data_ceiling.py: re-rendering a suite scene's frames at its own supersampling gives back
its stored sharp frames (up to their 8-bit rounding), finer sampling scores below that on the
aliased floor, and a folder without suite_config.json is refused."""
import pytest

from d2gs_np.data.suite import write_suite_scene
from example_fixtures import load_example

KW = dict(width=64, height=36, num_frames=3, subframes=2, num_test_views=1)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return write_suite_scene(tmp_path_factory.mktemp("ceiling") / "wall_disk", "wall_disk", seed=0, **KW)


def test_its_own_sampling_reproduces_the_sharp_frames_and_finer_sampling_scores_lower(scene_dir):
    mod = load_example("data_ceiling.py")
    own = mod.ceiling(scene_dir, supersample=2)
    # 8-bit PNG rounding alone: uniform error of 1/255 per step, PSNR = 20 log10(255 sqrt 12) = 58.9 dB;
    # a wrong pose, time or intrinsics would cost tens of dB
    assert own["frames"] == 3 and own["psnr"] > 55.0
    fine = mod.ceiling(scene_dir, supersample=6)
    assert fine["psnr"] < own["psnr"] - 10.0  # the stored frames' aliasing is what finer sampling removes
    assert fine["psnr_bottom"] < fine["psnr_top"]  # most of it on the gravel floor at the bottom
    assert mod.ceiling(scene_dir, supersample=2, every=2)["frames"] == 2


def test_a_folder_without_its_suite_config_is_refused(tmp_path):
    mod = load_example("data_ceiling.py")
    with pytest.raises(FileNotFoundError, match="suite_config.json is missing"):
        mod.ceiling(tmp_path)
