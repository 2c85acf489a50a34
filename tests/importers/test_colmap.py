"""d2gs import-colmap: COLMAP's text and binary sparse models read and written, poses taken as
cam_T_world unchanged, distorted cameras undistorted, bad input refused (docs/dataset_format.md §9)."""
import json
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from d2gs_np.cli import main
from d2gs_np.data.io import load_scene
from d2gs_np.data.suite import write_suite_scene
from d2gs_np.geometry.camera import project_points
from d2gs_np.importers.colmap import (
    ColmapCamera, ColmapImage, ColmapModel, camera_intrinsics, colmap_to_cam_T_world, read_model,
    undistort_image, write_model)

POSE_TOL = 1e-9  # the brief's round-trip tolerance; text floats are written shortest-repr, so only rounding in
# the quaternion <-> matrix conversions and the scene file's OpenGL inversion remains (~1e-15)


def _quat_wxyz(R):
    """COLMAP's (QW, QX, QY, QZ) of a rotation, computed by SciPy (scalar-last) rather than our code."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def colmap_model_of(scene, rng, model="PINHOLE", dist=(), num_points=40):
    """A COLMAP model of ``scene``'s cameras and given poses: image ids in an order unlike the names,
    random points in front of the cameras, each observed where it projects into a frame."""
    f0 = scene.frames[0]
    K = f0.K
    params = {"PINHOLE": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], "SIMPLE_PINHOLE": [K[0, 0], K[0, 2], K[1, 2]],
              "OPENCV": [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist], "SIMPLE_RADIAL": [K[0, 0], K[0, 2], K[1, 2], *dist]}
    cams = {7: ColmapCamera(7, model, f0.width, f0.height, np.array(params[model], dtype=np.float64))}
    n = scene.num_frames
    ids = [100 + 3 * (n - k) for k in range(n)]  # descending ids: name order is not id order
    # points: random pixels of frame 0 at random depths, in world coordinates
    T0 = scene.frames[0].cam_T_world
    uv = rng.uniform([2, 2], [f0.width - 2, f0.height - 2], size=(num_points, 2))
    z = rng.uniform(2.0, 5.0, size=num_points)
    pc = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], axis=1)
    xyz = (pc - T0[:3, 3]) @ T0[:3, :3]
    images, tracks = {}, [[] for _ in range(num_points)]
    for k, fr in enumerate(scene.frames):
        T = fr.cam_T_world
        proj, depth = project_points(xyz, T, K)
        seen = np.flatnonzero((depth > 0) & (proj[:, 0] >= 0) & (proj[:, 0] < fr.width) & (proj[:, 1] >= 0)
                              & (proj[:, 1] < fr.height))
        for j, p in enumerate(seen):
            tracks[p].append((ids[k], j))
        images[ids[k]] = ColmapImage(ids[k], _quat_wxyz(T[:3, :3]), T[:3, 3].copy(), 7, f"cam/{k:03d}.png",
                                     proj[seen], seen.astype(np.int64) + 1000)
    return ColmapModel(cams, images, np.arange(num_points, dtype=np.int64) + 1000, xyz,
                       rng.integers(0, 256, size=(num_points, 3)).astype(np.uint8), rng.uniform(0, 1, num_points),
                       [np.array(t, dtype=np.int64).reshape(-1, 2) for t in tracks])


def write_images(scene, src_root, images_dir):
    (images_dir / "cam").mkdir(parents=True)
    for k, fr in enumerate(scene.frames):
        shutil.copy(src_root / fr.file_path, images_dir / f"cam/{k:03d}.png")


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    root = tmp_path_factory.mktemp("colmap")
    write_suite_scene(root / "suite", "photo_room", 0, num_frames=6, width=64, height=36)
    scene = load_scene(root / "suite")
    write_images(scene, root / "suite", root / "images")
    return root, scene


def assert_models_equal(a: ColmapModel, b: ColmapModel):
    assert a.cameras.keys() == b.cameras.keys() and a.images.keys() == b.images.keys()
    for cid in a.cameras:
        ca, cb = a.cameras[cid], b.cameras[cid]
        assert (ca.model, ca.width, ca.height) == (cb.model, cb.width, cb.height)
        assert np.array_equal(ca.params, cb.params)
    for iid in a.images:
        ia, ib = a.images[iid], b.images[iid]
        assert (ia.camera_id, ia.name) == (ib.camera_id, ib.name)
        for f in ("qvec", "tvec", "xys", "point3D_ids"):
            assert np.array_equal(getattr(ia, f), getattr(ib, f)), f
    for f in ("point_ids", "xyz", "rgb", "error"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    assert len(a.tracks) == len(b.tracks) and all(np.array_equal(s, t) for s, t in zip(a.tracks, b.tracks))


def test_text_and_binary_models_import_to_the_suite_cameras(suite, tmp_path):
    root, scene = suite
    model = colmap_model_of(scene, np.random.default_rng(0))
    write_model(model, tmp_path / "txt", ".txt")
    bin_model = ColmapModel(**{**model.__dict__, "cameras": {7: ColmapCamera(
        7, "SIMPLE_PINHOLE", 64, 36, model.cameras[7].params[[0, 2, 3]])}})
    write_model(bin_model, tmp_path / "bin", ".bin")
    # the readers give back what was written, and text and binary agree exactly
    assert_models_equal(read_model(tmp_path / "txt"), model)
    assert_models_equal(read_model(tmp_path / "bin"), bin_model)
    assert_models_equal(read_model(tmp_path / "txt"), ColmapModel(**{**read_model(tmp_path / "bin").__dict__,
                                                                     "cameras": model.cameras}))
    for fmt in ("txt", "bin"):
        out = tmp_path / f"scene_{fmt}"
        assert main(["import-colmap", str(tmp_path / fmt), str(root / "images"), str(out)]) == 0
        got = load_scene(out)
        assert got.num_frames == scene.num_frames
        assert [f.time for f in got.frames] == pytest.approx(np.linspace(0, 1, scene.num_frames), abs=1e-15)
        for a, b in zip(got.frames, scene.frames):  # name order = the suite's frame order
            assert np.max(np.abs(a.cam_T_world - b.cam_T_world)) < POSE_TOL
            assert np.array_equal(a.K, b.K) and (a.width, a.height) == (b.width, b.height)
            assert np.array_equal(a.image, b.image)
        assert np.array_equal(got.points3d, model.xyz)
        assert np.array_equal(np.round(got.points3d_colors * 255), model.rgb)
        rep = json.loads((out / "import_report.json").read_text())
        assert rep["format"] == {"txt": "text", "bin": "binary"}[fmt] and rep["undistorted"] == {}


def test_colmap_pose_is_world_to_camera_with_opencv_axes():
    # COLMAP's documented convention, computed independently: the centre is -R^T t and a point in
    # front of the camera has z > 0 and projects to K (x/z, y/z) with y pointing down the image
    rng = np.random.default_rng(1)
    R = Rotation.random(random_state=2).as_matrix()
    t = rng.normal(size=3)
    T = colmap_to_cam_T_world(_quat_wxyz(R), t)
    assert np.max(np.abs(T[:3, :3] - R)) < 1e-14 and np.array_equal(T[:3, 3], t)
    centre = -R.T @ t
    below = centre + R.T @ np.array([0.0, 1.0, 4.0])  # 1 unit down the camera's y, 4 ahead
    K = np.array([[100.0, 0, 32], [0, 100.0, 18], [0, 0, 1]])
    uv, z = project_points(below[None], T, K)
    assert z[0] == pytest.approx(4.0) and uv[0] == pytest.approx([32.0, 18.0 + 25.0])
    # a non-unit quaternion is normalised, as COLMAP normalises on read
    assert np.max(np.abs(colmap_to_cam_T_world(3.0 * _quat_wxyz(R), t) - T)) < 1e-14


def _smooth(u, v):
    """A smooth test picture, a function of continuous pixel coordinates (centres at +0.5)."""
    return 0.5 + 0.25 * np.sin(u / 5.0) * np.cos(v / 7.0) + 0.2 * np.sin((u + v) / 11.0)


@pytest.mark.parametrize("model,dist", [("OPENCV", (-0.12, 0.03, 0.002, -0.001)), ("SIMPLE_RADIAL", (0.08,))])
def test_distorted_cameras_are_undistorted_to_their_own_pinhole(model, dist):
    W, H = 96, 64
    cam = ColmapCamera(1, model, W, H, np.array(
        [80.0, 82.0, 47.0, 33.5, *dist] if model == "OPENCV" else [80.0, 47.0, 33.5, *dist]))
    K, d = camera_intrinsics(cam)
    # the distorted picture: each distorted pixel centre's ideal position, by inverting COLMAP's
    # OPENCV model (written out here from its definition, not OpenCV's code) by fixed-point iteration
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    k1, k2, p1, p2 = d
    xd, yd = (jj.ravel() + 0.5 - K[0, 2]) / K[0, 0], (ii.ravel() + 0.5 - K[1, 2]) / K[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(200):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        x = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
        y = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    assert np.max(np.abs(x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd)) < 1e-12  # converged
    ideal = np.stack([K[0, 0] * x + K[0, 2], K[1, 1] * y + K[1, 2]], axis=1)
    distorted = _smooth(ideal[:, 0], ideal[:, 1]).reshape(H, W)
    img = np.repeat(distorted[:, :, None], 3, axis=2)
    out = undistort_image(img, K, d)
    truth = _smooth(jj + 0.5, ii + 0.5)
    inner = (slice(8, H - 8), slice(8, W - 8))  # away from the borders, where sources fall outside
    # bilinear resampling of a picture with wavelengths >= 30 px: errors of a few 1e-3
    assert np.max(np.abs(out[inner][..., 0] - truth[inner])) < 5e-3
    # without the half-pixel shift the picture would be off by half a pixel: far worse
    shifted = _smooth(jj + 1.0, ii + 1.0)
    assert np.max(np.abs(shifted[inner] - truth[inner])) > 5 * np.max(np.abs(out[inner][..., 0] - truth[inner]))


def test_a_distorted_model_imports_with_the_pinhole_part_as_k(suite, tmp_path):
    root, scene = suite
    model = colmap_model_of(scene, np.random.default_rng(3), "OPENCV", (-0.05, 0.01, 0.0, 0.0))
    write_model(model, tmp_path / "m", ".txt")
    assert main(["import-colmap", str(tmp_path / "m"), str(root / "images"), str(tmp_path / "out")]) == 0
    got = load_scene(tmp_path / "out")
    assert all(np.array_equal(f.K, scene.frames[0].K) for f in got.frames)
    rep = json.loads((tmp_path / "out" / "import_report.json").read_text())
    assert rep["undistorted"]["7"]["new_K"] == scene.frames[0].K.tolist()
    assert not np.array_equal(got.frames[0].image, scene.frames[0].image)


# ----------------------------------------------------------------------------- refusals
def _refused(argv, capsys, *needles):
    status = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and err[0].startswith("d2gs import-colmap: error:"), err
    for n in needles:
        assert n in err[0], (n, err[0])


def test_bad_models_are_refused_before_any_work(suite, tmp_path, capsys):
    root, scene = suite
    model = colmap_model_of(scene, np.random.default_rng(4))
    good = write_model(model, tmp_path / "good", ".txt")
    out = tmp_path / "out"
    # a missing file
    part = tmp_path / "part"
    shutil.copytree(good, part)
    (part / "points3D.txt").unlink()
    _refused(["import-colmap", part, root / "images", out], capsys, "points3D.txt", "missing")
    # no model folder at all
    _refused(["import-colmap", tmp_path / "nowhere", root / "images", out], capsys, "does not exist")
    # an unsupported camera model, named
    fish = ColmapModel(**{**model.__dict__, "cameras": {7: ColmapCamera(7, "OPENCV_FISHEYE", 64, 36,
                                                                          np.array([50.0, 50, 32, 18, 0, 0, 0, 0]))}})
    _refused(["import-colmap", write_model(fish, tmp_path / "fish", ".bin"), root / "images", out], capsys,
             "OPENCV_FISHEYE", "not supported", "image_undistorter")
    # a model name COLMAP does not have
    bad = tmp_path / "bad"
    shutil.copytree(good, bad)
    text = (bad / "cameras.txt").read_text().replace("PINHOLE", "PINHOLE_X")
    (bad / "cameras.txt").write_text(text)
    _refused(["import-colmap", bad, root / "images", out], capsys, "PINHOLE_X", "cameras.txt line")
    # an image listed without its file
    few = tmp_path / "few_images"
    shutil.copytree(root / "images", few)
    (few / "cam" / "003.png").unlink()
    _refused(["import-colmap", good, few, out], capsys, "cam/003.png", "not in")
    # a truncated binary file
    trunc = tmp_path / "trunc"
    write_model(model, trunc, ".bin")
    raw = (trunc / "images.bin").read_bytes()
    (trunc / "images.bin").write_bytes(raw[: len(raw) // 2])
    _refused(["import-colmap", trunc, root / "images", out], capsys, "images.bin", "truncated")
    # nothing was written by any refusal
    assert not out.exists()
    # a non-empty output folder without --overwrite
    out.mkdir()
    (out / "x").write_text("keep")
    _refused(["import-colmap", good, root / "images", out], capsys, "not empty", "--overwrite")
    assert [p.name for p in out.iterdir()] == ["x"]
    assert main(["import-colmap", str(good), str(root / "images"), str(out), "--overwrite"]) == 0


def test_binary_reader_agrees_with_pycolmap(suite, tmp_path):
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is an optional extra (pip install .[colmap]); "
                                   "without it COLMAP's own reader cannot be compared")
    root, scene = suite
    model = colmap_model_of(scene, np.random.default_rng(5))
    write_model(model, tmp_path / "ours", ".bin")
    rec = pycolmap.Reconstruction(str(tmp_path / "ours"))  # COLMAP's reader on our files
    assert sorted(rec.images) == sorted(model.images) and sorted(rec.points3D) == sorted(model.point_ids)
    cam = rec.cameras[7]
    assert cam.model.name == "PINHOLE" and np.array_equal(cam.params, model.cameras[7].params)
    K = camera_intrinsics(model.cameras[7])[0]
    for iid, im in model.images.items():
        theirs = rec.images[iid]
        assert theirs.name == im.name
        # COLMAP's cam_from_world is our cam_T_world, and its projection (pixel centres at +0.5) is ours
        T = colmap_to_cam_T_world(im.qvec, im.tvec)
        assert np.max(np.abs(theirs.cam_from_world().matrix() - T[:3])) < 1e-14
        ours, _ = project_points(model.xyz, T, K)
        for x, uv in zip(model.xyz, ours):
            assert np.max(np.abs(np.ravel(theirs.project_point(x)) - uv)) < 1e-9
    for pid, xyz, rgb, track in zip(model.point_ids, model.xyz, model.rgb, model.tracks):
        p = rec.points3D[int(pid)]
        assert np.array_equal(p.xyz, xyz) and np.array_equal(p.color, rgb)
        assert sorted((e.image_id, e.point2D_idx) for e in p.track.elements) == sorted(map(tuple, track.tolist()))
    # and our readers on COLMAP's writing, both formats
    (tmp_path / "theirs_bin").mkdir()
    (tmp_path / "theirs_txt").mkdir()
    rec.write_binary(str(tmp_path / "theirs_bin"))
    rec.write_text(str(tmp_path / "theirs_txt"))
    for d in ("theirs_bin", "theirs_txt"):
        back = read_model(tmp_path / d)
        assert np.array_equal(back.cameras[7].params, model.cameras[7].params)
        for iid, im in model.images.items():
            assert back.images[iid].name == im.name
            assert np.max(np.abs(colmap_to_cam_T_world(back.images[iid].qvec, back.images[iid].tvec)
                                 - colmap_to_cam_T_world(im.qvec, im.tvec))) < 1e-12
            assert np.array_equal(back.images[iid].point3D_ids, im.point3D_ids)
        order = np.argsort(back.point_ids)
        assert np.array_equal(back.point_ids[order], model.point_ids)
        assert np.array_equal(back.xyz[order], model.xyz) and np.array_equal(back.rgb[order], model.rgb)
