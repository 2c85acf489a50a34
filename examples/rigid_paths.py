"""The rigid movers' initial paths against the suite's true movers (``MotionInitConfig.rigid``,
docs/results.md §4: the object bundle's window, session 56).

For each suite scene and seed, the scene is made as ``d2gs experiment static-depth`` makes it for a
variant of that experiment, the run is set up as the trainer sets it up (the bundle adjustment of
the given poses, the seeds, the motion initialisation) and, for every rigid cluster against every
true mover, the error of the cluster's turn from the clip's middle frame is measured in the camera:
the object-in-camera rotation Q_n = C_n R_n (C_n the frame's camera rotation, R_n the object's)
relative to the middle frame's, Q_n Q_mid^T, against the true one. This is free of the world's
gauge (the bundle adjustment's frame differs from the truth's by a similarity) and of a cluster's
own frame, and counts the cameras' rotation error too (small beside a mover's). Each mover is scored
by the cluster that follows it best (median over frames, degrees), with the set-up's seconds.

    python examples/rigid_paths.py --variant stereo_prior_fused_rigid_bundle [--set motion_init.bundle_window=8]
        [--scenes cube_sign,big_mover,wall_disk,crossing] [--seeds 0 1] [--out runs/rigid_paths]

Writes results.json under --out (one row per scene, seed and mover, with its per-frame errors) and
prints a table.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np

MOVER_SCENES = ("cube_sign", "big_mover", "wall_disk", "crossing")


def turn_errors_deg(cam_R, obj_R, cam_R_true, obj_R_true, ref):
    """Per-frame error (N,) in degrees of the object's turn from frame ``ref``, measured in the
    camera: angle of (Q_n Q_ref^T)(Qt_n Qt_ref^T)^T with Q_n = cam_R[n] @ obj_R[n] (object ->
    camera) and Qt the same of the truth. cam_R, obj_R, cam_R_true, obj_R_true: (N, 3, 3)
    rotations (cam_R world -> camera, obj_R object -> world)."""
    arrs = [np.asarray(a, np.float64) for a in (cam_R, obj_R, cam_R_true, obj_R_true)]
    N = len(arrs[0])
    for name, a in zip(("cam_R", "obj_R", "cam_R_true", "obj_R_true"), arrs):
        if a.shape != (N, 3, 3) or not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite (N, 3, 3) rotations with N = {N}; got {a.shape}")
    if not 0 <= int(ref) < N:
        raise ValueError(f"ref must be a frame index in [0, {N}); got {ref}")
    Q = arrs[0] @ arrs[1]
    Qt = arrs[2] @ arrs[3]
    rel = Q @ np.swapaxes(Q[ref:ref + 1], 1, 2)
    rel_t = Qt @ np.swapaxes(Qt[ref:ref + 1], 1, 2)
    E = rel @ np.swapaxes(rel_t, 1, 2)
    return _angle_deg(E)


def _angle_deg(R):
    """(..., 3, 3) rotations -> (...,) their angle in degrees (so3_log's, exact near 0 and pi)."""
    from d2gs_np.geometry.so3 import so3_log

    return np.degrees(np.linalg.norm(so3_log(R), axis=-1))


def best_clusters(errors):
    """errors {(cluster, mover): (N,) per-frame degrees} -> {mover: (cluster, median degrees)}, each
    mover scored by the cluster whose median error is least."""
    out = {}
    for (c, m), e in errors.items():
        med = float(np.median(e))
        if m not in out or med < out[m][1]:
            out[m] = (c, med)
    return out


def _override(cfg, assignment):
    """cfg with one ``section.field=value`` (value a Python literal) set, through the config's own
    validation."""
    import ast

    key, _, value = assignment.partition("=")
    sec, _, field = key.partition(".")
    if not value or not hasattr(cfg, sec) or not hasattr(getattr(cfg, sec), field):
        raise ValueError(f"--set {assignment!r}: give section.field=value of the ExperimentConfig")
    sub = getattr(cfg, sec)
    return dataclasses.replace(cfg, **{sec: dataclasses.replace(sub, **{field: ast.literal_eval(value)})})


def measure(scene_name, seed, variant_name, sets=(), work="runs/rigid_paths"):
    """Rows (one per true mover) of a variant's initial rigid paths on one suite scene and seed."""
    from d2gs_np.data.io import load_scene
    from d2gs_np.data.suite import build_suite_world, mover_pose, resolve
    from d2gs_np.experiments.sweep import EXPERIMENTS, _make_scene, variant_config
    from d2gs_np.scene.rigid import cluster_poses
    from d2gs_np.train.setup import set_up_run

    variants = {v.name: v for v in EXPERIMENTS["static-depth"]}
    if variant_name not in variants:
        raise ValueError(f"unknown static-depth variant {variant_name!r}; choose from {sorted(variants)}")
    var = variants[variant_name]
    cfg = variant_config(var, None, quiet=True, seed=int(seed))
    for s in sets:
        cfg = _override(cfg, s)  # dataclasses.replace validates the changed config
    if not cfg.motion_init.rigid:
        raise ValueError(f"variant {variant_name!r} has no rigid movers (motion_init.rigid is off): nothing to measure")
    scene = load_scene(_make_scene(work, scene_name, var, int(seed), 1.0, None))
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        setup = set_up_run(scene, cfg, d, overwrite=True)
    seconds = time.perf_counter() - t0
    model = setup.state.model
    blocks = {k: v for k, v in model.params.items() if k.startswith("rigid.")}
    times = np.array([f.time for f in scene.frames])
    ref = len(times) // 2
    cam_R = model.start_poses[:, :3, :3]
    cam_R_true = np.stack([f.gt_cam_T_world[:3, :3] for f in scene.frames])
    obj_R = np.stack([cluster_poses(blocks, t, cfg.deform)[0] for t in times])  # (N, C, 3, 3)
    movers = build_suite_world(resolve(scene_name, int(seed))).movers
    errors, turns = {}, {}
    for m, mover in enumerate(movers):
        true_R = np.stack([mover_pose(mover, t)[0] for t in times])
        turns[m] = float(_angle_deg(true_R @ true_R[ref].T).max())  # the mover's own turn from the middle frame
        for c in range(obj_R.shape[1]):
            errors[(c, m)] = turn_errors_deg(cam_R, obj_R[:, c], cam_R_true, true_R, ref)
    rows = []
    for m, (c, med) in sorted(best_clusters(errors).items()):
        rows.append({"scene": scene_name, "seed": int(seed), "variant": variant_name, "set": list(sets),
                     "mover": movers[m].kind, "true_turn_deg": turns[m], "cluster": int(c), "median_deg": med,
                     "per_frame_deg": [float(e) for e in errors[(c, m)]], "setup_seconds": seconds})
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variant", required=True, help="a static-depth variant with rigid movers")
    ap.add_argument("--set", action="append", default=[], help="section.field=value on the variant's config")
    ap.add_argument("--scenes", default=",".join(MOVER_SCENES))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--out", default="runs/rigid_paths")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.scenes.split(","):
        for seed in args.seeds:
            for r in measure(name, seed, args.variant, args.set, out):
                rows.append(r)
                print(f"{name:10s} seed {seed}  {r['mover']:9s} (turns {r['true_turn_deg']:5.1f} deg)  median error "
                      f"{r['median_deg']:6.1f} deg  worst frame {max(r['per_frame_deg']):6.1f}  set-up "
                      f"{r['setup_seconds']:5.1f} s", flush=True)
    (out / "results.json").write_text(json.dumps(rows, indent=1))
    print(f"wrote {out / 'results.json'}")


if __name__ == "__main__":
    main()
