"""COLMAP sparse models in (``d2gs import-colmap``; docs/dataset_format.md §9).

A sparse model is a folder with ``cameras``, ``images`` and ``points3D`` in COLMAP's text
(``.txt``) or binary (``.bin``, little-endian) format (https://colmap.github.io/format.html); when
both are present the binary one is read, as COLMAP does. The readers and the (small) writers
follow that page and COLMAP's ``read_write_model.py`` field by field; ``rigs`` and ``frames``
files (COLMAP >= 3.12) are not needed and ignored.

Poses: COLMAP stores each image's world-to-camera rotation as a Hamilton quaternion (QW, QX, QY,
QZ) and translation (TX, TY, TZ), camera axes x right, y down, z forward: that is our in-memory
``cam_T_world`` with OpenCV axes, so ``cam_T_world = [[R(q), t], [0, 0, 0, 1]]`` with no axis
change (``colmap_to_cam_T_world``). Pixels: COLMAP puts the centre of the top-left pixel at (0.5,
0.5), as we do (docs/conventions.md §2), so its principal point is used as it is.

Cameras: SIMPLE_PINHOLE and PINHOLE are taken as they are. SIMPLE_RADIAL, RADIAL and OPENCV are
COLMAP's names for OpenCV's distortion model with (k1), (k1, k2) and (k1, k2, p1, p2): their
images are undistorted with OpenCV (``cv2.initUndistortRectifyMap`` + bilinear ``cv2.remap``) to a
pinhole camera of the same size whose K is the model's own focal lengths and principal point
(``undistort_image``); output pixels whose source falls outside the image are black (the corners,
under barrel distortion). Other models (fisheyes, FULL_OPENCV, FOV, ...) are refused, naming the
model.
"""
from __future__ import annotations

import struct
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from d2gs_np.data.io import write_scene
from d2gs_np.data.scene import Frame, Scene
from d2gs_np.geometry.camera import make_intrinsics
from d2gs_np.geometry.quaternion import quat_to_rotmat, rotmat_to_quat
from d2gs_np.importers.folders import REPORT_FILE, write_report, check_out_folder, read_rgb

__all__ = ["CAMERA_MODELS", "SUPPORTED_MODELS", "ColmapCamera", "ColmapImage", "ColmapModel", "find_model",
           "read_model", "write_model", "colmap_to_cam_T_world", "cam_T_world_to_colmap", "camera_intrinsics",
           "undistort_image", "import_colmap", "REPORT_FILE"]

# COLMAP's camera models: id -> (name, number of parameters) (src/colmap/sensor/models.h)
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5), 14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4),
    16: ("EUCM", 6), 17: ("EQUIRECTANGULAR", 2),
}
MODEL_IDS = {name: (mid, n) for mid, (name, n) in CAMERA_MODELS.items()}
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
_PARTS = ("cameras", "images", "points3D")
_UNDISTORT_HINT = ("undistort the images first with COLMAP (colmap image_undistorter --image_path IMAGES "
                   "--input_path SPARSE --output_path DENSE), then import DENSE/sparse and DENSE/images")


@dataclass
class ColmapCamera:
    camera_id: int
    model: str  # a name of CAMERA_MODELS
    width: int
    height: int
    params: np.ndarray  # (num_params,) float64, in COLMAP's order for the model


@dataclass
class ColmapImage:
    image_id: int
    qvec: np.ndarray  # (4,) world-to-camera rotation, Hamilton quaternion (w, x, y, z)
    tvec: np.ndarray  # (3,) world-to-camera translation
    camera_id: int
    name: str  # path relative to the images folder
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (K, 2) keypoints, pixels
    point3D_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (K,) -1 = no 3D point


@dataclass
class ColmapModel:
    cameras: dict  # camera_id -> ColmapCamera
    images: dict  # image_id -> ColmapImage
    point_ids: np.ndarray  # (P,) int64 POINT3D_ID
    xyz: np.ndarray  # (P, 3) float64 world positions
    rgb: np.ndarray  # (P, 3) uint8 colours
    error: np.ndarray  # (P,) float64 reprojection error, pixels
    tracks: list  # P arrays (L, 2) int64 of (IMAGE_ID, POINT2D_IDX)


