"""A real video end to end: ``d2gs import-video`` -> a short ``d2gs train`` -> ``d2gs eval``.

    python examples/video_to_run.py CLIP.mp4 --out runs/clip [--size 320x180] [--stride 2]
        [--max-frames 24] [--time-budget 300]

No real hand-held clip ships with any package available here: scikit-image's and OpenCV's Python
packages carry still images only (imageio's sample videos are downloaded at run time, which this
machine cannot do), and no data set may be downloaded from elsewhere. So this example was run on
the suite's blurry frames written as a video (``--demo``: wall_disk, seed 0, as MJPG .avi), not
on a real clip; pass your own phone video to run it on one. Without ground truth ``d2gs eval``
reports what it can (the trained model's fit to the input frames), not deblurring quality.
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


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("video", nargs="?", default=None)
    ap.add_argument("--demo", action="store_true", help="use a suite scene written as a video instead")
    ap.add_argument("--out", default="runs/video_to_run")
    ap.add_argument("--size", default=None)
    ap.add_argument("--stride", default="1")
    ap.add_argument("--max-frames", default=None)
    ap.add_argument("--time-budget", default="120")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    video = _demo_clip(out / "demo.avi") if a.demo else a.video
    if video is None:
        ap.error("pass a VIDEO or --demo")
    args = ["import-video", str(video), str(out / "scene"), "--overwrite", "--stride", a.stride]
    args += (["--size", a.size] if a.size else []) + (["--max-frames", a.max_frames] if a.max_frames else [])
    for cmd in (args, ["train", str(out / "scene"), "--out", str(out / "run"), "--time-budget", a.time_budget],
                ["eval", str(out / "run")]):
        print("d2gs " + " ".join(cmd), flush=True)
        rc = d2gs(cmd)
        if rc:
            sys.exit(rc)


if __name__ == "__main__":
    main()
