"""The scene suite: photographs as textures, exact ray casting, movers and their masks, pose error."""
import dataclasses
import json

import numpy as np
import pytest

from d2gs_np.data import suite
from d2gs_np.data.io import load_scene
from d2gs_np.data.raycast import stratified_offsets
from d2gs_np.geometry.camera import project_points
from d2gs_np.geometry.se3 import se3_inverse, se3_log

TINY = dict(width=48, height=27, num_frames=4, num_test_views=2, subframes=4)
# Re-rendering with the public functions repeats the same float64 operations: only the order of the
# sub-frame sum can differ (<= 16 terms of size <= 1).
RERENDER_ATOL = 1e-12
# Ray-plane intersection in float64 at distances ~5: a few ulps of the coordinates.
DEPTH_ATOL = 1e-9


@pytest.fixture(scope="module", params=sorted(suite.SUITE))
def tiny_scene(request):
    return request.param, suite.make_suite_scene(request.param, **TINY)


def test_textures_are_photographs_in_range():
    for name in suite.TEXTURES:
        img = suite.load_texture(name)
        assert img.ndim == 3 and img.shape[2] == 3 and min(img.shape[:2]) >= 256
        assert img.min() >= 0.0 and img.max() <= 1.0
        assert img.std() > 0.05, f"{name} has no texture"
    with pytest.raises(ValueError, match="unknown texture"):
        suite.load_texture("plasma")


def test_every_suite_scene_renders_with_the_expected_content(tiny_scene):
    name, scene = tiny_scene
    assert scene.num_frames == TINY["num_frames"] and len(scene.test_frames) == 2
    moving = scene.has_moving_pixels
    assert moving == (name != "photo_room"), f"{name}: moving pixels {moving}"
    for f in scene.frames:
        assert f.image.shape == (27, 48, 3) and np.all(np.isfinite(f.image))
        assert 0.0 <= f.image.min() and f.image.max() <= 1.0
        assert f.sharp.std() > 0.03  # textured, not flat
    # blurry input differs from the sharp mid-exposure frame (exposure > 0 in every suite preset)
    assert any(np.abs(f.image - f.sharp).max() > 0.02 for f in scene.frames)


def test_crossing_card_enters_and_leaves_the_frame():
    scene = suite.make_suite_scene("crossing", **{**TINY, "num_frames": 9, "exposure_fraction": 0.0, "subframes": 1})
    covered = np.array([f.mask.mean() for f in scene.frames])
    assert covered[0] == 0.0 and covered[-1] == 0.0 and covered.max() > 0.02


def test_big_mover_covers_about_a_quarter_of_the_frame():
    scene = suite.make_suite_scene("big_mover", **{**TINY, "exposure_fraction": 0.0, "subframes": 1})
    covered = np.mean([f.mask.mean() for f in scene.frames])
    assert 0.15 < covered < 0.5


def test_masks_are_exactly_where_movers_change_the_image():
    cfg = suite.resolve("cube_sign", **TINY)
    world = suite.build_suite_world(cfg)
    still = dataclasses.replace(world, movers=())
    K = suite._intrinsics(cfg)
    T = suite.suite_camera_pose(world, 0.3)
    img, mask = suite.render_suite_view(world, T, 0.3, K, 48, 27, 2)
    img0, mask0 = suite.render_suite_view(still, T, 0.3, K, 48, 27, 2)
    assert mask.any() and not mask0.any()
    np.testing.assert_array_equal(img[~mask], img0[~mask])
    assert np.abs(img[mask] - img0[mask]).max() > 0.05


def test_depth_map_is_the_exact_ray_cast_depth_of_the_back_wall():
    cfg = suite.resolve("photo_room", **TINY)
    world = suite.build_suite_world(cfg)
    K = suite._intrinsics(cfg)
    T = suite.suite_camera_pose(world, 0.5)
    depth = suite.suite_depth_map(world, T, 0.5, K, 48, 27)
    back = min(world.patches, key=lambda p: p.centre[2])
    # points on the back wall projected into the camera: their pixel's depth is their camera z
    pts = np.array([[x, y, back.centre[2]] for x in (-0.9, 0.0, 0.7) for y in (1.2, 1.8)])
    uv, z = project_points(pts, T, K)
    i, j = np.floor(uv[:, 1]).astype(int), np.floor(uv[:, 0]).astype(int)
    # move each point to its pixel centre on the wall plane, then compare depths exactly
    c = se3_inverse(T)[:3, 3]
    Rt = T[:3, :3].T
    for (ii, jj) in zip(i, j):
        d = Rt @ np.linalg.solve(K, [jj + 0.5, ii + 0.5, 1.0])
        s = (back.centre[2] - c[2]) / d[2]
        assert abs(depth[ii, jj] - s) < DEPTH_ATOL


