"""Read and write scene folders (``docs/dataset_format.md``), with validation.

On disk: ``transforms.json`` (training frames, the blurry video), optional
``transforms_test.json`` (evaluation views), 8-bit PNG images, masks (255 =
dynamic) and sharp ground truth; poses are OpenGL/Nerfstudio camera-to-world
matrices (x right, y up, looking down -z). In memory (``d2gs_np.data.scene``):
``cam_T_world`` world-to-camera with OpenCV axes,
``cam_T_world = inv(c2w @ diag(1, -1, -1, 1))``; images float64 (H, W, 3) in
[0, 1]; masks bool (H, W).

Validation happens in this order so that bad scenes fail early and cheaply:
JSON syntax and every field of both JSON files, then the existence of every
referenced file and its PNG header (size, bit depth, colour type -- 33 bytes
per file), and only then the decoding of the pixels. Errors name the file and
the frame (its index in the JSON ``frames`` list and its ``file_path``) and
say how to fix it. Missing files raise FileNotFoundError; everything else
ValueError.

Choices the format leaves open:
- Frames of each file are returned sorted by ``time`` (stable: frames with
  equal times keep their file order).
- Intrinsics of ``transforms_test.json`` default to its own top-level values,
  then to those of ``transforms.json``; a frame may override any of them.
- A ``file_path`` without an extension that exists only with ``.png``
  appended (the D-NeRF/Blender habit) is accepted and stored with ``.png``.
- JSON ``null`` for an optional field means absent. Unknown fields are
  ignored. Nerfstudio distortion fields (k1..k4, p1, p2) must be zero and
  ``camera_model``, if given, a pinhole one: this project has no distortion.
- Images must be 8-bit RGB (or palette) PNGs; RGBA is rejected rather than
  composited onto a guessed background. Masks must be 8-bit (or 1-bit)
  greyscale PNGs, 0/255 (thresholded at > 127) or 0/1 (1 = moving), decided
  once for the scene from its brightest mask pixel.

Plausibility (docs/dataset_format.md §5): impossible content is refused
(ValueError), implausible content accepted with one ``SceneWarning`` line
each (``d2gs_np.base.checks``), issued once the whole scene is read and kept in
``Scene.warnings``: intrinsics outside a plausible field of view or principal
point, a camera far from the others, frames sharing a time, poses rigid only
up to rounding (re-orthonormalised), a frame of one flat colour.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np

from d2gs_np.base.checks import SceneWarning, name_items, warn
from d2gs_np.constants import POSE_ROUNDING_TOL, RIGID_TOL
from d2gs_np.data.scene import Frame, Scene
from d2gs_np.geometry.camera import (
    cam_T_world_to_opengl_c2w,
    check_intrinsics,
    check_rigid,
    make_intrinsics,
    opengl_c2w_to_cam_T_world,
)
from d2gs_np.geometry.se3 import nearest_rigid

__all__ = ["load_scene", "write_scene", "TRANSFORMS_FILE", "TRANSFORMS_TEST_FILE"]

TRANSFORMS_FILE = "transforms.json"
TRANSFORMS_TEST_FILE = "transforms_test.json"
POINTS_FILE = "points3d.ply"  # sparse points written by write_scene when the scene has them

_INTRINSIC_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
_POSE_KEYS = (
    ("transform_matrix", "cam_T_world"),
    ("gt_transform_matrix", "gt_cam_T_world"),
    ("gt_exposure_start", "gt_exposure_start"),
    ("gt_exposure_end", "gt_exposure_end"),
)
_MASK_THRESHOLD = 127  # mask pixels > 127 are dynamic (255 = dynamic, 0 = static)
_MASK_DEPTHS = (1, 8)  # bit depths of greyscale mask PNGs: 8-bit, or 1-bit (a saved bool array; decoded as 0/255)
# Plausible pinhole intrinsics (docs/dataset_format.md §5). The field of view of an image axis,
# 2 atan(size / (2 f)), outside _FOV_WARN_DEG is implausible for a video camera (1 deg: a 2000 mm
# lens on a full-frame sensor; 170 deg: a fisheye, which a pinhole without distortion cannot model)
# and warned about; outside _FOV_REFUSE_DEG the focal length cannot be in pixels (f below 0.0044 or
# above 5700 image sizes: metres, millimetres or divided by the image size) and is refused.
_FOV_WARN_DEG = (1.0, 170.0)
_FOV_REFUSE_DEG = (0.01, 179.0)
# A principal point outside the image is warned about (the optical axis of a video frame crosses it;
# a crop or a resize without scaling cx, cy moves it out); more than this many image sizes outside,
# refused (cx, cy in other units or of another resolution).
_PRINCIPAL_POINT_MAX_OUTSIDE = 5.0
# A training camera whose centre lies farther from the median centre than these multiples of the
# cameras' spread (the median distance from the median centre) is warned about / refused: it sets
# the camera extent (1.1 x the largest distance; the position learning rates, pruning and
# densification) alone. The spread is taken at least 1/1000 of the cameras' median distance from the
# origin and of scene_scale: cameras on a tripod have none.
_CAMERA_OUTLIER_WARN = 100.0
_CAMERA_OUTLIER_REFUSE = 1e6
_CAMERA_SPREAD_FLOOR = 1e-3
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_HEADER_BYTES = 26  # signature (8) + IHDR length/type (8) + width, height (8) + depth, colour (2)
_PNG_COLOR_NAMES = {0: "greyscale", 2: "RGB", 3: "palette", 4: "greyscale+alpha", 6: "RGBA"}


# ------------------------------------------------------------------ small checkers
def _is_number(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _finite(value):
    try:
        return _is_number(value) and math.isfinite(value)
    except OverflowError:  # an int too large for a float
        return False


def _number(value, where, field):
    if not _finite(value):
        raise ValueError(f"{where}: '{field}' must be a finite number; got {value!r}")
    return float(value)


def _positive_int(value, where, field):
    if not _finite(value) or value != int(value) or value <= 0:
        raise ValueError(f"{where}: '{field}' must be a positive integer; got {value!r}")
    return int(value)


def _matrix4(value, where, field):
    """Nested 4x4 list of numbers -> ((4, 4) float64 rigid, deviation): a rotation rigid only up to
    rounding (``POSE_ROUNDING_TOL``) is re-orthonormalised (``nearest_rigid``), anything else refused."""
    ok = (
        isinstance(value, list)
        and len(value) == 4
        and all(isinstance(row, list) and len(row) == 4 and all(_is_number(x) for x in row) for row in value)
    )
    if not ok:
        raise ValueError(f"{where}: '{field}' must be a 4x4 nested list of numbers (row-major); got {value!r}")
    try:
        M = np.array(value, dtype=np.float64)
    except OverflowError:
        raise ValueError(f"{where}: '{field}' has an entry too large for a float64") from None
    M, dev = nearest_rigid(M, f"{where}: '{field}'")
    return M, float(dev)


def _frame_label(source, index, frame):
    fp = frame.get("file_path") if isinstance(frame, dict) else None
    return f"{source} frames[{index}]" + (f" ({fp!r})" if isinstance(fp, str) else "")


# ------------------------------------------------------------------------ JSON
def _read_json(path):
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path} is not UTF-8 text ({e}); save it as UTF-8 JSON") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(
            f"{path} is not valid JSON: {e.msg} at line {e.lineno}, column {e.colno}; fix the syntax"
        ) from None
    if not isinstance(data, dict):
        raise ValueError(f"{path} must hold a JSON object with a 'frames' list; got a {type(data).__name__}")
    frames = data.get("frames")
    if not isinstance(frames, list):
        has = "it has none" if frames is None else f"its 'frames' is a JSON {_json_kind(frames)}"
        raise ValueError(f"{path} must have a 'frames' list (one entry per image); {has}")
    if len(frames) == 0:
        raise ValueError(f"{path} has an empty 'frames' list; a scene needs at least one frame")
    return data


def _json_kind(value):
    """The JSON name of a parsed value's type, for messages ("object" for a dict)."""
    return {dict: "object", str: "string", bool: "boolean", int: "number", float: "number"}.get(type(value), "value")


