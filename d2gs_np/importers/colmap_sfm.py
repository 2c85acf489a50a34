"""pycolmap as the pose backend of ``d2gs import-video --sfm pycolmap`` (docs/dataset_format.md §8).

``register_colmap`` runs COLMAP's own structure from motion on the decoded (and resized) frames in a
temporary workspace: SIFT features (``pycolmap.extract_features``, one SIMPLE_PINHOLE camera shared
by all frames, started at the importer's focal length and principal point), exhaustive or
sequential matching with geometric verification, and incremental mapping. The largest model is
written in COLMAP's binary format and read back with ``importers.colmap.read_model``, whose poses
are world-to-camera with OpenCV axes and pixels centred at +0.5, as ours (``colmap_to_cam_T_world``):
reading the files rather than pycolmap's objects keeps us on the stable file format, not on
pycolmap's Python API, which changed between versions. The result is an ``SfmResult`` in the
classical registration's gauge (``video.sfm.fix_gauge``: frame 0 at the identity, median point
depth 1), so the importer's motion masks, mask rounds (features masked by COLMAP's own
``mask_path``) and scene writing run unchanged (``video.importer.PoseBackend``).

Frames the largest model leaves out are refused with a ValueError naming them, as the classical
registration refuses frames it cannot register (``UnregisteredFramesError`` carries the partial
registration for measurements). The focal length is refined unless given; when it leaves [0.5, 2]
x its start (the classical rule), the mapping is run again with it held at the start.

Why this module is in ``importers/`` and not in ``video/``: it reads COLMAP models with
``importers.colmap`` and ``importers/`` sits above ``video/`` in the layering
(``tests/test_layers.py``); ``video.importer.import_video`` takes it as a ``PoseBackend`` argument,
so ``video/`` never imports it.

pycolmap is an optional extra (``pip install pycolmap``, or ``pip install -e '.[colmap]'``):
``require_pycolmap`` turns its absence into a one-line ValueError before any work.
"""
from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from d2gs_np.base.checks import check_choice, check_int, check_number
from d2gs_np.geometry.camera import project_points
from d2gs_np.importers.colmap import camera_intrinsics, colmap_to_cam_T_world, read_model
from d2gs_np.video.importer import ImportConfig, PoseBackend, import_video
from d2gs_np.video.sfm import SfmConfig, SfmResult, fix_gauge

__all__ = ["ColmapSfmConfig", "UnregisteredFramesError", "require_pycolmap", "register_colmap", "colmap_backend",
           "import_video_pycolmap", "INSTALL_HINT"]

INSTALL_HINT = "pip install pycolmap (or pip install -e '.[colmap]')"
FOCAL_RANGE = (0.5, 2.0)  # refined focal / start outside this: mapped again with the focal fixed (as sfm.py)


class UnregisteredFramesError(ValueError):
    """Frames pycolmap's largest model does not contain. ``frames``: their indices; ``result``: the
    SfmResult of the registered ones (cam_T_world NaN for the others); ``info``: the backend's report."""

    def __init__(self, message, frames, result, info):
        super().__init__(message)
        self.frames, self.result, self.info = frames, result, info


