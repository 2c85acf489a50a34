"""``d2gs import-video``: a video (or image folder) -> a scene folder with poses, masks, sparse points.

Pipeline (docs/dataset_format.md §8): ``decode.read_frames`` -> intrinsics guess ->
``tracks.klt_tracks`` -> ``sfm.register_video`` (two-view start, PnP, bundle adjustment with the
focal length) -> ``static_motion`` (two groups of tracks that move together, ``segment``: the
group that owns the frame border, registered alone, replaces a registration that followed a
mover) -> ``masks.static_motion_masks`` -> a second registration that leaves out features
inside the masks, and new masks (``ImportConfig.mask_rounds``; if that registration fails, or
leaves frames weakly constrained that were not, the first one is kept) -> sparse points on the
masks dropped -> ``write_scene`` with ``points3d.ply``
and ``import_report.json`` (per-frame keypoints and inlier observations, weakly constrained
frames, the focal length, the reprojection error, the static-world check).

Pose backends: the classical registration above is the default; ``import_video(backend=...)``
takes another (a ``PoseBackend``: ``d2gs_np.importers.colmap_sfm`` runs pycolmap, ``d2gs
import-video --sfm pycolmap``), which replaces ``register_video`` in the first registration and in
the mask rounds; the static-world check needs the KLT tracks and runs for the classical one only.
The motion masks, the dropped points and the scene folder are the same for both, and the report's
``sfm`` entry says which backend ran and what it measured.

Intrinsics: ``focal`` (pixels, at the output size) if given and then kept fixed; otherwise the
guess of a 65 degree horizontal field of view, f = 0.5 max(W, H) / tan(32.5 deg) = 0.785
max(W, H) (a phone's main camera filming 16:9 video), refined by the bundle adjustment. The
principal point is the image centre. Times are spread evenly over [0, 1] (``k / (N - 1)``);
``exposure_fraction`` is left absent (unknown: learned, docs/method.md §4).
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from d2gs_np.base.checks import check_int, check_number
from d2gs_np.data.io import write_scene
from d2gs_np.data.scene import Frame, Scene
from d2gs_np.geometry.camera import make_intrinsics
from d2gs_np.geometry.trajectory import ate
from d2gs_np.video.decode import check_decode_args, read_frames
from d2gs_np.video.masks import MaskConfig, static_motion_masks
from d2gs_np.video.segment import border_share, track_groups
from d2gs_np.video.sfm import SfmConfig, register_video
from d2gs_np.pose.tracks import klt_tracks

__all__ = ["ImportConfig", "PoseBackend", "import_video", "guess_focal", "REPORT_FILE", "GUESS_FOV_X_DEG"]

REPORT_FILE = "import_report.json"
GUESS_FOV_X_DEG = 65.0  # horizontal field of view assumed when no focal length is given


def guess_focal(width, height):
    """Focal length (pixels) of a GUESS_FOV_X_DEG field of view across the longer side."""
    return 0.5 * max(width, height) / np.tan(np.radians(GUESS_FOV_X_DEG) / 2)


@dataclass(frozen=True)
class ImportConfig:
    stride: int = 1
    max_frames: int = None
    size: tuple = None  # (W, H)
    focal: float = None  # pixels at the output size; None: guessed and refined
    start: float = None  # seconds (video only)
    end: float = None
    masks: bool = True  # compute motion masks
    # registration passes without features on masked pixels, each followed by new masks; one
    # helps, a second helps one scene and hurts another (docs/results.md §13)
    mask_rounds: int = 1
    # which rigid motion is the static world (``static_motion``): when the smaller of two groups of
    # tracks that move together holds at least this share of them (0: never checked), the group
    # owning more of the frame border is registered alone, and replaces the registration when their
    # trajectories differ by more than other_motion_ate (median point depths)
    other_motion_share: float = 0.25
    other_motion_ate: float = 0.01
    sfm: SfmConfig = field(default_factory=SfmConfig)
    mask: MaskConfig = field(default_factory=MaskConfig)

    def __post_init__(self):
        if self.focal is not None:
            check_number(self.focal, "ImportConfig.focal", 0.0, lo_open=True, hint="pixels")
        check_number(self.other_motion_share, "ImportConfig.other_motion_share", 0.0, 1.0)
        check_number(self.other_motion_ate, "ImportConfig.other_motion_ate", 0.0)
        check_int(self.mask_rounds, "ImportConfig.mask_rounds", 0)
        if not isinstance(self.sfm, SfmConfig) or not isinstance(self.mask, MaskConfig):
            raise TypeError("ImportConfig.sfm must be an SfmConfig and ImportConfig.mask a MaskConfig")


@dataclass(frozen=True)
class PoseBackend:
    """A camera registration ``import_video`` runs instead of the classical one.

    ``register(images, K, refine_focal, masks, log) -> (SfmResult, info)``: images a list of (H, W, 3)
    uint8 frames, K (3, 3) the starting intrinsics, masks None or one (H, W) bool array per frame
    (True = moving: no features there); the SfmResult in ``register_video``'s gauge and layout, every
    frame registered (else a ValueError naming the frames), info a JSON-able dict for the report.
    """

    name: str
    register: Callable

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise TypeError(f"PoseBackend.name must be a non-empty str; got {self.name!r}")
        if not callable(self.register):
            raise TypeError(f"PoseBackend.register must be callable; got {type(self.register).__name__}")


def _drop_points(res, keep):
    """SfmResult without the sparse points where keep (P,) is False (and their observations)."""
    new_id = np.full(len(res.points), -1)
    new_id[keep] = np.arange(int(keep.sum()))
    o = keep[res.obs_point]
    return dataclasses.replace(res, points=res.points[keep], colors=res.colors[keep], obs_frame=res.obs_frame[o],
                               obs_point=new_id[res.obs_point[o]], obs_uv=res.obs_uv[o])


def _subset(tracks, keep):
    """The tracks where keep (num_tracks,) is True, renumbered, in klt_tracks' layout. The points per
    frame stay those of all tracks: register_video's texture check is about the frames, and a frame
    with few of the group's points fails its PnP with its own error."""
    obs_f, obs_t, obs_uv, _, nkp = tracks
    sel = keep[obs_t]
    _, sub_t = np.unique(obs_t[sel], return_inverse=True)
    return obs_f[sel], sub_t.astype(np.int64), obs_uv[sel], int(sub_t.max()) + 1 if sel.any() else 0, nkp