def _check_camera_model(d, where):
    model = d.get("camera_model")
    if model is not None and model not in _PINHOLE_MODELS:
        raise ValueError(
            f"{where}: camera_model {model!r} is not supported; only pinhole cameras "
            f"({', '.join(_PINHOLE_MODELS)} with zero distortion). Undistort the images first."
        )
    for k in _DISTORTION_KEYS:
        v = d.get(k)
        if v is not None and (not _is_number(v) or v != 0):
            raise ValueError(
                f"{where}: distortion coefficient '{k}' = {v!r}, but this project has no lens "
                "distortion model; undistort the images and set it to 0 (or remove it)"
            )


def _top_intrinsics(data):
    return {k: data[k] for k in _INTRINSIC_KEYS if data.get(k) is not None}


def _top_level_optional(data, where):
    out = {}
    v = data.get("exposure_fraction")
    if v is not None:
        v = _number(v, where, "exposure_fraction")
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{where}: 'exposure_fraction' must be in [0, 1] (a fraction of the frame interval); got {v}")
    out["exposure_fraction"] = v
    v = data.get("scene_scale")
    if v is not None:
        v = _number(v, where, "scene_scale")
        if v <= 0:
            raise ValueError(f"{where}: 'scene_scale' must be positive (world units); got {v}")
    out["scene_scale"] = v
    v = data.get("blur_subframes")
    out["blur_subframes"] = None if v is None else _positive_int(v, where, "blur_subframes")
    v = data.get("poses_trusted")
    if v is not None and not isinstance(v, bool):
        raise ValueError(f"{where}: 'poses_trusted' must be true or false (are the given poses exact?); got {v!r}")
    out["poses_trusted"] = v
    v = data.get("ply_file_path")
    if v is not None and (not isinstance(v, str) or not v.strip() or os.path.isabs(v)):
        raise ValueError(f"{where}: 'ply_file_path' must be a path relative to the scene folder; got {v!r}")
    out["ply_file_path"] = v
    return out


class _Spec:
    """Validated metadata of one frame plus where its files are."""

    __slots__ = ("label", "short", "fields", "image_file", "mask_file", "sharp_file", "depth_file", "prior_file",
                 "rounding")


def _resolve_path(root, rel, label, field):
    if not isinstance(rel, str) or not rel.strip():
        raise ValueError(f"{label}: '{field}' must be a non-empty string path relative to the scene folder; got {rel!r}")
    if os.path.isabs(rel):
        raise ValueError(f"{label}: '{field}' = {rel!r} is absolute; paths must be relative to the scene folder")
    full = root / rel
    if not full.exists() and not Path(rel).suffix and (root / (rel + ".png")).exists():
        rel = rel + ".png"  # D-NeRF / Blender style path without extension
        full = root / rel
    return rel, full


