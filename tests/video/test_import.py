"""d2gs import-video: decoding, registration, masks, errors, the seeding hook (docs/dataset_format.md §8)."""
import json

import cv2
import numpy as np
import pytest

from d2gs_np.data.io import load_scene
from d2gs_np.data.suite import build_suite_world, make_suite_scene, render_suite_view, resolve
from d2gs_np.geometry.camera import camera_center, make_intrinsics
from d2gs_np.geometry.so3 import so3_exp, so3_log
from d2gs_np.evaluation.metrics import ate
from d2gs_np.video.decode import read_frames
from d2gs_np.video.importer import ImportConfig, import_video
from d2gs_np.video.sfm import register_video

from import_fixtures import SMALL, H, W, depth as _depth, suite_scene as _scene, write_folder as _write_folder


def test_image_folder_import_registers_the_blurry_suite_frames(tmp_path):
    """Blurry frames only, focal unknown: the trajectory within 2 % of the scene depth after Sim(3) alignment."""
    sc = _scene("photo_room")
    rep = import_video(_write_folder(sc, tmp_path / "frames"), tmp_path / "scene", log=None)
    out = load_scene(tmp_path / "scene")
    assert out.num_frames == sc.num_frames and out.has_masks and out.points3d is not None
    assert [f.time for f in out.frames] == pytest.approx(np.linspace(0, 1, sc.num_frames))
    gt = np.stack([f.gt_cam_T_world for f in sc.frames])
    est = np.stack([f.cam_T_world for f in out.frames])
    assert ate(est, gt) / _depth("photo_room") < 0.02
    assert json.loads((tmp_path / "scene" / "import_report.json").read_text())["frames"] == sc.num_frames
    assert rep["reprojection_rms_px"] < 1.0
    # a static scene: the motion masks stay (almost) empty
    assert np.mean([f.mask.mean() for f in out.frames]) < 0.03


def test_video_file_round_trip(tmp_path):
    sc = _scene("photo_room")
    path = tmp_path / "clip.avi"
    He = H - H % 2  # MJPG keeps an even height: crop the last row
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, He))
    assert w.isOpened()
    w.set(cv2.VIDEOWRITER_PROP_QUALITY, 100)
    for f in sc.frames:
        w.write(np.ascontiguousarray(np.round(f.image[:He, :, ::-1] * 255).astype(np.uint8)))
    w.release()
    dec = read_frames(path, stride=2)
    assert len(dec.images) == 12 and dec.source_index == list(range(0, 24, 2)) and dec.fps == pytest.approx(10.0)
    assert dec.images[0].shape == (He, W, 3) and dec.images[0].dtype == np.uint8
    assert np.abs(dec.images[3].astype(float) / 255 - sc.frames[6].image[:He]).mean() < 0.05  # lossy codec
    dec = read_frames(path, size=(120, 68), start=0.3, end=1.0)  # frames 3..9 at 10 fps
    assert dec.source_index == list(range(3, 10)) and dec.images[0].shape == (68, 120, 3)
    import_video(path, tmp_path / "scene", ImportConfig(masks=False), log=None)
    out = load_scene(tmp_path / "scene")
    gt = np.stack([f.gt_cam_T_world for f in sc.frames])
    assert ate(np.stack([f.cam_T_world for f in out.frames]), gt) / _depth("photo_room") < 0.03
    assert not any(f.mask.any() for f in out.frames)


def test_pure_rotation_is_detected_and_falls_back(tmp_path):
    cfg = resolve("photo_room", 0, **SMALL)
    world = build_suite_world(cfg)
    K = make_intrinsics(200.0, 200.0, 120.0, 67.5)
    from d2gs_np.geometry.camera import look_at
    T0 = look_at(world.eye, world.target)
    rots = [so3_exp(np.array([0.0, 0.03 * k, 0.005 * k])) for k in range(6)]
    poses = []
    for R in rots:
        T = T0.copy()
        T[:3, :3] = R @ T0[:3, :3]
        T[:3, 3] = R @ T0[:3, 3]  # same centre
        poses.append(T)
    imgs = [render_suite_view(world, T, 0.0, K, W, H)[0] for T in poses]
    res = register_video(imgs, K, refine_focal=False, log=None)
    assert res.rotation_only
    assert np.allclose(camera_center(res.cam_T_world), 0.0)
    for k in range(6):  # relative rotations from frame 0 within 0.2 deg
        Rrel_est = res.cam_T_world[k, :3, :3] @ res.cam_T_world[0, :3, :3].T
        Rrel = poses[k][:3, :3] @ poses[0][:3, :3].T
        assert np.degrees(np.linalg.norm(so3_log(Rrel_est.T @ Rrel))) < 0.2


