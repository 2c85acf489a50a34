"""Tests for d2gs_np.data.io: scene-folder round trip and validation errors."""
import json
import shutil

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from d2gs_np.base.checks import SceneWarning
from d2gs_np.constants import RIGID_TOL
from d2gs_np.data.io import load_scene, write_scene
from d2gs_np.data.scene import Frame, Scene
from d2gs_np.geometry.camera import cam_T_world_to_opengl_c2w, make_intrinsics

# Poses pass through two rigid inverses and a sign flip: a few float64 roundings.
POSE_TOL = 1e-12
# 8-bit quantisation with rounding: |x - round(255 x) / 255| <= 0.5 / 255 (+ rounding of the division).
QUANT_TOL = 1.0 / 510 + 1e-12

W, H = 16, 12


def _pose(rng):
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.standard_normal(3)
    return T


def _frame(rng, i, time, full=True, prefix="images", w=W, h=H):
    fr = Frame(
        file_path=f"{prefix}/{i:04d}.png",
        time=time,
        cam_T_world=_pose(rng),
        K=make_intrinsics(20.0, 21.5, w / 2 + 0.25, h / 2 - 0.5),
        width=w,
        height=h,
        image=rng.random((h, w, 3)),
    )
    if full:
        fr.mask = rng.random((h, w)) < 0.3
        fr.mask_path = f"masks/{i:04d}.png"
        fr.sharp = rng.random((h, w, 3))
        fr.sharp_file_path = f"sharp/{i:04d}.png"
        fr.gt_cam_T_world = _pose(rng)
        fr.gt_exposure_start = _pose(rng)
        fr.gt_exposure_end = _pose(rng)
    return fr


def _scene(rng, n=4, full=True, times=None):
    times = np.linspace(0.0, 1.0, n) if times is None else times
    frames = [_frame(rng, i, float(t), full) for i, t in enumerate(times)]
    test = [_frame(rng, 100 + i, float(t), False, prefix="test") for i, t in enumerate([0.2, 0.7])] if full else []
    kw = dict(exposure_fraction=0.5, scene_scale=3.25, blur_subframes=9) if full else {}
    return Scene(frames=frames, test_frames=test, **kw)


@pytest.fixture
def scene_dir(tmp_path):
    rng = np.random.default_rng(0)
    scene = _scene(rng)
    root = tmp_path / "scene"
    write_scene(scene, root)
    return root, scene


def _edit_json(root, fn, name="transforms.json"):
    p = root / name
    data = json.loads(p.read_text())
    fn(data)
    p.write_text(json.dumps(data))


# ------------------------------------------------------------------ round trip
def _assert_frames_equal(a, b):
    assert a.file_path == b.file_path and a.time == b.time
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_array_equal(a.K, b.K)
    for attr in ("cam_T_world", "gt_cam_T_world", "gt_exposure_start", "gt_exposure_end"):
        x, y = getattr(a, attr), getattr(b, attr)
        assert (x is None) == (y is None), attr
        if x is not None:
            np.testing.assert_allclose(y, x, rtol=0, atol=POSE_TOL)
    for attr in ("image", "sharp"):
        x, y = getattr(a, attr), getattr(b, attr)
        assert (x is None) == (y is None), attr
        if x is not None:
            assert y.dtype == np.float64 and y.shape == x.shape
            assert np.max(np.abs(y - x)) <= QUANT_TOL
    assert (a.mask is None) == (b.mask is None)
    if a.mask is not None:
        assert b.mask.dtype == np.bool_
        np.testing.assert_array_equal(a.mask, b.mask)
        assert a.mask_path == b.mask_path
    assert a.sharp_file_path == b.sharp_file_path


def test_round_trip(scene_dir):
    root, scene = scene_dir
    loaded = load_scene(root)
    assert loaded.num_frames == 4 and len(loaded.test_frames) == 2
    for a, b in zip(scene.frames, loaded.frames):
        _assert_frames_equal(a, b)
    for a, b in zip(scene.test_frames, loaded.test_frames):
        _assert_frames_equal(a, b)
    assert loaded.exposure_fraction == 0.5 and loaded.scene_scale == 3.25 and loaded.blur_subframes == 9
    assert loaded.root == root
    assert loaded.has_masks and loaded.has_sharp and loaded.has_gt_poses