def _parse_frame(root, source, index, frame, defaults):
    label = _frame_label(source, index, frame)
    if not isinstance(frame, dict):
        raise ValueError(f"{label} must be a JSON object; got {frame!r}")
    for req in ("file_path", "time", "transform_matrix"):
        if frame.get(req) is None:
            raise ValueError(f"{label}: missing required field '{req}' (see docs/dataset_format.md §3)")
    _check_camera_model(frame, label)
    spec = _Spec()
    spec.label = label
    f = {}
    f["file_path"], spec.image_file = _resolve_path(root, frame["file_path"], label, "file_path")
    spec.short = f"frames[{index}] ({f['file_path']!r})"
    t = _number(frame["time"], label, "time")
    if not 0.0 <= t <= 1.0:
        raise ValueError(f"{label}: 'time' must be a normalised timestamp in [0, 1]; got {t}")
    f["time"] = t
    spec.rounding = 0.0  # largest deviation from rigid of the frame's poses that were re-orthonormalised
    for key, attr in _POSE_KEYS:
        if frame.get(key) is not None:
            c2w, dev = _matrix4(frame[key], label, key)
            if dev > RIGID_TOL:
                spec.rounding = max(spec.rounding, dev)
            f[attr] = opengl_c2w_to_cam_T_world(c2w)
    intr = dict(defaults)
    intr.update({k: frame[k] for k in _INTRINSIC_KEYS if frame.get(k) is not None})
    for k in _INTRINSIC_KEYS:
        if k not in intr:
            raise ValueError(
                f"{label}: missing intrinsic '{k}'; give it at the top level of {source} "
                "(shared by all frames) or in the frame"
            )
    f["width"] = _positive_int(intr["w"], label, "w")
    f["height"] = _positive_int(intr["h"], label, "h")
    fx = _number(intr["fl_x"], label, "fl_x")
    fy = _number(intr["fl_y"], label, "fl_y")
    if fx <= 0 or fy <= 0:
        raise ValueError(f"{label}: focal lengths must be positive (pixels); got fl_x={fx}, fl_y={fy}")
    cx, cy = _number(intr["cx"], label, "cx"), _number(intr["cy"], label, "cy")
    lo, hi = _FOV_REFUSE_DEG
    for key, focal, size, axis in (("fl_x", fx, f["width"], "width"), ("fl_y", fy, f["height"], "height")):
        f_min, f_max = _focal_for(hi, size), _focal_for(lo, size)
        if not f_min <= focal <= f_max:
            side = f"below {f_min:.3g} px, a {hi:g}" if focal < f_min else f"above {f_max:.3g} px, a {lo:g}"
            raise ValueError(
                f"{label}: {key} = {focal:g} px is {side} deg field of view over the {size} px {axis}: not a focal "
                "length in pixels; convert it to pixels (a focal length in mm or metres, or divided by the image "
                "size?)")
    for key, c, size, axis in (("cx", cx, f["width"], "width"), ("cy", cy, f["height"], "height")):
        out = max(-c, c - size) / size  # image sizes outside [0, size]
        if out > _PRINCIPAL_POINT_MAX_OUTSIDE:
            raise ValueError(
                f"{label}: principal point {key} = {c:g} px lies {out:.3g} image {axis}s outside the {size} px "
                f"image (more than {_PRINCIPAL_POINT_MAX_OUTSIDE:g} is refused): give cx, cy in pixels of this "
                "image (the image centre is w/2, h/2)")
    f["K"] = make_intrinsics(fx, fy, cx, cy)
    spec.mask_file = spec.sharp_file = spec.depth_file = spec.prior_file = None
    if frame.get("depth_file_path") is not None:
        f["depth_file_path"], spec.depth_file = _resolve_path(root, frame["depth_file_path"], label, "depth_file_path")
    if frame.get("depth_prior_file_path") is not None:
        f["depth_prior_file_path"], spec.prior_file = _resolve_path(root, frame["depth_prior_file_path"], label,
                                                                    "depth_prior_file_path")
    if frame.get("mask_path") is not None:
        f["mask_path"], spec.mask_file = _resolve_path(root, frame["mask_path"], label, "mask_path")
    if frame.get("sharp_file_path") is not None:
        f["sharp_file_path"], spec.sharp_file = _resolve_path(root, frame["sharp_file_path"], label, "sharp_file_path")
    spec.fields = f
    return spec


def _fov_deg(focal, size):
    """Field of view in degrees of ``size`` pixels at focal length ``focal`` pixels."""
    return math.degrees(2.0 * math.atan(size / (2.0 * focal)))


def _focal_for(fov_deg, size):
    """The focal length (pixels) that gives ``size`` pixels a field of view of ``fov_deg`` degrees."""
    return size / (2.0 * math.tan(math.radians(fov_deg) / 2.0))


def _which(specs, group):
    """'all N frames' or the frames of ``group`` named."""
    if len(group) == len(specs) > 1:
        return f"all {len(specs)} frames"
    return name_items([s.short for s in group])


def _check_duplicates(specs, source):
    first = {}
    for s in specs:
        key = os.path.normpath(s.fields["file_path"])
        if key in first:
            raise ValueError(f"{source} {s.short} repeats {first[key].short}: the same image twice; each frame "
                             "must appear once in 'frames', remove the duplicate entry")
        first[key] = s