def static_motion(imgs, K, cfg, tracks, res, log=None):
    """The registration of the static world: ``res``, or that of one group of tracks (``segment``).

    The tracks are split into two groups that move together (``segment.track_groups``). When the
    smaller holds at least ``cfg.other_motion_share`` of the grouped tracks, the group whose points
    own more of the frame border (``segment.border_share``) is taken for the static world and
    registered on its own. If its trajectory disagrees with ``res`` by more than
    ``cfg.other_motion_ate`` (ATE after a similarity alignment, in units of the median point depth),
    ``res`` followed a compromise with a mover and the group's registration replaces it (the
    importer's masks and second pass then bring the rest of the static tracks back); otherwise, as
    in a static scene whose planes split into groups, ``res`` is kept. Returns (registration, info
    for the report).
    """
    obs_f, obs_t, obs_uv, T, _ = tracks
    N, (H, W) = len(imgs), imgs[0].shape[:2]
    info = {"checked": False}
    if cfg.other_motion_share <= 0 or res.rotation_only or T == 0:
        return res, info
    lab = track_groups(obs_f, obs_t, obs_uv, T)
    n0, n1 = int(np.sum(lab == 0)), int(np.sum(lab == 1))
    share = min(n0, n1) / max(n0 + n1, 1)
    info.update(groups=[n0, n1], smaller_share=share)
    if share < cfg.other_motion_share:
        return res, info
    on = lab[obs_t]
    own0 = border_share(obs_uv[on == 0], obs_f[on == 0], obs_uv[on == 1], obs_f[on == 1], N, W, H)
    if not np.isfinite(own0):  # the groups never share a frame: nothing to compare
        return res, info
    info["checked"] = True
    static = 0 if own0 >= 0.5 else 1
    info.update(border_share=own0 if static == 0 else 1.0 - own0, static_group=static)
    try:
        alt = register_video(imgs, K, cfg.sfm, refine_focal=cfg.focal is None, log=None,
                             tracks=_subset(tracks, lab == static))
    except ValueError as e:
        if log:
            log(f"tracks in two groups ({n0}, {n1}); group {static} (owns {100 * info['border_share']:.0f}% of the "
                f"frame border) cannot be registered on its own ({str(e)[:120]}): keeping the registration")
        info.update(registered=False)
        return res, info
    dis = float(ate(res.cam_T_world, alt.cam_T_world))
    switch = dis > cfg.other_motion_ate
    info.update(registered=True, disagreement=dis, switched=switch)
    if log:
        log(f"tracks in two groups ({n0}, {n1}); group {static} owns {100 * info['border_share']:.0f}% of the frame "
            f"border and, registered alone, differs from the registration by {100 * dis:.2f}% of the median depth: "
            + ("the registration followed a mover; using the group's" if switch else "keeping the registration"))
    return (alt if switch else res), info


