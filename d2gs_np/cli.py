"""Command line: ``d2gs {demo, make-scene, import-video, import-colmap, import-dyblurf, train, eval, report, experiment,
render, export-ply, export-trajectory, refcheck}``.

Every command validates its inputs before starting work and exits with a
one-line error (status 2) naming the problem. Input accepted but implausible
(``d2gs_np.base.checks.InputWarning``) is printed as one line ``d2gs CMD: warning: ...``
on stderr when issued (a training run also keeps it in its log). Each command's help names the
page of docs/ that explains it (docs/architecture.md §2 maps the code to the docs).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from d2gs_np.train.checkpoint import check_output_path

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")  # what save_image (OpenCV) writes


def _int_at_least(lo):
    """An argparse type: an integer >= lo; argparse names the flag in its error (status 2)."""
    def parse(text):
        try:
            v = int(text)
        except ValueError:
            v = None
        if v is None or v < lo:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lo}; got {text!r}")
        return v
    return parse


def _finite_float(lo=-math.inf, positive=False):
    """An argparse type: a finite number >= lo (> 0 with ``positive``); NaN and inf are refused here,
    before any work, rather than deep in a run."""
    want = "a finite number" + (" > 0" if positive else f" >= {lo:g}" if lo > -math.inf else "")

    def parse(text):
        try:
            v = float(text)
        except ValueError:
            v = math.nan
        if not math.isfinite(v) or v < lo or (positive and v <= 0):
            raise argparse.ArgumentTypeError(f"must be {want}; got {text!r}")
        return v
    return parse


_COUNT = _int_at_least(1)  # steps, frames, pixels, jobs ...
_SEED = _int_at_least(0)  # NumPy's generators take seeds >= 0
_SECONDS = _finite_float(positive=True)


class _Parser(argparse.ArgumentParser):
    """argparse with the CLI's own error format: one line, ``d2gs CMD: error: ...``, status 2
    (argparse would print the usage block first)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _cmd_make_scene(args):
    from d2gs_np.data.suite import SUITE, write_suite_scene
    from d2gs_np.data.synthetic import PRESETS, write_synthetic_scene

    if args.preset not in PRESETS and args.preset not in SUITE:
        raise ValueError(f"--preset must be a suite scene {sorted(SUITE)} or a regression preset "
                         f"{sorted(PRESETS)}; got {args.preset!r}")
    check_output_path(args.out, "output scene folder")
    out = Path(args.out)
    if out.is_dir() and any(out.iterdir()) and not args.overwrite:
        raise ValueError(f"scene folder {out} is not empty; pass --overwrite to replace its scene, or choose a new "
                         "folder")
    suite = args.preset in SUITE
    overrides = {}
    for arg, suite_field, regression_field in (
            ("frames", "num_frames", "num_frames"), ("width", "width", "width"), ("height", "height", "height"),
            ("exposure", "exposure_fraction", "exposure_fraction"),
            ("rot_noise_deg", "rot_noise_deg", "rot_noise_deg"), ("trans_noise", "trans_noise", "trans_noise_fraction")):
        v = getattr(args, arg)
        if v is not None:
            overrides[suite_field if suite else regression_field] = v
    if not suite and overrides.get("exposure_fraction") == 0.0:
        overrides["subframes"] = 1
    t0 = time.perf_counter()
    if suite:
        path = write_suite_scene(args.out, args.preset, args.seed, overwrite=args.overwrite, **overrides)
    else:
        path = write_synthetic_scene(args.out, args.preset, args.seed, overwrite=args.overwrite, **overrides)
    print(f"wrote {args.preset} scene (seed {args.seed}) to {path} in {time.perf_counter() - t0:.1f}s")


def _load_config(args):
    from d2gs_np.train.config import ExperimentConfig
    import dataclasses

    cfg = ExperimentConfig.load(args.config) if getattr(args, "config", None) else ExperimentConfig()
    changes = {}
    if getattr(args, "iters", None) is not None:
        changes["iters"] = args.iters
    if getattr(args, "time_budget", None) is not None:
        changes["time_budget"] = args.time_budget
    if getattr(args, "seed", None) is not None:
        changes["seed"] = args.seed
    if getattr(args, "quiet", False):
        changes["quiet"] = True
    for name in ("blur", "dynamic"):
        v = getattr(args, name, None)
        if v is not None:
            changes[name] = v
    if changes:
        cfg = cfg.replace(train=dataclasses.replace(cfg.train, **changes))
    if getattr(args, "n", None) is not None:
        cfg = cfg.replace(blur=dataclasses.replace(cfg.blur, num_virtual=args.n))
    if getattr(args, "pose_solver", None) is not None or getattr(args, "pose_every", None) is not None:
        ps = {k: v for k, v in (("mode", getattr(args, "pose_solver", None)), ("every", getattr(args, "pose_every", None)))
              if v is not None}
        cfg = cfg.replace(pose_solver=dataclasses.replace(cfg.pose_solver, **ps))
    return cfg