def _intrinsics_warnings(specs, source):
    """One warning per implausible value (field of view, principal point), naming the frames that have it."""
    groups = {}
    lo, hi = _FOV_WARN_DEG
    for s in specs:
        f, K = s.fields, s.fields["K"]
        w, h, fx, fy = f["width"], f["height"], K[0, 0], K[1, 1]
        fovs = (_fov_deg(fx, w), _fov_deg(fy, h))
        if not all(lo <= v <= hi for v in fovs):
            msg = (f"fl_x, fl_y = {fx:g}, {fy:g} px give a field of view of {fovs[0]:.4g} x {fovs[1]:.4g} deg over "
                   f"the {w}x{h} image, outside the [{lo:g}, {hi:g}] deg of a video camera (fl_x in "
                   f"[{_focal_for(hi, w):.3g}, {_focal_for(lo, w):.3g}], fl_y in [{_focal_for(hi, h):.3g}, "
                   f"{_focal_for(lo, h):.3g}] px); a wrong focal length renders every view at the wrong scale: check "
                   "its unit (pixels) and the image size it belongs to")
            groups.setdefault(msg, []).append(s)
        for key, c, size, axis in (("cx", K[0, 2], f["width"], "width"), ("cy", K[1, 2], f["height"], "height")):
            if not 0.0 <= c <= size:
                msg = (f"principal point {key} = {c:g} px lies outside the image (0 to {size} px, its {axis}); the "
                       "optical axis of a video frame passes through the image: check cx, cy (a crop, or a resize "
                       "without scaling them?)")
                groups.setdefault(msg, []).append(s)
    return [f"{source}: {_which(specs, group)}: {msg}" for msg, group in groups.items()]


def _parse_file(root, path, defaults):
    data = _read_json(path)
    _check_camera_model(data, path.name)
    intr = dict(defaults)
    intr.update(_top_intrinsics(data))
    specs = [_parse_frame(root, path.name, i, fr, intr) for i, fr in enumerate(data["frames"])]
    _check_duplicates(specs, path.name)
    specs.sort(key=lambda s: s.fields["time"])  # stable
    return data, specs


def _times_warnings(specs, source):
    """Frames of one video have distinct times: a warning names those that share one."""
    by_time = {}
    for s in specs:
        by_time.setdefault(s.fields["time"], []).append(s)
    shared = [(t, g) for t, g in by_time.items() if len(g) > 1]
    if not shared:
        return []
    why = ("frames of one video have distinct times, and the deformation model takes frames of one time for one "
           "instant (a moving object in the same place in all of them); give frame k of N the time k / (N - 1)")
    if len(by_time) == 1:
        return [f"{source}: all {len(specs)} frames have time {specs[0].fields['time']:g}; {why}"]
    parts = [f"{name_items([s.short for s in g])} share time {t:g}" for t, g in shared]
    more = f" (and {len(parts) - 3} more times)" if len(parts) > 3 else ""
    return [f"{source}: {'; '.join(parts[:3])}{more}; {why}"]


def _camera_outlier_warnings(specs, source, scene_scale):
    """Refuse a training camera absurdly far from all the others, warn about one far (module constants)."""
    if len(specs) < 3:
        return []  # with two cameras neither is the odd one
    T = np.stack([s.fields["cam_T_world"] for s in specs])
    centres = -np.einsum("nji,nj->ni", T[:, :3, :3], T[:, :3, 3])  # -R^T t
    median = np.median(centres, axis=0)
    dist = np.linalg.norm(centres - median, axis=1)
    spread = max(float(np.median(dist)), _CAMERA_SPREAD_FLOOR * float(np.median(np.linalg.norm(centres, axis=1))),
                 _CAMERA_SPREAD_FLOOR * (scene_scale or 0.0))
    if not spread > 0.0:
        return []  # every camera at the origin: nothing to compare with
    ratio = dist / spread
    far = [i for i in np.argsort(-ratio) if ratio[i] > _CAMERA_OUTLIER_WARN]
    if not far:
        return []
    worst = far[0]
    named = name_items([f"{specs[i].short} at {dist[i]:.3g}" for i in far])
    what = (f"{source}: the camera centre of {named} from the cameras' median centre, up to {ratio[worst]:.3g} x "
            f"their spread ({spread:.3g}, the median distance)")
    if ratio[worst] > _CAMERA_OUTLIER_REFUSE:
        raise ValueError(f"{what}, beyond the {_CAMERA_OUTLIER_REFUSE:g} x refused: not a camera of this video; fix "
                         "its transform_matrix (a translation in other units?) or remove the frame")
    return [f"{what}, above the {_CAMERA_OUTLIER_WARN:g} x of a plausible camera path; a far camera alone sets "
            "the camera extent (the position learning rates, pruning and densification): check its transform_matrix"]


# ------------------------------------------------------------------------- PNG
def _png_header(path, label, what):
    """Existence and PNG header check -> (width, height, bit_depth, color_type)."""
    if path.is_dir():
        raise ValueError(f"{label}: {what} path {path} is a folder, not a PNG file; fix the path in the JSON")
    if not path.is_file():
        raise FileNotFoundError(f"{label}: {what} file {path} does not exist; fix the path in the JSON or add the file")
    with open(path, "rb") as fh:
        head = fh.read(_PNG_HEADER_BYTES)
    if len(head) < _PNG_HEADER_BYTES or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ValueError(f"{label}: {what} file {path} is not a valid PNG (bad or truncated header); re-save it as PNG")
    width = int.from_bytes(head[16:20], "big")
    height = int.from_bytes(head[20:24], "big")
    return width, height, head[24], head[25]


def _check_png(path, label, what, width, height, gray):
    w, h, depth, color = _png_header(path, label, what)
    kind = _PNG_COLOR_NAMES.get(color, f"colour type {color}")
    if gray and color == 0 and depth in _MASK_DEPTHS:
        pass
    elif depth != 8:
        need = "8-bit (or 1-bit) greyscale PNG" if gray else "8-bit PNG"
        raise ValueError(f"{label}: {what} {path} has {depth}-bit channels; the format needs {need}")
    if gray and color != 0:
        raise ValueError(f"{label}: {what} {path} is {kind}; masks must be single-channel 8-bit greyscale PNG "
                         "(255 or 1 = dynamic, 0 = static)")
    if not gray and color not in (2, 3):
        fix = " (composite it onto a background and save RGB)" if color in (4, 6) else ""
        raise ValueError(f"{label}: {what} {path} is {kind}; images must be 8-bit RGB PNG{fix}")
    if (w, h) != (width, height):
        raise ValueError(
            f"{label}: {what} {path} is {w}x{h} pixels but the frame's intrinsics say w={width}, h={height}; "
            "fix w/h (and fl_x, fl_y, cx, cy) or resize the image"
        )