# ------------------------------------------------------------------ poses and cameras
def colmap_to_cam_T_world(qvec, tvec) -> np.ndarray:
    """(4, 4) cam_T_world of a COLMAP image pose: [[R(q), t], [0, 0, 0, 1]], no axis change (both are
    world-to-camera with x right, y down, z forward); q is normalised first."""
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(np.asarray(qvec, dtype=np.float64))
    T[:3, 3] = np.asarray(tvec, dtype=np.float64)
    return T


def cam_T_world_to_colmap(cam_T_world):
    """(qvec (4,) with qw >= 0, tvec (3,)) of a (4, 4) cam_T_world: the inverse of colmap_to_cam_T_world."""
    T = np.asarray(cam_T_world, dtype=np.float64)
    return rotmat_to_quat(T[:3, :3]), T[:3, 3].copy()


def camera_intrinsics(cam: ColmapCamera):
    """(K (3, 3), OpenCV distortion (k1, k2, p1, p2) or None) of a supported camera; ValueError
    naming any other model."""
    p = np.asarray(cam.params, dtype=np.float64)
    if cam.model not in SUPPORTED_MODELS:
        raise ValueError(f"camera {cam.camera_id} has the COLMAP model {cam.model}, which is not supported "
                         f"(supported: {', '.join(SUPPORTED_MODELS)}); {_UNDISTORT_HINT}")
    if cam.model == "SIMPLE_PINHOLE":
        return make_intrinsics(p[0], p[0], p[1], p[2]), None
    if cam.model == "PINHOLE":
        return make_intrinsics(p[0], p[1], p[2], p[3]), None
    if cam.model == "SIMPLE_RADIAL":
        return make_intrinsics(p[0], p[0], p[1], p[2]), np.array([p[3], 0.0, 0.0, 0.0])
    if cam.model == "RADIAL":
        return make_intrinsics(p[0], p[0], p[1], p[2]), np.array([p[3], p[4], 0.0, 0.0])
    return make_intrinsics(p[0], p[1], p[2], p[3]), p[4:8].copy()  # OPENCV


def undistort_image(img, K, dist) -> np.ndarray:
    """``img`` (H, W, C) of a camera K (3, 3) with OpenCV distortion ``dist`` (k1, k2, p1, p2),
    resampled (bilinear) as the pinhole camera K of the same size; black where the source is outside.

    OpenCV puts pixel centres at integers, we (and COLMAP) at +0.5: its K has cx - 0.5, cy - 0.5.
    """
    H, W = img.shape[:2]
    K_cv = np.array(K, dtype=np.float64)
    K_cv[0, 2] -= 0.5
    K_cv[1, 2] -= 0.5
    map_x, map_y = cv2.initUndistortRectifyMap(K_cv, np.asarray(dist, dtype=np.float64), None, K_cv, (W, H),
                                               cv2.CV_32FC1)
    return cv2.remap(np.ascontiguousarray(img), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0)


# ------------------------------------------------------------------ reading
def find_model(sparse_dir):
    """(folder Path, ".bin" or ".txt") of the sparse model in ``sparse_dir``: binary when all three
    binary files are there (COLMAP's rule), else text; FileNotFoundError naming what is missing."""
    d = Path(sparse_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"COLMAP sparse model folder {d} does not exist (it holds cameras, images and "
                                "points3D .bin or .txt, e.g. sparse/0)")
    for ext in (".bin", ".txt"):
        if all((d / (p + ext)).is_file() for p in _PARTS):
            return d, ext
    have = sorted(p.name for p in d.iterdir() if p.stem in _PARTS and p.suffix in (".bin", ".txt"))
    missing = [p + ext for ext in (".bin", ".txt") for p in _PARTS if not (d / (p + ext)).is_file()]
    raise FileNotFoundError(f"{d} holds no complete COLMAP sparse model: it needs cameras, images and points3D, all "
                            f".bin or all .txt; found {have or 'none of them'}, missing {missing}")


def read_model(sparse_dir) -> ColmapModel:
    """The sparse model of ``sparse_dir`` (``find_model``), text or binary."""
    d, ext = find_model(sparse_dir)
    if ext == ".bin":
        return ColmapModel(read_cameras_binary(d / "cameras.bin"), read_images_binary(d / "images.bin"),
                           *read_points3D_binary(d / "points3D.bin"))
    return ColmapModel(read_cameras_text(d / "cameras.txt"), read_images_text(d / "images.txt"),
                       *read_points3D_text(d / "points3D.txt"))


