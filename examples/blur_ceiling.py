"""How well can the geodesic blur model (docs/method.md §4, Eq. 9) explain a synthetic scene's blur at all?

For each hand-shake setting, with the TRUE exposure endpoints and the TRUE scene (ray cast, no
Gaussians), this measures per frame:

- input: PSNR of the blurry input against the sharp frame (what deblurring must beat);
- geodesic blur: PSNR of the n-view blur along the geodesic between the true endpoints against the
  blurry input (how well the model's blur can match the data);
- geodesic mid: PSNR of a sharp render at the geodesic midpoint against the sharp frame (the best
  deblurred view a perfect model could give: the true camera curves inside the exposure, the model
  cannot);
- three-knot blur: PSNR of the n-view blur along the three-knot path through the true start,
  middle and end poses (``TrajectoryConfig.path = "three_knot"``, docs/method.md §4) against the
  blurry input; its middle view is the true mid-exposure pose, so its "mid" is the sharp frame;
- mid rotation error between the geodesic midpoint and the true mid-exposure pose (degrees);
- true rotation spread over the exposure (degrees).

    python examples/blur_ceiling.py --frames 0 5 11 17 23
    python examples/blur_ceiling.py --suite            # every scene of the suite
    python examples/blur_ceiling.py --num-frames 12 --width 160 --height 90 --frames 0 3 5 8 11  # demo scene
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from d2gs_np.data import synthetic as sy
from d2gs_np.geometry.se3 import se3_exp, se3_interpolate, se3_inverse, se3_log
from d2gs_np.evaluation.metrics import psnr

SETTINGS = {
    "base shake x1 (mild)": dict(shake_scale=1.0, shake_freq_scale=1.0),
    "base shake x2.5 (old dynamic preset)": dict(shake_scale=2.5, shake_freq_scale=1.0),
    "slow shake x8 at 1/4 frequency (dynamic preset)": dict(shake_scale=8.0, shake_freq_scale=0.25),
}


def frame_ceiling(pose_fn, render_fn, t, tau, subframes, n):
    """Per-frame figures (see module docstring) of the frame at mid-exposure time t.

    pose_fn(times (M,)) -> true cam_T_world (M, 4, 4); render_fn(T, time) -> sharp image."""
    u_sub = np.linspace(0.0, 1.0, subframes)
    times = t + (u_sub - 0.5) * tau
    blurry = np.mean([render_fn(T, s) for T, s in zip(pose_fn(times), times)], axis=0)
    T_s, T_mid, T_e = pose_fn(np.array([t - tau / 2, t, t + tau / 2]))
    u = np.linspace(0.0, 1.0, n)
    geo = np.mean([render_fn(se3_interpolate(T_s, T_e, ui), t + (ui - 0.5) * tau) for ui in u], axis=0)
    T_geo_mid = se3_interpolate(T_s, T_e, 0.5)
    sharp = render_fn(T_mid, t)
    mid_err = np.degrees(np.linalg.norm(se3_log(T_geo_mid @ se3_inverse(T_mid))[3:]))
    spread = np.degrees(np.linalg.norm(se3_log(T_e @ se3_inverse(T_s))[3:]))
    knots = np.stack([se3_log(T @ se3_inverse(T_mid)) for T in (T_s, T_mid, T_e)])
    three = np.mean([render_fn(P, t + (ui - 0.5) * tau) for P, ui in zip(three_knot_poses(T_mid, knots, u), u)],
                    axis=0)
    return psnr(blurry, sharp), psnr(geo, blurry), psnr(three, blurry), psnr(render_fn(T_geo_mid, t), sharp), \
        mid_err, spread


def three_knot_poses(T_ref, knots, u):
    """exp(c(u)) T_ref with c the quadratic through the tangents knots (3, 6) at u = 0, 1/2, 1."""
    from d2gs_np.blur.virtual_poses import knot_weights

    return se3_exp(knot_weights(u) @ knots) @ T_ref


def regression_worlds(args):
    """(name, pose_fn, render_fn, times, tau, subframes) of the regression preset's shake settings."""
    for name, overrides in SETTINGS.items():
        cfg = dataclasses.replace(sy.PRESETS["dynamic"], seed=args.seed, num_frames=args.num_frames,
                                  width=args.width, height=args.height, **overrides)
        world = sy.build_world(cfg)
        K = sy.intrinsics(cfg)
        yield (name, lambda t, w=world: sy.camera_pose(w, t),
               lambda T, t, w=world, c=cfg, K=K: sy.render_view(w, T, t, K, c.width, c.height, c.supersample)[0],
               sy.frame_times(cfg), sy.exposure_length(cfg), cfg.subframes)


def suite_worlds(args):
    """The same for every scene of the suite (d2gs_np/data/suite.py)."""
    from d2gs_np.data import suite

    for name in suite.SUITE:
        cfg = suite.resolve(name, args.seed, num_frames=args.num_frames, width=args.width, height=args.height)
        world = suite.build_suite_world(cfg)
        K = suite._intrinsics(cfg)
        yield (name, lambda t, w=world: suite.suite_camera_pose(w, t),
               lambda T, t, w=world, c=cfg, K=K: suite.render_suite_view(w, T, t, K, c.width, c.height,
                                                                         c.supersample)[0],
               np.linspace(0.0, 1.0, cfg.num_frames), cfg.exposure_fraction / (cfg.num_frames - 1), cfg.subframes)


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, nargs="+", default=[0, 5, 11, 17, 23])
    ap.add_argument("--n", type=int, default=8, help="virtual views of the model's blur")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--num-frames", type=int, default=24)
    ap.add_argument("--width", type=int, default=240)
    ap.add_argument("--height", type=int, default=135)
    ap.add_argument("--suite", action="store_true", help="measure the scene suite instead of the regression preset")
    args = ap.parse_args()
    if args.n < 1:
        raise SystemExit(f"--n must be >= 1; got {args.n}")
    bad = [k for k in args.frames if not 0 <= k < args.num_frames]
    if bad:
        raise SystemExit(f"--frames {bad} out of range: the scene has {args.num_frames} frames (--num-frames)")
    print(f"true endpoints, true scene; n = {args.n}; frames {args.frames}; means over frames\n")
    print("| setting | input vs sharp dB | geodesic blur vs input dB | three-knot blur vs input dB "
          "| geodesic mid vs sharp dB | mid rot err deg | spread deg | s |")
    print("|---|---|---|---|---|---|---|---|")
    for name, pose_fn, render_fn, times, tau, subframes in (suite_worlds(args) if args.suite
                                                            else regression_worlds(args)):
        t0 = time.perf_counter()
        r = np.array([frame_ceiling(pose_fn, render_fn, times[k], tau, subframes, args.n) for k in args.frames])
        m = r.mean(axis=0)
        print(f"| {name} | {m[0]:.2f} | {m[1]:.2f} | {m[2]:.2f} | {m[3]:.2f} | {m[4]:.3f} | {m[5]:.2f} "
              f"| {time.perf_counter() - t0:.1f} |")

if __name__ == "__main__":
    main()