# ------------------------------------------------------------------ depth maps
def _check_npy(path, label, width, height, field="depth_file_path"):
    """Existence and .npy header check of a depth map (or of a depth prior, ``field``): a 2-D
    float array of the frame's size."""
    what = "depth" if field == "depth_file_path" else "depth prior"
    if path.is_dir():
        raise ValueError(f"{label}: {what} path {path} is a folder, not a .npy file; fix '{field}' in the JSON")
    if not path.is_file():
        raise FileNotFoundError(f"{label}: {what} file {path} does not exist; fix '{field}' in the JSON or "
                                "add the file")
    try:
        with open(path, "rb") as fh:
            major, _ = np.lib.format.read_magic(fh)
            read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(fh)
    except (ValueError, OSError) as e:
        raise ValueError(f"{label}: {what} file {path} is not a valid .npy array ({e}); save it with numpy.save") from e
    if shape != (height, width) or not np.issubdtype(dtype, np.floating):
        raise ValueError(f"{label}: {what} file {path} holds a {dtype} array of shape {shape}; the format needs a float "
                         f"array of shape (h, w) = ({height}, {width}): "
                         + ("camera z per pixel" if what == "depth" else "an estimated depth or disparity per pixel"))


def _bad_depth(d):
    """Pixels of a depth map that are no camera z: NaN, zero or negative (-inf included)."""
    return np.isnan(d) | (d <= 0)


def _decode_depth(path, label):
    d = np.load(path, allow_pickle=False).astype(np.float64)
    bad = _bad_depth(d)
    if np.any(bad):
        raise ValueError(f"{label}: depth file {path} has {int(bad.sum())} pixel(s) that are NaN or not positive; depth "
                         "is the camera z of the first surface (> 0), +inf where the ray hits nothing")
    return d


def _bad_prior(d):
    """Pixels of a depth prior that are neither an estimate (finite, > 0) nor NaN (no estimate)."""
    return ~np.isnan(d) & ~(np.isfinite(d) & (d > 0))


def _decode_prior(path, label):
    d = np.load(path, allow_pickle=False).astype(np.float64)
    bad = _bad_prior(d)
    if np.any(bad):
        raise ValueError(f"{label}: depth prior file {path} has {int(bad.sum())} pixel(s) that are infinite, zero or "
                         "negative; a prior holds an estimated depth or disparity (> 0) per pixel, NaN where there "
                         "is none")
    if not np.any(~np.isnan(d)):
        raise ValueError(f"{label}: depth prior file {path} is NaN everywhere; drop 'depth_prior_file_path' for this "
                         "frame or give it an estimate")
    return d


def _decode(path, label, what, gray):
    flags = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
    arr = cv2.imread(str(path), flags)
    if arr is None:
        raise ValueError(f"{label}: could not decode {what} {path} (corrupt or truncated PNG); re-save or replace it")
    if gray:
        return arr  # uint8; made bool by _binarise_masks once the scene's encoding is known
    return arr[:, :, ::-1].astype(np.float64) / 255.0  # BGR -> RGB, [0, 1]


def _binarise_masks(pairs):
    """(spec, frame) pairs with raw uint8 masks -> bool masks, True = moving; returns warnings. The
    encoding is the scene's: 0/255 (> 127 moving, anti-aliased greys allowed) when its brightest mask
    pixel is >= 128, 0/1 (1 moving) when it is 1; 2 to 127 is neither and refused (read as 0/255,
    every pixel static). A 0/1 mask among 0/255 ones is warned about."""
    pairs = [(s, f) for s, f in pairs if f.mask is not None]
    if not pairs:
        return []
    peaks = [int(f.mask.max()) for _, f in pairs]
    top = max(peaks)
    if 1 < top <= _MASK_THRESHOLD:
        s = pairs[peaks.index(top)][0]
        raise ValueError(f"{s.label}: mask {s.mask_file} holds the brightest pixel of the scene's motion masks, {top}: "
                         "neither 0/255 masks (moving > 127) nor 0/1 masks (moving = 1), so every pixel would count "
                         "as static; save the masks with 255 (or 1) = moving, 0 = static")
    threshold = _MASK_THRESHOLD if top > _MASK_THRESHOLD else 0
    odd = [s for (s, _), p in zip(pairs, peaks) if p == 1] if threshold else []
    for _, f in pairs:
        f.mask = f.mask > threshold
    if not odd:
        return []
    return [f"the masks of {name_items([s.label for s in odd], 2)} hold only 0 and 1 while the others are 0/255 "
            "masks: read as 0/255 (moving > 127) they are all static; save every mask with one encoding"]


def _flat_image_warnings(pairs):
    """A training frame whose image is one flat colour (a blank export?) is warned about; every frame
    flat is refused by training (``train.setup.validate_scene_for_training``)."""
    flat = [s for s, f in pairs if f.image is not None and np.all(f.image == f.image[0, 0])]
    if not flat:
        return []
    return [f"{TRANSFORMS_FILE}: {_which([s for s, _ in pairs], flat)} "
            f"{'is' if len(flat) == 1 else 'are'} one flat colour (a black or blank export?): nothing there to "
            "learn but one colour"]