def _model_name(mid, where):
    if mid not in CAMERA_MODELS:
        raise ValueError(f"{where}: unknown COLMAP camera model id {mid} (known: 0-{max(CAMERA_MODELS)}); "
                         f"{_UNDISTORT_HINT}")
    return CAMERA_MODELS[mid]


def _data_lines(path):
    """(line number, stripped line) of a text file, comments and blank lines left out."""
    with open(path, encoding="utf-8") as fh:
        for i, line in enumerate(fh, 1):
            s = line.strip()
            if s and not s.startswith("#"):
                yield i, s


def read_cameras_text(path) -> dict:
    cams = {}
    for i, line in _data_lines(path):
        tok = line.split()
        where = f"{path} line {i}"
        try:
            cid, model, w, h = int(tok[0]), tok[1], int(tok[2]), int(tok[3])
            params = np.array([float(v) for v in tok[4:]])
        except (IndexError, ValueError):
            raise ValueError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]; got {line!r}") from None
        if model not in MODEL_IDS:
            raise ValueError(f"{where}: unknown COLMAP camera model {model!r}; {_UNDISTORT_HINT}")
        if len(params) != MODEL_IDS[model][1]:
            raise ValueError(f"{where}: the model {model} has {MODEL_IDS[model][1]} parameters; got {len(params)}")
        cams[cid] = ColmapCamera(cid, model, w, h, params)
    return cams


def read_images_text(path) -> dict:
    """Two lines per image: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then its POINTS2D as
    (X, Y, POINT3D_ID) triples; the second line may be empty (an image without keypoints)."""
    images = {}
    with open(path, encoding="utf-8") as fh:
        lines = fh.read().splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        where = f"{path} line {i}"
        tok = line.split(maxsplit=9)
        try:
            iid = int(tok[0])
            q = np.array([float(v) for v in tok[1:5]])
            t = np.array([float(v) for v in tok[5:8]])
            cid, name = int(tok[8]), tok[9].strip()
        except (IndexError, ValueError):
            raise ValueError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME; got {line!r}") from None
        pts = lines[i].split() if i < len(lines) else []
        i += 1
        if len(pts) % 3:
            raise ValueError(f"{path} line {i}: POINTS2D of image {iid} must be (X, Y, POINT3D_ID) triples; "
                             f"got {len(pts)} values")
        try:
            xys = np.array([[float(pts[k]), float(pts[k + 1])] for k in range(0, len(pts), 3)]).reshape(-1, 2)
            ids = np.array([int(pts[k + 2]) for k in range(0, len(pts), 3)], dtype=np.int64)
        except ValueError:
            raise ValueError(f"{path} line {i}: POINTS2D of image {iid} are not numbers") from None
        images[iid] = ColmapImage(iid, q, t, cid, name, xys, ids)
    return images


def read_points3D_text(path):
    """(point_ids, xyz, rgb, error, tracks) of points3D.txt."""
    ids, xyz, rgb, err, tracks = [], [], [], [], []
    for i, line in _data_lines(path):
        tok = line.split()
        try:
            if len(tok) < 8 or (len(tok) - 8) % 2:
                raise ValueError
            ids.append(int(tok[0]))
            xyz.append([float(v) for v in tok[1:4]])
            rgb.append([int(v) for v in tok[4:7]])
            err.append(float(tok[7]))
            tracks.append(np.array([int(v) for v in tok[8:]], dtype=np.int64).reshape(-1, 2))
        except ValueError:
            raise ValueError(f"{path} line {i}: expected POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, "
                             f"POINT2D_IDX) pairs; got {line[:120]!r}") from None
    return _points(ids, xyz, rgb, err, tracks, path)


def _points(ids, xyz, rgb, err, tracks, path):
    rgb = np.array(rgb, dtype=np.int64).reshape(-1, 3)
    if np.any((rgb < 0) | (rgb > 255)):
        raise ValueError(f"{path}: point colours must be in 0..255")
    return (np.array(ids, dtype=np.int64), np.array(xyz, dtype=np.float64).reshape(-1, 3), rgb.astype(np.uint8),
            np.array(err, dtype=np.float64), tracks)