def _cmd_train(args):
    from d2gs_np.data.io import load_scene
    from d2gs_np.train.run_folder import check_run_folder
    from d2gs_np.train.trainer import Trainer, TrainingInterrupted

    check_output_path(args.out, "--out")
    cfg = _load_config(args)  # config errors before the scene is read
    overwrite = getattr(args, "overwrite", False)
    # a finished run in --out, or --resume without a checkpoint: refused before the scene is read
    check_run_folder(args.out, args.resume, overwrite, flags=("--resume", "--overwrite"))
    try:
        scene = load_scene(args.scene)
        trainer = Trainer(scene, cfg, args.out, resume=args.resume, overwrite=overwrite)
        result = trainer.run()
    except TrainingInterrupted as e:
        raise KeyboardInterrupt(f"{e}; continue with: {_resume_command(args)}") from None
    except KeyboardInterrupt:  # before the first write into the run folder (Trainer._open_run_folder)
        raise KeyboardInterrupt(f"before training started; nothing in {args.out} was changed") from None
    print(f"trained {result.steps} steps in {result.train_seconds:.1f}s; run in {args.out}")
    return trainer


def _resume_command(args) -> str:
    """The ``d2gs train`` command that continues the run ``args`` started: its options, --resume."""
    import shlex

    words = ["d2gs", "train", str(args.scene), "--out", str(args.out)]
    for flag in ("config", "iters", "time_budget", "seed", "blur", "dynamic", "n", "pose_solver", "pose_every"):
        value = getattr(args, flag, None)
        if value is not None:
            words += ["--" + flag.replace("_", "-"), str(value)]
    words += ["--resume"] + (["--quiet"] if getattr(args, "quiet", False) else [])
    return shlex.join(words)


def _cmd_eval(args):
    from d2gs_np.evaluation.runs import evaluate_run, verdict

    result = evaluate_run(args.run, args.scene, test_pose_steps=args.test_pose_opt,
                          note=lambda line: print(f"d2gs eval: note: {line}", file=sys.stderr))
    print(json.dumps(result, indent=2))
    for line in verdict(result):
        print(f"d2gs eval: {line}")
    print(f"wrote {Path(args.run) / 'metrics.json'}")


def _read_pose_file(path):
    """A JSON file with either "cam_T_world" (internal, world->camera OpenCV) or "transform_matrix"
    (docs/dataset_format.md §2: OpenGL camera-to-world)."""
    from d2gs_np.geometry.camera import opengl_c2w_to_cam_T_world
    from d2gs_np.geometry.se3 import check_rigid

    path = Path(path)
    if path.is_dir():
        raise ValueError(f"--pose {path} is a folder; pass a pose JSON file")
    if not path.exists():
        raise FileNotFoundError(f"pose file {path} does not exist")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"pose file {path} is not valid JSON ({e}); fix the syntax") from None
    if not isinstance(data, dict):
        raise ValueError(f"pose file {path} must hold a JSON object with 'cam_T_world' or 'transform_matrix'")
    if "cam_T_world" in data:
        T = np.asarray(data["cam_T_world"], dtype=np.float64)
    elif "transform_matrix" in data:
        T = opengl_c2w_to_cam_T_world(np.asarray(data["transform_matrix"], dtype=np.float64))
    else:
        raise ValueError(f"pose file {path} needs a 'cam_T_world' or a 'transform_matrix' 4x4 entry")
    check_rigid(T, f"pose in {path}")
    return T


def _cmd_render(args):
    from d2gs_np.evaluation.runs import load_run
    from d2gs_np.reporting.plots import save_image

    if not 0.0 <= args.time <= 1.0:
        raise ValueError(f"--time must be in [0, 1]; got {args.time}")
    if Path(args.out).suffix.lower() not in IMAGE_SUFFIXES:
        raise ValueError(f"--out {args.out} needs an image extension ({', '.join(IMAGE_SUFFIXES)}); "
                         f"e.g. --out {Path(args.out).with_suffix('.png')}")
    check_output_path(args.out, "--out", is_file=True)
    pose = _read_pose_file(args.pose) if args.pose else None
    model = load_run(args.run).model
    k = int(np.argmin(np.abs(model.times - args.time)))  # nearest training frame: its camera
    pose = model.mid_pose(k) if pose is None else pose
    img = model.render(pose, args.time, model.Ks[k], model.widths[k], model.heights[k])
    save_image(args.out, img)
    print(f"wrote {args.out}")