@dataclass(frozen=True)
class ColmapSfmConfig:
    """Settings of the pycolmap registration. Validated on construction. COLMAP's defaults are
    for photo collections; the changed values are for short, small, blurry video clips."""

    matcher: str = "exhaustive"  # or "sequential": each frame with the next ``overlap`` ones
    overlap: int = 10
    # SIFT DoG peak threshold: blur lowers contrast (COLMAP's default 0.02 / 3; as our SIFT's low
    # contrast threshold in SfmConfig.features)
    peak_threshold: float = 0.004
    max_num_features: int = 8192
    # two-view start: COLMAP asks for 100 inliers at a 16 deg triangulation angle, which neighbouring
    # frames of a short clip seldom have
    init_min_num_inliers: int = 30
    init_min_tri_angle_deg: float = 4.0
    abs_pose_min_num_inliers: int = 15  # a frame's PnP (COLMAP: 30; a 240x135 frame has few features)
    min_num_matches: int = 15  # verified matches a frame pair needs to be used
    num_threads: int = 1  # feature extraction, matching and mapping (-1: all cores)
    seed: int = 0  # pycolmap.set_random_seed and the RANSAC / mapper seeds
    weak_observations: int = SfmConfig.weak_observations  # fewer inlier observations: a weak frame (as SfmConfig)

    def __post_init__(self):
        check_choice(self.matcher, "ColmapSfmConfig.matcher", ("exhaustive", "sequential"))
        for name in ("overlap", "max_num_features", "init_min_num_inliers", "abs_pose_min_num_inliers",
                     "min_num_matches", "weak_observations"):
            check_int(getattr(self, name), f"ColmapSfmConfig.{name}", 1)
        check_int(self.seed, "ColmapSfmConfig.seed", 0)
        if not isinstance(self.num_threads, int) or isinstance(self.num_threads, bool) or \
                not (self.num_threads == -1 or self.num_threads >= 1):
            raise ValueError(f"ColmapSfmConfig.num_threads must be -1 (all cores) or >= 1; got {self.num_threads!r}")
        check_number(self.peak_threshold, "ColmapSfmConfig.peak_threshold", 0.0, lo_open=True)
        check_number(self.init_min_tri_angle_deg, "ColmapSfmConfig.init_min_tri_angle_deg", 0.0, lo_open=True)


def require_pycolmap():
    """The pycolmap module, or a one-line ValueError with the install command."""
    try:
        import pycolmap
    except ImportError:
        raise ValueError(f"--sfm pycolmap needs the optional package pycolmap, which is not installed: "
                         f"{INSTALL_HINT}; or use --sfm classical") from None
    return pycolmap


def _write_frames(ws, images, masks):
    """Frames as ws/images/NNNN.png (uint8) and, with masks, COLMAP's masks ws/masks/NNNN.png.png
    (black = no features there: our True = moving)."""
    (ws / "images").mkdir()
    names = [f"{k:04d}.png" for k in range(len(images))]
    for name, img in zip(names, images):
        u8 = img if img.dtype == np.uint8 else np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
        cv2.imwrite(str(ws / "images" / name), np.ascontiguousarray(u8[:, :, ::-1]))
    if masks is not None:
        (ws / "masks").mkdir()
        for name, m in zip(names, masks):
            cv2.imwrite(str(ws / "masks" / f"{name}.png"), np.where(m, 0, 255).astype(np.uint8))
    return names


def _features_and_matches(pycolmap, ws, K, cfg, masks):
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_PINHOLE"
    reader.camera_params = ",".join(repr(float(v)) for v in (K[0, 0], K[0, 2], K[1, 2]))  # COLMAP's pixel centres are ours (+0.5)
    if masks is not None:
        reader.mask_path = str(ws / "masks")
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = cfg.num_threads
    ext.sift.peak_threshold = cfg.peak_threshold
    ext.sift.max_num_features = cfg.max_num_features
    db = ws / "database.db"
    pycolmap.extract_features(db, ws / "images", camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=ext, device=pycolmap.Device.cpu)
    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = cfg.num_threads
    verify = pycolmap.TwoViewGeometryOptions()
    verify.min_num_inliers = cfg.min_num_matches
    verify.ransac.random_seed = cfg.seed
    if cfg.matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=match, verification_options=verify, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.overlap
        pairing.quadratic_overlap = False
        pairing.num_threads = cfg.num_threads
        pycolmap.match_sequential(db, matching_options=match, pairing_options=pairing, verification_options=verify,
                                  device=pycolmap.Device.cpu)
    return db