class _Bytes:
    """Little-endian reads from a file's bytes; a short read is a truncated file (ValueError)."""

    def __init__(self, path):
        self.path, self.buf, self.pos = path, Path(path).read_bytes(), 0

    def take(self, fmt, what):
        fmt = "<" + fmt
        n = struct.calcsize(fmt)
        if self.pos + n > len(self.buf):
            raise ValueError(f"{self.path} is truncated: {what} needs bytes {self.pos}-{self.pos + n} of "
                             f"{len(self.buf)}; export the model again")
        out = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += n
        return out

    def array(self, dtype, count, what):
        dt = np.dtype(dtype)
        n = dt.itemsize * count
        if self.pos + n > len(self.buf):
            raise ValueError(f"{self.path} is truncated: {what} needs bytes {self.pos}-{self.pos + n} of "
                             f"{len(self.buf)}; export the model again")
        out = np.frombuffer(self.buf, dtype=dt, count=count, offset=self.pos).copy()
        self.pos += n
        return out

    def cstring(self, what):
        end = self.buf.find(b"\x00", self.pos)
        if end < 0:
            raise ValueError(f"{self.path} is truncated: {what} has no terminating NUL; export the model again")
        s = self.buf[self.pos:end].decode("utf-8")
        self.pos = end + 1
        return s


def read_cameras_binary(path) -> dict:
    """uint64 count; per camera int32 CAMERA_ID, int32 MODEL_ID, uint64 WIDTH, HEIGHT, float64 PARAMS[]."""
    r = _Bytes(path)
    (n,) = r.take("Q", "the camera count")
    cams = {}
    for k in range(n):
        cid, mid, w, h = r.take("iiQQ", f"camera {k}")
        name, npar = _model_name(mid, f"{path} camera {cid}")
        cams[cid] = ColmapCamera(cid, name, int(w), int(h), r.array("<f8", npar, f"camera {cid}'s parameters"))
    return cams


def read_images_binary(path) -> dict:
    """uint64 count; per image int32 IMAGE_ID, float64 QW QX QY QZ TX TY TZ, int32 CAMERA_ID, NAME
    (NUL-terminated UTF-8), uint64 num_points2D, then (float64 X, float64 Y, int64 POINT3D_ID) each."""
    r = _Bytes(path)
    (n,) = r.take("Q", "the image count")
    images = {}
    for k in range(n):
        iid, qw, qx, qy, qz, tx, ty, tz, cid = r.take("idddddddi", f"image {k}")
        name = r.cstring(f"image {iid}'s name")
        (npts,) = r.take("Q", f"image {iid}'s keypoint count")
        rec = r.array([("x", "<f8"), ("y", "<f8"), ("id", "<i8")], npts, f"image {iid}'s keypoints")
        images[iid] = ColmapImage(iid, np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]), cid, name,
                                  np.stack([rec["x"], rec["y"]], axis=1), rec["id"].astype(np.int64))
    return images


def read_points3D_binary(path):
    """uint64 count; per point uint64 POINT3D_ID, float64 X Y Z, uint8 R G B, float64 ERROR, uint64
    track length, then (int32 IMAGE_ID, int32 POINT2D_IDX) each."""
    r = _Bytes(path)
    (n,) = r.take("Q", "the point count")
    ids, xyz, rgb, err, tracks = [], [], [], [], []
    for k in range(n):
        pid, x, y, z, cr, cg, cb, e, length = r.take("QdddBBBdQ", f"point {k}")
        ids.append(pid)
        xyz.append((x, y, z))
        rgb.append((cr, cg, cb))
        err.append(e)
        tracks.append(r.array("<i4", 2 * length, f"point {pid}'s track").astype(np.int64).reshape(-1, 2))
    return _points(ids, xyz, rgb, err, tracks, path)


# ------------------------------------------------------------------ writing (fixtures, round trips)
def write_model(model: ColmapModel, folder, ext=".bin") -> Path:
    """Write ``model`` as cameras, images and points3D ``ext`` (".bin" or ".txt") into ``folder``
    (created); floats in text as Python's shortest round-trip repr, so text reads back exactly."""
    if ext not in (".bin", ".txt"):
        raise ValueError(f"ext must be '.bin' or '.txt'; got {ext!r}")
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    (_write_binary if ext == ".bin" else _write_text)(model, d)
    return d