def _cmd_export_ply(args):
    from d2gs_np.data.ply import write_ply
    from d2gs_np.evaluation.runs import load_run
    from d2gs_np.scene.gaussians import DYNAMIC, STATIC
    from d2gs_np.scene.render_inputs import render_inputs_fwd
    from d2gs_np.train.model import SCENE_PREFIXES

    if not 0.0 <= args.time <= 1.0:
        raise ValueError(f"--time must be in [0, 1]; got {args.time}")
    check_output_path(args.out, "output file", is_file=True)
    model = load_run(args.run).model
    scene_params = {n: v for n, v in model.params.items() if n.startswith(SCENE_PREFIXES)}
    ri, _ = render_inputs_fwd(scene_params, args.time, model.config.deform)
    # Scales and opacities do not change with time: export the stored log-scales and logits
    # (exact, and finite even where the sigmoid saturates).
    sets = [p for p in (STATIC, DYNAMIC) if f"{p}.means" in scene_params]
    log_scales = np.concatenate([scene_params[f"{p}.log_scales"] for p in sets])
    logits = np.concatenate([scene_params[f"{p}.opacity_logits"] for p in sets])
    write_ply(args.out, ri["means"], log_scales, ri["quats"], logits, ri["colors"])
    print(f"wrote {ri['means'].shape[0]} Gaussians at t = {args.time} to {args.out}")


def _cmd_export_trajectory(args):
    from d2gs_np.evaluation.runs import load_run
    from d2gs_np.importers.tum import write_tum

    check_output_path(args.out, "output file", is_file=True)
    model = load_run(args.run).model
    # normalised times, or seconds when the frame rate is known (frame k at k / fps for even times)
    stamps = model.times if args.fps is None else model.times * (max(model.num_frames - 1, 1) / args.fps)
    write_tum(args.out, stamps, model.mid_poses())
    print(f"wrote the {model.num_frames} optimised mid-exposure poses of {args.run} to {args.out} (TUM format)")


def _parse_size(text):
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--size must be WIDTHxHEIGHT in pixels, e.g. 320x180; got {text!r}") from None
    return (w, h)


def _cmd_import_video(args):
    from d2gs_np.video.importer import ImportConfig, import_video

    if args.sfm == "pycolmap":  # refused before any work when the optional package is missing
        from d2gs_np.importers.colmap_sfm import require_pycolmap
        require_pycolmap()
    check_output_path(args.out, "output scene folder")
    cfg = ImportConfig(stride=args.stride, max_frames=args.max_frames,
                       size=None if args.size is None else _parse_size(args.size), focal=args.focal,
                       start=args.start, end=args.end, masks=not args.no_masks)
    if args.sfm == "pycolmap":
        from d2gs_np.importers.colmap_sfm import import_video_pycolmap
        import_video_pycolmap(args.video, args.out, cfg, overwrite=args.overwrite)
    else:
        import_video(args.video, args.out, cfg, overwrite=args.overwrite)


def _cmd_import_colmap(args):
    from d2gs_np.importers.colmap import import_colmap

    check_output_path(args.out, "output scene folder")
    import_colmap(args.sparse, args.images, args.out, overwrite=args.overwrite)


def _cmd_import_dyblurf(args):
    from d2gs_np.importers.dyblurf import import_dyblurf

    check_output_path(args.out, "output scene folder")
    import_dyblurf(args.folder, args.out, size=args.size, overwrite=args.overwrite)