def test_files_follow_dataset_format(scene_dir):
    """The JSON stores OpenGL camera-to-world; masks are 0/255; images RGB (not BGR)."""
    root, scene = scene_dir
    data = json.loads((root / "transforms.json").read_text())
    assert {k: data[k] for k in ("w", "h")} == {"w": W, "h": H}
    fr0 = scene.frames[0]
    c2w = np.array(data["frames"][0]["transform_matrix"])
    np.testing.assert_allclose(c2w, cam_T_world_to_opengl_c2w(fr0.cam_T_world), atol=POSE_TOL)
    # OpenGL camera looks down -z: the world point one unit in front of the camera is at
    # camera z = +1 in OpenCV axes.
    ahead = c2w[:3, :3] @ np.array([0.0, 0.0, -1.0]) + c2w[:3, 3]
    np.testing.assert_allclose(fr0.cam_T_world[:3, :3] @ ahead + fr0.cam_T_world[:3, 3], [0, 0, 1], atol=POSE_TOL)
    mask_png = cv2.imread(str(root / fr0.mask_path), cv2.IMREAD_UNCHANGED)
    assert set(np.unique(mask_png)) <= {0, 255}
    bgr = cv2.imread(str(root / fr0.file_path), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(bgr[..., 2], np.round(fr0.image[..., 0] * 255).astype(np.uint8))
    test = json.loads((root / "transforms_test.json").read_text())
    assert [f["file_path"] for f in test["frames"]] == ["test/0100.png", "test/0101.png"]
    assert "exposure_fraction" not in test


def test_write_clips_out_of_range_values(tmp_path):
    rng = np.random.default_rng(1)
    scene = _scene(rng, n=2, full=False)
    scene.frames[0].image[0, 0] = [-0.5, 1.7, 0.5]
    write_scene(scene, tmp_path / "s")
    loaded = load_scene(tmp_path / "s")
    np.testing.assert_allclose(loaded.frames[0].image[0, 0], [0.0, 1.0, 128 / 255], atol=1e-15)


def test_frames_sorted_by_time(tmp_path):
    rng = np.random.default_rng(2)
    times = [0.9, 0.1, 0.5, 0.1, 0.0]
    scene = _scene(rng, n=5, full=False, times=times)
    write_scene(scene, tmp_path / "s")
    with pytest.warns(SceneWarning, match=r"frames\[1\] \('images/0001.png'\) and frames\[3\] .* share time 0.1;"):
        loaded = load_scene(tmp_path / "s")
    assert [f.time for f in loaded.frames] == sorted(times)
    # Stable: of the two frames at t = 0.1, file order (frame 1 before frame 3) is kept
    assert [f.file_path for f in loaded.frames] == [f"images/{i:04d}.png" for i in (4, 1, 3, 2, 0)]
    for f in loaded.frames:
        src = scene.frames[int(f.file_path[7:11])]
        np.testing.assert_allclose(f.cam_T_world, src.cam_T_world, atol=POSE_TOL)


def test_intrinsics_override(tmp_path):
    rng = np.random.default_rng(3)
    scene = _scene(rng, n=3, full=False)
    # Frame 1: different size and intrinsics (e.g. a cropped frame)
    odd = _frame(rng, 1, 0.5, full=False, w=10, h=8)
    odd.K = make_intrinsics(11.0, 12.0, 4.5, 3.75)
    scene.frames[1] = odd
    root = tmp_path / "s"
    write_scene(scene, root)
    data = json.loads((root / "transforms.json").read_text())
    assert "fl_x" not in data["frames"][0] and data["frames"][1]["fl_x"] == 11.0
    assert data["frames"][1]["w"] == 10
    loaded = load_scene(root)
    np.testing.assert_array_equal(loaded.frames[1].K, odd.K)
    assert (loaded.frames[1].width, loaded.frames[1].height) == (10, 8)
    np.testing.assert_array_equal(loaded.frames[0].K, scene.frames[0].K)
    # Hand-written partial override: only fl_x; the rest comes from the top level
    _edit_json(root, lambda d: d["frames"][2].update({"fl_x": 33.0}))
    loaded = load_scene(root)
    K2 = loaded.frames[2].K
    assert K2[0, 0] == 33.0 and K2[1, 1] == 21.5 and K2[0, 2] == W / 2 + 0.25


def test_test_file_intrinsics_default_to_training_ones(scene_dir):
    root, scene = scene_dir

    def drop(d):
        for k in ("w", "h", "fl_x", "fl_y", "cx", "cy"):
            d.pop(k)

    _edit_json(root, drop, "transforms_test.json")
    loaded = load_scene(root)
    np.testing.assert_array_equal(loaded.test_frames[0].K, scene.frames[0].K)


def test_optional_fields_absent_are_none(tmp_path):
    rng = np.random.default_rng(4)
    scene = _scene(rng, n=2, full=False)
    root = tmp_path / "s"
    write_scene(scene, root)
    data = json.loads((root / "transforms.json").read_text())
    for k in ("exposure_fraction", "scene_scale", "blur_subframes"):
        assert k not in data
    for k in ("mask_path", "sharp_file_path", "gt_transform_matrix", "gt_exposure_start", "gt_exposure_end"):
        assert k not in data["frames"][0]
    assert not (root / "transforms_test.json").exists()
    loaded = load_scene(root)
    assert loaded.exposure_fraction is None and loaded.scene_scale is None and loaded.blur_subframes is None
    assert loaded.test_frames == []
    f = loaded.frames[0]
    assert f.mask is None and f.mask_path is None and f.sharp is None and f.sharp_file_path is None
    assert f.gt_cam_T_world is None and f.gt_exposure_start is None and f.gt_exposure_end is None
    assert not loaded.has_masks and not loaded.has_gt_poses


def test_load_without_images(scene_dir):
    root, _ = scene_dir
    s = load_scene(root, load_images=False)
    assert all(f.image is None and f.mask is None and f.sharp is None for f in s.frames)
    assert s.frames[0].mask_path == "masks/0000.png"


def test_extensionless_file_path_is_accepted(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d["frames"][0].update({"file_path": "./images/0000"}))
    s = load_scene(root)
    assert s.frames[0].file_path == "./images/0000.png" and s.frames[0].image is not None


def test_write_refuses_non_empty_folder_and_removes_stale_test_file(scene_dir):
    root, scene = scene_dir
    with pytest.raises(ValueError, match="not empty.*overwrite=True"):
        write_scene(scene, root)
    scene.test_frames = []
    write_scene(scene, root, overwrite=True)
    assert not (root / "transforms_test.json").exists()
    assert load_scene(root).test_frames == []


def test_write_validates_before_writing(tmp_path):
    rng = np.random.default_rng(5)
    scene = _scene(rng, n=3, full=False)
    scene.frames[2].image = None
    with pytest.raises(ValueError, match=r"scene.frames\[2\]: image is None"):
        write_scene(scene, tmp_path / "s")
    assert not (tmp_path / "s").exists()
    scene = _scene(rng, n=3, full=False)
    scene.frames[1].cam_T_world[0, 0] = 2.0
    with pytest.raises(ValueError, match=r"scene.frames\[1\]: cam_T_world.*not rigid"):
        write_scene(scene, tmp_path / "s")
    scene = _scene(rng, n=3, full=False)
    scene.frames[1].file_path = scene.frames[0].file_path
    with pytest.raises(ValueError, match="also used by"):
        write_scene(scene, tmp_path / "s")


# ------------------------------------------------------------ validation errors
def test_missing_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="scene folder .*nope.* does not exist"):
        load_scene(tmp_path / "nope")