def _map(pycolmap, ws, db, cfg, refine_focal, tag):
    """Incremental mapping; the largest model's sizes of all models, and the largest read back."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    opts.random_seed = cfg.seed
    opts.min_num_matches = cfg.min_num_matches
    opts.min_model_size = 3
    opts.ba_refine_focal_length = refine_focal
    opts.mapper.abs_pose_refine_focal_length = refine_focal
    opts.mapper.init_min_num_inliers = cfg.init_min_num_inliers
    opts.mapper.init_min_tri_angle = cfg.init_min_tri_angle_deg
    opts.mapper.abs_pose_min_num_inliers = cfg.abs_pose_min_num_inliers
    opts.mapper.num_threads = cfg.num_threads
    opts.mapper.random_seed = cfg.seed
    out = ws / f"sparse_{tag}"
    out.mkdir()
    recs = pycolmap.incremental_mapping(db, ws / "images", out, opts)
    sizes = sorted((int(r.num_reg_images()) for r in recs.values()), reverse=True)
    if not recs:
        return None, sizes
    best = max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    model_dir = out / "largest"
    model_dir.mkdir()
    best.write(str(model_dir))
    return read_model(model_dir), sizes


def _to_result(model, names, weak_observations, log_lines):
    """SfmResult of a COLMAP model of the frames ``names`` (NaN poses where not registered), our gauge
    from the registered frames; and the registered frame indices."""
    N = len(names)
    index = {n: k for k, n in enumerate(names)}
    K, _ = camera_intrinsics(model.cameras[next(iter(model.images.values())).camera_id])  # one shared camera
    poses = np.full((N, 4, 4), np.nan)
    nkp = np.zeros(N, dtype=np.int64)
    row = {int(pid): i for i, pid in enumerate(model.point_ids)}
    o_f, o_p, o_uv = [], [], []
    for im in model.images.values():
        k = index[im.name]
        poses[k] = colmap_to_cam_T_world(im.qvec, im.tvec)
        nkp[k] = len(im.xys)
        seen = im.point3D_ids >= 0
        o_f.append(np.full(int(seen.sum()), k))
        o_p.append(np.array([row[int(p)] for p in im.point3D_ids[seen]], dtype=np.int64))
        o_uv.append(im.xys[seen])
    o_f, o_p, o_uv = np.concatenate(o_f), np.concatenate(o_p), np.concatenate(o_uv).reshape(-1, 2)
    reg = np.flatnonzero(np.isfinite(poses[:, 0, 0]))
    if not len(o_f):  # no 3D point: no depth to fix the scale with
        raise ValueError(f"pycolmap registered frames {reg.tolist()} but triangulated no points; use --sfm classical")
    # our gauge on the registered frames: fix_gauge puts its first pose at the identity
    sub = np.full(N, -1)
    sub[reg] = np.arange(len(reg))
    p_reg, pts = fix_gauge(poses[reg], model.xyz, sub[o_f], o_p)
    poses[reg] = p_reg
    uvp = np.zeros_like(o_uv)
    for k in reg:
        s = o_f == k
        uvp[s] = project_points(pts[o_p[s]], poses[k], K)[0]
    rms = float(np.sqrt(np.mean(np.sum((uvp - o_uv) ** 2, axis=1)))) if len(o_uv) else float("nan")
    nobs = np.bincount(o_f, minlength=N)
    weak = [int(k) for k in reg if nobs[k] < weak_observations]
    res = SfmResult(poses, K, pts, model.rgb.astype(np.float64) / 255.0, o_f, o_p, o_uv, nkp, nobs, weak, False,
                    None, float("nan"), rms, log_lines)
    return res, reg


def register_colmap(images, K, config: ColmapSfmConfig = None, refine_focal=True, masks=None, log=print):
    """Camera poses, the shared focal length and sparse points of a frame sequence by pycolmap
    (module docstring). images: list of (H, W, 3) uint8 (or float in [0, 1]) frames; K (3, 3) the
    starting intrinsics; masks None or one (H, W) bool per frame, True = moving (no features).
    Returns (SfmResult, info); UnregisteredFramesError (a ValueError) names frames left out."""
    pycolmap = require_pycolmap()
    cfg = ColmapSfmConfig() if config is None else config
    if not isinstance(cfg, ColmapSfmConfig):
        raise TypeError(f"config must be a ColmapSfmConfig; got {type(cfg).__name__}")
    N = len(images)
    if N < 2:
        raise ValueError(f"need at least 2 frames to register a video; got {N}")
    K = np.array(K, dtype=np.float64)
    if masks is not None and (len(masks) != N or any(np.shape(m) != np.shape(images[0])[:2] for m in masks)):
        raise ValueError(f"masks must be one (H, W) bool array per frame ({N} frames of "
                         f"{np.shape(images[0])[:2]}); got {len(masks)}")
    msgs = []

    def say(s):
        msgs.append(s)
        if log is not None:
            log(s)

    t0 = time.perf_counter()
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # COLMAP's INFO and WARNING lines would drown ours; errors stay
    try:
        pycolmap.set_random_seed(cfg.seed)
        with tempfile.TemporaryDirectory(prefix="d2gs_colmap_") as tmp:
            ws = Path(tmp)
            names = _write_frames(ws, images, masks)
            db = _features_and_matches(pycolmap, ws, K, cfg, masks)
            model, sizes = _map(pycolmap, ws, db, cfg, refine_focal, "refined" if refine_focal else "fixed")
            focal_retry = False
            if model is not None and refine_focal:
                f = camera_intrinsics(next(iter(model.cameras.values())))[0][0, 0]
                if not FOCAL_RANGE[0] <= f / K[0, 0] <= FOCAL_RANGE[1]:
                    say(f"pycolmap: the focal length drifted to {f:.1f} px from {K[0, 0]:.1f} px; mapping again "
                        "with it fixed")
                    model, sizes = _map(pycolmap, ws, db, cfg, False, "fixed")
                    focal_retry = True
    finally:
        pycolmap.logging.minloglevel = level
    if model is None or not model.images:
        raise UnregisteredFramesError(
            f"could not register frames {list(range(N))}: pycolmap found no initial pair among the {N} frames (too "
            "blurry, too little texture or parallax); use --sfm classical, or film more slowly",
            list(range(N)), None, {"backend": "pycolmap", "models": sizes})
    res, reg = _to_result(model, names, cfg.weak_observations, msgs)
    info = {"pycolmap_version": getattr(pycolmap, "__version__", "unknown"), "matcher": cfg.matcher,
            "model_sizes": sizes, "registered_frames": int(len(reg)),
            "colmap_mean_reprojection_error_px": float(np.mean(model.error)) if len(model.error) else float("nan"),
            "focal_fixed_after_drift": focal_retry, "run_seconds": time.perf_counter() - t0}
    say(f"pycolmap: registered {len(reg)}/{N} frames (models of {sizes} frames), {len(res.points)} points, "
        f"reprojection rms {res.reprojection_rms_px:.2f} px, focal {res.K[0, 0]:.1f} px, "
        f"{info['run_seconds']:.1f}s")
    missing = sorted(set(range(N)) - set(reg.tolist()))
    if missing:
        raise UnregisteredFramesError(
            f"could not register frames {missing}: pycolmap's largest model holds {len(reg)} of the {N} frames; "
            "drop them (--start/--end, --stride) or use --sfm classical", missing, res, info)
    return res, info


def colmap_backend(config: ColmapSfmConfig = None) -> PoseBackend:
    """``register_colmap`` as the importer's PoseBackend."""
    cfg = ColmapSfmConfig() if config is None else config

    def register(images, K, refine_focal, masks, log):
        return register_colmap(images, K, cfg, refine_focal=refine_focal, masks=masks, log=log)

    return PoseBackend("pycolmap", register)


def import_video_pycolmap(source, out, config: ImportConfig = None, colmap: ColmapSfmConfig = None,
                          overwrite=False, log=print) -> dict:
    """``import_video`` with pycolmap's registration (``d2gs import-video --sfm pycolmap``)."""
    require_pycolmap()
    return import_video(source, out, config, overwrite=overwrite, log=log, backend=colmap_backend(colmap))