def _write_text(m: ColmapModel, d: Path):
    r = repr
    with open(d / "cameras.txt", "w", encoding="utf-8") as fh:
        fh.write("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
                 f"# Number of cameras: {len(m.cameras)}\n")
        for c in m.cameras.values():
            fh.write(" ".join([str(c.camera_id), c.model, str(c.width), str(c.height)]
                              + [r(float(p)) for p in c.params]) + "\n")
    with open(d / "images.txt", "w", encoding="utf-8") as fh:
        fh.write("# Image list with two lines of data per image:\n"
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
                 f"# Number of images: {len(m.images)}\n")
        for im in m.images.values():
            fh.write(" ".join([str(im.image_id)] + [r(float(v)) for v in (*im.qvec, *im.tvec)]
                              + [str(im.camera_id), im.name]) + "\n")
            fh.write(" ".join(f"{r(float(x))} {r(float(y))} {int(p)}" for (x, y), p in zip(im.xys, im.point3D_ids))
                     + "\n")
    with open(d / "points3D.txt", "w", encoding="utf-8") as fh:
        fh.write("# 3D point list with one line of data per point:\n"
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                 f"# Number of points: {len(m.point_ids)}\n")
        for k in range(len(m.point_ids)):
            fh.write(" ".join([str(int(m.point_ids[k]))] + [r(float(v)) for v in m.xyz[k]]
                              + [str(int(v)) for v in m.rgb[k]] + [r(float(m.error[k]))]
                              + [str(int(v)) for v in np.asarray(m.tracks[k]).ravel()]) + "\n")