def test_blurry_frame_is_the_mean_of_its_subframes():
    cfg = suite.resolve("wall_disk", **TINY)
    scene = suite.generate_suite(cfg)
    world = suite.build_suite_world(cfg)
    K = suite._intrinsics(cfg)
    k = 2
    tk = scene.frames[k].time
    tau = cfg.exposure_fraction / (cfg.num_frames - 1)
    ts = tk + (np.linspace(0, 1, cfg.subframes) - 0.5) * tau
    acc = np.zeros((27, 48, 3))
    for t, o in zip(ts, stratified_offsets(cfg.subframes)):  # each sub-frame's rays shifted in their cells
        acc += suite.render_suite_view(world, suite.suite_camera_pose(world, t), t, K, 48, 27, cfg.blur_supersample,
                                       o)[0]
    np.testing.assert_allclose(scene.frames[k].image, acc / len(ts), atol=RERENDER_ATOL)
    sharp = suite.render_suite_view(world, suite.suite_camera_pose(world, tk), tk, K, 48, 27, cfg.supersample)[0]
    np.testing.assert_allclose(scene.frames[k].sharp, sharp, atol=RERENDER_ATOL)
    # the true depth: through the pixel centres from the true mid-exposure pose at the frame's time
    depth = suite.suite_depth_map(world, suite.suite_camera_pose(world, tk), tk, K, 48, 27)
    np.testing.assert_array_equal(scene.frames[k].depth, depth)
    T = scene.test_frames[1].cam_T_world
    np.testing.assert_array_equal(scene.test_frames[1].depth,
                                  suite.suite_depth_map(world, T, scene.test_frames[1].time, K, 48, 27))
    np.testing.assert_allclose(scene.frames[k].gt_exposure_start, suite.suite_camera_pose(world, ts[0]), atol=1e-12)


def test_sharp_variant_has_identical_input_and_truth():
    scene = suite.make_suite_scene("cube_sign", **{**TINY, "exposure_fraction": 0.0, "subframes": 1,
                                                        "rot_noise_deg": 0.0, "trans_noise": 0.0})
    for f in scene.frames:
        np.testing.assert_array_equal(f.image, f.sharp)
        np.testing.assert_array_equal(f.cam_T_world, f.gt_cam_T_world)


@pytest.mark.parametrize("drift", [0.0, 0.5, 1.0])
def test_pose_error_has_the_requested_rms_and_drift(drift):
    rng = np.random.default_rng(0)
    n = 400
    delta = suite.pose_errors(n, 0.75, 0.08, drift, rng)
    rot = np.linalg.norm(delta[:, 3:], axis=1)
    trans = np.linalg.norm(delta[:, :3], axis=1)
    np.testing.assert_allclose(np.sqrt(np.mean(rot ** 2)), np.deg2rad(0.75), rtol=1e-12)
    np.testing.assert_allclose(np.sqrt(np.mean(trans ** 2)), 0.08, rtol=1e-12)
    # lag-1 autocorrelation: ~0 for i.i.d. error, ~1 for a random walk, in between for a mix
    x = delta[:, 3]
    r1 = np.corrcoef(x[:-1], x[1:])[0, 1]
    if drift == 0.0:
        assert abs(r1) < 0.2
    elif drift == 1.0:
        assert r1 > 0.9
    else:
        assert 0.2 < r1 < 0.9


def test_given_poses_carry_the_pose_error_of_the_preset():
    cfg = suite.resolve("cube_sign", **{**TINY, "num_frames": 12})
    scene = suite.generate_suite(cfg)
    world = suite.build_suite_world(cfg)
    d = np.array([se3_log(f.cam_T_world @ se3_inverse(f.gt_cam_T_world)) for f in scene.frames])
    rms_rot = np.sqrt(np.mean(np.sum(d[:, 3:] ** 2, axis=1)))
    np.testing.assert_allclose(rms_rot, np.deg2rad(cfg.rot_noise_deg), rtol=1e-9)
    assert scene.scene_scale == world.depth


def test_deterministic_for_a_seed_and_different_across_seeds():
    a = suite.make_suite_scene("cube_sign", seed=1, **TINY)
    b = suite.make_suite_scene("cube_sign", seed=1, **TINY)
    c = suite.make_suite_scene("cube_sign", seed=2, **TINY)
    np.testing.assert_array_equal(a.frames[1].image, b.frames[1].image)
    np.testing.assert_array_equal(a.frames[1].cam_T_world, b.frames[1].cam_T_world)
    assert not np.array_equal(a.frames[1].cam_T_world, c.frames[1].cam_T_world)


def test_write_and_load_round_trip(tmp_path):
    path = suite.write_suite_scene(tmp_path / "s", "wall_disk", 0, **TINY)
    scene = load_scene(path)
    assert scene.num_frames == TINY["num_frames"] and scene.has_masks and scene.has_sharp
    cfg = json.loads((path / "suite_config.json").read_text())
    assert cfg["family"] == "wall_disk" and cfg["width"] == 48