def test_errors_before_work(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        import_video(tmp_path / "nope.mp4", tmp_path / "o", log=None)
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video at all" * 10)
    with pytest.raises(ValueError, match="could not open|no frame could be decoded"):
        import_video(bad, tmp_path / "o", log=None)
    few = tmp_path / "few"
    few.mkdir()
    for k in range(2):
        cv2.imwrite(str(few / f"{k}.png"), np.zeros((20, 20, 3), np.uint8))
    with pytest.raises(ValueError, match="only 2 frame"):
        import_video(few, tmp_path / "o", log=None)
    with pytest.raises(ValueError, match="apply to a video file"):
        read_frames(few, start=1.0)
    with pytest.raises(ValueError, match="must be >= 1"):
        read_frames(few, stride=0)
    out = tmp_path / "full"
    out.mkdir()
    (out / "x").write_text("x")
    with pytest.raises(ValueError, match="not empty"):
        import_video(few, out, log=None)


def test_untextured_and_unregistrable_frames_are_named(tmp_path):
    sc = _scene("photo_room")
    imgs = [f.image for f in sc.frames[:6]]
    K = sc.frames[0].K
    flat = list(imgs)
    flat[3] = np.full_like(imgs[0], 0.5)
    with pytest.raises(ValueError, match=r"frames \[3\] have no usable texture"):
        register_video(flat, K, log=None)
    # a frame of another place: textured (smoothed noise), but nothing matches the rest. (Six frames
    # of photo_room keep at most ~1.5 px of parallax between the KLT tracks: they may count as a pure
    # rotation, whose fallback names the pair it cannot chain.)
    noise = cv2.GaussianBlur(np.random.default_rng(0).random((H, W, 3)), (0, 0), 1.0)
    other = list(imgs) + [noise]
    with pytest.raises(ValueError, match=r"(could not register frames|frames) \[6\]|frames 5 and 6: too few matches"):
        register_video(other, K, log=None)


def test_sparse_points_seed_the_initialisation(tmp_path):
    from d2gs_np.scene.config import InitConfig
    from d2gs_np.scene.initialize import initialize_points

    sc = _scene("photo_room")
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, 50), rng.uniform(0.5, 1.5, 50), rng.uniform(-2, -1, 50)]
    sc_pts = make_suite_scene("photo_room", 0, **SMALL)
    sc_pts.points3d, sc_pts.points3d_colors = pts, np.full((50, 3), 0.25)
    cfg = InitConfig(dense_frames=0, random_fill_points=10, dynamic_points=0)
    s_pts, cols, _, _, info = initialize_points(sc_pts, cfg, np.random.default_rng(1))
    n = info["num_static_triangulated"]
    assert 0 < n <= 50 and info["num_pairs"] == 0  # no feature matching
    assert all(np.min(np.linalg.norm(pts - p, axis=1)) == 0 for p in s_pts[:n])  # the given points
    assert np.all(cols[:n] == 0.25)
    s_def, _, _, _, info_def = initialize_points(sc, cfg, np.random.default_rng(1))
    assert info_def["num_pairs"] > 0  # without points3d: the triangulation, as before
    # a scene folder round trip keeps them
    from d2gs_np.data.io import write_scene
    write_scene(sc_pts, tmp_path / "s")
    back = load_scene(tmp_path / "s")
    np.testing.assert_allclose(back.points3d, pts)
    np.testing.assert_allclose(back.points3d_colors, np.round(0.25 * 255) / 255)


def test_register_video_with_given_tracks_is_the_same_registration():
    """register_video(tracks=klt_tracks(...)) reproduces the registration that tracks by itself (the
    importer tracks once and registers subsets), and names malformed tracks before any work."""
    from d2gs_np.pose.tracks import klt_tracks

    sc = make_suite_scene("wall_disk", 0, subframes=4, num_test_views=0, num_frames=10)
    imgs = [f.image for f in sc.frames]
    K = make_intrinsics(190.0, 190.0, W / 2, H / 2)
    a = register_video(imgs, K, log=None)
    tracks = klt_tracks(imgs)
    b = register_video(imgs, K, log=None, tracks=tracks)
    assert np.array_equal(a.cam_T_world, b.cam_T_world) and np.array_equal(a.points, b.points)
    f, t, uv, T, _ = tracks
    with pytest.raises(ValueError, match="tracks must be"):
        register_video(imgs, K, log=None, tracks=(f, t, uv))
    with pytest.raises(ValueError, match="points_per_frame"):
        register_video(imgs, K, log=None, tracks=(f, t, uv[:, :1], T, tracks[4]))
    with pytest.raises(ValueError, match="track ids"):
        register_video(imgs, K, log=None, tracks=(f, t, uv, 3, tracks[4]))
    bad = uv.copy()
    bad[5] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        register_video(imgs, K, log=None, tracks=(f, t, bad, T, tracks[4]))
    with pytest.raises(ValueError, match="no masks"):
        register_video(imgs, K, log=None, tracks=tracks, masks=[np.zeros((H, W), bool)] * len(imgs))
