"""Where a trained run's error sits, on a suite scene whose true world is known (#40, #44).

For each run folder (trained on a scene written by ``d2gs make-scene`` or ``d2gs experiment``:
its folder holds ``suite_config.json``, from which the true world is rebuilt, and the true depth
maps of ``docs/dataset_format.md §3``, cast from the world for a scene written before them), four
diagnoses:

1. **Novel views, by what went wrong** (docs/method.md §10 aligns the test views as ``d2gs eval``
   does). Each test pixel with a true surface is put in one class: ``moving`` (the test view's
   motion mask); a static pixel whose true 3D point no training frame sees (``unseen``: outside
   every training view or hidden there, tested against the training frames' true depth maps at
   their true poses); else by the rendered depth d against the true depth d*: ``in_front`` (d <
   0.9 d*: a floater, or a surface pulled towards the camera), ``behind`` (d > 1.1 d*), ``depth_ok``.
   Per class: its share of the pixels, its share of the squared error, and its PSNR. The same for
   the training frames (deblurred views) beside it: a class that holds the novel views' error but
   not the training views' is what does not generalise. Also ``dynamic_on_static``: the share of
   static pixels whose colour the dynamic set changes by more than 0.05 (rendered with and without
   it): the dynamic set explaining the static world.
2. **Depth of the static set where things move.** In each training frame's moving pixels, the
   depth of the static set rendered alone against the true depth of the world without its
   movers: ``static_fills_movers`` is the share of those pixels where the static set alone sits
   in front (d < 0.9 d*_background): static Gaussians painting the movers.
3. **Does the dynamic set follow the movers?** The dynamic Gaussians with opacity > 0.3, at the
   middle frame's time, carried into the true frame (the Sim(3) alignment of ``d2gs eval``) and
   projected into its true camera: those whose pixel sees a mover within 10 % of their depth are
   ``on_mover``; the surface point each of them sits on is followed through the clip
   (``data.suite.mover_point_tracks``) and compared with the Gaussian's own deformed centre
   projected into every frame: the median tracking error (px) over Gaussians and frames, and its
   90th percentile. A motion model that follows the mover has errors near the blur's width or
   less; one that does not, tens of pixels.
4. **How far the model's depth moves a novel view's pixels.** For each test view and the
   training frame of its time (the nearest): each static pixel of that frame with a true depth,
   lifted at the true depth and at the model's rendered depth (in the truth's units, the
   alignment's scale), both projected into the test view through the true relative pose. The
   ``parallax`` (px) is how far the true point moves between the two views; the ``shift`` (px)
   is how far apart the two projections land: what the depth error alone costs the novel view.
   Also the signed relative depth error's median, 10th and 90th percentiles: a shift from
   depths scattered about the truth (Gaussians layered in front of and behind a surface) or
   from a world too near or too far as a whole.

    python examples/run_diagnosis.py RUN [RUN ...] [--out diagnosis.json]

Prints one table per diagnosis. The renders are float64, at full resolution; a 240 x 135 scene
takes 10-30 s per run.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

CLASSES = ("moving", "unseen", "in_front", "behind", "depth_ok")
_NEAR, _FAR = 0.9, 1.1  # depth ratio bounds of "depth_ok"


def _world(scene_dir):
    from d2gs_np.data import suite

    p = Path(scene_dir) / "suite_config.json"
    if not p.is_file():
        raise FileNotFoundError(f"{p} is missing: run_diagnosis.py needs a suite scene (it rebuilds the true world)")
    return suite.build_suite_world(suite.SuiteConfig(**json.loads(p.read_text())))


def _static_only(params):
    return {n: v for n, v in params.items() if n.startswith("static.")}


def _render(model, params, pose, t, f):
    """Renderer outputs of ``params`` (a subset of the model's scene blocks) at pose, time t."""
    from d2gs_np.render.api import render_fwd
    from d2gs_np.scene.render_inputs import render_inputs_fwd

    ri, _ = render_inputs_fwd(params, float(t), model.config.deform)
    out, _ = render_fwd(ri["means"], ri["quats"], ri["scales"], ri["opacities"], ri["colors"],
                        np.asarray(pose, np.float64), np.asarray(f.K, np.float64), int(f.width), int(f.height),
                        model.background, dataclasses.replace(model.config.render, raster_float32=False))
    return out


def _classify(view_pose, f, depth, moving, frames, check_seen):
    """Class index (H, W) of each pixel (-1: no true surface), CLASSES order."""
    t = f.depth
    cls = np.full(t.shape, -1)
    ok = np.isfinite(t) & (t > 0)
    cls[ok & moving] = 0
    stat = ok & ~moving
    ratio = np.where(stat, depth / np.where(stat, t, 1.0), 1.0)
    cls[stat & (ratio < _NEAR)] = 2
    cls[stat & (ratio > _FAR)] = 3
    cls[stat & (ratio >= _NEAR) & (ratio <= _FAR)] = 4
    if check_seen:
        from d2gs_np.evaluation.runs import seen_by_training

        cls[stat & ~seen_by_training(view_pose, f, frames)] = 1
    return cls


def _tally(acc, cls, err):
    for c in range(len(CLASSES)):
        sel = cls == c
        acc[c, 0] += sel.sum()
        acc[c, 1] += err[sel].sum()


def _table(acc):
    n, e = acc[:, 0], acc[:, 1]
    out = {}
    for c, name in enumerate(CLASSES):
        mse = e[c] / (3 * n[c]) if n[c] else None
        out[name] = {"pixel_share": float(n[c] / max(n.sum(), 1)), "error_share": float(e[c] / max(e.sum(), 1e-300)),
                     "psnr": None if not mse else float(-10 * np.log10(mse))}
    return out


def depth_shift(uv, true_depth, model_depth, K, rel):
    """(parallax (P,), shift (P,)) in pixels of the pixels ``uv`` (P, 2) of one view, lifted at
    ``true_depth`` and at ``model_depth`` (P,) and projected through ``rel`` (4, 4: that camera
    to another, same intrinsics K): how far each true point moves between the two views, and how
    far its projection at the model's depth lands from the true one (diagnosis 4)."""
    rays = np.linalg.solve(K, np.vstack([uv.T, np.ones(len(uv))]))

    def project(z):
        Y = rel[:3, :3] @ (rays * z) + rel[:3, 3:4]
        q = K @ Y
        return (q[:2] / q[2]).T

    p_true = project(np.asarray(true_depth, np.float64))
    return np.linalg.norm(p_true - uv, axis=1), np.linalg.norm(project(np.asarray(model_depth, np.float64)) - p_true,
                                                                 axis=1)


def diagnose(run_dir) -> dict:
    from d2gs_np.data import suite
    from d2gs_np.data.io import load_scene
    from d2gs_np.evaluation import metrics
    from d2gs_np.evaluation.runs import align_with_orientations, load_run
    from d2gs_np.geometry.camera import project_points
    from d2gs_np.scene.render_inputs import render_inputs_fwd

    run = load_run(run_dir)
    scene_dir = run.meta.get("scene_root")
    scene = load_scene(scene_dir)
    if not (scene.has_gt_poses and scene.test_frames):
        raise ValueError(f"{scene_dir}: the diagnosis needs true poses and test views (a suite scene)")
    world = _world(scene_dir)
    if not scene.has_depth:  # a suite scene written before scenes carried depth maps: cast them
        for f in scene.frames:
            f.depth = suite.suite_depth_map(world, f.gt_cam_T_world, f.time, f.K, f.width, f.height)
        for f in scene.test_frames:  # a test view's pose is its true pose
            f.depth = suite.suite_depth_map(world, f.cam_T_world, f.time, f.K, f.width, f.height)
    model = run.model
    params = {n: v for n, v in model.params.items() if n.startswith(("static.", "dynamic."))}
    static = _static_only(params)
    mids = model.mid_poses()
    gt = np.stack([f.gt_cam_T_world for f in scene.frames])
    s, R, t = align_with_orientations(mids, gt, scene.scene_scale)  # gt ~= s R est + t
    si, Ri, ti = metrics.sim3_inverse(s, R, t)
    res = {"run": str(run_dir), "scene": Path(scene_dir).name}

    # 1. error by class, novel views and training frames
    nvs, dvs = np.zeros((len(CLASSES), 2)), np.zeros((len(CLASSES), 2))
    dyn_changed, static_px = 0, 0
    for f in scene.test_frames:
        pose = metrics.sim3_apply_to_poses(si, Ri, ti, f.cam_T_world)
        full = _render(model, params, pose, f.time, f)
        moving = np.zeros(f.depth.shape, bool) if f.mask is None else f.mask
        cls = _classify(f.cam_T_world, f, full["expected_depth"] / si, moving, scene.frames, True)
        _tally(nvs, cls, ((full["image"] - f.image) ** 2).sum(-1))
        if any(n.startswith("dynamic.") for n in params):
            alone = _render(model, static, pose, f.time, f)["image"]
            stat = (cls >= 1)
            dyn_changed += int((np.abs(full["image"] - alone).max(-1)[stat] > 0.05).sum())
            static_px += int(stat.sum())
    for k, f in enumerate(scene.frames):
        full = _render(model, params, mids[k], f.time, f)
        moving = np.zeros(f.depth.shape, bool) if f.mask is None else f.mask
        cls = _classify(f.gt_cam_T_world, f, s * full["expected_depth"], moving, scene.frames, False)
        _tally(dvs, cls, ((full["image"] - f.sharp) ** 2).sum(-1))
    res["nvs_classes"], res["dvs_classes"] = _table(nvs), _table(dvs)

    # 4. how far the model's static depth moves each test view's pixels
    times = np.array([f.time for f in scene.frames])
    shifts = []
    for f in scene.test_frames:
        k = int(np.argmin(np.abs(times - f.time)))
        g = scene.frames[k]
        model_depth = s * _render(model, params, mids[k], g.time, g)["expected_depth"]
        ok = np.isfinite(g.depth) & (g.depth > 0) & np.isfinite(model_depth) & (model_depth > 0)
        if g.mask is not None:
            ok &= ~g.mask
        rows, cols = np.nonzero(ok)
        uv = np.stack([cols + 0.5, rows + 0.5], axis=1)
        par, shift = depth_shift(uv, g.depth[ok], model_depth[ok], g.K, f.cam_T_world @ np.linalg.inv(gt[k]))
        rel = model_depth[ok] / g.depth[ok] - 1.0
        shifts.append({"time": float(f.time), "frame": k, "parallax_px": float(np.median(par)),
                       "shift_px": float(np.median(shift)), "shift_over_1px": float(np.mean(shift > 1.0)),
                       "depth_error_median": float(np.median(rel)), "depth_error_p10": float(np.percentile(rel, 10)),
                       "depth_error_p90": float(np.percentile(rel, 90))})
    res["nvs_depth_shift"] = shifts
    res["dynamic_on_static"] = dyn_changed / static_px if static_px else None

    # 2. the static set alone in the moving pixels, against the world without its movers
    bare = dataclasses.replace(world, movers=())
    fills, total = 0, 0
    for k, f in enumerate(scene.frames):
        if f.mask is None or not f.mask.any():
            continue
        d_static = s * _render(model, static, mids[k], f.time, f)["expected_depth"]
        d_bg = suite.suite_depth_map(bare, f.gt_cam_T_world, f.time, f.K, f.width, f.height)
        m = f.mask & np.isfinite(d_bg)
        fills += int((d_static[m] < _NEAR * d_bg[m]).sum())
        total += int(m.sum())
    res["static_fills_movers"] = fills / total if total else None

    # 3. the dynamic set against the movers' true motion
    nd = len(params.get("dynamic.means", ()))
    res["num_dynamic"], res["num_static"] = int(nd), int(len(params["static.means"]))
    if nd and world.movers:
        k0 = len(scene.frames) // 2
        f0 = scene.frames[k0]
        ns = len(params["static.means"])
        op = 1.0 / (1.0 + np.exp(-params["dynamic.opacity_logits"]))
        keep = op > 0.3
        X = np.stack([render_inputs_fwd(params, float(f.time), model.config.deform)[0]["means"][ns:][keep]
                      for f in scene.frames])  # (M, G, 3), reconstruction frame
        Xg = s * np.einsum("ij,mgj->mgi", R, X) + t  # true frame
        uv0, z0 = project_points(Xg[k0], f0.gt_cam_T_world, f0.K)
        j, i = np.floor(uv0[:, 0]).astype(int), np.floor(uv0[:, 1]).astype(int)
        inside = (z0 > 0) & (j >= 0) & (j < f0.width) & (i >= 0) & (i < f0.height)
        on = np.zeros(len(z0), bool)
        on[inside] = f0.mask[i[inside], j[inside]] & (np.abs(z0[inside] - f0.depth[i[inside], j[inside]])
                                                      <= 0.1 * f0.depth[i[inside], j[inside]])
        res["dynamic_opaque"] = int(keep.sum())
        res["dynamic_on_mover"] = float(on.mean()) if len(on) else None
        if on.any():
            poses = np.stack([f.gt_cam_T_world for f in scene.frames])
            Ks = np.stack([f.K for f in scene.frames])
            times = np.array([f.time for f in scene.frames])
            truth = suite.mover_point_tracks(world, f0.gt_cam_T_world, f0.K, f0.time, uv0[on], poses, Ks, times)
            ours = np.stack([project_points(Xg[q][on], poses[q], Ks[q])[0] for q in range(len(poses))])
            err = np.linalg.norm(ours - truth, axis=-1)  # (M, G'); NaN where the point left every mover
            err = err[np.isfinite(err)]
            res["tracking_px_median"] = float(np.median(err)) if err.size else None
            res["tracking_px_p90"] = float(np.percentile(err, 90)) if err.size else None
    return res


def _print(rows):
    print(f"{'run':40s} " + "  ".join(f"{c:>17s}" for c in CLASSES) + "   (novel views: pixel % / error % / PSNR)")
    for r in rows:
        cells = [f"{100 * v['pixel_share']:4.1f}/{100 * v['error_share']:4.1f}/"
                 f"{v['psnr'] if v['psnr'] is not None else float('nan'):5.1f}" for v in r["nvs_classes"].values()]
        print(f"{Path(r['run']).name[:40]:40s} " + "  ".join(f"{c:>17s}" for c in cells))
    print(f"{'run':40s} " + "  ".join(f"{c:>17s}" for c in CLASSES) + "   (training frames)")
    for r in rows:
        cells = [f"{100 * v['pixel_share']:4.1f}/{100 * v['error_share']:4.1f}/"
                 f"{v['psnr'] if v['psnr'] is not None else float('nan'):5.1f}" for v in r["dvs_classes"].values()]
        print(f"{Path(r['run']).name[:40]:40s} " + "  ".join(f"{c:>17s}" for c in cells))
    print(f"{'run':40s} {'dyn on static %':>15s} {'static fills movers %':>21s} {'dynamic (opaque)':>17s} "
          f"{'on mover %':>10s} {'track px med / p90':>18s}")

    def pct(x):
        return "-" if x is None else f"{100 * x:.1f}"
    for r in rows:
        track = (f"{r['tracking_px_median']:.1f} / {r['tracking_px_p90']:.1f}" if r.get("tracking_px_median") is not None
                 else "-")
        print(f"{Path(r['run']).name[:40]:40s} {pct(r['dynamic_on_static']):>15s} {pct(r['static_fills_movers']):>21s} "
              f"{r['num_dynamic']:>8d} ({r.get('dynamic_opaque', 0):>6d}) {pct(r.get('dynamic_on_mover')):>10s} "
              f"{track:>18s}")


def _print_shifts(rows):
    print(f"{'run':40s} {'t':>5s} {'parallax px':>11s} {'shift px':>8s} {'> 1 px %':>8s} "
          f"{'depth err med / p10 / p90':>26s}   (static pixels, novel views)")
    for r in rows:
        for v in r["nvs_depth_shift"]:
            print(f"{Path(r['run']).name[:40]:40s} {v['time']:5.2f} {v['parallax_px']:11.1f} {v['shift_px']:8.2f} "
                  f"{100 * v['shift_over_1px']:8.0f} {v['depth_error_median']:+8.3f} / {v['depth_error_p10']:+.3f} / "
                  f"{v['depth_error_p90']:+.3f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run folders trained on suite scenes")
    ap.add_argument("--out", help="also write the results as JSON here")
    args = ap.parse_args(argv)
    rows = [diagnose(r) for r in args.runs]
    _print(rows)
    _print_shifts(rows)
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=1) + "\n")
    return rows


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