# --------------------------------------------------------------------- loading
def load_scene(path, load_images=True) -> Scene:
    """Load a scene folder (docs/dataset_format.md) into a validated ``Scene``.

    path: the scene folder. load_images: if False, only metadata is read (file
    existence and PNG headers are still checked); ``image``, ``mask`` and
    ``sharp`` stay None.

    Frames of ``transforms.json`` and of ``transforms_test.json`` (if present)
    are each sorted by ``time``. Poses come back as ``cam_T_world`` (OpenCV),
    images as float64 (H, W, 3) RGB in [0, 1] (value / 255), masks as bool
    (H, W) (pixel > 127 of 0/255 masks, 1 of 0/1 masks). Implausible content
    gives a ``SceneWarning`` (module docstring). Top-level ``exposure_fraction``, ``scene_scale``,
    ``blur_subframes`` come from ``transforms.json``; absent -> None.
    Raises FileNotFoundError for a missing folder or file, ValueError for any
    invalid content; see the module docstring for the order of checks.
    """
    root = Path(path)
    if not root.exists():
        raise FileNotFoundError(f"scene folder {root} does not exist")
    if not root.is_dir():
        raise ValueError(f"scene path {root} is not a folder; pass the folder that holds {TRANSFORMS_FILE}")
    tf = root / TRANSFORMS_FILE
    if not tf.is_file():
        raise FileNotFoundError(
            f"no {TRANSFORMS_FILE} in scene folder {root}; every scene needs one (see docs/dataset_format.md §1)"
        )

    # 1. JSON contents
    data, train = _parse_file(root, tf, {})
    optional = _top_level_optional(data, TRANSFORMS_FILE)
    test = []
    tt = root / TRANSFORMS_TEST_FILE
    if tt.exists():
        _, test = _parse_file(root, tt, _top_intrinsics(data))
    # implausible content: warned about once the whole scene is read (docs/dataset_format.md §5)
    notes = _intrinsics_warnings(train, TRANSFORMS_FILE) + _intrinsics_warnings(test, TRANSFORMS_TEST_FILE)
    notes += _times_warnings(train, TRANSFORMS_FILE)
    notes += _camera_outlier_warnings(train, TRANSFORMS_FILE, optional["scene_scale"])
    rounded = [s for s in train + test if s.rounding > 0.0]
    if rounded:
        notes.append(f"re-orthonormalised the poses of {len(rounded)} frame(s) "
                     f"({name_items([s.label for s in rounded], 2)}): rigid only up to rounding, largest deviation "
                     f"{max(s.rounding for s in rounded):.2g} (max |R^T R - I|, |det R - 1|); up to "
                     f"{POSE_ROUNDING_TOL:g}, what an export rounded to 4 or more decimals gives, a rotation is "
                     "projected to the nearest one")

    # 2. files exist, headers agree with the intrinsics
    ply_rel = optional.pop("ply_file_path")
    if ply_rel is not None and not (root / ply_rel).is_file():
        state = "is a folder" if (root / ply_rel).is_dir() else "does not exist"
        raise FileNotFoundError(f"{TRANSFORMS_FILE}: 'ply_file_path' {ply_rel!r} {state} in {root}; "
                                "fix the path or remove the field")
    for spec in train + test:
        w, h = spec.fields["width"], spec.fields["height"]
        _check_png(spec.image_file, spec.label, "image", w, h, gray=False)
        if spec.mask_file is not None:
            _check_png(spec.mask_file, spec.label, "mask", w, h, gray=True)
        if spec.sharp_file is not None:
            _check_png(spec.sharp_file, spec.label, "sharp image", w, h, gray=False)
        if spec.depth_file is not None:
            _check_npy(spec.depth_file, spec.label, w, h)
        if spec.prior_file is not None:
            _check_npy(spec.prior_file, spec.label, w, h, "depth_prior_file_path")

    # 3. pixels
    def build(spec):
        fr = Frame(**spec.fields)
        if load_images:
            fr.image = _decode(spec.image_file, spec.label, "image", gray=False)
            if spec.mask_file is not None:
                fr.mask = _decode(spec.mask_file, spec.label, "mask", gray=True)
            if spec.sharp_file is not None:
                fr.sharp = _decode(spec.sharp_file, spec.label, "sharp image", gray=False)
            if spec.depth_file is not None:
                fr.depth = _decode_depth(spec.depth_file, spec.label)
            if spec.prior_file is not None:
                fr.depth_prior = _decode_prior(spec.prior_file, spec.label)
        return fr

    frames, test_frames = [build(s) for s in train], [build(s) for s in test]
    notes += _binarise_masks(list(zip(train + test, frames + test_frames)))
    notes += _flat_image_warnings(list(zip(train, frames)))
    scene = Scene(
        frames=frames,
        test_frames=test_frames,
        root=root,
        warnings=notes,
        **optional,
    )
    if ply_rel is not None:  # optional sparse points (docs/dataset_format.md §4)
        from d2gs_np.data.ply import read_points_ply

        scene.points3d, scene.points3d_colors = read_points_ply(root / ply_rel)
    for message in notes:
        warn(message, SceneWarning)
    return scene


# --------------------------------------------------------------------- writing
def _check_out_path(rel, where, field, suffix=".png"):
    if not isinstance(rel, str) or not rel:
        raise ValueError(f"{where}: {field} must be a non-empty relative path string; got {rel!r}")
    p = Path(rel)
    if p.is_absolute() or ".." in p.parts:
        raise ValueError(f"{where}: {field} {rel!r} must be a relative path inside the scene folder")
    if p.suffix.lower() != suffix:
        what = "images are written as PNG" if suffix == ".png" else "depth maps are written as .npy"
        raise ValueError(f"{where}: {field} {rel!r} must end in {suffix} ({what})")
    return p.as_posix()