def _cmd_demo(args):
    """Small built-in scene -> train the full method -> evaluate -> report.html."""
    from d2gs_np.data.suite import SUITE, write_suite_scene
    from d2gs_np.data.synthetic import PRESETS, write_synthetic_scene
    from d2gs_np.evaluation.runs import evaluate_run, verdict
    from d2gs_np.reporting.html import write_report
    from d2gs_np.reporting.plots import plot_error_vs_time

    if args.preset not in PRESETS and args.preset not in SUITE:
        raise ValueError(f"--preset must be a suite scene {sorted(SUITE)} or a regression preset {sorted(PRESETS)}; "
                         f"got {args.preset!r}")
    size = DEMO_QUICK_SCENE if args.quick else DEMO_SCENE
    iters = args.iters if args.iters is not None else (None if args.config else
                                                       (DEMO_QUICK_ITERS if args.quick else DEMO_ITERS))
    if iters is not None and iters < 1:
        raise ValueError(f"--iters must be >= 1; got {iters}")
    budget = args.time_budget
    if budget is None and not args.quick and args.iters is None:
        budget = DEMO_BUDGET  # the schedule of DEMO_ITERS steps runs on the budget's clock
    if budget is not None and not budget > 0:
        raise ValueError(f"--time-budget must be > 0 seconds; got {budget}")
    check_output_path(args.out, "--out")
    out = Path(args.out)
    scene_dir = out / "scene"
    ns = argparse.Namespace(scene=str(scene_dir), out=str(out / "run"), config=args.config, iters=iters,
                            time_budget=budget, seed=args.seed, quiet=False, blur=None, dynamic=None,
                            n=None, resume=False, overwrite=True)
    _load_config(ns)  # a bad --config fails here, before the scene is made
    t0 = time.perf_counter()
    if args.preset in SUITE:
        write_suite_scene(scene_dir, args.preset, args.seed, overwrite=True, **size)
    else:
        write_synthetic_scene(scene_dir, args.preset, args.seed, overwrite=True, **size)
    print(f"[demo] made the built-in {args.preset!r} scene ({size}) in {time.perf_counter() - t0:.1f}s")
    runs = [out / "run"]
    baseline = None
    if not args.no_baseline:
        # The no-blur baseline (n = 1, no pose refinement) trains beside the method on the same
        # budget, each on half the cores, so the report compares like with like.
        runs.append(out / "noblur")
        baseline = _start_baseline(ns, runs[1])
        print(f"[demo] the no-blur baseline trains beside it in another process ({runs[1]}; "
              "--no-baseline leaves it out)")
    try:
        _cmd_train(ns)
    finally:
        if baseline is not None and baseline.poll() is None and sys.exc_info()[0] is not None:
            baseline.terminate()
    if baseline is not None and baseline.wait() != 0:
        raise RuntimeError(f"the no-blur baseline failed (status {baseline.returncode}); its log: "
                           f"{out / 'noblur.log'}; or run the demo with --no-baseline")
    result = evaluate_run(out / "run")
    base_result = evaluate_run(runs[1]) if baseline is not None else None
    plot_error_vs_time(runs, out / "error_vs_time.png")
    report = write_report(runs, out / "report.html", title=f"d2gs demo: {args.preset} scene")
    print(json.dumps(result, indent=2))
    for line in verdict(result, base_result):
        print(f"[demo] {line}")
    print(f"[demo] report: {report} (open it in a browser); total {time.perf_counter() - t0:.0f}s")


def _start_baseline(ns, out):
    """Start ``d2gs train`` of the no-blur baseline of the demo's run ``ns`` into ``out`` in a child
    process with half the cores (this process keeps the rest); returns the Popen."""
    import os
    import subprocess

    import numba

    cores = os.cpu_count() or 2
    mine, theirs = max(1, cores - cores // 2), max(1, cores // 2)
    numba.set_num_threads(min(mine, numba.config.NUMBA_NUM_THREADS))
    cmd = [sys.executable, "-m", "d2gs_np.cli", "train", ns.scene, "--out", str(out), "--blur", "off",
           "--pose-solver", "off", "--overwrite", "--quiet", "--seed", str(ns.seed)]
    for flag, value in (("--config", ns.config), ("--iters", ns.iters), ("--time-budget", ns.time_budget)):
        if value is not None:
            cmd += [flag, str(value)]
    Path(out).mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "NUMBA_NUM_THREADS": str(theirs), "OMP_NUM_THREADS": str(theirs)}
    with open(Path(out).parent / "noblur.log", "w") as log:
        return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)


def _cmd_report(args):
    from d2gs_np.reporting.html import write_report

    if args.frames < 1:
        raise ValueError(f"--frames must be >= 1; got {args.frames}")
    if len(args.runs) > 1 and args.out is None:
        raise ValueError("several runs need --out FILE.html for their side-by-side report")
    out = args.out or str(Path(args.runs[0]) / "report.html")
    check_output_path(out, "--out" if args.out else "report file", is_file=True)
    for run in args.runs:  # a run without metrics.json is evaluated, which writes it
        if Path(run).is_dir() and not (Path(run) / "metrics.json").exists():
            check_output_path(Path(run) / "metrics.json", "metrics file", is_file=True)
    path = write_report(args.runs, out, num_frames=args.frames)
    print(f"wrote {path}")


def _cmd_experiment(args):
    from d2gs_np.experiments.sweep import run_experiment

    if args.budget is None and args.iters is None:
        raise ValueError("give --budget SECONDS or --iters N per cell")
    check_output_path(args.out, "--out")
    cmd = "d2gs experiment " + " ".join(sys.argv[2:]) if len(sys.argv) > 2 else ""
    records = run_experiment(args.name, args.out, args.scenes, args.seeds, budget=args.budget, iters=args.iters,
                             size=args.size, jobs=args.jobs, threads=args.threads, scheduler=args.scheduler,
                             retries=args.retries, config_path=args.config, variants=args.variants,
                             frames=args.frames, command=cmd)
    out = Path(args.out)
    print((out / f"{args.name}.md").read_text())
    failed = [r for r in records if r["status"] != "ok"]
    print(f"wrote {out / (args.name + '.md')}, {out / (args.name + '.csv')}, {out / (args.name + '_error_vs_time.png')}")
    if failed:
        raise ValueError(f"{len(failed)} of {len(records)} cells failed: "
                         + "; ".join(f"{r['scene']}/{r['variant']}/s{r['seed']}: {r['error']}" for r in failed))


