"""examples/depth_prior_alignment.py: with the true poses a modelled video prior aligned to the
static points puts the seeds at the truth (to its modelled error), where the rule does not; a
scene without movers or true depth is refused."""
import pytest

from d2gs_np.data.suite import write_suite_scene
from example_fixtures import load_example

# 120x68, 8 frames, true poses: the static points are measured to a few per cent, and the prior
# carries a smooth 10 % error and 2 px edges, so the seeds' median sits within 10 % of the truth;
# the rule puts big_mover's panel (at 2, in front of a wall at 5) near 0.8 x 5 = 4, twice too deep.
KW = dict(width=120, height=68, num_frames=8, subframes=4, num_test_views=0, supersample=2,
          rot_noise_deg=0.0, trans_noise=0.0)
MEDIAN_TOL = 0.1


@pytest.fixture(scope="module")
def big_mover(tmp_path_factory):
    return write_suite_scene(tmp_path_factory.mktemp("prior") / "big_mover", "big_mover", seed=0, **KW)


def test_the_video_prior_puts_the_seeds_at_the_truth_and_the_rule_does_not(big_mover):
    ex = load_example("depth_prior_alignment.py")
    rows = ex.alignment_table(big_mover, poses="true")
    assert rows["_static"] < 0.05
    video = rows["prior (video, depth)"]
    assert video["aligned"] == "8/8" and abs(video["ratio"][0] - 1.0) < MEDIAN_TOL
    assert rows["static_median"]["ratio"][0] > 1.5  # the panel's depth is not the wall's


def test_a_scene_without_movers_is_refused(tmp_path):
    ex = load_example("depth_prior_alignment.py")
    folder = write_suite_scene(tmp_path / "room", "photo_room", seed=0, **KW)
    with pytest.raises(ValueError, match="needs true depth maps and moving pixels"):
        ex.alignment_table(folder, poses="true")