def _check_pose_attr(T, where, attr):
    T = np.asarray(T)
    if T.shape != (4, 4):
        raise ValueError(f"{where}: {attr} must have shape (4, 4); got {T.shape}")
    check_rigid(T, f"{where}: {attr}")


def _check_rgb(img, where, attr, w, h):
    if img is None:
        raise ValueError(f"{where}: {attr} is None; load the scene with load_images=True before writing it")
    if not isinstance(img, np.ndarray) or not np.issubdtype(img.dtype, np.floating):
        raise TypeError(f"{where}: {attr} must be a float array in [0, 1]; got {getattr(img, 'dtype', type(img))}")
    if img.shape != (h, w, 3):
        raise ValueError(f"{where}: {attr} must have shape (H, W, 3) = ({h}, {w}, 3); got {img.shape}")
    if not np.all(np.isfinite(img)):
        raise ValueError(f"{where}: {attr} contains NaN or inf")


def _plan_frame(fr, where, used):
    """Validate one frame and return (json dict without intrinsics, list of (rel, kind, array))."""
    if not isinstance(fr, Frame):
        raise TypeError(f"{where} must be a Frame; got {type(fr).__name__}")
    w, h = fr.width, fr.height
    if not (isinstance(w, (int, np.integer)) and isinstance(h, (int, np.integer)) and w > 0 and h > 0):
        raise ValueError(f"{where}: width and height must be positive integers; got {w!r}, {h!r}")
    check_intrinsics(fr.K, f"{where}: K")
    t = float(fr.time)
    if not (math.isfinite(t) and 0.0 <= t <= 1.0):
        raise ValueError(f"{where}: time must be in [0, 1]; got {fr.time}")
    rel = _check_out_path(fr.file_path, where, "file_path")
    stem = Path(rel).stem
    d = {"file_path": rel, "time": t}
    writes = []
    for key, attr in _POSE_KEYS:
        T = getattr(fr, attr)
        if T is None:
            if attr == "cam_T_world":
                raise ValueError(f"{where}: cam_T_world is None; every frame needs a pose")
            continue
        _check_pose_attr(T, where, attr)
        d[key] = cam_T_world_to_opengl_c2w(np.asarray(T, dtype=np.float64)).tolist()
    _check_rgb(fr.image, where, "image", w, h)
    writes.append((rel, "rgb", fr.image))
    if fr.mask is not None or fr.mask_path is not None:
        if fr.mask is None:
            raise ValueError(f"{where}: mask_path is set but mask is None; load with load_images=True first")
        if not isinstance(fr.mask, np.ndarray) or fr.mask.dtype != np.bool_ or fr.mask.shape != (h, w):
            raise ValueError(f"{where}: mask must be a bool array of shape ({h}, {w}); got "
                             f"{getattr(fr.mask, 'dtype', type(fr.mask))} {getattr(fr.mask, 'shape', '')}")
        mrel = _check_out_path(fr.mask_path or f"masks/{stem}.png", where, "mask_path")
        d["mask_path"] = mrel
        writes.append((mrel, "mask", fr.mask))
    if fr.sharp is not None or fr.sharp_file_path is not None:
        _check_rgb(fr.sharp, where, "sharp", w, h)
        srel = _check_out_path(fr.sharp_file_path or f"sharp/{stem}.png", where, "sharp_file_path")
        d["sharp_file_path"] = srel
        writes.append((srel, "rgb", fr.sharp))
    if fr.depth is not None or fr.depth_file_path is not None:
        if fr.depth is None:
            raise ValueError(f"{where}: depth_file_path is set but depth is None; load with load_images=True first")
        dep = np.asarray(fr.depth)
        if dep.shape != (h, w) or not np.issubdtype(dep.dtype, np.floating):
            raise ValueError(f"{where}: depth must be a float array of shape ({h}, {w}); got {dep.dtype} {dep.shape}")
        if np.any(_bad_depth(dep)):
            raise ValueError(f"{where}: depth has NaN or non-positive values; it is camera z (> 0), +inf for no hit")
        parent = Path(rel).parent
        default = (parent.parent if parent.name == "images" else parent) / "depth" / f"{stem}.npy"
        drel = _check_out_path(fr.depth_file_path or default.as_posix(), where, "depth_file_path", ".npy")
        d["depth_file_path"] = drel
        writes.append((drel, "depth", dep))
    if fr.depth_prior is not None or fr.depth_prior_file_path is not None:
        if fr.depth_prior is None:
            raise ValueError(f"{where}: depth_prior_file_path is set but depth_prior is None; load with "
                             "load_images=True first")
        pri = np.asarray(fr.depth_prior)
        if pri.shape != (h, w) or not np.issubdtype(pri.dtype, np.floating):
            raise ValueError(f"{where}: depth_prior must be a float array of shape ({h}, {w}); got {pri.dtype} "
                             f"{pri.shape}")
        if np.any(_bad_prior(pri)) or not np.any(~np.isnan(pri)):
            raise ValueError(f"{where}: depth_prior has infinite, zero or negative values, or no estimate at all; "
                             "it is an estimated depth or disparity (> 0), NaN where there is none")
        parent = Path(rel).parent
        default = (parent.parent if parent.name == "images" else parent) / "depth_prior" / f"{stem}.npy"
        prel = _check_out_path(fr.depth_prior_file_path or default.as_posix(), where, "depth_prior_file_path", ".npy")
        d["depth_prior_file_path"] = prel
        writes.append((prel, "depth", pri))
    for r, _, _ in writes:
        if r in used:
            raise ValueError(f"{where}: output path {r!r} is also used by {used[r]}; give each file its own path")
        used[r] = where
    return d, writes