def test_a_modelled_depth_prior_leaves_the_video_as_it_was_and_follows_the_truth():
    base = suite.make_suite_scene("crossing", 0, **TINY)
    rel = 0.1
    video = suite.make_suite_scene("crossing", 0, depth_prior="video", prior_edge_px=0.0, prior_rel_error=rel, **TINY)
    mono = suite.make_suite_scene("crossing", 0, depth_prior="monocular", prior_edge_px=0.0, prior_rel_error=0.0,
                                  **TINY)
    for a, b, c in zip(base.frames, video.frames, mono.frames):
        assert np.array_equal(a.image, b.image) and np.array_equal(a.mask, b.mask)  # its own random stream
        assert np.array_equal(a.cam_T_world, c.cam_T_world) and a.depth_prior is None
        hit = np.isfinite(a.depth)
        assert np.array_equal(np.isfinite(b.depth_prior), hit) and np.all(c.depth_prior[hit] > 0)
    # "video": one scale for the clip, times a smooth error of the given log standard deviation
    logs = [np.log(b.depth_prior / a.depth)[np.isfinite(a.depth)] for a, b in zip(base.frames, video.frames)]
    clip_scale = np.exp(np.median(np.concatenate(logs)))
    for lg in logs:
        # a smooth field over a 48 px frame has few degrees of freedom: its frame mean wanders by
        # about its own standard deviation, so the bound is 3 sigma, not a tight one
        assert abs(np.median(lg) - np.log(clip_scale)) < 3 * rel
        assert 0.3 * rel < np.std(lg) < 3 * rel
    # "monocular" without edge blur or error: exactly a disparity up to a positive scale and a shift
    for a, c in zip(base.frames, mono.frames):
        hit = np.isfinite(a.depth)
        x = 1.0 / a.depth[hit]
        A = np.stack([x, np.ones_like(x)], axis=1)
        (scale, shift), *_ = np.linalg.lstsq(A, c.depth_prior[hit], rcond=None)
        assert scale > 0 and np.max(np.abs(A @ (scale, shift) - c.depth_prior[hit])) < 1e-9


def test_a_shared_prior_error_repeats_on_every_frame_and_leaves_the_rest_as_it_was():
    kw = dict(depth_prior="video", prior_edge_px=0.0, prior_rel_error=0.1, **TINY)
    own = suite.make_suite_scene("crossing", 0, **kw)
    none = suite.make_suite_scene("crossing", 0, prior_shared_error=0.0, **kw)
    half = suite.make_suite_scene("crossing", 0, prior_shared_error=0.5, **kw)
    full = suite.make_suite_scene("crossing", 0, prior_shared_error=1.0, **kw)
    logs = {n: [np.log(b.depth_prior / b.depth) for b in sc.frames] for n, sc in
            (("own", own), ("half", half), ("full", full))}
    for a, b in zip(own.frames, none.frames):  # a share of 0 draws nothing more: the same priors
        np.testing.assert_array_equal(a.depth_prior, b.depth_prior)
    hit = np.isfinite(own.frames[0].depth) & np.isfinite(own.frames[1].depth)

    def corr(lg):  # the correlation of two frames' log errors over the pixels both hit
        return np.corrcoef(lg[0][hit], lg[1][hit])[0, 1]
    # all shared: every frame's error the same field (one clip scale), to rounding; half: between
    assert np.max(np.abs(logs["full"][0][hit] - logs["full"][1][hit])) < 1e-12
    assert abs(corr(logs["own"])) < corr(logs["half"]) < 0.999


@pytest.mark.parametrize("bad, match", [
    (dict(family="moon_base"), "family"),
    (dict(depth_prior="lidar"), "SuiteConfig.depth_prior"),
    (dict(prior_rel_error=-0.1), "prior_rel_error"),
    (dict(prior_shared_error=1.5), "prior_shared_error"),
    (dict(exposure_fraction=1.5), "exposure_fraction"),
    (dict(rot_noise_deg=-1.0), "pose noise"),
    (dict(drift=2.0), "drift"),
    (dict(width=8), "width"),
    (dict(exposure_fraction=0.5, subframes=1), "subframes"),
])
def test_bad_config_is_rejected_with_a_clear_error(bad, match):
    with pytest.raises(ValueError, match=match):
        suite.SuiteConfig(**bad)


def test_unknown_preset_or_override_is_rejected():
    with pytest.raises(ValueError, match="unknown suite preset"):
        suite.resolve("dynamic")
    with pytest.raises(TypeError, match="unknown SuiteConfig override"):
        suite.resolve("cube_sign", shaky=True)
