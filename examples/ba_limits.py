"""What limits the bundle adjustment's trajectory on a scene with true poses: the tracks' noise or
their geometry? (docs/method.md §5, the initial poses; issue #39's ATE target.)

For each scene folder (with true poses, ``gt_cam_T_world``) this runs the adjustment of
``pose/given.py`` three times on the same KLT tracks, from the same given poses:

- real: the tracks as measured in the blurry frames (what training starts from);
- exact: every track's observations replaced by the projections, through the TRUE poses, of its
  point triangulated with the true poses: the same frames, tracks and pixels, no measurement error;
- exact + noise: the same with Gaussian pixel noise of ``--noise`` px.

If "exact" is not much better than "real", better tracking cannot help: the frames the tracks
leave out (held at their given poses) and the directions the tracks do not see (a far, flat
background's translation) are the limit. Per frame it prints the camera-centre error after the
similarity alignment of ``geometry.trajectory.ate`` (in % of the scene scale's unit), and the ATE
of the held and of the free frames apart.

    python examples/ba_limits.py SCENE [SCENE ...] [--noise 0.3]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from d2gs_np.data.io import load_scene
from d2gs_np.geometry.camera import camera_center
from d2gs_np.geometry.trajectory import align_trajectory, ate, sim3_apply_to_poses
from d2gs_np.pose.config import PoseInitConfig
from d2gs_np.pose.given import adjust_given_poses, triangulate_tracks
from d2gs_np.pose.tracks import klt_tracks


def centre_errors(T, gt):
    """Per-frame camera-centre error of poses T after their similarity alignment onto gt."""
    s, R, t = align_trajectory(T, gt)
    return np.linalg.norm(camera_center(sim3_apply_to_poses(s, R, t, T)) - camera_center(gt), axis=1)


def exact_tracks(tracks, gt, K, noise_px=0.0, seed=0):
    """The same tracks with their observations projected from points triangulated with the true
    poses (plus ``noise_px`` Gaussian pixel noise); tracks that cannot be triangulated are dropped."""
    of, ot, ouv, nt = tracks[:4]
    X, ok = triangulate_tracks(gt, K, of, ot, ouv, nt, min_views=2, min_parallax_deg=0.0)
    keep = ok[ot]
    P = K @ gt[:, :3, :]
    h = np.einsum("oij,oj->oi", P[of[keep]], np.c_[X, np.ones(nt)][ot[keep]])
    uv = h[:, :2] / h[:, 2:] + noise_px * np.random.default_rng(seed).standard_normal((int(keep.sum()), 2))
    _, track = np.unique(ot[keep], return_inverse=True)
    return of[keep], track.astype(np.int64), uv, int(track.max()) + 1


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", help="scene folders with true poses")
    ap.add_argument("--noise", type=float, default=0.3, help="pixel noise of the third run (default 0.3)")
    args = ap.parse_args(argv)
    cfg = PoseInitConfig()
    for folder in args.scenes:
        scene = load_scene(folder)
        frames = scene.frames
        if any(f.gt_cam_T_world is None for f in frames):
            raise ValueError(f"{folder}: every frame needs a true pose (gt_cam_T_world) to measure against")
        given = np.stack([f.cam_T_world for f in frames])
        gt = np.stack([f.gt_cam_T_world for f in frames])
        K = frames[0].K
        masks = None if any(f.mask is None for f in frames) else [f.mask for f in frames]
        t0 = time.perf_counter()
        tracks = klt_tracks([f.image for f in frames], cfg.tracks, masks=masks, seed=0)
        runs = {"real": tracks, "exact": exact_tracks(tracks, gt, K),
                f"exact + {args.noise:g} px": exact_tracks(tracks, gt, K, args.noise)}
        print(f"{folder}: {tracks[3]} tracks, {len(tracks[0])} observations ({time.perf_counter() - t0:.1f} s)")
        e = centre_errors(given, gt)
        print(f"  {'given':16s} ATE {ate(given, gt):.4f}           | " + " ".join(f"{x * 100:.1f}" for x in e))
        for name, tr in runs.items():
            T, info = adjust_given_poses(None, None, given, K, cfg, seed=0, tracks=tr)
            held = np.asarray(info.get("held_frames", []), dtype=np.int64)
            free = np.setdiff1d(np.arange(len(frames)), held)
            e = centre_errors(T, gt)
            rms = lambda idx: float(np.sqrt(np.mean(e[idx] ** 2))) if len(idx) else float("nan")  # noqa: E731
            status = "kept" if info["kept"] else f"declined: {info.get('reason')}"
            print(f"  {name:16s} ATE {ate(T, gt):.4f} ({ate(T, gt) / ate(given, gt):.2f} x), held {len(held)} "
                  f"frames {rms(held):.4f}, free {rms(free):.4f}; {info.get('points', 0)} points, {status}")
            print(f"  {'':16s} held {held.tolist()} | " + " ".join(f"{x * 100:.1f}" for x in e))


if __name__ == "__main__":
    main()