def _intrinsics_dict(fr):
    K = np.asarray(fr.K, dtype=np.float64)
    return {"w": int(fr.width), "h": int(fr.height), "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
            "cx": float(K[0, 2]), "cy": float(K[1, 2])}


def _json_doc(frames, entries, extra):
    top = _intrinsics_dict(frames[0])  # shared intrinsics: the first frame's; others override
    doc = dict(top)
    doc.update(extra)
    out = []
    for fr, d in zip(frames, entries):
        own = _intrinsics_dict(fr)
        d = dict(d)
        d.update({k: v for k, v in own.items() if v != top[k]})
        out.append(d)
    doc["frames"] = out
    return doc


def write_scene(scene: Scene, path, overwrite=False) -> None:
    """Write ``scene`` as a scene folder (docs/dataset_format.md).

    Training frames go to ``transforms.json``, test frames (if any) to
    ``transforms_test.json``, each image to its ``file_path`` (test frames: as
    given, e.g. ``test/...``). Top-level intrinsics are those of the first
    frame of each file; frames that differ carry overrides. Poses are written
    as OpenGL camera-to-world; gt poses only where present. Images are 8-bit
    PNG: round(clip(x, 0, 1) * 255); masks 0/255 (default path
    ``masks/<stem>.png`` if a frame has a mask but no ``mask_path``; sharp
    likewise ``sharp/<stem>.png``). Optional top-level fields are written only
    when not None. Everything is validated before anything is written.

    path: target folder, created if needed. If it exists and is not empty,
    overwrite=True is required; then files are replaced and a stale
    ``transforms_test.json`` is removed when the scene has no test frames
    (other existing files are left alone).
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a d2gs_np.data.scene.Scene; got {type(scene).__name__}")
    if len(scene.frames) == 0:
        raise ValueError("scene has no frames; nothing to write")
    root = Path(path)
    if root.exists():
        if not root.is_dir():
            raise ValueError(f"{root} exists and is not a folder")
        if any(root.iterdir()) and not overwrite:
            raise ValueError(f"scene folder {root} is not empty; pass overwrite=True to write into it")

    extra = {}
    if scene.exposure_fraction is not None:
        v = float(scene.exposure_fraction)
        if not (math.isfinite(v) and 0.0 <= v <= 1.0):
            raise ValueError(f"scene.exposure_fraction must be in [0, 1]; got {scene.exposure_fraction}")
        extra["exposure_fraction"] = v
    if scene.scene_scale is not None:
        v = float(scene.scene_scale)
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"scene.scene_scale must be positive and finite; got {scene.scene_scale}")
        extra["scene_scale"] = v
    if scene.blur_subframes is not None:
        if not isinstance(scene.blur_subframes, (int, np.integer)) or scene.blur_subframes <= 0:
            raise ValueError(f"scene.blur_subframes must be a positive integer; got {scene.blur_subframes!r}")
        extra["blur_subframes"] = int(scene.blur_subframes)
    if scene.poses_trusted is not None:
        if not isinstance(scene.poses_trusted, bool):
            raise ValueError(f"scene.poses_trusted must be True, False or None; got {scene.poses_trusted!r}")
        extra["poses_trusted"] = scene.poses_trusted

    if scene.points3d is not None:
        from d2gs_np.data.ply import write_points_ply

        pts = np.asarray(scene.points3d, dtype=np.float64)
        cols = np.full_like(pts, 0.5) if scene.points3d_colors is None else scene.points3d_colors
        if pts.ndim != 2 or pts.shape[1] != 3 or np.shape(cols) != pts.shape or not np.all(np.isfinite(pts)):
            raise ValueError(f"scene.points3d must be finite (P, 3) with points3d_colors of the same shape; got "
                             f"{pts.shape} and {np.shape(cols)}")
        extra["ply_file_path"] = POINTS_FILE

    used = {}
    plans = {}
    for attr in ("frames", "test_frames"):
        frames = getattr(scene, attr)
        plans[attr] = [_plan_frame(fr, f"scene.{attr}[{i}]", used) for i, fr in enumerate(frames)]

    root.mkdir(parents=True, exist_ok=True)
    for attr in ("frames", "test_frames"):
        for _, writes in plans[attr]:
            for rel, kind, arr in writes:
                out = root / rel
                out.parent.mkdir(parents=True, exist_ok=True)
                if kind == "depth":  # float32: a relative rounding of 6e-8, far below any depth error worth scoring
                    np.save(out, np.asarray(arr, dtype=np.float32), allow_pickle=False)
                    continue
                if kind == "mask":
                    px = np.where(arr, 255, 0).astype(np.uint8)
                else:
                    q = np.round(np.clip(np.asarray(arr, dtype=np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)
                    px = np.ascontiguousarray(q[:, :, ::-1])  # RGB -> BGR for OpenCV
                if not cv2.imwrite(str(out), px):
                    raise OSError(f"could not write {out}")

    if scene.points3d is not None:
        write_points_ply(root / POINTS_FILE, pts, cols)
    docs = [(TRANSFORMS_FILE, "frames", extra)]
    if scene.test_frames:
        docs.append((TRANSFORMS_TEST_FILE, "test_frames", {}))
    elif (root / TRANSFORMS_TEST_FILE).exists():
        (root / TRANSFORMS_TEST_FILE).unlink()  # stale: this scene has no test views
    for name, attr, ext in docs:
        frames = getattr(scene, attr)
        doc = _json_doc(frames, [d for d, _ in plans[attr]], ext)
        with open(root / name, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=2)
            fh.write("\n")
