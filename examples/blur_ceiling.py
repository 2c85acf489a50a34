"""How well can the geodesic blur model (METHOD.md Eq. 9) explain a synthetic scene's blur at all?

For each hand-shake setting, with the TRUE exposure endpoints and the TRUE scene (ray cast, no
Gaussians), this measures per frame:

- input: PSNR of the blurry input against the sharp frame (what deblurring must beat);
- geodesic blur: PSNR of the n-view blur along the geodesic between the true endpoints against the
  blurry input (how well the model's blur can match the data);
- geodesic mid: PSNR of a sharp render at the geodesic midpoint against the sharp frame (the best
  deblurred view a perfect model could give: the true camera curves inside the exposure, the model
  cannot);
- mid rotation error between the geodesic midpoint and the true mid-exposure pose (degrees);
- true rotation spread over the exposure (degrees).

    python examples/blur_ceiling.py --frames 0 5 11 17 23
    python examples/blur_ceiling.py --num-frames 12 --width 160 --height 90 --frames 0 3 5 8 11  # demo scene
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from d2gs_np.data import synthetic as sy
from d2gs_np.geometry.se3 import se3_interpolate, se3_inverse, se3_log
from d2gs_np.metrics import psnr

SETTINGS = {
    "base shake x1 (mild)": dict(shake_scale=1.0, shake_freq_scale=1.0),
    "base shake x2.5 (old dynamic preset)": dict(shake_scale=2.5, shake_freq_scale=1.0),
    "slow shake x8 at 1/4 frequency (dynamic preset)": dict(shake_scale=8.0, shake_freq_scale=0.25),
}


def frame_ceiling(world, cfg, k, n):
    """Per-frame figures (see module docstring) for frame k of the generator config ``cfg``."""
    K, W, H, ss = sy.intrinsics(cfg), cfg.width, cfg.height, cfg.supersample
    tau, t = sy.exposure_length(cfg), sy.frame_times(cfg)[k]

    def render(T, time_):
        return sy.render_view(world, T, time_, K, W, H, ss)[0]

    u_sub = np.linspace(0.0, 1.0, cfg.subframes)
    times = t + (u_sub - 0.5) * tau
    blurry = np.mean([render(T, s) for T, s in zip(sy.camera_pose(world, times), times)], axis=0)
    T_s, T_mid, T_e = sy.camera_pose(world, np.array([t - tau / 2, t, t + tau / 2]))
    u = np.linspace(0.0, 1.0, n)
    geo = np.mean([render(se3_interpolate(T_s, T_e, ui), t + (ui - 0.5) * tau) for ui in u], axis=0)
    T_geo_mid = se3_interpolate(T_s, T_e, 0.5)
    sharp = render(T_mid, t)
    mid_err = np.degrees(np.linalg.norm(se3_log(T_geo_mid @ se3_inverse(T_mid))[3:]))
    spread = np.degrees(np.linalg.norm(se3_log(T_e @ se3_inverse(T_s))[3:]))
    return psnr(blurry, sharp), psnr(geo, blurry), psnr(render(T_geo_mid, t), sharp), mid_err, spread


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, nargs="+", default=[0, 5, 11, 17, 23])
    ap.add_argument("--n", type=int, default=8, help="virtual views of the model's blur")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--num-frames", type=int, default=24)
    ap.add_argument("--width", type=int, default=240)
    ap.add_argument("--height", type=int, default=135)
    args = ap.parse_args()
    if args.n < 1:
        raise SystemExit(f"--n must be >= 1; got {args.n}")
    bad = [k for k in args.frames if not 0 <= k < args.num_frames]
    if bad:
        raise SystemExit(f"--frames {bad} out of range: the scene has {args.num_frames} frames (--num-frames)")
    print(f"true endpoints, true scene; n = {args.n}; frames {args.frames}; means over frames\n")
    print("| setting | input vs sharp dB | geodesic blur vs input dB | geodesic mid vs sharp dB "
          "| mid rot err deg | spread deg | s |")
    print("|---|---|---|---|---|---|---|")
    for name, overrides in SETTINGS.items():
        t0 = time.perf_counter()
        cfg = dataclasses.replace(sy.PRESETS["dynamic"], seed=args.seed, num_frames=args.num_frames,
                                  width=args.width, height=args.height, **overrides)
        world = sy.build_world(cfg)
        r = np.array([frame_ceiling(world, cfg, k, args.n) for k in args.frames])
        m = r.mean(axis=0)
        print(f"| {name} | {m[0]:.2f} | {m[1]:.2f} | {m[2]:.2f} | {m[3]:.3f} | {m[4]:.2f} "
              f"| {time.perf_counter() - t0:.1f} |")


if __name__ == "__main__":
    main()
