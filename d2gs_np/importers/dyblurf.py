"""DyBluRF / Stereo Blur scene folders in (``d2gs import-dyblurf``; docs/dataset_format.md §11).

The layout of DyBluRF's data (github.com/huiqiang-sun/DyBluRF, its README and ``load_llff_data.py``):

    FOLDER/
      images/ or images_<size>/   blurry frames of the left camera (size e.g. 512x288, or a factor 4)
      sharp_images/               sharp frames of the left camera (deblurring ground truth; optional)
      inference_images/           sharp frames of the right camera (novel-view ground truth; optional)
      motion_masks/               coarse motion masks of the left frames (optional)
      poses_bounds.npy            LLFF poses: left and right interleaved (rows L0, R0, L1, R1, ...)
      sparse/                     COLMAP's model of those poses, if kept (optional: its points3D)

Each folder is read in file-name order. ``poses_bounds.npy`` holds one row of 17 numbers per
image: a 3x5 matrix flattened row by row, ``[R | t | (h, w, f)]``, then the near and far depth
bounds. ``[R | t]`` is camera-to-world whose rotation columns are the camera's axes in LLFF's order
**[down, right, backwards]** (LLFF's imgs2poses builds it from COLMAP's OpenCV axes [right, down,
forward] as columns (y, x, -z)); (h, w) is the size of the full-resolution ``images/`` and f its
focal length in pixels. Ours is OpenCV [right, down, forward] as world-to-camera, so

    c2w_opencv = [col1, col0, -col2 | t],    cam_T_world = inv(c2w_opencv)

(``llff_to_cam_T_world``; DyBluRF's loader makes OpenGL's [right, up, backwards] = [col1, -col0,
col2] from the same columns). Intrinsics of an image of W x H pixels: fx = f W / w, fy = f H / h,
principal point at the image centre (W / 2, H / 2): LLFF keeps COLMAP's principal point at the
centre of a pinhole camera and stores only f.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from d2gs_np.data.io import write_scene
from d2gs_np.data.scene import Frame, Scene
from d2gs_np.geometry.camera import camera_center, make_intrinsics
from d2gs_np.geometry.se3 import nearest_rigid, se3_inverse
from d2gs_np.importers.colmap import find_model, read_model
from d2gs_np.importers.folders import (REPORT_FILE, check_out_folder, list_images, read_grey, read_rgb, resize_to,
                                       write_report)

__all__ = ["llff_to_cam_T_world", "cam_T_world_to_llff", "import_dyblurf", "image_folder_name", "REPORT_FILE"]

POSES_FILE = "poses_bounds.npy"
_ASPECT_SLACK_PX = 1.0  # a resized folder's width may differ by rounding from w H / h (LLFF rounds it)


def llff_to_cam_T_world(rows) -> np.ndarray:
    """(..., 4, 4) cam_T_world of LLFF pose rows (..., 15) or (..., 3, 5) (module docstring)."""
    M = np.asarray(rows, dtype=np.float64)
    M = M.reshape(M.shape[:-1] + (3, 5)) if M.shape[-1] == 15 else M
    c2w = np.zeros(M.shape[:-2] + (4, 4))
    c2w[..., :3, 0] = M[..., :, 1]  # x right   = LLFF's second column
    c2w[..., :3, 1] = M[..., :, 0]  # y down    = LLFF's first column
    c2w[..., :3, 2] = -M[..., :, 2]  # z forward = minus LLFF's backwards
    c2w[..., :3, 3] = M[..., :, 3]
    c2w[..., 3, 3] = 1.0
    c2w, _ = nearest_rigid(c2w, f"{POSES_FILE} pose")  # float32 files are rigid only to rounding
    return se3_inverse(c2w)


def cam_T_world_to_llff(cam_T_world, h, w, f) -> np.ndarray:
    """(15,) LLFF row [R | t | (h, w, f)] of a (4, 4) cam_T_world: the inverse of llff_to_cam_T_world."""
    c2w = se3_inverse(np.asarray(cam_T_world, dtype=np.float64))
    R = c2w[:3, :3]
    return np.concatenate([R[:, 1:2], R[:, 0:1], -R[:, 2:3], c2w[:3, 3:4], [[h], [w], [f]]], axis=1).ravel()


def image_folder_name(size) -> str:
    """``images`` (size None) or ``images_<size>`` (e.g. "512x288", "4"), as LLFF names them."""
    if size is None:
        return "images"
    size = str(size).strip()
    if not size or "/" in size or "\\" in size:
        raise ValueError(f"--size must name an images_<size> folder, e.g. 512x288 or 4; got {size!r}")
    return f"images_{size}"


def _listing(folder: Path, name, n, required=False):
    """The image files of FOLDER/name, or None when the optional folder is absent; ValueError when
    their count is not the n left frames."""
    path = folder / name
    if not path.is_dir():
        if required:
            have = sorted(p.name for p in folder.iterdir() if p.is_dir() and p.name.startswith("images"))
            raise FileNotFoundError(f"{path} does not exist (image folders in {folder}: {have or 'none'}); "
                                    "pass --size to pick images_<size>")
        return None
    files = list_images(path, name)
    if n is not None and len(files) != n:
        raise ValueError(f"{path} has {len(files)} images but {POSES_FILE} describes {n} stereo pairs; DyBluRF "
                         "expects one per left frame (remove extra files or restore missing ones)")
    return files


def _read_poses(folder: Path):
    path = folder / POSES_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist; a DyBluRF / LLFF scene folder holds its camera poses there")
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as e:
        raise ValueError(f"{path} is not a NumPy array file ({e})") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] < 2 or arr.shape[0] % 2:
        raise ValueError(f"{path} must be (2N, 17): per image a 3x5 [R | t | (h, w, f)] and near, far, rows of the "
                         f"left and right cameras interleaved; got shape {arr.shape}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{path} holds NaN or inf")
    hwf = arr[:, :15].reshape(-1, 3, 5)[:, :, 4]
    if np.any(hwf <= 0):
        raise ValueError(f"{path}: the (h, w, f) column must be positive; got {hwf[np.any(hwf <= 0, axis=1)][0]}")
    return arr


def _intrinsics(hwf, W, H, where):
    """K of an image of W x H pixels from LLFF's (h, w, f) of the full-size images."""
    h, w, f = hwf
    if abs(w * H / h - W) > _ASPECT_SLACK_PX:
        raise ValueError(f"{where} is {W}x{H}, not a resize of the {w:g}x{h:g} images of {POSES_FILE} (aspect "
                         "ratio differs); use images resized from the originals")
    return make_intrinsics(f * W / w, f * H / h, W / 2.0, H / 2.0)