def _check_out(out, overwrite):
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise ValueError(f"output scene folder {out} exists and is not empty; choose a new folder or pass "
                         "--overwrite")
    return out


def import_video(source, out, config: ImportConfig = None, overwrite=False, log=print,
                 backend: PoseBackend = None) -> dict:
    """Import ``source`` into the scene folder ``out``; returns the report (also written as JSON).
    backend: None for the classical registration, or a PoseBackend (module docstring)."""
    cfg = ImportConfig() if config is None else config
    if not isinstance(cfg, ImportConfig):
        raise TypeError(f"config must be an ImportConfig; got {type(cfg).__name__}")
    if backend is not None and not isinstance(backend, PoseBackend):
        raise TypeError(f"backend must be a PoseBackend or None; got {type(backend).__name__}")
    check_decode_args(source, cfg.stride, cfg.max_frames, cfg.size, cfg.start, cfg.end)
    out = _check_out(out, overwrite)
    t0 = time.perf_counter()
    dec = read_frames(source, cfg.stride, cfg.max_frames, cfg.size, cfg.start, cfg.end, log=log)
    imgs = dec.images
    N = len(imgs)
    H, W = imgs[0].shape[:2]
    f0 = cfg.focal if cfg.focal is not None else guess_focal(W, H)
    K = make_intrinsics(f0, f0, W / 2.0, H / 2.0)
    if log:
        log(f"intrinsics: focal {f0:.1f} px ({'given' if cfg.focal is not None else 'guessed, refined below'}), "
            f"principal point at the centre")
    refine = cfg.focal is None
    t_sfm = time.perf_counter()  # seconds in the registrations (not the masks) go to the report's "sfm"
    if backend is None:
        tracks = None
        if cfg.sfm.tracker == "klt":
            tracks = klt_tracks(imgs, cfg.sfm.tracks, None, seed=cfg.sfm.features.seed)
        res = register_video(imgs, K, cfg.sfm, refine_focal=refine, log=log, tracks=tracks)
        sfm_info = {}
        motion_info = {"checked": False}
        if tracks is not None:
            res, motion_info = static_motion(imgs, K, cfg, tracks, res, log)

        def register_masked(masks):
            return register_video(imgs, K, cfg.sfm, refine_focal=refine, masks=masks, log=log), {}
    else:
        res, sfm_info = backend.register(imgs, K, refine, None, log)
        motion_info = {"checked": False, "reason": f"the static-world check needs the classical KLT tracks; the "
                                                   f"{backend.name} backend ran"}

        def register_masked(masks):
            return backend.register(imgs, K, refine, masks, log)
    sfm_seconds = time.perf_counter() - t_sfm
    masks = [np.zeros((H, W), dtype=bool) for _ in range(N)]
    mask_info = {}
    if cfg.masks:
        def _masks(res):
            return static_motion_masks(imgs, res.cam_T_world, res.K, res.points, res.obs_frame, res.obs_point,
                                       res.obs_uv, cfg.mask, log=log)
        masks, mask_info = _masks(res)
        for rnd in range(cfg.mask_rounds):
            if res.rotation_only or not any(m.any() for m in masks):
                break
            t_sfm = time.perf_counter()
            try:
                res2, info2 = register_masked(masks)
            except ValueError as e:
                if log:
                    log(f"registration without the masked pixels failed ({str(e)[:200]}); keeping the previous one")
                break
            finally:
                sfm_seconds += time.perf_counter() - t_sfm
            weaker = sorted(set(res2.weak_frames) - set(res.weak_frames))
            if weaker:  # the masks took too much of these frames: their poses would rest on a few points
                if log:
                    log(f"registration without the masked pixels leaves frames {weaker} weakly constrained; keeping "
                        "the previous one")
                break
            res, sfm_info = res2, info2
            masks, mask_info = _masks(res)
        sfm_points = len(res.points)
        res = _drop_points(res, mask_info["static_points"])
        if log:
            log(f"motion masks: {100 * float(np.mean(mask_info['moving_fraction'])):.1f}% of pixels moving on average")
    else:
        sfm_points = len(res.points)
    # scene scale: 95th percentile of the sparse points' depths in their frames
    z = np.einsum("oij,oj->oi", res.cam_T_world[res.obs_frame, :3, :3], res.points[res.obs_point])[:, 2] \
        + res.cam_T_world[res.obs_frame, 2, 3]
    scale = float(np.percentile(z, 95)) if z.size else 1.0
    frames = []
    for k in range(N):
        frames.append(Frame(file_path=f"images/{k:04d}.png", time=k / (N - 1), cam_T_world=res.cam_T_world[k],
                            K=res.K.copy(), width=W, height=H, image=imgs[k].astype(np.float64) / 255.0,
                            mask=masks[k], mask_path=f"masks/{k:04d}.png"))
    scene = Scene(frames=frames, scene_scale=scale, points3d=res.points, points3d_colors=res.colors)
    write_scene(scene, out, overwrite=overwrite)
    report = {
        "source": str(source), "frames": N, "size": [W, H], "source_frames": dec.source_index,
        "source_names": dec.names, "fps": dec.fps, "focal_px": float(res.K[0, 0]),
        "focal_given": cfg.focal is not None, "rotation_only": res.rotation_only,
        "init_pair": None if res.init_pair is None else list(res.init_pair),
        "init_parallax_deg": res.init_parallax_deg,
        "reprojection_rms_px": res.reprojection_rms_px, "num_points": int(len(res.points)),
        "keypoints_per_frame": res.num_keypoints.tolist(), "observations_per_frame": res.num_observations.tolist(),
        "weak_frames": res.weak_frames, "moving_fraction": mask_info.get("moving_fraction"),
        "static_motion": motion_info,
        "sfm": {"backend": "classical" if backend is None else backend.name, "registered_frames": N,
                "reprojection_rms_px": res.reprojection_rms_px, "points": int(sfm_points),
                "seconds": sfm_seconds, **sfm_info},
        "seconds": time.perf_counter() - t0, "log": res.log,
        "config": {k: v for k, v in asdict(cfg).items() if k not in ("sfm", "mask")},
    }
    with open(out / REPORT_FILE, "w", encoding="utf-8") as fh:
        json.dump(report, fh, indent=2, default=float)
        fh.write("\n")
    if log:
        log(f"wrote {N} frames, {len(res.points)} sparse points and masks to {out} in {report['seconds']:.1f}s"
            + (f"; weakly constrained frames: {res.weak_frames}" if res.weak_frames else ""))
    return report
