"""d2gs import-dyblurf: a Stereo Blur folder in DyBluRF's layout, made from a suite scene the way
LLFF's imgs2poses writes poses_bounds.npy, imports back to the suite's cameras
(docs/dataset_format.md §11)."""
import json

import cv2
import numpy as np
import pytest

from d2gs_np.cli import main
from d2gs_np.data.io import load_scene
from d2gs_np.data.suite import build_suite_world, generate_suite, render_suite_view, resolve, suite_depth_map
from d2gs_np.geometry.camera import cam_T_world_to_opengl_c2w
from d2gs_np.importers.colmap import ColmapCamera, ColmapImage, ColmapModel, write_model
from d2gs_np.importers.dyblurf import cam_T_world_to_llff, llff_to_cam_T_world

POSE_TOL = 1e-9  # the brief's round-trip tolerance (float64 file; rounding of two inversions remains)
BASELINE = 0.12  # stereo baseline of the fixture's right camera, world units (the suite's depth is ~4)
SIZE = dict(num_frames=6, width=64, height=36)


def _save_png(path, img):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.round(np.clip(img, 0, 1)[:, :, ::-1] * 255).astype(np.uint8))


def imgs2poses_rows(w2c_mats, hwf, bounds):
    """poses_bounds.npy rows the way LLFF's imgs2poses (DyBluRF's scripts/save_poses_nerf.py) builds
    them from COLMAP's world-to-camera matrices: c2w as (3, 5, N) with hwf, the rotation columns
    switched from COLMAP's [right, down, forward] to [down, right, backwards], each raveled row by row."""
    c2w = np.linalg.inv(w2c_mats)
    poses = c2w[:, :3, :4].transpose([1, 2, 0])
    poses = np.concatenate([poses, np.tile(np.asarray(hwf).reshape(3, 1)[..., None], [1, 1, poses.shape[-1]])], 1)
    poses = np.concatenate([poses[:, 1:2, :], poses[:, 0:1, :], -poses[:, 2:3, :], poses[:, 3:4, :],
                            poses[:, 4:5, :]], 1)
    return np.array([np.concatenate([poses[..., i].ravel(), bounds[i]], 0) for i in range(poses.shape[2])])


@pytest.fixture(scope="module")
def stereo(tmp_path_factory):
    """A DyBluRF scene folder from the photo_room suite clip: the blurry and sharp left frames, a right
    camera BASELINE to the right of each left one (rendered sharp), masks, interleaved poses."""
    root = tmp_path_factory.mktemp("dyblurf")
    config = resolve("photo_room", 0, **SIZE)
    scene, world = generate_suite(config), build_suite_world(config)
    folder = root / "dense"
    shift = np.eye(4)
    shift[0, 3] = -BASELINE  # right camera centre = left centre + BASELINE along the left camera's x
    left = [f.cam_T_world for f in scene.frames]
    right = [shift @ T for T in left]
    K, W, H = scene.frames[0].K, config.width, config.height
    rng = np.random.default_rng(0)
    masks = []
    for k, f in enumerate(scene.frames):
        _save_png(folder / "images" / f"{k:05d}.png", f.image)
        _save_png(folder / "images_32x18" / f"{k:05d}.png", cv2.resize(f.image, (32, 18), interpolation=cv2.INTER_AREA))
        _save_png(folder / "sharp_images" / f"{k:05d}.png", f.sharp)
        img, _ = render_suite_view(world, right[k], f.time, K, W, H)
        _save_png(folder / "inference_images" / f"{k:05d}.png", img)
        m = np.zeros((H, W), dtype=bool)
        x, y = rng.integers(0, W - 10), rng.integers(0, H - 8)
        m[y:y + 8, x:x + 10] = True
        masks.append(m)
        (folder / "motion_masks").mkdir(exist_ok=True)
        cv2.imwrite(str(folder / "motion_masks" / f"{k:05d}.png"), np.where(m, 255, 0).astype(np.uint8))
    # name order L0, R0, L1, R1, ...: the rows alternate as DyBluRF's README says
    w2c = np.stack([T for pair in zip(left, right) for T in pair])
    bounds = []
    for k, T in enumerate(w2c):
        z = suite_depth_map(world, T, scene.frames[k // 2].time, K, W, H)
        z = z[np.isfinite(z)]
        bounds.append([np.percentile(z, 5), np.percentile(z, 95)])
    np.save(folder / "poses_bounds.npy", imgs2poses_rows(w2c, [H, W, K[0, 0]], np.array(bounds)))
    return folder, scene, left, right, masks


def test_llff_axes_are_down_right_backwards():
    # a camera at c looking along world +z with OpenCV axes (x right = world x, y down = world y):
    # LLFF's columns are its axes in the world in the order [down, right, backwards]
    c = np.array([1.0, -2.0, 3.0])
    row = np.concatenate([np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]]), c[:, None], [[36], [64], [50]]], 1)
    T = llff_to_cam_T_world(row.ravel())
    assert np.array_equal(T[:3, :3], np.eye(3)) and np.allclose(T[:3, 3], -c, atol=0)
    # DyBluRF's own loader turns the same columns into OpenGL c2w [right, up, backwards] = [c1, -c0, c2]
    rng = np.random.default_rng(1)
    for _ in range(5):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        q *= np.sign(np.linalg.det(q))
        M = np.concatenate([q, rng.normal(size=(3, 1)), [[36], [64], [50]]], 1)
        gl = np.concatenate([M[:, 1:2], -M[:, 0:1], M[:, 2:3], M[:, 3:4]], 1)
        ours = cam_T_world_to_opengl_c2w(llff_to_cam_T_world(M))
        assert np.max(np.abs(ours[:3] - gl)) < 1e-14
        assert np.max(np.abs(cam_T_world_to_llff(llff_to_cam_T_world(M), 36, 64, 50) - M.ravel())) < 1e-14