def import_dyblurf(folder, out, size=None, overwrite=False, log=print) -> dict:
    """Import a DyBluRF / Stereo Blur scene folder into the scene folder ``out``: training frames from
    the left camera (blurry images, sharp images, motion masks), test views from the right camera
    (``inference_images``); returns the report (also ``import_report.json``)."""
    t0 = time.perf_counter()
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"DyBluRF scene folder {folder} does not exist (it holds images/, poses_bounds.npy, "
                                "...; DyBluRF's configs point at <scene>/dense)")
    out = check_out_folder(out, overwrite)
    arr = _read_poses(folder)
    n = arr.shape[0] // 2
    img_dir = image_folder_name(size)
    blurry = _listing(folder, img_dir, None, required=True)
    if len(blurry) != n:
        raise ValueError(f"{folder / img_dir} has {len(blurry)} images but {POSES_FILE} has {arr.shape[0]} rows; "
                         f"DyBluRF interleaves left and right poses, so {2 * len(blurry)} rows are expected")
    sharp = _listing(folder, "sharp_images", n)
    right = _listing(folder, "inference_images", n)
    masks = _listing(folder, "motion_masks", n)
    points = None
    if (folder / "sparse").is_dir():
        try:
            model = read_model(find_model(folder / "sparse")[0])
            points = (model.xyz, model.rgb.astype(np.float64) / 255.0) if len(model.point_ids) else None
        except FileNotFoundError:
            points = None  # an incomplete sparse/ folder: no points, the poses are all that is needed

    rows = arr[:, :15].reshape(-1, 3, 5)
    poses = llff_to_cam_T_world(rows)
    left_T, right_T = poses[0::2], poses[1::2]
    hwf_left, hwf_right = rows[0::2, :, 4], rows[1::2, :, 4]
    frames, tests = [], []
    W = H = None
    for k in range(n):
        img = read_rgb(blurry[k], "blurry image")
        if W is None:
            H, W = img.shape[:2]
        elif img.shape[:2] != (H, W):
            raise ValueError(f"{blurry[k]} is {img.shape[1]}x{img.shape[0]}, the first image {W}x{H}; all frames "
                             "must have one size")
        stem = blurry[k].stem
        t = k / (n - 1) if n > 1 else 0.0
        fr = Frame(file_path=f"images/{stem}.png", time=t, cam_T_world=left_T[k],
                   K=_intrinsics(hwf_left[k], W, H, blurry[k]), width=W, height=H, image=img)
        if sharp is not None:  # DyBluRF shows them beside renders of the training size
            fr.sharp = resize_to(read_rgb(sharp[k], "sharp image"), W, H)
            fr.sharp_file_path = f"sharp/{stem}.png"
        if masks is not None:  # DyBluRF: nearest-neighbour resize, moving where the mask is above 0
            fr.mask = resize_to(read_grey(masks[k], "motion mask"), W, H, nearest=True) > 0
            fr.mask_path = f"masks/{stem}.png"
        frames.append(fr)
        if right is not None:  # DyBluRF's evaluation resizes them to the render size (area)
            tests.append(Frame(file_path=f"test/{right[k].stem}.png", time=t, cam_T_world=right_T[k],
                               K=_intrinsics(hwf_right[k], W, H, f"{blurry[k]} (right camera)"), width=W, height=H,
                               image=resize_to(read_rgb(right[k], "inference image"), W, H)))
    far = arr[0::2, 16]
    scene = Scene(frames=frames, test_frames=tests,
                  scene_scale=float(np.median(far)) if np.all(far > 0) else None,
                  points3d=None if points is None else points[0], points3d_colors=None if points is None else points[1])
    write_scene(scene, out, overwrite=overwrite)
    baseline = np.linalg.norm(camera_center(left_T) - camera_center(right_T), axis=1)
    report = {
        "source": str(folder), "images": img_dir, "frames": n, "size": [W, H],
        "names": [p.name for p in blurry], "sharp": sharp is not None, "test_views": len(tests),
        "motion_masks": masks is not None, "points3d": 0 if points is None else int(len(points[0])),
        "focal_px": [float(frames[0].K[0, 0]), float(frames[0].K[1, 1])],
        "stereo_baseline_median": float(np.median(baseline)), "scene_scale": scene.scene_scale,
        "poses": "LLFF [down, right, backwards] camera-to-world -> OpenCV cam_T_world = inv([c1, c0, -c2 | t])",
        "seconds": time.perf_counter() - t0,
    }
    write_report(out, report)
    if log:
        log(f"wrote {n} left frames ({W}x{H}, {img_dir}), {len(tests)} right-camera test views"
            f"{', sharp frames' if sharp is not None else ''}{', motion masks' if masks is not None else ''} to {out} "
            f"in {report['seconds']:.1f}s")
    return report