def _write_binary(m: ColmapModel, d: Path):
    with open(d / "cameras.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(m.cameras)))
        for c in m.cameras.values():
            fh.write(struct.pack("<iiQQ", c.camera_id, MODEL_IDS[c.model][0], c.width, c.height))
            fh.write(np.asarray(c.params, dtype="<f8").tobytes())
    with open(d / "images.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(m.images)))
        for im in m.images.values():
            fh.write(struct.pack("<i7di", im.image_id, *map(float, im.qvec), *map(float, im.tvec), im.camera_id))
            fh.write(im.name.encode("utf-8") + b"\x00")
            rec = np.zeros(len(im.point3D_ids), dtype=[("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
            rec["x"], rec["y"], rec["id"] = im.xys[:, 0], im.xys[:, 1], im.point3D_ids
            fh.write(struct.pack("<Q", len(rec)) + rec.tobytes())
    with open(d / "points3D.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(m.point_ids)))
        for k in range(len(m.point_ids)):
            track = np.asarray(m.tracks[k], dtype="<i4").reshape(-1, 2)
            fh.write(struct.pack("<Q3d3BdQ", int(m.point_ids[k]), *map(float, m.xyz[k]), *map(int, m.rgb[k]),
                                 float(m.error[k]), len(track)))
            fh.write(track.tobytes())


# ------------------------------------------------------------------ the importer
def _frame_path(name):
    """Scene-relative PNG path of an image named ``name`` (relative to the images folder)."""
    return (Path("images") / Path(name).with_suffix(".png")).as_posix()


def _check_model(model: ColmapModel, images_dir: Path):
    """Refuse, before any pixel is read: no images, an image whose camera is missing, an unsupported
    camera model, an image listed without its file, two images that would share an output file."""
    if not model.images:
        raise ValueError("the COLMAP model registers no images; nothing to import")
    used = {im.camera_id for im in model.images.values()}
    lost = sorted({c for c in used if c not in model.cameras})
    if lost:
        raise ValueError(f"images refer to cameras {lost}, which cameras.txt/.bin does not list; export the model again")
    for cid in sorted(used):
        camera_intrinsics(model.cameras[cid])
    names = sorted(im.name for im in model.images.values())
    missing = [n for n in names if not (images_dir / n).is_file()]
    if missing:
        raise FileNotFoundError(f"{len(missing)} of the {len(names)} images the model lists are not in {images_dir}: "
                                f"{', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}; pass the folder the "
                                "model was made from (the image names are relative to it)")
    seen = {}
    for n in names:
        p = _frame_path(n)
        if p in seen:
            raise ValueError(f"images {seen[p]!r} and {n!r} would both be written to {p}; rename one of them")
        seen[p] = n


def _scene_scale(model, frames_by_id):
    """95th percentile of the sparse points' depths in the images that observe them (the
    importers' ``scene_scale``, as ``import-video``'s), or None without observations."""
    z = []
    for k, track in enumerate(model.tracks):
        for iid in np.unique(np.asarray(track).reshape(-1, 2)[:, 0]):
            T = frames_by_id.get(int(iid))
            if T is not None:
                z.append(T[2, :3] @ model.xyz[k] + T[2, 3])
    z = np.array(z)
    z = z[z > 0]
    return float(np.percentile(z, 95)) if z.size else None


def import_colmap(sparse_dir, images_dir, out, overwrite=False, log=print) -> dict:
    """Import a COLMAP sparse model and its images into the scene folder ``out``; returns the
    report (also written as ``import_report.json``). Frames are the registered images in name
    order, times spread evenly over [0, 1] in that order; the 3D points become the scene's
    ``points3d.ply`` (docs/dataset_format.md §9)."""
    t0 = time.perf_counter()
    images_dir = Path(images_dir)
    if not images_dir.is_dir():
        raise FileNotFoundError(f"images folder {images_dir} does not exist; pass the folder the COLMAP model's "
                                "image names are relative to")
    out = check_out_folder(out, overwrite)
    folder, ext = find_model(sparse_dir)
    model = read_model(folder)
    _check_model(model, images_dir)

    ordered = sorted(model.images.values(), key=lambda im: im.name)
    N = len(ordered)
    frames, undistorted, poses = [], {}, {}
    for k, im in enumerate(ordered):
        cam = model.cameras[im.camera_id]
        K, dist = camera_intrinsics(cam)
        img = read_rgb(images_dir / im.name, "image")
        if img.shape[:2] != (cam.height, cam.width):
            raise ValueError(f"image {im.name} is {img.shape[1]}x{img.shape[0]} but its camera {cam.camera_id} is "
                             f"{cam.width}x{cam.height}; pass the images the model was made from (not resized)")
        if dist is not None and np.any(dist != 0):
            img = undistort_image(img, K, dist)
            undistorted[cam.camera_id] = {"model": cam.model, "distortion_k1_k2_p1_p2": dist.tolist(),
                                          "new_K": K.tolist()}
        T = colmap_to_cam_T_world(im.qvec, im.tvec)
        poses[im.image_id] = T
        frames.append(Frame(file_path=_frame_path(im.name), time=k / (N - 1) if N > 1 else 0.0, cam_T_world=T,
                            K=K, width=cam.width, height=cam.height, image=np.clip(img, 0.0, 1.0)))
    has_points = len(model.point_ids) > 0
    scene = Scene(frames=frames, scene_scale=_scene_scale(model, poses) if has_points else None,
                  points3d=model.xyz if has_points else None,
                  points3d_colors=model.rgb.astype(np.float64) / 255.0 if has_points else None)
    write_scene(scene, out, overwrite=overwrite)
    report = {
        "source": str(folder), "format": "binary" if ext == ".bin" else "text", "images_dir": str(images_dir),
        "frames": N, "names": [im.name for im in ordered], "image_ids": [im.image_id for im in ordered],
        "cameras": {str(c.camera_id): {"model": c.model, "width": c.width, "height": c.height,
                                       "params": np.asarray(c.params).tolist()} for c in model.cameras.values()},
        "undistorted": {str(k): v for k, v in undistorted.items()},
        "num_points": int(len(model.point_ids)), "scene_scale": scene.scene_scale,
        "poses": "COLMAP world-to-camera (OpenCV axes) taken as cam_T_world unchanged",
        "seconds": time.perf_counter() - t0,
    }
    write_report(out, report)
    if log:
        log(f"wrote {N} frames ({len(model.cameras)} camera(s), {len(undistorted)} undistorted) and "
            f"{len(model.point_ids)} sparse points from the COLMAP model in {folder} to {out} "
            f"in {report['seconds']:.1f}s")
    return report