def test_import_gives_back_the_suite_cameras(stereo, tmp_path):
    folder, scene, left, right, masks = stereo
    out = tmp_path / "scene"
    assert main(["import-dyblurf", str(folder), str(out)]) == 0
    got = load_scene(out)
    n = scene.num_frames
    assert got.num_frames == n and len(got.test_frames) == n
    assert [f.time for f in got.frames] == pytest.approx(np.linspace(0, 1, n), abs=1e-15)
    assert [f.time for f in got.test_frames] == pytest.approx(np.linspace(0, 1, n), abs=1e-15)
    for k in range(n):
        a, t, s = got.frames[k], got.test_frames[k], scene.frames[k]
        assert np.max(np.abs(a.cam_T_world - left[k])) < POSE_TOL
        assert np.max(np.abs(t.cam_T_world - right[k])) < POSE_TOL
        assert np.max(np.abs(a.K - s.K)) < POSE_TOL and np.max(np.abs(t.K - s.K)) < POSE_TOL
        assert (a.width, a.height) == (s.width, s.height)
        q = np.round(s.image * 255) / 255  # the fixture's 8-bit PNGs
        assert np.array_equal(a.image, q) and np.array_equal(a.sharp, np.round(s.sharp * 255) / 255)
        assert np.array_equal(a.mask, masks[k])
    # the right camera sits BASELINE to the right of the left one, in the left camera's frame
    rel = right[0] @ np.linalg.inv(left[0])
    assert np.allclose(rel[:3, 3], [-BASELINE, 0, 0], atol=1e-12)
    rep = json.loads((out / "import_report.json").read_text())
    assert rep["stereo_baseline_median"] == pytest.approx(BASELINE, abs=1e-9)
    assert rep["images"] == "images" and rep["test_views"] == n and rep["motion_masks"]