def test_missing_transforms_json(tmp_path):
    with pytest.raises(FileNotFoundError, match="no transforms.json in scene folder"):
        load_scene(tmp_path)


def test_malformed_json(scene_dir):
    root, _ = scene_dir
    (root / "transforms.json").write_text('{"frames": [ {"file_path": "a.png",, } ]}')
    with pytest.raises(ValueError, match=r"transforms.json is not valid JSON: .* line 1, column"):
        load_scene(root)


def test_malformed_test_json_names_test_file(scene_dir):
    root, _ = scene_dir
    (root / "transforms_test.json").write_text("{")
    with pytest.raises(ValueError, match="transforms_test.json is not valid JSON"):
        load_scene(root)


@pytest.mark.parametrize("field", ["file_path", "time", "transform_matrix"])
def test_missing_required_frame_field(scene_dir, field):
    root, _ = scene_dir
    _edit_json(root, lambda d: d["frames"][2].pop(field))
    with pytest.raises(ValueError, match=rf"transforms.json frames\[2\].*missing required field '{field}'"):
        load_scene(root)


def test_missing_intrinsics(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d.pop("fl_y"))
    with pytest.raises(ValueError, match=r"frames\[0\].*missing intrinsic 'fl_y'.*top level"):
        load_scene(root)


def test_empty_frame_list(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d.update({"frames": []}))
    with pytest.raises(ValueError, match="empty 'frames' list"):
        load_scene(root)


def test_no_frames_key(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d.pop("frames"))
    with pytest.raises(ValueError, match="must have a 'frames' list"):
        load_scene(root)


@pytest.mark.parametrize("what, rel", [("image", "images/0001.png"), ("mask", "masks/0001.png"),
                                       ("sharp image", "sharp/0001.png"), ("image", "test/0101.png")])
def test_missing_files(scene_dir, what, rel):
    root, _ = scene_dir
    (root / rel).unlink()
    with pytest.raises(FileNotFoundError, match=rf"{what} file .*{rel} does not exist"):
        load_scene(root)