DEMO_PRESET = "cube_sign"  # the suite scene with every component on: movers, blur, noisy poses
# the suite's frame count at two thirds of its resolution: small enough for a laptop's budget, with
# exposures short enough for the method to beat its input in it (why not 12 frames: docs/results.md §2)
DEMO_SCENE = {"num_frames": 24, "width": 160, "height": 90}
DEMO_ITERS = 2000  # the schedule's length; DEMO_BUDGET decides where it ends
DEMO_BUDGET = 420.0  # seconds of training: the whole demo within 10 minutes on 2 cores, install and JIT included (docs/results.md §2)
DEMO_QUICK_SCENE = {"num_frames": 6, "width": 96, "height": 54}
DEMO_QUICK_ITERS = 80  # a smoke run: every stage, the blur model and the report, in about a minute


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="d2gs",
        description="D2GS on the CPU: sharp dynamic 3D Gaussians and camera trajectories from motion-blurred "
                    "monocular video. The method is explained in docs/method.md, the scene folder in "
                    "docs/dataset_format.md.",
        epilog="Documentation (in the source repository): docs/method.md (the method, equations and choices), "
               "docs/conventions.md (renderer conventions), docs/dataset_format.md (scene folders), "
               "docs/architecture.md (code layout), docs/refcheck.md (checking a faster port). Each command's --help "
               "names its page.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    d = sub.add_parser("demo", help="make a small scene of the suite (blurry, moving objects, noisy poses), train, "
                       "evaluate, write "
                       "report.html (docs/method.md)",
                       description="Make a built-in blurry dynamic scene, train on it with the full method, "
                                   "evaluate and write DIR/report.html (one self-contained file). What is trained "
                                   "and measured: docs/method.md §4-10.")
    d.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    d.add_argument("--quick", action="store_true",
                   help=f"a smoke run of about a minute ({DEMO_QUICK_SCENE['num_frames']} frames "
                        f"{DEMO_QUICK_SCENE['width']}x{DEMO_QUICK_SCENE['height']}, {DEMO_QUICK_ITERS} steps)")
    d.add_argument("--preset", default=DEMO_PRESET,
                   help="the scene: a suite scene (photo_room, wall_disk, cube_sign, crossing, big_mover) or a "
                        f"regression preset (static, sharp, dynamic). Default {DEMO_PRESET}")
    d.add_argument("--iters", type=_COUNT, default=None,
                   help=f"training steps (default: a {DEMO_ITERS}-step schedule on a {DEMO_BUDGET:.0f} s budget)")
    d.add_argument("--time-budget", type=_SECONDS, default=None,
                   help=f"seconds of training; the schedule completes within it (default {DEMO_BUDGET:.0f}, none "
                        "with --quick or --iters)")
    d.add_argument("--config", default=None, help="experiment config JSON")
    d.add_argument("--seed", type=_SEED, default=0)
    d.add_argument("--no-baseline", action="store_true",
                   help="leave out the no-blur baseline that otherwise trains beside the method (n = 1, no pose "
                        "refinement, same budget, half the cores each)")
    d.set_defaults(func=_cmd_demo)

    m = sub.add_parser("make-scene", help="generate a synthetic scene folder with ground truth "
                       "(docs/dataset_format.md)",
                       description="Generate a synthetic scene folder with full ground truth, in the format of "
                                   "docs/dataset_format.md; the scene families are described in "
                                   "docs/architecture.md §8.")
    m.add_argument("out", help="output scene folder")
    m.add_argument("--preset", default="dynamic",
                   help="a suite scene (photo_room, wall_disk, cube_sign, crossing, big_mover; photographs, "
                        "realistic motion and pose error) or a regression preset (static, sharp, dynamic: "
                        "the project's older, easier scenes). Default dynamic")
    m.add_argument("--seed", type=_SEED, default=0)
    m.add_argument("--frames", type=_COUNT, default=None)
    m.add_argument("--width", type=_COUNT, default=None)
    m.add_argument("--height", type=_COUNT, default=None)
    m.add_argument("--exposure", type=_finite_float(0.0), default=None,
                   help="exposure / frame interval in [0, 1] (0: sharp video)")
    m.add_argument("--rot-noise-deg", type=_finite_float(0.0), default=None,
                   help="pose error in rotation: RMS angle in degrees (suite); per-axis std (regression presets)")
    m.add_argument("--trans-noise", type=_finite_float(0.0), default=None,
                   help="pose error in translation: RMS fraction of the scene depth (suite); per-axis std as a "
                        "fraction of the scene scale (regression presets)")
    m.add_argument("--overwrite", action="store_true", help="replace an existing scene folder")
    m.set_defaults(func=_cmd_make_scene)

    v = sub.add_parser("import-video", help="video or image folder -> scene folder with classical poses, motion "
                       "masks and sparse points (docs/dataset_format.md)",
                       description="Import a casual video (any file OpenCV decodes) or a folder of images into a "
                                   "scene folder: frames, camera poses and focal length from features, PnP and a "
                                   "bundle adjustment, motion masks from optical flow, sparse points for "
                                   "initialisation (docs/dataset_format.md §8).")
    v.add_argument("video", help="video file (.mp4, .avi, .mov, ...) or folder of images (name order)")
    v.add_argument("out", help="output scene folder")
    v.add_argument("--stride", type=_COUNT, default=1, help="keep every K-th frame (default 1)")
    v.add_argument("--max-frames", type=_COUNT, default=None, help="stop after this many kept frames")
    v.add_argument("--size", default=None, help="resize frames to WIDTHxHEIGHT pixels (default: as decoded)")
    v.add_argument("--focal", type=_finite_float(positive=True), default=None,
                   help="focal length in pixels at the output size (default: a 65 deg field of view, refined)")
    v.add_argument("--start", type=_finite_float(0.0), default=None, help="start time in seconds (video files)")
    v.add_argument("--end", type=_finite_float(0.0), default=None, help="end time in seconds (video files)")
    v.add_argument("--no-masks", action="store_true", help="write empty motion masks (a static scene)")
    v.add_argument("--sfm", choices=("classical", "pycolmap"), default="classical",
                   help="pose backend: our KLT tracks, PnP and bundle adjustment (default), or COLMAP's SIFT and "
                        "incremental mapping through the optional package pycolmap (docs/dataset_format.md §8)")
    v.add_argument("--overwrite", action="store_true", help="write into an existing, non-empty folder")
    v.set_defaults(func=_cmd_import_video)

    c = sub.add_parser("import-colmap", help="COLMAP sparse model and its images -> scene folder "
                       "(docs/dataset_format.md §9)",
                       description="Import a COLMAP sparse model (cameras, images, points3D; .bin or .txt) and its "
                                   "images into a scene folder: frames in image-name order at evenly spaced times, "
                                   "COLMAP's poses as they are (world-to-camera, OpenCV axes), its points as the "
                                   "static initial points; SIMPLE_RADIAL, RADIAL and OPENCV images undistorted "
                                   "(docs/dataset_format.md §9).")
    c.add_argument("sparse", help="sparse model folder (e.g. sparse/0)")
    c.add_argument("images", help="the images folder the model's image names are relative to")
    c.add_argument("out", help="output scene folder")
    c.add_argument("--overwrite", action="store_true", help="write into an existing, non-empty folder")
    c.set_defaults(func=_cmd_import_colmap)

    db = sub.add_parser("import-dyblurf", help="DyBluRF / Stereo Blur scene folder -> scene folder "
                        "(docs/dataset_format.md §11)",
                        description="Import a scene of DyBluRF's Stereo Blur data (images/ or images_<size>/, "
                                    "sharp_images/, inference_images/, motion_masks/, poses_bounds.npy): training "
                                    "frames from the left camera with their sharp frames and masks, test views from "
                                    "the right camera; LLFF poses converted to ours (docs/dataset_format.md §11).")
    db.add_argument("folder", help="the scene folder (DyBluRF's configs use <scene>/dense)")
    db.add_argument("out", help="output scene folder")
    db.add_argument("--size", default=None,
                    help="read images_<SIZE>/ instead of images/, e.g. 512x288 (DyBluRF trains at a height of 288) "
                         "or 4")
    db.add_argument("--overwrite", action="store_true", help="write into an existing, non-empty folder")
    db.set_defaults(func=_cmd_import_dyblurf)

    t = sub.add_parser("train", help="train on a scene folder (docs/method.md §7-8)",
                       description="Train on a scene folder (docs/dataset_format.md). Stages, progressive "
                                   "resolution and the rest of the schedule: docs/method.md §7-8; what is left "
                                   "out and why: docs/method.md §9. The run folder must be new or empty unless "
                                   "--resume or --overwrite is given. Checkpoints (atomic) are written every "
                                   "train.checkpoint_every steps and every train.checkpoint_seconds of wall clock "
                                   "(default 500 steps, 300 s); Ctrl-C finishes the step, writes one and prints the "
                                   "command that resumes (exit status 130).")
    t.add_argument("scene", help="scene folder (docs/dataset_format.md)")
    t.add_argument("--out", required=True,
                   help="run folder (checkpoints, logs); new or empty, unless --resume or --overwrite")
    t.add_argument("--config", default=None, help="experiment config JSON (see ExperimentConfig)")
    t.add_argument("--iters", type=_COUNT, default=None)
    t.add_argument("--time-budget", type=_SECONDS, default=None,
                   help="seconds of training: the run ends when they are spent, its schedule complete; a schedule "
                        "that ends earlier trains on at its end (docs/method.md §7)")
    t.add_argument("--seed", type=_SEED, default=None)
    t.add_argument("--blur", choices=["auto", "on", "off"], default=None,
                   help="blur model (default auto; docs/method.md §4, §9)")
    t.add_argument("--dynamic", choices=["auto", "on", "off"], default=None,
                   help="dynamic set (default auto; docs/method.md §2, §9)")
    t.add_argument("--n", type=_COUNT, default=None, help="virtual views per blurry frame (docs/method.md §4)")
    t.add_argument("--pose-solver", choices=["auto", "on", "off"], default=None,
                   help="pose refinement between Adam steps (docs/method.md §5); auto: unless the poses are trusted")
    t.add_argument("--pose-every", type=_COUNT, default=None, help="schedule steps between pose solver calls")
    t.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its latest checkpoint, on the same scene with the same "
                        "options (only --iters, --time-budget and --quiet may change)")
    t.add_argument("--overwrite", action="store_true",
                   help="replace the run in a non-empty --out; its files stay until the new run's first "
                        "checkpoint, written once setup is done")
    t.add_argument("--quiet", action="store_true")
    t.set_defaults(func=_cmd_train)

    e = sub.add_parser("eval", help="evaluate a run; writes RUN/metrics.json (docs/method.md §10)",
                       description="Evaluate a run against its scene's ground truth and write RUN/metrics.json: "
                                   "deblurring and novel view synthesis, trajectory errors (docs/method.md §10, "
                                   "docs/dataset_format.md §6). Novel views are scored with the test poses "
                                   "through a global alignment (nvs) and beside the camera of their frame, "
                                   "DyBluRF's protocol (nvs_rig).")
    e.add_argument("run")
    e.add_argument("--scene", default=None,
                   help="scene folder (default: the one the run was trained on); it must hold the frames the run "
                        "was trained on (a copy of that folder will do)")
    e.add_argument("--test-pose-opt", type=_int_at_least(0), default=0, metavar="N",
                   help="also score novel views after refining each test pose on the frozen scene for N steps "
                        "(the BARF / BAD-Gaussians protocol; reported as nvs_pose_opt beside nvs). Default 0: off")
    e.set_defaults(func=_cmd_eval)

    r = sub.add_parser("render", help="render a run at a time and pose to PNG (docs/conventions.md)",
                       description="Render a trained run, sharp, at a normalised time and a camera pose. Camera "
                                   "model, axes and pixel centres: docs/conventions.md §2; pose files in scene "
                                   "convention: docs/dataset_format.md §2.")
    r.add_argument("run")
    r.add_argument("--time", type=_finite_float(), required=True, help="normalised time in [0, 1]")
    r.add_argument("--pose", default=None, help="JSON with cam_T_world or transform_matrix (OpenGL c2w); "
                   "default: the optimised pose of the nearest training frame")
    r.add_argument("--out", required=True, help="output PNG")
    r.set_defaults(func=_cmd_render)

    rp = sub.add_parser("report", help="write the HTML report of one run, or of several side by side "
                        "(docs/method.md §10)",
                        description="Write one self-contained HTML file (images embedded): metrics beside the "
                                    "blurry-input baseline, pictures with zoomed crops, novel views, camera "
                                    "trajectories, error against wall-clock time and what was left out. "
                                    "Evaluation protocol: docs/method.md §10.")
    rp.add_argument("runs", nargs="+", help="run folders (trained; evaluated if RUN/metrics.json is missing)")
    rp.add_argument("--out", default=None, help="output HTML (default RUN/report.html for one run)")
    rp.add_argument("--frames", type=_COUNT, default=3, help="frames shown per run (default 3)")
    rp.set_defaults(func=_cmd_report)

    from d2gs_np.experiments.sweep import EXPERIMENTS  # light: the sweep imports Dask only to run

    names = " | ".join(EXPERIMENTS)
    ex = sub.add_parser("experiment", help="run a sweep of training runs on Dask and write one table "
                        "(docs/method.md §10)",
                        description=f"Run an experiment ({names}) over scenes and seeds: every cell an independent run in OUT/runs/NAME, in parallel on Dask's "
                                    "local process pool or on a dask.distributed cluster (--scheduler). Finished "
                                    "cells are never recomputed; failed ones are retried, then reported. Writes "
                                    "OUT/NAME.md, NAME.csv and NAME_error_vs_time.png. Baselines and metrics: "
                                    "docs/method.md §10.")
    ex.add_argument("name", help=names)
    ex.add_argument("--out", required=True, help="output folder (scenes, runs, table)")
    ex.add_argument("--scenes", nargs="+", required=True, help="suite scenes or regression presets")
    ex.add_argument("--seeds", nargs="+", type=_SEED, default=[0])
    ex.add_argument("--variants", nargs="+", default=None, help="only these variants of the experiment")
    ex.add_argument("--budget", type=_SECONDS, default=None, help="seconds of training per cell")
    ex.add_argument("--iters", type=_COUNT, default=None, help="steps per cell (default: the config's)")
    ex.add_argument("--size", type=_finite_float(positive=True), default=1.0,
                    help="image size factor on the scene's default size")
    ex.add_argument("--frames", type=_COUNT, default=None, help="frames per scene (default: the scene's)")
    ex.add_argument("--jobs", type=_COUNT, default=1, help="cells at once on the local scheduler (default 1)")
    ex.add_argument("--threads", type=_COUNT, default=None,
                    help="Numba threads per cell (default: cores // jobs, the whole machine)")
    ex.add_argument("--scheduler", default=None, help="address of a dask.distributed scheduler (default: local)")
    ex.add_argument("--retries", type=_int_at_least(0), default=1, help="retries of a failed cell (default 1)")
    ex.add_argument("--config", default=None, help="base experiment config JSON for every cell")
    ex.set_defaults(func=_cmd_experiment)

    x = sub.add_parser("export-ply", help="export the Gaussians at a time in the standard 3DGS PLY layout "
                       "(docs/method.md §2)",
                       description="Export the Gaussians of a run, deformed to a time, in the standard 3DGS PLY "
                                   "layout (log-scales, opacity logits, wxyz quaternions, RGB colours; "
                                   "docs/method.md §2).")
    x.add_argument("run")
    x.add_argument("--time", type=_finite_float(), required=True)
    x.add_argument("out", help="output .ply")
    x.set_defaults(func=_cmd_export_ply)

    tr = sub.add_parser("export-trajectory", help="write a run's optimised camera trajectory in the TUM format "
                        "(docs/dataset_format.md §10)",
                        description="Write the optimised mid-exposure camera poses of a run as a TUM trajectory, one "
                                    "line 'timestamp tx ty tz qx qy qz qw' per training frame: camera-to-world, OpenCV "
                                    "camera axes (docs/dataset_format.md §10), for evo or the TUM tools.")
    tr.add_argument("run")
    tr.add_argument("out", help="output .txt")
    tr.add_argument("--fps", type=_finite_float(positive=True), default=None,
                    help="frames per second of the video: timestamps in seconds, t (N - 1) / fps (default: the "
                         "frames' normalised times in [0, 1])")
    tr.set_defaults(func=_cmd_export_trajectory)
    from d2gs_np.refcheck.cli import add_refcheck_parser  # the reference-check kit (docs/refcheck.md)
    add_refcheck_parser(sub)
    return p