def test_a_resized_folder_scales_the_focal_length(stereo, tmp_path):
    folder, scene, left, _, _ = stereo
    out = tmp_path / "small"
    assert main(["import-dyblurf", str(folder), str(out), "--size", "32x18"]) == 0
    got = load_scene(out)
    K = scene.frames[0].K
    for f in got.frames + got.test_frames:
        assert (f.width, f.height) == (32, 18)
        assert np.max(np.abs(f.K - np.diag([0.5, 0.5, 1.0]) @ K)) < 1e-12  # f W / w, f H / h, centre
    assert np.max(np.abs(got.frames[2].cam_T_world - left[2])) < POSE_TOL
    # sharp frames, masks and test images follow the training size
    assert got.frames[0].sharp.shape == (18, 32, 3) and got.frames[0].mask.shape == (18, 32)
    assert got.test_frames[0].image.shape == (18, 32, 3)


def test_sparse_points_are_taken_when_the_model_is_there(stereo, tmp_path):
    import shutil
    folder, scene, left, _, _ = stereo
    copy = tmp_path / "dense"
    shutil.copytree(folder, copy)
    xyz = np.random.default_rng(2).normal(size=(10, 3))
    rgb = np.full((10, 3), 200, dtype=np.uint8)
    K = scene.frames[0].K
    cams = {1: ColmapCamera(1, "SIMPLE_PINHOLE", 64, 36, np.array([K[0, 0], K[0, 2], K[1, 2]]))}
    images = {1: ColmapImage(1, np.array([1.0, 0, 0, 0]), np.zeros(3), 1, "00000.png")}
    write_model(ColmapModel(cams, images, np.arange(10), xyz, rgb, np.zeros(10), [np.zeros((0, 2))] * 10),
                copy / "sparse", ".bin")
    assert main(["import-dyblurf", str(copy), str(tmp_path / "out")]) == 0
    got = load_scene(tmp_path / "out")
    assert np.array_equal(got.points3d, xyz)


def _refused(argv, capsys, *needles):
    status = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and err[0].startswith("d2gs import-dyblurf: error:"), err
    for n in needles:
        assert n in err[0], (n, err[0])


def test_bad_folders_are_refused_before_any_work(stereo, tmp_path, capsys):
    import shutil
    folder, *_ = stereo
    out = tmp_path / "out"
    _refused(["import-dyblurf", tmp_path / "none", out], capsys, "does not exist")
    _refused(["import-dyblurf", folder, out, "--size", "100x50"], capsys, "images_100x50", "does not exist",
             "images_32x18")
    bad = tmp_path / "bad"
    shutil.copytree(folder, bad)
    arr = np.load(bad / "poses_bounds.npy")
    np.save(bad / "poses_bounds.npy", arr[:-2])  # one stereo pair short
    _refused(["import-dyblurf", bad, out], capsys, "rows", "interleaves")
    np.save(bad / "poses_bounds.npy", arr[:, :15])
    _refused(["import-dyblurf", bad, out], capsys, "(2N, 17)")
    (bad / "poses_bounds.npy").unlink()
    _refused(["import-dyblurf", bad, out], capsys, "poses_bounds.npy", "does not exist")
    np.save(bad / "poses_bounds.npy", arr)
    (bad / "sharp_images" / "00003.png").unlink()
    _refused(["import-dyblurf", bad, out], capsys, "sharp_images", "5 images", "6 stereo pairs")
    assert not out.exists()


def test_an_imported_benchmark_scene_trains_and_scores_deblurring_and_novel_views(stereo, tmp_path):
    # the benchmark's protocol: deblurring against sharp_images, novel views against the right
    # camera's inference_images, placed through the given (COLMAP) poses: there are no true ones
    folder, *_ = stereo
    scene, run = tmp_path / "scene", tmp_path / "run"
    assert main(["import-dyblurf", str(folder), str(scene)]) == 0
    assert main(["train", str(scene), "--out", str(run), "--iters", "4", "--quiet"]) == 0
    assert main(["eval", str(run)]) == 0
    m = json.loads((run / "metrics.json").read_text())
    assert "trajectory" not in m  # no true poses to score a trajectory against
    assert np.isfinite(m["dvs"]["psnr"]) and np.isfinite(m["input_blur"]["psnr"])
    assert m["nvs"]["aligned_to"] == "given poses" and m["nvs"]["num_images"] == len(load_scene(scene).test_frames)
    assert 5.0 < m["nvs"]["psnr"] < 60.0