def test_corrupt_png_body(scene_dir):
    """Valid header, broken data: found when decoding, error names the path."""
    root, _ = scene_dir
    p = root / "sharp" / "0002.png"
    b = p.read_bytes()
    p.write_bytes(b[: len(b) // 2])
    with pytest.raises(ValueError, match=r"could not decode sharp image .*sharp/0002.png.*corrupt"):
        load_scene(root)
    # Metadata-only loading does not decode, so it passes
    load_scene(root, load_images=False)


def test_corrupt_png_header(scene_dir):
    root, _ = scene_dir
    (root / "images" / "0003.png").write_bytes(b"not a png at all, just text")
    with pytest.raises(ValueError, match=r"image file .*images/0003.png is not a valid PNG"):
        load_scene(root)


def test_image_size_mismatch(scene_dir):
    root, _ = scene_dir
    cv2.imwrite(str(root / "images" / "0001.png"), np.zeros((H, W + 1, 3), np.uint8))
    with pytest.raises(ValueError, match=rf"images/0001.png is {W + 1}x{H} pixels but .* w={W}, h={H}"):
        load_scene(root)


def test_mask_size_mismatch(scene_dir):
    root, _ = scene_dir
    cv2.imwrite(str(root / "masks" / "0002.png"), np.zeros((H - 2, W, 1), np.uint8))
    with pytest.raises(ValueError, match=rf"mask .*masks/0002.png is {W}x{H - 2} pixels"):
        load_scene(root)


def test_mask_must_be_single_channel(scene_dir):
    root, _ = scene_dir
    cv2.imwrite(str(root / "masks" / "0002.png"), np.zeros((H, W, 3), np.uint8))
    with pytest.raises(ValueError, match="masks must be single-channel"):
        load_scene(root)


def test_rgba_and_16bit_images_rejected(scene_dir):
    root, _ = scene_dir
    cv2.imwrite(str(root / "images" / "0000.png"), np.zeros((H, W, 4), np.uint8))
    with pytest.raises(ValueError, match="is RGBA; images must be 8-bit RGB PNG"):
        load_scene(root)
    cv2.imwrite(str(root / "images" / "0000.png"), np.zeros((H, W, 3), np.uint16))
    with pytest.raises(ValueError, match="16-bit channels"):
        load_scene(root)


def test_header_checks_run_before_any_decoding(scene_dir):
    """A wrong-size mask in the last frame is reported even though an earlier
    image is undecodable: all headers are checked before pixels are read."""
    root, _ = scene_dir
    p = root / "images" / "0000.png"
    p.write_bytes(p.read_bytes()[:60])
    cv2.imwrite(str(root / "masks" / "0003.png"), np.zeros((H, W - 1), np.uint8))
    with pytest.raises(ValueError, match="masks/0003.png is"):
        load_scene(root)


def test_json_checked_before_files(scene_dir):
    root, _ = scene_dir
    shutil.rmtree(root / "images")
    _edit_json(root, lambda d: d["frames"][3].update({"time": 1.5}))
    with pytest.raises(ValueError, match="time"):
        load_scene(root)


def test_non_rigid_pose(scene_dir):
    root, _ = scene_dir

    def shear(d):
        d["frames"][1]["transform_matrix"][0][1] += 0.01

    _edit_json(root, shear)
    with pytest.raises(ValueError, match=r"transforms.json frames\[1\].*'transform_matrix' is not rigid"):
        load_scene(root)


def test_non_rigid_gt_pose(scene_dir):
    root, _ = scene_dir

    def scale(d):
        d["frames"][2]["gt_exposure_end"][1][1] *= 1.5

    _edit_json(root, scale)
    with pytest.raises(ValueError, match=r"frames\[2\].*'gt_exposure_end' is not rigid"):
        load_scene(root)


def test_non_finite_pose(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d["frames"][0]["transform_matrix"][2].__setitem__(3, float("nan")))
    with pytest.raises(ValueError, match=r"frames\[0\].*'transform_matrix' contains NaN or inf"):
        load_scene(root)


def test_pose_wrong_shape(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d["frames"][0]["transform_matrix"].pop())
    with pytest.raises(ValueError, match=r"'transform_matrix' must be a 4x4 nested list"):
        load_scene(root)


@pytest.mark.parametrize("t", [-0.01, 1.0001])
def test_time_out_of_range(scene_dir, t):
    root, _ = scene_dir
    _edit_json(root, lambda d: d["frames"][1].update({"time": t}))
    with pytest.raises(ValueError, match=r"frames\[1\].*'time' must be a normalised timestamp in \[0, 1\]"):
        load_scene(root)


def test_time_not_a_number(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d["frames"][1].update({"time": "0.5"}))
    with pytest.raises(ValueError, match="'time' must be a finite number"):
        load_scene(root)


@pytest.mark.parametrize("v", [-0.1, 1.5])
def test_exposure_fraction_out_of_range(scene_dir, v):
    root, _ = scene_dir
    _edit_json(root, lambda d: d.update({"exposure_fraction": v}))
    with pytest.raises(ValueError, match=r"'exposure_fraction' must be in \[0, 1\]"):
        load_scene(root)


@pytest.mark.parametrize("where", ["top", "frame"])
@pytest.mark.parametrize("value", [0.0, -20.0])
def test_non_positive_focal_length(scene_dir, where, value):
    root, _ = scene_dir
    if where == "top":
        _edit_json(root, lambda d: d.update({"fl_x": value}))
    else:
        _edit_json(root, lambda d: d["frames"][3].update({"fl_y": value}))
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        load_scene(root)


def test_bad_width(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d.update({"w": 16.5}))
    with pytest.raises(ValueError, match="'w' must be a positive integer"):
        load_scene(root)


def test_bad_blur_subframes_and_scene_scale(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d.update({"blur_subframes": 0}))
    with pytest.raises(ValueError, match="'blur_subframes' must be a positive integer"):
        load_scene(root)
    _edit_json(root, lambda d: d.update({"blur_subframes": 5, "scene_scale": -1.0}))
    with pytest.raises(ValueError, match="'scene_scale' must be positive"):
        load_scene(root)


def test_distortion_rejected(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d.update({"k1": 0.0, "p1": 0.0}))
    load_scene(root, load_images=False)  # zeros are fine (Nerfstudio writes them)
    _edit_json(root, lambda d: d.update({"k1": 0.01}))
    with pytest.raises(ValueError, match="distortion coefficient 'k1'.*undistort"):
        load_scene(root)
    _edit_json(root, lambda d: d.update({"k1": 0.0, "camera_model": "OPENCV_FISHEYE"}))
    with pytest.raises(ValueError, match="camera_model 'OPENCV_FISHEYE' is not supported"):
        load_scene(root)


def test_mask_threshold_at_127(scene_dir):
    """Anti-aliased masks: pixels > 127 are dynamic, <= 127 static."""
    root, _ = scene_dir
    m = np.zeros((H, W), np.uint8)
    m[0, :4] = [1, 127, 128, 254]
    cv2.imwrite(str(root / "masks" / "0000.png"), m)
    mask = load_scene(root).frames[0].mask
    assert mask[0, :4].tolist() == [False, False, True, True] and mask.sum() == 2


# ------------------------------------------------------------------ plausibility (issue #41)
def _no_warnings():
    """A context in which any warning fails the test."""
    import warnings
    ctx = warnings.catch_warnings()
    ctx.__enter__()
    warnings.simplefilter("error")
    return ctx


def test_clean_scene_loads_without_warnings(scene_dir):
    root, _ = scene_dir
    ctx = _no_warnings()
    try:
        load_scene(root)
    finally:
        ctx.__exit__(None, None, None)


def _masks_as(root, fn):
    for p in sorted((root / "masks").glob("*.png")):
        cv2.imwrite(str(p), fn(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)))


def test_zero_one_masks_read_as_the_0_255_ones(scene_dir):
    root, scene = scene_dir
    _masks_as(root, lambda m: (m > 127).astype(np.uint8))
    loaded = load_scene(root)
    for a, b in zip(scene.frames, loaded.frames):
        np.testing.assert_array_equal(b.mask, a.mask)
    assert loaded.has_moving_pixels


def test_one_bit_masks_read_as_bool(scene_dir):
    """A bool array saved by Pillow is a 1-bit greyscale PNG."""
    from PIL import Image
    root, scene = scene_dir
    for f in scene.frames:
        Image.fromarray(f.mask).save(root / f.mask_path)
    assert (root / scene.frames[0].mask_path).read_bytes()[24] == 1  # bit depth 1
    for a, b in zip(scene.frames, load_scene(root).frames):
        np.testing.assert_array_equal(b.mask, a.mask)


def test_masks_of_neither_encoding_refused(scene_dir):
    root, _ = scene_dir
    _masks_as(root, lambda m: (m > 127).astype(np.uint8) * 127)  # 127: static under the > 127 rule
    with pytest.raises(ValueError, match="brightest pixel of the scene's motion masks, 127: neither 0/255"):
        load_scene(root)
    load_scene(root, load_images=False)  # the pixels are not read: nothing to say


def test_a_zero_one_mask_among_0_255_ones_is_warned(scene_dir):
    root, scene = scene_dir
    cv2.imwrite(str(root / "masks" / "0002.png"), scene.frames[2].mask.astype(np.uint8))
    with pytest.warns(SceneWarning, match=r"the masks of transforms.json frames\[2\] .* hold only 0 and 1"):
        loaded = load_scene(root)
    assert not loaded.frames[2].mask.any()


def test_frames_without_masks(scene_dir):
    root, _ = scene_dir
    assert load_scene(root).frames_without_masks == []
    _edit_json(root, lambda d: [d["frames"][i].pop("mask_path") for i in (0, 2)])
    assert load_scene(root).frames_without_masks == [0, 2]
    assert load_scene(root, load_images=False).frames_without_masks == [0, 2]
    _edit_json(root, lambda d: [f.pop("mask_path", None) for f in d["frames"]])
    assert load_scene(root).frames_without_masks == []  # no masks at all: a static scene


def test_duplicate_entry_refused_in_either_spelling(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d["frames"].append(dict(d["frames"][0], file_path="./images/0000.png", time=0.5)))
    with pytest.raises(ValueError, match=r"frames\[4\] \('./images/0000.png'\) repeats frames\[0\]"):
        load_scene(root)


def test_test_views_may_share_a_time(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: [f.update(time=0.3) for f in d["frames"]], name="transforms_test.json")
    ctx = _no_warnings()
    try:
        load_scene(root, load_images=False)
    finally:
        ctx.__exit__(None, None, None)


@pytest.mark.parametrize("fx, fy, outcome", [
    (20.0, 21.5, None),  # the fixture's: 44 x 31 deg
    (0.5, 21.5, "warn"),  # 172.8 deg over 16 px
    (1000.0, 21.5, "warn"),  # 0.92 deg
    (0.05, 21.5, "refuse"),  # 179.4 deg: below 0.0698 px
    (20.0, 1e6, "refuse"),  # 6.9e-4 deg over 12 px
])
def test_focal_length_plausibility(scene_dir, fx, fy, outcome):
    root, _ = scene_dir
    _edit_json(root, lambda d: d.update(fl_x=fx, fl_y=fy))
    _edit_json(root, lambda d: d.update(fl_x=fx, fl_y=fy), name="transforms_test.json")
    if outcome == "refuse":
        with pytest.raises(ValueError, match=r"transforms.json frames\[0\] .*: fl_[xy] = .* px is (below|above) "
                                             r".* px, a .* deg field of view .*not a focal length in pixels"):
            load_scene(root, load_images=False)
    elif outcome == "warn":
        with pytest.warns(SceneWarning, match=r"transforms(_test)?.json: all \d frames: fl_x, fl_y = .* outside the "
                                              r"\[1, 170\] deg of a video camera") as record:
            load_scene(root, load_images=False)
        assert [str(w.message).split(":")[0] for w in record] == ["transforms.json", "transforms_test.json"]
    else:
        ctx = _no_warnings()
        try:
            load_scene(root, load_images=False)
        finally:
            ctx.__exit__(None, None, None)


def test_focal_length_bounds_are_the_fields_of_view(scene_dir):
    """The refusal bounds printed are the focal lengths of a 179 deg and a 0.01 deg view: just inside
    them loads (with a warning), just outside is refused."""
    root, _ = scene_dir
    lo, hi = W / (2 * np.tan(np.radians(179.0) / 2)), W / (2 * np.tan(np.radians(0.01) / 2))
    for fx, ok in ((lo * 1.001, True), (lo * 0.999, False), (hi * 0.999, True), (hi * 1.001, False)):
        _edit_json(root, lambda d: d.update(fl_x=fx))
        if ok:
            with pytest.warns(SceneWarning):
                load_scene(root, load_images=False)
        else:
            with pytest.raises(ValueError, match="not a focal length in pixels"):
                load_scene(root, load_images=False)


def test_principal_point_plausibility(scene_dir):
    root, _ = scene_dir
    _edit_json(root, lambda d: d["frames"][1].update(cx=-3.0))
    with pytest.warns(SceneWarning, match=r"transforms.json: frames\[1\] \('images/0001.png'\): principal point "
                                          r"cx = -3 px lies outside the image \(0 to 16 px"):
        load_scene(root, load_images=False)
    _edit_json(root, lambda d: d["frames"][1].update(cx=-16.0 * 5.01))
    with pytest.raises(ValueError, match=r"frames\[1\] .*principal point cx = -80.16 px lies 5.01 image widths "
                                         r"outside"):
        load_scene(root, load_images=False)
    _edit_json(root, lambda d: d["frames"][1].update(cx=-16.0 * 4.99))
    with pytest.warns(SceneWarning):
        load_scene(root, load_images=False)


def _centres_scene(tmp_path, centres):
    rng = np.random.default_rng(7)
    scene = _scene(rng, n=len(centres), full=False)
    for f, c in zip(scene.frames, centres):
        f.cam_T_world[:3, 3] = -f.cam_T_world[:3, :3] @ np.asarray(c, float)  # camera centre c
    write_scene(scene, tmp_path / "s")
    return tmp_path / "s"


def test_far_camera_warned_absurd_one_refused(tmp_path):
    line = [(0.1 * k, 0.0, 3.0) for k in range(6)]  # spread: median distance 0.15 from the median centre
    root = _centres_scene(tmp_path, line[:5] + [(20.25, 0.0, 3.0)])
    with pytest.warns(SceneWarning, match=r"the camera centre of frames\[5\] \('images/0005.png'\) at 20 from "
                                          r"the cameras' median centre, up to 133 x their spread \(0.15"):
        load_scene(root, load_images=False)
    ctx = _no_warnings()
    try:  # 15 x the spread: a plausible path
        load_scene(_centres_scene(tmp_path / "ok", line[:5] + [(2.5, 0.0, 3.0)]), load_images=False)
    finally:
        ctx.__exit__(None, None, None)
    root = _centres_scene(tmp_path / "absurd", line[:5] + [(0.0, 2e6, 3.0)])
    with pytest.raises(ValueError, match=r"frames\[5\] .* at 2e\+06 .* beyond the 1e\+06 x refused"):
        load_scene(root, load_images=False)


def test_tripod_cameras_measure_the_spread_from_the_origin(tmp_path):
    """Cameras that do not move have no spread: 1/1000 of their distance from the origin stands in."""
    root = _centres_scene(tmp_path, [(0.0, 0.0, 3.0)] * 4 + [(0.0, 0.1, 3.0)])
    ctx = _no_warnings()
    try:  # 0.1 from the others = 33 x 0.003
        load_scene(root, load_images=False)
    finally:
        ctx.__exit__(None, None, None)
    root = _centres_scene(tmp_path / "far", [(0.0, 0.0, 3.0)] * 4 + [(0.0, 1.0, 3.0)])
    with pytest.warns(SceneWarning, match=r"up to 333 x their spread \(0.003"):
        load_scene(root, load_images=False)


def _round_poses(root, decimals, name="transforms.json"):
    def fn(d):
        for f in d["frames"]:
            for key in ("transform_matrix", "gt_transform_matrix", "gt_exposure_start", "gt_exposure_end"):
                if key in f:
                    f[key] = np.round(np.array(f[key]), decimals).tolist()
    _edit_json(root, fn, name=name)


def test_poses_rounded_to_6_decimals_are_projected_to_rotations(tmp_path):
    rng = np.random.default_rng(11)
    scene = _scene(rng, n=12)  # 12 frames x 4 poses: some are off by more than RIGID_TOL once rounded
    write_scene(scene, tmp_path / "s")
    root = tmp_path / "s"
    _round_poses(root, 6)
    _round_poses(root, 6, name="transforms_test.json")
    with pytest.warns(SceneWarning, match=r"re-orthonormalised the poses of \d+ frame\(s\) .* largest deviation "
                                          r"[12]\.\de-06") as record:
        loaded = load_scene(root, load_images=False)
    assert len(record) == 1  # said once for the scene
    for a, b in zip(scene.frames + scene.test_frames, loaded.frames + loaded.test_frames):
        for attr in ("cam_T_world", "gt_cam_T_world", "gt_exposure_start", "gt_exposure_end"):
            x, y = getattr(a, attr), getattr(b, attr)
            if x is None:
                continue
            R = y[:3, :3]
            assert np.abs(R.T @ R - np.eye(3)).max() <= RIGID_TOL and abs(np.linalg.det(R) - 1) <= RIGID_TOL
            # rounding moved each entry by <= 5e-7; the projection keeps the rotation within 1e-6 of the
            # original, and the camera centre (the exported translation, kept) within the rounding
            assert np.abs(R - x[:3, :3]).max() <= 1e-6
            centre = lambda T: -np.linalg.solve(T[:3, :3], T[:3, 3])  # noqa: E731 (R may be off by RIGID_TOL)
            assert np.abs(centre(y) - centre(x)).max() <= 5e-7 + POSE_TOL


def test_poses_within_rigid_tol_are_kept_bitwise(scene_dir):
    root, _ = scene_dir
    before = load_scene(root, load_images=False)
    _round_poses(root, 12)  # off by 5e-13: rigid already
    ctx = _no_warnings()
    try:
        after = load_scene(root, load_images=False)
    finally:
        ctx.__exit__(None, None, None)
    for a, b in zip(before.frames, after.frames):
        c2w = np.round(cam_T_world_to_opengl_c2w(a.cam_T_world), 12)
        from d2gs_np.geometry.camera import opengl_c2w_to_cam_T_world
        np.testing.assert_array_equal(b.cam_T_world, opengl_c2w_to_cam_T_world(c2w))


def test_rounding_tolerance_admits_4_decimals_not_3(scene_dir):
    root, _ = scene_dir
    _round_poses(root, 4)
    with pytest.warns(SceneWarning, match="re-orthonormalised"):
        load_scene(root, load_images=False)
    _round_poses(root, 2)  # up to 2.6e-2 off: a scale or shear
    with pytest.raises(ValueError, match=r"is not rigid: the singular values of R .* a scale or shear"):
        load_scene(root, load_images=False)


def test_warnings_are_issued_once_the_scene_is_read_and_kept_on_it(scene_dir):
    root, scene = scene_dir
    cv2.imwrite(str(root / "images" / "0001.png"), np.zeros((H, W, 3), np.uint8))  # a blank frame
    _edit_json(root, lambda d: d["frames"][3].update(time=d["frames"][2]["time"]))
    with pytest.warns(SceneWarning) as record:
        loaded = load_scene(root)
    assert [str(w.message) for w in record] == loaded.warnings
    assert loaded.warnings[0].startswith("transforms.json: frames[2] ('images/0002.png') and frames[3] "
                                         "('images/0003.png') share time")
    assert loaded.warnings[1].startswith("transforms.json: frames[1] ('images/0001.png') is one flat colour")
    with pytest.warns(SceneWarning):
        assert load_scene(root, load_images=False).warnings == loaded.warnings[:1]  # pixels not read


# ------------------------------------------------------------------ depth maps
# Depth maps are written as float32: a relative rounding of at most 2^-24 ~ 6e-8.
DEPTH_RTOL = 2.0 ** -24


def _with_depth(rng, scene):
    for fr in scene.frames + scene.test_frames:
        d = 1.0 + 4.0 * rng.random((fr.height, fr.width))
        d[0, 0] = np.inf  # a ray that hits nothing
        fr.depth = d
    return scene


def test_depth_maps_round_trip_beside_their_images(tmp_path):
    rng = np.random.default_rng(3)
    scene = _with_depth(rng, _scene(rng))
    write_scene(scene, tmp_path / "s")
    assert (tmp_path / "s" / "depth" / "0000.npy").is_file()  # beside images/, as masks/ and sharp/ are
    assert (tmp_path / "s" / "test" / "depth" / "0100.npy").is_file()  # test views: under test/
    loaded = load_scene(tmp_path / "s")
    assert loaded.has_depth
    for a, b in zip(scene.frames + scene.test_frames, loaded.frames + loaded.test_frames):
        assert b.depth.dtype == np.float64 and np.isposinf(b.depth[0, 0])
        np.testing.assert_allclose(b.depth, a.depth, rtol=DEPTH_RTOL, atol=0)
    assert load_scene(tmp_path / "s", load_images=False).frames[0].depth is None  # metadata only


def test_a_scene_without_depth_maps_has_none():
    rng = np.random.default_rng(4)
    assert not _scene(rng).has_depth


@pytest.mark.parametrize("bad, match", [
    (lambda p: np.save(p, np.ones((H, W + 1))), r"shape \(1[0-9], 1[0-9]\).*needs a float array of shape"),
    (lambda p: np.save(p, np.ones((H, W), np.int32)), "int32 array"),
    (lambda p: p.write_bytes(b"not an npy file"), "not a valid .npy array"),
    (lambda p: p.unlink(), "depth file .* does not exist"),
])
def test_a_bad_depth_file_is_refused_before_any_pixel_is_decoded(tmp_path, bad, match):
    rng = np.random.default_rng(5)
    write_scene(_with_depth(rng, _scene(rng)), tmp_path / "s")
    img = tmp_path / "s" / "images" / "0000.png"
    img.write_bytes(img.read_bytes()[:60])  # a valid header, a truncated body: fails only at decoding
    bad(tmp_path / "s" / "depth" / "0002.npy")
    with pytest.raises((ValueError, FileNotFoundError), match=match) as e:
        load_scene(tmp_path / "s")
    assert "frames[2]" in str(e.value) or "0002" in str(e.value)


# ------------------------------------------------------------------ depth priors
def _with_prior(rng, scene):
    for fr in scene.frames:
        p = 0.2 + rng.random((fr.height, fr.width))
        p[1, 2] = np.nan  # no estimate at this pixel
        fr.depth_prior = p
    return scene


def test_depth_priors_round_trip_with_their_missing_pixels(tmp_path):
    rng = np.random.default_rng(13)
    scene = _with_prior(rng, _scene(rng))
    write_scene(scene, tmp_path / "s")
    assert (tmp_path / "s" / "depth_prior" / "0000.npy").is_file()
    loaded = load_scene(tmp_path / "s")
    assert loaded.has_depth_prior and not loaded.has_depth  # a prior is not a true depth
    for a, b in zip(scene.frames, loaded.frames):
        assert b.depth_prior.dtype == np.float64 and np.isnan(b.depth_prior[1, 2])
        np.testing.assert_allclose(b.depth_prior, a.depth_prior, rtol=DEPTH_RTOL, atol=0)  # float32 on disk
    assert not _scene(rng).has_depth_prior


_NOT_DEPTH = ("frames\\[1\\].*depth file .* 1 pixel.*NaN or not positive", "depth has NaN or non-positive values")
_NOT_PRIOR = ("frames\\[1\\].*depth prior file .* 1 pixel.*infinite, zero or negative",
              "depth_prior has infinite, zero or negative values")


@pytest.mark.parametrize("kind, value, matches", [
    ("depth", np.nan, _NOT_DEPTH), ("depth", 0.0, _NOT_DEPTH), ("depth", -1.0, _NOT_DEPTH),
    ("depth", -np.inf, _NOT_DEPTH),
    # a prior may lack an estimate (NaN) but not be infinite: it is a depth or a disparity
    ("depth_prior", 0.0, _NOT_PRIOR), ("depth_prior", -1.0, _NOT_PRIOR), ("depth_prior", np.inf, _NOT_PRIOR),
])
def test_a_map_that_is_not_a_positive_depth_or_estimate_is_refused(tmp_path, kind, value, matches):
    rng = np.random.default_rng(6)
    scene = (_with_depth if kind == "depth" else _with_prior)(rng, _scene(rng))
    write_scene(scene, tmp_path / "s")
    path = tmp_path / "s" / kind / "0001.npy"
    d = np.load(path)
    d[3, 4] = value
    np.save(path, d)
    with pytest.raises(ValueError, match=matches[0]):
        load_scene(tmp_path / "s")
    getattr(scene.frames[1], kind)[3, 4] = value  # and the writer refuses it before writing anything
    with pytest.raises(ValueError, match=matches[1]):
        write_scene(scene, tmp_path / "t")
    assert not (tmp_path / "t").exists()


def test_a_prior_without_any_estimate_and_a_missing_prior_file_are_refused(tmp_path):
    rng = np.random.default_rng(15)
    write_scene(_with_prior(rng, _scene(rng)), tmp_path / "s")
    np.save(tmp_path / "s" / "depth_prior" / "0002.npy", np.full((H, W), np.nan))
    with pytest.raises(ValueError, match="frames\\[2\\].*NaN everywhere; drop 'depth_prior_file_path'"):
        load_scene(tmp_path / "s")
    (tmp_path / "s" / "depth_prior" / "0002.npy").unlink()
    with pytest.raises(FileNotFoundError, match="depth prior file .* does not exist; fix 'depth_prior_file_path'"):
        load_scene(tmp_path / "s", load_images=False)  # found by the header pass, before any pixel