@contextlib.contextmanager
def _input_warnings_as_lines(args):
    """Within: each InputWarning (docs/dataset_format.md §5) is printed as one line
    ``d2gs CMD: warning: ...`` on stderr, every time it is issued; other warnings as Python prints them."""
    from d2gs_np.base.checks import InputWarning

    command = " ".join(c for c in (args.command, getattr(args, "refcheck_command", None)) if c)
    with warnings.catch_warnings():
        warnings.simplefilter("always", InputWarning)
        original = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            if not issubclass(category, InputWarning):
                return original(message, category, filename, lineno, file, line)
            print(f"d2gs {command}: warning: {message}", file=sys.stderr, flush=True)
        warnings.showwarning = show
        yield


def main(argv=None):
    from d2gs_np.refcheck.cli import CheckFailed

    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # argparse's refusal (one line, status 2) or --help (0): a status, as below
        return e.code
    command = " ".join(c for c in (args.command, getattr(args, "refcheck_command", None)) if c)
    try:
        with _input_warnings_as_lines(args):
            args.func(args)
    except CheckFailed as e:
        print(f"d2gs {e}", file=sys.stderr)
        return 1
    except (ValueError, TypeError, OSError) as e:  # OSError: FileNotFoundError, PermissionError, a full disk ...
        print(f"d2gs {command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # Ctrl-C: one line (what was kept, how to go on), the shell's status
        print(f"d2gs {command}: interrupted" + (f": {e}" if str(e) else ""), file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
